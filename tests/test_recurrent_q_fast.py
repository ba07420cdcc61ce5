"""The recurrent Q-learner's fast path (ferl/actors/recurrent_q_fast.py, docs/performance.md): its
replay step (torch.func.grad of the loss, then Adam with the step sizes as tensors) equals the
eager reference ``adam_step`` (autograd.grad, the written-out Adam), and DRQN trained with
``compile=true`` (the replay's BPTT and the episodes in graphs of a fixed number of steps) takes
the same actions as ``compile=false`` at every episode length, its returns and TD errors within float32 rounding. Resume and
determinism of the compiled path: tests/test_tmaze_resume.py."""

import numpy as np
import pytest
import torch

from ferl.actors.recurrent_q_fast import adam_scalars, replay_step
from ferl.replay import new_replay, store_episode
from test_fast_path import episodes
from test_recurrent_q import actor, padded_batch


def with_replay(agent, batch: dict) -> None:
    """The batch's episodes (R, B, …) stored as the replay's first B episodes."""
    episodes = [{k: v[:, b] for k, v in batch.items()} for b in range(batch["lengths"].shape[1])]
    agent.replay = new_replay(episodes[0], 8)
    for b, one in enumerate(episodes):
        store_episode(agent.replay, b, one)
    agent.episodes = len(episodes)


@pytest.mark.parametrize("head,memory", [("linear", "gru"), ("free_energy", "lstm"), ("expected_energy", "esn")])
def test_the_replay_step_equals_the_eager_adam_step(head, memory):
    """Three Adam steps on replayed padded episodes: ``replay_step`` (run eagerly here; compiled
    it is the same function) against ``adam_step``, from equal actors drawing equal episodes."""
    reference, fast = actor(head, memory, seed=5), actor(head, memory, seed=5)
    for agent in (reference, fast):
        for name in agent.names:  # a target network that differs from the online one
            getattr(agent, f"{name}_target").mul_(0.9)
        with_replay(agent, padded_batch(T=5, B=4, seed=1))
    lr = 0.03
    for k in range(1, 4):
        reference.adam_step(reference.sample(), lr)
        replay_step(fast, fast.draw(), *adam_scalars(lr, k, torch.device("cpu")))
        for name in reference.names:
            torch.testing.assert_close(getattr(fast, name), getattr(reference, name), rtol=1e-5, atol=1e-7, msg=name)
            for moment in ("_m", "_v"):
                torch.testing.assert_close(getattr(fast, name + moment), getattr(reference, name + moment))
    moved = [not torch.equal(getattr(fast, n), getattr(fast, n + "_target") / 0.9) for n in fast.names]
    assert any(moved)  # the steps moved the parameters (the comparison is not of untouched ones)


@pytest.mark.parametrize("head,memory", [("linear", "gru"), ("free_energy", "lstm")])
def test_the_compiled_replay_in_chunks_equals_the_eager_adam_step_at_every_length(head, memory):
    """The fast path's replay step (``compile_updates``: the BPTT in compiled chunks of
    CHUNK_STEPS steps, the Adam update compiled) against ``adam_step`` eagerly, two steps each at
    T_max of 11, 51 and 201: episodes longer than a chunk, the last chunk padded, and one graph of
    each kind for all three lengths (the chunks' shapes do not depend on T_max)."""
    from torch._dynamo.utils import counters

    from ferl import compiled as fast

    torch._dynamo.reset()
    graphs = []
    for T in (11, 51, 201):
        reference, compiled = actor(head, memory, seed=3), actor(head, memory, seed=3)
        compiled.compile_updates(torch.device("cpu"))
        for agent in (reference, compiled):
            for name in agent.names:
                getattr(agent, f"{name}_target").mul_(0.9)
            with_replay(agent, padded_batch(T=T, B=3, seed=T))
        for k in range(1, 3):
            reference.adam_step(reference.sample(), 0.03)
            compiled.adam_steps += 1
            compiled.fast_update(compiled, compiled.draw(), *adam_scalars(0.03, k, torch.device("cpu")))
        for name in reference.names:
            torch.testing.assert_close(
                getattr(compiled, name), getattr(reference, name), rtol=1e-4, atol=1e-6, msg=name
            )
        graphs.append(counters["stats"]["unique_graphs"])
    assert T > 2 * fast.CHUNK_STEPS and T % fast.CHUNK_STEPS  # several chunks, the last one padded
    assert graphs[0] > 0 and graphs[0] == graphs[-1]  # 51 and 201 compiled nothing new


def test_the_transformers_compiled_replay_loss_and_gradient_equal_eager_ones():
    """The transformer core has no loop over time: on the fast path its whole loss is one graph
    (``compile_updates``). Its value and gradient at T_max = 11 against the eager ``loss``'s.
    (Gradients, not Adam steps: the key bias's gradient is zero up to rounding, softmax being
    blind to it, and Adam's m / √v turns rounding noise into steps of size α.)"""
    torch._dynamo.reset()
    agent = actor("linear", "transformer", seed=4, context=12, heads=2)
    agent.compile_updates(torch.device("cpu"))
    assert agent.chunk is None and agent.replay_loss != agent.loss  # the loss is compiled whole
    batch = padded_batch(T=11, B=3, seed=2)
    p = agent.params()

    def value_and_gradient(loss):
        trained = {name: p[name].detach().clone().requires_grad_() for name in agent.names}
        value = loss({**p, **trained}, batch)
        return value, torch.autograd.grad(value, tuple(trained.values()))

    value, grads = value_and_gradient(agent.replay_loss)
    eager_value, eager_grads = value_and_gradient(agent.loss)
    torch.testing.assert_close(value, eager_value, rtol=1e-5, atol=1e-6)
    for name, g, eager in zip(agent.names, grads, eager_grads):
        torch.testing.assert_close(g, eager, rtol=1e-4, atol=1e-6, msg=name)
    assert any(float(g.abs().max()) > 1e-3 for g in eager_grads)  # a gradient that is not all zero


DRQN_TINY = (
    "experiment=table4_1_matching",
    "actor=drqn",
    "predictor=none",
    "n_runs=3",
    "trainer.n_sample=10",
    "trainer.n_episodes=80",
    "trainer.log_every=20",
    "trainer.td_sample_every=10",
    "trainer.final_window=20",
    "actor.batch_episodes=4",
)


def test_compiled_drqn_equals_eager(tmp_path, capsys):
    """DRQN at reduced scale, compile=true against compile=false: both graphs compiled (no
    warning that one runs eagerly), the same steps in every episode of every run, returns and
    TD errors within float32 rounding."""
    eager_summary, eager = episodes(tmp_path, "eager", "compile=false", tiny=DRQN_TINY)
    summary, fast = episodes(tmp_path, "fast", "compile=true", tiny=DRQN_TINY)
    assert "cannot be compiled" not in capsys.readouterr().err
    assert summary["compile_time_s"] > 0  # the compiled functions ran (their first calls timed)
    assert summary["metrics"]["env_steps_total"] == eager_summary["metrics"]["env_steps_total"]
    for key in ("steps", "correct_goal"):
        np.testing.assert_array_equal(fast[key], eager[key], err_msg=key)
    for key in ("discounted_return", "terminal_reward", "td_abs_mean", "td_sampled"):
        np.testing.assert_allclose(fast[key], eager[key], rtol=1e-4, atol=1e-5, err_msg=key)


PASSIVE_TINY = (
    "experiment=passive_tmaze",
    "trainer=algorithm1",
    "actor=drqn",
    "predictor=none",
    "n_runs=2",
    "trainer.n_episodes=6",
    "trainer.log_every=3",
    "trainer.td_sample_every=2",
    "trainer.final_window=3",
    "actor.batch_episodes=2",
)


@pytest.mark.parametrize("corridor", [10, 50, 200])
def test_compiled_episodes_equal_eager_ones_at_every_length(tmp_path, capsys, corridor):
    """The passive maze at T_max = L + 1 of 11, 51 and 201, longer than one graph's CHUNK_STEPS
    steps (the last chunk padded past T_max): compile=true against compile=false, every graph
    compiled (no warning that one runs eagerly), the same steps and goals in every episode of
    every run, returns and TD errors within float32 rounding."""
    from conftest import train_job, validated_config

    def run(name: str, compile: bool) -> tuple[dict, dict]:
        config = validated_config([*PASSIVE_TINY, f"env.corridor_length={corridor}", f"compile={compile}"])
        summary = train_job(config, tmp_path / name)
        with np.load(tmp_path / name / "records" / "episodes.npz") as ep:
            return summary, dict(ep)

    _, eager = run("eager", False)
    summary, fast = run("fast", True)
    assert "eagerly" not in capsys.readouterr().err
    assert summary["compile_time_s"] > 0
    assert eager["td_sampled"].shape[-1] == corridor + 1
    for key in ("steps", "correct_goal"):
        np.testing.assert_array_equal(fast[key], eager[key], err_msg=key)
    for key in ("discounted_return", "terminal_reward", "td_abs_mean", "td_sampled"):
        np.testing.assert_allclose(fast[key], eager[key], rtol=1e-4, atol=1e-5, err_msg=key)
