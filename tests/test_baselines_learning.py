"""The baseline agents learn (issue 4/8), at reduced scale through train.py with the configs that
`make baselines` runs: each clearly above what memoryless FERL reaches on the matching T-maze
(correct-goal rate near chance, tests/test_memoryless.py), the oracle at the optimum."""

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, run_train, validated_config


def run_analyze(path):
    return subprocess.run(
        [sys.executable, str(ROOT / "analyze.py"), str(path)], cwd=ROOT, capture_output=True, text=True, timeout=300
    )


def train(run_dir, *overrides) -> dict:
    result = run_train(*overrides, "n_runs=2", f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads((run_dir / "summary.json").read_text())


def manifest(run_dir) -> dict:
    return json.loads((run_dir / "records" / "run.json").read_text())


def test_oracle_solves_the_matching_maze_on_its_true_state(tmp_path):
    summary = train(
        tmp_path / "run", "experiment=table4_1_matching", "actor=oracle", "predictor=none", "trainer.n_episodes=1500"
    )
    facts = manifest(tmp_path / "run")
    assert facts["env"]["true_state"] and facts["env"]["observation_size"] == (3 + 2) * 4
    assert facts["actor"]["kind"] == "tabular_q"
    assert summary["metrics"]["solved"] == [1, 1]
    np.testing.assert_allclose(
        summary["metrics"]["final_discounted_return"], summary["optimal"]["discounted_return"], rtol=1e-5
    )


def test_oracle_on_the_floor_earns_near_the_optimal_rate_without_the_image_tests(tmp_path):
    summary = train(
        tmp_path / "run",
        "experiment=ch3_floor",
        "actor=oracle",
        "actor.gamma=0.9",
        "actor.beta.end=2",
        "env.patches=4",
        "trainer.steps=15000",
    )
    # a uniformly random walk earns < 1 a step here; the optimal policy 8
    assert min(summary["metrics"]["reward_per_step_last10pct"]) > 0.85 * summary["optimal"]["reward_per_step"]
    assert "greedy_accuracy" not in summary["metrics"]  # no test images for a true-state view
    assert not (tmp_path / "run" / "records" / "floor_test.npz").exists()
    result = run_analyze(tmp_path / "run")  # the generic figures only: no test images to draw
    assert result.returncode == 0, result.stderr[-2000:]
    assert (tmp_path / "run" / "analysis" / "report.md").is_file()


def test_drqn_remembers_the_signal_of_the_matching_maze(tmp_path):
    summary = train(
        tmp_path / "run", "experiment=table4_1_matching", "actor=drqn", "predictor=none", "trainer.n_episodes=2500"
    )
    assert manifest(tmp_path / "run")["predictors"] == {}
    assert np.mean(summary["metrics"]["final_correct_goal_rate"]) >= 0.9  # memoryless: ≈ 0.5


def test_mlp_q_on_the_elman_memory_learns_the_regular_maze(tmp_path):
    """With a briefly trained Elman predictor (150 epochs; on the matching maze MLP-Q needs the
    full 400 of Table 4.1, 75 s here), on the regular maze, whose start signal a memoryless agent
    cannot see at the junction either."""
    summary = train(
        tmp_path / "run", "experiment=table4_1_regular", "actor=mlp_q", "trainer.n_epoch=150", "trainer.n_episodes=3000"
    )
    assert manifest(tmp_path / "run")["actor"]["kind"] == "mlp_q"
    assert np.mean(summary["metrics"]["final_correct_goal_rate"]) >= 0.9  # memoryless: ≈ 0.5


@pytest.mark.parametrize(
    "overrides, key",
    [
        (("experiment=ch3_floor", "actor=drqn"), "actor=drqn"),  # a continuing task has no episodes
        (("experiment=large_action", "actor=oracle"), "env.true_state"),  # no true-state view there
    ],
)
def test_a_baseline_where_it_cannot_run_is_one_clear_line(tmp_path, overrides, key):
    run_dir = tmp_path / "run"
    result = run_train(*overrides, "n_runs=1", f"hydra.run.dir={run_dir}")
    assert result.returncode != 0
    message = result.stderr.strip().splitlines()
    assert len(message) == 1 and key in message[0], result.stderr[-1000:]
    assert not run_dir.exists()


def test_every_job_of_make_baselines_composes_and_validates():
    """The job table of baselines/side_by_side.py: each composes to the agent it names, and
    passes the checks train.py makes before any work."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("side_by_side", ROOT / "baselines" / "side_by_side.py")
    side_by_side = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(side_by_side)
    jobs = side_by_side.train_jobs()
    expected = {
        "ferl": "FERLActor",
        "memoryless": "FERLActor",
        "mlp_q": "MLPQActor",
        "drqn": "RecurrentQActor",
        "oracle": "TabularQActor",
    }
    assert {name.split("/")[0] for name in jobs} == {"floor", "matching", "bit", "pixel", "corridor20"}
    for name, overrides in jobs.items():
        cfg = validated_config(overrides)
        agent = name.split("/")[1]
        assert cfg.actor._target_.endswith(expected[agent]), name
        assert (not cfg.get("predictor")) == (agent in ("memoryless", "drqn", "oracle") or name.startswith("floor")), (
            name
        )
        assert bool(cfg.env.get("true_state")) == (agent == "oracle"), name
