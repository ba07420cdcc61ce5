"""Sallans & Hinton (2004)'s large-action task: rewards against a brute-force reading of the task,
run views and checkpoints, the experiment end to end, and learning at reduced scale."""

import json

import numpy as np
import torch

from conftest import run_train
from ferl.bits import to_bits
from ferl.envs.large_action import LargeActionTask


def make_task(R=3, **kw):
    return LargeActionTask(R, torch.Generator().manual_seed(0), seed=11, **kw)


def brute_force_reward(keys, key_actions, s, bits):
    """The task's definition, one run at a time in NumPy: the first key state at the least
    Hamming distance from s, then the action bits that agree with its key action."""
    distances = [int(np.abs(s - k).sum()) for k in keys]
    nearest = distances.index(min(distances))
    return int((bits == key_actions[nearest]).sum())


def test_rewards_follow_the_definition():
    task = make_task(R=3)
    g = torch.Generator().manual_seed(1)
    for _ in range(50):
        s = task.state.clone()
        action = torch.randint(2**40, (3,), generator=g)
        _, reward, terminated, _ = task.step(action)
        assert not terminated.any()
        bits = to_bits(action, 40).numpy()
        for r in range(3):
            want = brute_force_reward(task.keys[r].numpy(), task.key_actions[r].numpy(), s[r].numpy(), bits[r])
            assert reward[r].item() == want


def test_key_actions_earn_the_optimum_and_states_are_uniform():
    task = make_task(R=2)
    keys, key_actions = task.keys, task.key_actions
    index = (key_actions * 2 ** torch.arange(39, -1, -1).double()).sum(-1).long()  # the key actions as indices
    for j in range(keys.shape[1]):
        assert torch.equal(task.reward(keys[:, j], index[:, j]), torch.full((2,), 40.0))
    assert task.optimal(0.0) == {"reward_per_step": 40.0, "random_reward_per_step": 20.0}
    states = torch.cat(task.step_inputs(4000)).view(-1, 12)
    assert abs(states.mean().item() - 0.5) < 0.01
    # each run draws its own keys from seed + r: run 1 of a 2-run batch is run 1 of a 3-run one
    assert torch.equal(make_task(R=3).keys[1], keys[1]) and not torch.equal(keys[0], keys[1])


def test_key_state_reading_draws_only_key_states():
    task = make_task(R=2, states="key_states")
    states = task.step_inputs(200)[0]
    for r in range(2):
        assert (states[:, r].unsqueeze(1) == task.keys[r]).all(-1).any(-1).all()


def test_run_views_and_state_dict():
    task = make_task(R=4)
    part = task.slice_runs(slice(1, 3))
    next_states = task.step_inputs(1)[0][0]
    part.step_with(torch.zeros(2, dtype=torch.long), next_states[1:3])
    assert torch.equal(task.state[1:3], next_states[1:3])  # the view moved the batch
    saved = {k: v.clone() if torch.is_tensor(v) else v for k, v in task.state_dict().items()}
    ahead = task.step_inputs(5)[0]
    task.load_state_dict(saved)
    assert torch.equal(task.step_inputs(5)[0], ahead)


def test_large_action_experiment_learns_at_reduced_scale(tmp_path):
    """3 runs × 4 000 steps, 20 Gibbs sweeps: every run's reward over the last 10 % of its steps is
    above a random policy's 20 by more than 6 standard errors of that mean (400 steps, s.d. √10)."""
    run_dir = tmp_path / "run"
    result = run_train(
        "experiment=large_action", "n_runs=3", "trainer.steps=4000", "actor.gibbs_sweeps=20", f"hydra.run.dir={run_dir}"
    )
    assert result.returncode == 0, result.stderr[-2000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["task"] == "large_action" and summary["optimal"]["reward_per_step"] == 40.0
    rewards = np.load(run_dir / "records" / "steps.npz")["rewards"]
    assert rewards.shape == (3, 4000)
    last = summary["metrics"]["reward_per_step_last10pct"]
    np.testing.assert_allclose(rewards[:, -400:].mean(1), last, rtol=1e-6)
    assert min(last) > 20 + 6 * np.sqrt(10 / 400)
