"""The digit floor's TD loop in chunks (ferl/trainers/chunks.py: td_steps): the chunk length
does not change a run, `compile=true` (torch.compile of the chunk, run by groups of runs on a CPU)
gives the eager results within floating-point tolerance, and the grouping changes no run."""

import threading

import numpy as np
import pytest
import torch

from conftest import train_job
from ferl.trainers import chunks, continuing_td
from ferl.trainers.chunks import chunk_length

TINY = [
    "n_runs=3",
    "trainer.steps=480",
    "trainer.log_every=160",
    "trainer.checkpoint_every=160",
    "trainer.test_per_class=5",
    "trainer.test_noise_levels=[0.125]",
]


@pytest.fixture(autouse=True)
def fresh_compiler():
    """Every test compiles afresh: one process compiles td_steps for a few actors (value forms,
    group sizes), more versions of one function than dynamo keeps (its recompile limit); a run
    of train.py compiles for one actor only."""
    torch._dynamo.reset()
    yield


def run(compose_cfg, tmp_path, name, *overrides):
    summary = train_job(compose_cfg([*TINY, *overrides]), tmp_path / name)
    with (
        np.load(tmp_path / name / "records" / "steps.npz") as train,
        np.load(tmp_path / name / "records" / "weights.npz") as weights,
    ):
        return summary, train["rewards"], train["td_errors"], weights["state_weights_after"]


def test_chunk_length_divides_the_run_and_the_intervals():
    assert chunk_length(30_000, 1000, 5000) == 8
    assert chunk_length(32_000, 1024, 4096) == 16
    assert chunk_length(1001, 1001, 1001) == 1
    assert chunk_length(32_000, 1024, 4096, most=4) == 4  # a Gibbs chain's chunk: at most ``most``


@pytest.mark.parametrize("td_rule", ["sarsa", "expected_sarsa"])
def test_chunked_steps_equal_single_steps(compose_cfg, tmp_path, monkeypatch, td_rule):
    chunked = run(compose_cfg, tmp_path, "chunked", f"actor.td_rule={td_rule}")
    monkeypatch.setattr(chunks, "MAX_CHUNK", 1)
    single = run(compose_cfg, tmp_path, "single", f"actor.td_rule={td_rule}")
    assert chunked[0]["metrics"] == single[0]["metrics"]
    for got, want in zip(chunked[1:], single[1:]):
        np.testing.assert_array_equal(got, want)


def test_prefetched_random_numbers_change_no_run(compose_cfg, tmp_path, monkeypatch):
    """trainer.prefetch draws the next chunks' random numbers on a second thread while a chunk
    runs: the same draws in the same order, so every run is bit-identical to drawing in turn."""
    monkeypatch.setattr(chunks, "MAX_CHUNK", 4)  # many chunks, so many prefetches
    threads = []
    draw = continuing_td.ContinuingTD.chunk_inputs
    monkeypatch.setattr(
        continuing_td.ContinuingTD,
        "chunk_inputs",
        lambda self, env: threads.append(threading.current_thread().name) or draw(self, env),
    )
    many = f"n_runs={continuing_td.PREFETCH_MIN_RUNS}"  # fewer runs draw in turn anyway
    prefetched = run(compose_cfg, tmp_path, "prefetched", many, "trainer.prefetch=3")
    assert threads and all(name.startswith("ferl-random") for name in threads)
    threads.clear()
    in_turn = run(compose_cfg, tmp_path, "in_turn", many, "trainer.prefetch=0")
    assert threads and not any(name.startswith("ferl-random") for name in threads)
    assert prefetched[0]["metrics"] == in_turn[0]["metrics"]
    for got, want in zip(prefetched[1:], in_turn[1:]):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("td_fresh, q", [(False, "free_energy"), (True, "free_energy"), (True, "expected_energy")])
def test_compiled_chunks_equal_eager_ones(compose_cfg, tmp_path, monkeypatch, td_fresh, q):
    monkeypatch.setattr(chunks, "MAX_CHUNK", 4)  # a short unrolled graph compiles faster
    actor = (f"actor.td_fresh={str(td_fresh).lower()}", f"actor.q={q}")
    eager = run(compose_cfg, tmp_path, "eager", *actor)
    # 3 runs in groups of 2: a full group and a remainder group of 1, each its own graph
    compiled = run(compose_cfg, tmp_path, "compiled", *actor, "compile=true", "trainer.compile_group_runs=2")
    np.testing.assert_array_equal(compiled[1], eager[1])  # the same actions, so the same rewards
    np.testing.assert_allclose(compiled[2], eager[2], rtol=1e-4, atol=1e-4)  # TD errors
    np.testing.assert_allclose(compiled[3], eager[3], rtol=1e-4, atol=1e-5)  # weights after training


def test_run_groups_do_not_change_a_run(compose_cfg, tmp_path, monkeypatch):
    """Identical, not just close: a compiled graph computes every run of its group with the same
    loops (its sums run over one run's own pixels and hidden units, none across runs), so a run's
    arithmetic does not depend on which group, or how large a group, it is in."""
    monkeypatch.setattr(chunks, "MAX_CHUNK", 4)
    pairs = run(compose_cfg, tmp_path, "pairs", "n_runs=5", "compile=true", "trainer.compile_group_runs=2")
    triples = run(compose_cfg, tmp_path, "triples", "n_runs=5", "compile=true", "trainer.compile_group_runs=3")
    assert pairs[0]["metrics"] == triples[0]["metrics"]
    for got, want in zip(pairs[1:], triples[1:]):
        np.testing.assert_array_equal(got, want)


def test_one_graph_serves_every_noise_level_up_to_half_and_both_ends(compose_cfg, tmp_path, monkeypatch):
    """The floor's noisy pixels a step (round(noise · 784)) are a size of the chunk's inputs, and
    the chunk is compiled generic in it (chunks.generic_inputs): another level up to half, noise 0
    (no noisy pixel, a size dynamo would specialise) and noise 1 (no clean pixel) trace no new
    graph, and that graph computes each level as eagerly within the tolerance above."""
    from torch._dynamo.utils import counters

    monkeypatch.setattr(chunks, "MAX_CHUNK", 4)
    before = counters["stats"]["unique_graphs"]
    run(compose_cfg, tmp_path, "first", "compile=true", "env.noise=0.125")
    graphs = counters["stats"]["unique_graphs"]
    assert graphs > before  # the first level was compiled, not run eagerly after a failed trace
    for noise in (0.25, 0.0, 1.0):
        compiled = run(compose_cfg, tmp_path, f"compiled{noise}", "compile=true", f"env.noise={noise}")
        assert counters["stats"]["unique_graphs"] == graphs, noise
        eager = run(compose_cfg, tmp_path, f"eager{noise}", f"env.noise={noise}")
        np.testing.assert_array_equal(compiled[1], eager[1])
        np.testing.assert_allclose(compiled[2], eager[2], rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(compiled[3], eager[3], rtol=1e-4, atol=1e-5)
