"""``predictor=none`` (CONTRACT §2): the FERL actor on the current observation only — the lower
bound that shows what memory buys. At reduced scale on the matching T-maze it learns to end its
episodes in a goal, but which goal is rewarded depends on the signal at the start, which it
cannot see at the junction: it stays near chance on that."""

import json

import numpy as np

from conftest import run_train


def test_memoryless_agent_finds_goals_but_not_the_rewarded_one(tmp_path):
    run_dir = tmp_path / "run"
    result = run_train(
        "experiment=table4_1_matching",
        "predictor=none",
        "n_runs=4",
        "trainer.n_episodes=3000",
        f"hydra.run.dir={run_dir}",
    )
    assert result.returncode == 0, result.stderr[-2000:]
    manifest = json.loads((run_dir / "records" / "run.json").read_text())
    assert manifest["predictors"] == {} and manifest["trainer"]["phases"] == ["actor"]  # no data to collect
    summary = json.loads((run_dir / "summary.json").read_text())
    with np.load(run_dir / "records" / "episodes.npz") as episodes:
        steps, terminal = episodes["steps"], episodes["terminal_reward"]
        correct = episodes["correct_goal"][:, -200:]
    # every step the run took was an actor step: no random collection
    np.testing.assert_array_equal(summary["metrics"]["env_steps_total"], steps.sum(1))
    reached, early = np.abs(terminal[:, -200:]) == 5.0, np.abs(terminal[:, :200]) == 5.0
    assert (
        reached.mean() > early.mean() + 0.25
    )  # (0.53 → 0.89) it learnt to walk to a goal (at β ≈ 0 at first: a random walk)
    rate = correct[reached].mean()
    assert 0.25 <= rate <= 0.75  # it cannot tell which goal the hidden start signal rewards
