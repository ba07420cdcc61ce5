"""The fast path (ferl/compiled.py): the T-maze phases compiled as fused chunks against independent
references and against the eager path; the first run's line; eager without a compiler.

Pattern-mode BPTT in compiled chunks (``PredictorBatch.fuse``) must equal per-run SGD by autograd
on each unpadded sequence (float64, so rounding cannot hide a wrong step): every step unrolls the
longest sequence with the shorter ones masked, and the chunks are filled with zero-weight
sequences. A compiled episode (``ActorEpisodes.fuses``) plays all T_max steps with the ended ones
masked, where eager stops when every run has ended: the same actions, and values within float32
rounding of the generated kernels.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import train_job
from ferl import compiled as fast
from ferl.predictors import training
from ferl.predictors.training import PredictorBatch
from test_predictor import data, make, reference_loss

CPU = torch.device("cpu")


@pytest.fixture(autouse=True)
def fresh_compiler():
    torch._dynamo.reset()
    yield


@pytest.mark.parametrize("batch_size", [1, 2])
def test_fused_bptt_equals_autograd_sgd_of_each_run_alone(monkeypatch, batch_size):
    """Chapter 5's two predictors as one compiled batch, 7 sequences of lengths 1 … 5 in chunks
    of 2 steps (so the last chunk, and with B = 2 the last step, is padded), two epochs, against
    θ ← θ − α ∇ mean_b Σ_t E_t by autograd for each predictor and run alone."""
    monkeypatch.setattr(training, "CHUNK_STEPS", 2)
    R, N, lr = 2, 7, 0.2
    kinds = [dict(reward_output="none", seed=30), dict(reward_output="linear", predict_obs=False, seed=40)]
    members = [make(R=R, lr=lr, batch_size=batch_size, **k) for k in kinds]
    y, a, _, lengths = data(R, N, 5, seed=6)
    r = torch.randn(R, N, 6, 1, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    batch = PredictorBatch(members, y, a, [None, r], lengths)
    batch.fuse(CPU)
    assert batch.chunk is not None
    g = torch.Generator().manual_seed(8)
    orders = [[torch.rand(R, N, generator=g).argsort(1) for _ in members] for _ in range(2)]
    for epoch in orders:
        batch.train_epoch(epoch)
    for k, (member, kind) in enumerate(zip(members, kinds)):
        for run in range(R):
            single = make(R=1, lr=lr, **{**kind, "seed": kind["seed"] + run})
            for epoch in orders:
                for step in epoch[k][run].split(batch_size):
                    losses = [
                        reference_loss(
                            single,
                            0,
                            y[run, i, : int(lengths[run, i]) + 1],
                            a[run, i, : int(lengths[run, i])],
                            r[run, i, : int(lengths[run, i]) + 1] if k else None,
                        )
                        for i in step.tolist()
                    ]
                    grads = torch.autograd.grad(torch.stack(losses).mean(), list(single.parameters()))
                    with torch.no_grad():
                        for q, gq in zip(single.parameters(), grads):
                            q -= lr * gq
            for (name, qb), qs in zip(member.named_parameters(), single.parameters()):
                torch.testing.assert_close(qb[run], qs[0], rtol=1e-10, atol=1e-10, msg=name)


BIT_TINY = (
    "experiment=table5_1_bit",
    "n_runs=3",
    "trainer.n_sample=300",
    "trainer.n_epoch=2",
    "trainer.n_episodes=60",
    "trainer.log_every=20",
    "trainer.td_sample_every=20",
    "trainer.final_window=20",
)


def episodes(tmp_path, name: str, *overrides, tiny=BIT_TINY) -> tuple[dict, dict]:
    """A run of ``tiny`` and ``overrides`` in process: its summary and its episodes.npz."""
    from conftest import compose_config

    summary = train_job(compose_config([*tiny, *overrides]), tmp_path / name)
    with np.load(tmp_path / name / "records" / "episodes.npz") as ep:
        return summary, dict(ep)


def eager_then_compiled(tmp_path, tiny) -> tuple[dict, dict, int]:
    """Runs of ``tiny`` with compile=false, then compile=true from a fresh compiler (which must
    compile something): both runs' episodes and the number of graphs the compiled one traced."""
    from torch._dynamo.utils import counters

    _, eager = episodes(tmp_path, "eager", "compile=false", tiny=tiny)
    torch._dynamo.reset()
    counters.clear()
    summary, fused = episodes(tmp_path, "fused", "compile=true", tiny=tiny)
    assert summary["compile_time_s"] > 0
    return eager, fused, counters["stats"]["unique_graphs"]


def test_compiled_phases_equal_eager_ones(tmp_path):
    """table5_1_bit (two predictors in one compiled BPTT batch, then compiled episodes) at
    reduced scale, compile=true against compile=false: the same actions in every episode of
    every run (steps, goals, conditions equal), returns and TD errors within float32 rounding."""
    eager_summary, eager = episodes(tmp_path, "eager", "compile=false")
    summary, fused = episodes(tmp_path, "fused", "compile=true")
    assert summary["metrics"]["env_steps_total"] == eager_summary["metrics"]["env_steps_total"]
    for key in ("steps", "correct_goal", "condition"):
        np.testing.assert_array_equal(fused[key], eager[key], err_msg=key)
    for key in ("discounted_return", "terminal_reward", "td_abs_mean", "td_sampled"):
        np.testing.assert_allclose(fused[key], eager[key], rtol=1e-4, atol=1e-5, err_msg=key)


def test_no_compiler_warns_once_and_runs_eagerly(capsys):
    with torch._inductor.config.patch({"cpp.cxx": ("no-such-compiler++",)}):  # undone fully (monkeypatch is not)
        assert fast.fast_path(True, CPU) is False
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("ferl: warning: compile=true: no C++ compiler")
    assert "eagerly" in lines[0]
    assert fast.fast_path(False, CPU) is False
    assert capsys.readouterr().err == ""


def test_the_first_run_says_it_compiles_and_later_ones_load(tmp_path):
    """Two processes compile the same function with one cache folder: the first prints one line
    naming the folder, the second loads from it and prints nothing."""
    script = (
        "import torch; from ferl.compiled import compiled, fast_path; assert fast_path(True, torch.device('cpu')); "
        "f = compiled(lambda x: torch.sigmoid(x) * 3 + 1, torch.device('cpu'), 'a test'); "
        "f(torch.ones(4)); f(torch.zeros(4))"
    )
    env = {"TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    first, second = (
        subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
        for _ in range(2)
    )
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    lines = [line for line in first.stderr.splitlines() if line.startswith("ferl:")]
    assert len(lines) == 1 and "compiled a test" in lines[0] and str(tmp_path / "cache") in lines[0]
    assert "ferl:" not in second.stderr


def test_what_cannot_be_compiled_warns_once_and_runs_eagerly(capsys):
    """A data-dependent branch breaks the graph, which fullgraph refuses: one warning naming
    what, then the function's own results, eagerly, on every call."""

    def branchy(x):
        return x + 1 if bool(x.sum() > 0) else x - 1

    f = fast.compiled(branchy, CPU, "a branchy step")
    assert torch.equal(f(torch.ones(3)), torch.full((3,), 2.0))
    assert torch.equal(f(-torch.ones(3)), torch.full((3,), -2.0))
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("ferl: warning: compile=true: a branchy step cannot be compiled")


@pytest.mark.parametrize("memory", ["lstm", "transformer"])
def test_fused_bptt_of_autograd_memories_equals_their_eager_epoch(monkeypatch, memory):
    """A memory whose BPTT is autograd's (``autograd_bptt``: the heads written out, the memory by
    ``torch.func.vjp``) compiles too: one SGD step per graph (MAX_UNROLLED_STEPS patched down, as
    at long T_max), every sequence unrolled to ``unroll_to`` = 8 > the longest (6), the online
    trainer's layout, two epochs of 6 padded sequences in steps of 2 — the same parameters as the
    eager epochs (float64, 1e-10). The gradients themselves are checked against finite
    differences in tests/test_memories.py."""
    from test_memories import data as memory_data
    from test_memories import make as make_memory

    monkeypatch.setattr(fast, "MAX_UNROLLED_STEPS", 8)
    y, a, r = memory_data(2, 6, 6)
    lengths = torch.tensor([[1, 4, 6, 2, 5, 3], [6, 1, 4, 3, 3, 2]])
    g = torch.Generator().manual_seed(8)
    orders = [torch.rand(2, 6, generator=g).argsort(1) for _ in range(2)]
    trained, initial = [], []
    for fused in (False, True):
        p = make_memory(memory, R=2, lr=0.3, batch_size=2, **({"context": 9} if memory == "transformer" else {}))
        initial = [q.clone() for q in p.parameters()]
        batch = PredictorBatch([p], y, a, [r], lengths)
        if fused:
            batch.fuse(CPU, unroll_to=8)
            assert batch.chunk is not None
        for order in orders:
            batch.train_epoch([order])
        trained.append([q.clone() for q in p.parameters()])
    assert all((q - q0).abs().max() > 1e-3 for q, q0 in zip(trained[1], initial))  # every parameter learnt
    for eager, compiled in zip(*trained):
        torch.testing.assert_close(compiled, eager, rtol=1e-10, atol=1e-10)


# the online trainer on an LSTM predictor, 2 runs of the regular maze's short episodes
ONLINE_LSTM = (
    "experiment=table4_1_regular",
    "trainer=online",
    "predictor.joint.memory=lstm",
    "n_runs=2",
    "env.max_steps=6",
)


def test_online_episodes_compiled_equal_eager_in_one_graph(tmp_path, monkeypatch):
    """The online trainer's episodes compiled in chunks of steps (EPISODES_FUSED_FROM patched down
    to this run's 30 episodes; the replay eager), β_k following the predictor's error and the
    curiosity η_k annealed from episode to episode, against compile=false: the same actions in
    every episode, returns and TD errors within float32 rounding, and one graph of steps for every
    episode (β_k and η_k are tensors, the predictor's weights read as the replay leaves them)."""
    from ferl.trainers import online_episodes

    monkeypatch.setattr(online_episodes, "EPISODES_FUSED_FROM", 30)
    tiny = (
        *ONLINE_LSTM,
        "trainer.n_episodes=30",
        "trainer.replay_sample=4",
        "trainer.curiosity=0.5",
        "trainer.log_every=10",
        "trainer.td_sample_every=10",
        "trainer.final_window=10",
    )
    eager, fused, graphs = eager_then_compiled(tmp_path, tiny)
    # the chunk of steps (max_steps 6: 2 calls of 4 steps, the last padded) and the FERL actor's update graphs
    # (``compile_updates``), each traced once, whatever β_k, η_k and the weights were
    assert graphs <= 3
    for key in ("steps", "correct_goal", "condition"):
        np.testing.assert_array_equal(fused[key], eager[key], err_msg=key)
    for key in ("discounted_return", "td_abs_mean", "td_sampled"):
        np.testing.assert_allclose(fused[key], eager[key], rtol=1e-4, atol=1e-5, err_msg=key)
    with np.load(tmp_path / "fused" / "records" / "online.npz") as online:
        k = np.arange(30)  # η_k = η · max(0, 1 − k / (0.5 N)) did change from episode to episode
        np.testing.assert_allclose(online["curiosity"][0], 0.5 * np.maximum(0, 1 - k / 15), rtol=1e-6)


@pytest.mark.parametrize("memory, more", [("lstm", ()), ("transformer", ()), ("gru", ("exploration=ez_greedy",))])
def test_one_episode_graph_serves_every_corridor(tmp_path, monkeypatch, memory, more):
    """The maze's tables ((L + 2)·4 rows) are generic in their sizes and T_min, T_max are tensors
    (``TMaze.tables_generic``), and every T_max plays chunks of EPISODE_CHUNK_STEPS steps: after
    corridor 3 (T_max 6), corridors 2, 5 and 7 (T_max 4, 9 and 17) trace no new graph, and that
    graph plays each as eagerly: the same actions, returns and TD errors within float32 rounding.
    Sized by T_max too, and generic: the transformer's cache of T_max + 1 tokens (its default
    context, ``generic_state``) and εz-greedy's draws and zeta CDF."""
    from torch._dynamo.utils import counters

    from ferl.trainers import online_episodes

    monkeypatch.setattr(online_episodes, "EPISODES_FUSED_FROM", 6)
    tiny = (
        *ONLINE_LSTM[:2],
        f"predictor.joint.memory={memory}",
        *ONLINE_LSTM[3:-1],
        *more,
        "trainer.n_episodes=6",
        "trainer.replay_sample=2",
        "trainer.final_window=3",
    )
    torch._dynamo.reset()
    counters.clear()
    episodes(tmp_path, "first", "compile=true", "env.corridor_length=3", "env.max_steps=6", tiny=tiny)
    graphs = counters["stats"]["unique_graphs"]
    assert graphs > 0
    for corridor, T_max in ((2, 4), (5, 9), (7, 17)):
        maze = (f"env.corridor_length={corridor}", f"env.max_steps={T_max}")
        _, fused = episodes(tmp_path, f"fused{corridor}", "compile=true", *maze, tiny=tiny)
        assert counters["stats"]["unique_graphs"] == graphs, corridor
        _, eager = episodes(tmp_path, f"eager{corridor}", "compile=false", *maze, tiny=tiny)
        for key in ("steps", "correct_goal", "condition"):
            np.testing.assert_array_equal(fused[key], eager[key], err_msg=key)
        for key in ("discounted_return", "td_abs_mean", "td_sampled"):
            np.testing.assert_allclose(fused[key], eager[key], rtol=1e-4, atol=1e-5, err_msg=key)


def test_one_episode_graph_serves_curiosity_on_and_off(tmp_path, monkeypatch):
    """The curiosity bonus η_k e^y_t is computed with η = 0 too (exactly 0), and η_k is a tensor:
    after a job without curiosity, one with η = 0.5 traces no new graph, and plays as eagerly."""
    from torch._dynamo.utils import counters

    from ferl.trainers import online_episodes

    monkeypatch.setattr(online_episodes, "EPISODES_FUSED_FROM", 6)
    tiny = (*ONLINE_LSTM, "trainer.n_episodes=6", "trainer.replay_sample=2", "trainer.final_window=3")
    torch._dynamo.reset()
    counters.clear()
    episodes(tmp_path, "off", "compile=true", "trainer.curiosity=0", tiny=tiny)
    graphs = counters["stats"]["unique_graphs"]
    assert graphs > 0
    _, fused = episodes(tmp_path, "on", "compile=true", "trainer.curiosity=0.5", tiny=tiny)
    assert counters["stats"]["unique_graphs"] == graphs
    _, eager = episodes(tmp_path, "on_eager", "compile=false", "trainer.curiosity=0.5", tiny=tiny)
    for key in ("steps", "correct_goal", "condition"):
        np.testing.assert_array_equal(fused[key], eager[key], err_msg=key)
    for key in ("discounted_return", "td_abs_mean", "td_sampled"):
        np.testing.assert_allclose(fused[key], eager[key], rtol=1e-4, atol=1e-5, err_msg=key)


def test_episodes_with_directed_exploration_compiled_equal_eager(tmp_path, monkeypatch, capsys):
    """εz-greedy's hooks keep their state in tensors (``EzGreedy.traceable``: the step counter and
    ε), so its episodes are compiled with the rest of the step: against compile=false, the same
    actions in every episode (options started, held and taken alike), returns and TD errors within
    float32 rounding, with ε falling from episode to episode and no warning of an eager fallback."""
    from ferl.trainers import online_episodes

    monkeypatch.setattr(online_episodes, "EPISODES_FUSED_FROM", 20)
    tiny = (
        *ONLINE_LSTM,
        "exploration=ez_greedy",
        "exploration.epsilon=0.5",
        "exploration.epsilon_end=0.1",
        "trainer.n_episodes=20",
        "trainer.replay_sample=2",
        "trainer.log_every=10",
        "trainer.td_sample_every=5",
        "trainer.final_window=10",
    )
    eager, fused, graphs = eager_then_compiled(tmp_path, tiny)
    assert 0 < graphs <= 3 and "eagerly" not in capsys.readouterr().err
    for key in ("steps", "correct_goal", "condition"):
        np.testing.assert_array_equal(fused[key], eager[key], err_msg=key)
    for key in ("discounted_return", "td_abs_mean", "td_sampled"):
        np.testing.assert_allclose(fused[key], eager[key], rtol=1e-4, atol=1e-5, err_msg=key)


def test_online_replay_compiled_equals_eager(tmp_path, monkeypatch):
    """The online trainer with an LSTM predictor, its replay's BPTT compiled (REPLAY_FUSED_FROM
    patched down to this run's 40 episodes) against compile=false: the same actions in every
    episode of every run, returns and TD errors within float32 rounding."""
    from ferl.trainers import online_episodes

    monkeypatch.setattr(online_episodes, "REPLAY_FUSED_FROM", 40)
    tiny = (
        *ONLINE_LSTM,
        "trainer.n_episodes=40",
        "trainer.replay_sample=8",
        "trainer.log_every=20",
        "trainer.td_sample_every=20",
        "trainer.final_window=20",
    )
    _, eager = episodes(tmp_path, "eager", "compile=false", tiny=tiny)
    summary, fused = episodes(tmp_path, "fused", "compile=true", tiny=tiny)
    assert summary["compile_time_s"] > 0  # the replay's graph (the episodes stay eager)
    for key in ("steps", "correct_goal", "condition"):
        np.testing.assert_array_equal(fused[key], eager[key], err_msg=key)
    for key in ("discounted_return", "td_abs_mean", "td_sampled"):
        np.testing.assert_allclose(fused[key], eager[key], rtol=1e-4, atol=1e-5, err_msg=key)


# the cue task's one-hot bits; stateless CartPole's real values (env.encoding=real, rows per step)
PYTHON_ENVS = {
    "bits": ("env.id=outside_env:CueRecall-v0", "+env.kwargs.delay=2", "env.optimal_return=0.8"),
    "real": ("env.id=stateless_cartpole:StatelessCartPole-v0", "env.encoding=real", "env.max_steps=30"),
}


@pytest.mark.parametrize("observations", list(PYTHON_ENVS))
def test_a_python_environments_agent_step_compiled_equals_eager(tmp_path, monkeypatch, observations):
    """``env=gymnasium`` (tests/outside_env.py's cue task, or stateless CartPole's real values, stepped
    in Python): the agent's half of each step (an LSTM predictor's memory, the FERL actor's choice
    and TD update) as one compiled graph between the environment's eager steps
    (EPISODES_FUSED_FROM patched down to this run's 30 episodes), against compile=false: the same
    actions in every episode, returns and TD errors within float32 rounding, and one graph of the
    step for every step and episode."""
    from ferl.trainers import online_episodes

    monkeypatch.syspath_prepend(str(Path(__file__).parent))  # where gymnasium imports the envs from
    monkeypatch.setattr(online_episodes, "EPISODES_FUSED_FROM", 30)
    tiny = (
        "experiment=popgym_repeat_previous_easy",
        *PYTHON_ENVS[observations],
        "predictor.joint.memory=lstm",
        "n_runs=2",
        "trainer.n_episodes=30",
        "trainer.replay_sample=4",
        "trainer.log_every=10",
        "trainer.td_sample_every=10",
        "trainer.final_window=10",
        "trainer.checkpoint_every=10",
    )
    eager, fused, graphs = eager_then_compiled(tmp_path, tiny)
    # the agent's step (and any of the actor's update graphs, ``compile_updates``), each traced once
    assert 1 <= graphs <= 3
    np.testing.assert_array_equal(fused["steps"], eager["steps"])
    for key in ("discounted_return", "return"):
        np.testing.assert_allclose(fused[key], eager[key], rtol=1e-4, atol=1e-5, err_msg=key)
    # CartPole's TD errors are large (|δ| ≈ 10–40, +1 a step), and the rounding of two kernels grows
    # through the weights as they learn: 4e-4 apart by episode 17 of 30, the actions still equal.
    # Within the first 11 episodes, 1e-4 absolute is 2.5e-6 of a δ of 40 (torch 2.8's kernels: a δ
    # of 0.80 among δs of 40 came 9e-5 apart). Episodes 0–10: td_sampled's first two samples
    first, atol = (11, 1e-4) if observations == "real" else (None, 1e-5)
    np.testing.assert_allclose(fused["td_abs_mean"][:, :first], eager["td_abs_mean"][:, :first], rtol=1e-4, atol=atol)
    sampled = fused["td_sampled_episodes"] < (first or np.inf)
    np.testing.assert_allclose(fused["td_sampled"][:, sampled], eager["td_sampled"][:, sampled], rtol=1e-4, atol=atol)
