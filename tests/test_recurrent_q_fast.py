"""The recurrent Q-learner's fast path (ferl/actors/recurrent_q_fast.py, docs/performance.md): its
replay step (torch.func.grad of the loss, then Adam with the step sizes as tensors) equals the
eager reference ``adam_step`` (autograd.grad, the written-out Adam), and DRQN trained with
``compile=true`` (the replay step and the whole episode each one compiled graph) takes the same
actions as ``compile=false``, its returns and TD errors within float32 rounding. Resume and
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


def test_episodes_too_long_to_compile_run_eagerly_with_one_warning(tmp_path, capsys, monkeypatch):
    """Episodes of more than MAX_UNROLLED_STEPS steps (patched down to 8; the matching maze's
    T_max is 10): one warning naming T_max, nothing compiled, the eager run's numbers exactly."""
    from ferl import compiled

    monkeypatch.setattr(compiled, "MAX_UNROLLED_STEPS", 8)
    tiny = (*DRQN_TINY, "trainer.n_episodes=20")
    _, eager = episodes(tmp_path, "eager", "compile=false", tiny=tiny)
    capsys.readouterr()
    summary, long = episodes(tmp_path, "long", "compile=true", tiny=tiny)
    lines = [line for line in capsys.readouterr().err.splitlines() if "too long to compile" in line]
    assert len(lines) == 1 and "T_max = 10 " in lines[0]
    assert summary["compile_time_s"] == 0
    for key in ("discounted_return", "td_abs_mean", "steps"):
        np.testing.assert_array_equal(long[key], eager[key], err_msg=key)
