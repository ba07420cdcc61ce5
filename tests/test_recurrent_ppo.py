"""baselines/recurrent_ppo.py (the optional sb3-contrib RecurrentPPO baseline): its run directory
holds what CONTRACT §2 and docs/records.md promise, its episode records are ones the regular T-maze
can produce, and analyze.py puts it beside a ferl run of the same maze in a sweep's "Agents side by
side" table; on an outside Gymnasium id (tests/outside_env.py) it describes the environment as
ferl's ``env=gymnasium`` does and records episodes the environment can produce; bad input is one
line. Skipped without sb3-contrib (`pip install -e '.[baselines]'`)."""

import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

pytest.importorskip("sb3_contrib")

from conftest import ROOT, compose_config, train_job
from ferl.analysis.records import Manifest
from ferl.envs.gymnasium_vector import GymnasiumEnv
from ferl.run.directory import RunDir
from reproduction.variants import VIEW_KEYS

GAMMA, T_MIN, T_MAX, GOAL = 0.95, 3, 10, 5.0
STEP, WALL = -0.1, -1.0
SEEDS = [3, 4]
MAZE = [
    "experiment=table4_1_regular",
    "n_runs=2",
    "trainer.n_sample=300",
    "trainer.n_epoch=2",
    "trainer.n_episodes=60",
    "trainer.final_window=20",
    "trainer.log_every=20",
]
TMAZE_METRICS = (
    "final_discounted_return",
    "final_steps_to_goal",
    "final_correct_goal_rate",
    "solved",
    "env_steps_total",
    "env_steps_to_solve",
)


# CueRecall (tests/outside_env.py) with MultiDiscrete actions: 3-step episodes, −0.1, −0.1, then ±1
TESTS = ROOT / "tests"
sys.path.insert(0, str(TESTS))  # GymnasiumEnv below imports outside_env, as the script does
CUE, CUE_KWARGS, CUE_GAMMA = "outside_env:CueRecall-v0", {"delay": 2, "grid_actions": True}, 0.9
CUE_SETTINGS = {"optimal_return": 0.8, "success_threshold": 0.0}


def run_script(*args, env=None):
    return subprocess.run(
        [sys.executable, str(ROOT / "baselines" / "recurrent_ppo.py"), *args],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A sweep folder: the baseline (2 runs, ~2 000 steps) and a tiny ferl run of the same maze, analysed."""
    root = tmp_path_factory.mktemp("ppo_sweep")
    done = run_script(
        "--env-id",
        "ferl/TMaze-v0",
        "--env-kwargs",
        json.dumps({"corridor_length": T_MIN}),
        "--runs",
        "2",
        "--seed",
        str(SEEDS[0]),
        "--steps",
        "2000",
        "--n-envs",
        "4",
        "--out",
        str(root / "ppo"),
    )
    assert done.returncode == 0, done.stderr
    ferl_run = RunDir(root / "ferl")
    ferl_run.write_summary(train_job(compose_config(MAZE), ferl_run.path))
    analysis = subprocess.run(
        [sys.executable, str(ROOT / "analyze.py"), str(root)], capture_output=True, text=True, timeout=300
    )
    assert analysis.returncode == 0, analysis.stderr
    return root, done.stdout


def reachable_returns(k: int, terminal: float) -> np.ndarray:
    """Every discounted return of a k-step episode whose last reward is ``terminal``: each earlier
    step a move (−0.1) or a wall bump (−1)."""
    head = np.zeros(1)
    for t in range(k - 1):
        head = np.concatenate([head + GAMMA**t * STEP, head + GAMMA**t * WALL])
    return head + GAMMA ** (k - 1) * terminal


def test_summary_has_the_contract_keys_one_value_per_seed(sweep):
    root, stdout = sweep
    summary = json.loads((root / "ppo" / "summary.json").read_text())
    assert (summary["experiment"], summary["task"], summary["seeds"]) == ("recurrent_ppo", "tmaze", SEEDS)
    for name in TMAZE_METRICS:
        assert len(summary["metrics"][name]) == len(SEEDS), name
    assert summary["optimal"]["discounted_return"] == pytest.approx(4.3175)  # CONTRACT §2
    assert summary["wall_time_s"] > 0 and summary["agent_steps_per_s"] > 0
    assert stdout.count("recurrent_ppo.py: run ") == len(SEEDS)  # one progress line per run


def test_episode_records_are_episodes_of_the_maze(sweep):
    root, _ = sweep
    ep = dict(np.load(root / "ppo" / "records" / "episodes.npz"))
    ret, steps, terminal = ep["discounted_return"], ep["steps"], ep["terminal_reward"]
    assert ret.shape == steps.shape == terminal.shape == ep["correct_goal"].shape == (2, ret.shape[1])
    assert ret.shape[1] > 100 and float(ep["gamma"]) == GAMMA and float(ep["optimal_steps"]) == T_MIN
    goal = np.abs(terminal) == GOAL
    np.testing.assert_array_equal(ep["correct_goal"], terminal == GOAL)
    assert np.all(steps[~goal] == T_MAX) and np.all((steps >= T_MIN) & (steps <= T_MAX))  # only cut-offs end elsewhere
    assert set(np.unique(ep["condition"])) <= {0, 1}
    for g, k, r in zip(terminal.ravel(), steps.ravel(), ret.ravel()):
        assert np.abs(reachable_returns(int(k), float(g)) - r).min() < 1e-4, (g, k, r)
    assert np.isnan(ep["td_abs_mean"]).all()

    summary = json.loads((root / "ppo" / "summary.json").read_text())["metrics"]
    np.testing.assert_allclose(summary["final_discounted_return"], ret[:, -200:].mean(1), rtol=1e-6)
    np.testing.assert_allclose(summary["final_correct_goal_rate"], ep["correct_goal"][:, -200:].mean(1))
    assert all(total >= max(2000, used) for total, used in zip(summary["env_steps_total"], steps.sum(1)))


def test_the_run_is_grouped_with_ferls_run_of_the_same_maze(sweep):
    root, _ = sweep
    ppo, ferl_run = Manifest.load(root / "ppo"), Manifest.load(root / "ferl")
    assert ppo.env == ferl_run.env
    assert (ppo.trainer["kind"], ppo.actor["kind"], ppo.predictors) == ("external", "recurrent_ppo", {})
    assert (root / "ppo" / "analysis" / "learning_curves.png").is_file()
    with open(root / "analysis" / "agents_side_by_side.csv") as f:
        rows = list(csv.DictReader(f))
    tasks = {r["task"] for r in rows if "trainer=external" in r["agent"]}
    assert len(tasks) == 1 and any(r["agent"] == "dissertation agent" for r in rows if r["task"] in tasks)
    rate = next(r for r in rows if "trainer=external" in r["agent"] and r["metric"] == "final_correct_goal_rate")
    summary = json.loads((root / "ppo" / "summary.json").read_text())["metrics"]
    assert float(rate["mean"]) == pytest.approx(np.mean(summary["final_correct_goal_rate"]), rel=1e-5)
    assert int(rate["n"]) == len(SEEDS)


def test_a_directory_holding_a_run_is_refused(sweep):
    root, _ = sweep
    done = run_script("--env-id", "ferl/TMaze-v0", "--steps", "10", "--out", str(root / "ppo"))
    assert done.returncode == 2 and "already holds a run" in done.stderr


@pytest.fixture(scope="module")
def cue(tmp_path_factory):
    """The baseline on an id that nothing in ferl names (2 runs of 2 048 steps, a few seconds)."""
    out = tmp_path_factory.mktemp("ppo_cue") / "ppo"
    done = run_script(
        "--env-id",
        CUE,
        "--env-kwargs",
        json.dumps(CUE_KWARGS),
        "--runs",
        "2",
        "--steps",
        "2048",
        "--n-envs",
        "2",
        "--gamma",
        str(CUE_GAMMA),
        "--optimal-return",
        "0.8",
        "--success-threshold",
        "0",
        "--out",
        str(out),
        env={**os.environ, "PYTHONPATH": str(TESTS)},
    )
    assert done.returncode == 0, done.stderr
    return out, done.stdout


def test_a_gymnasium_id_is_described_as_ferl_describes_it(cue):
    out, stdout = cue
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["experiment"], summary["task"]) == ("recurrent_ppo", "gymnasium")
    assert summary["optimal"] == {"return": 0.8}
    assert {"final_return", "final_success_rate", "solved", "env_steps_total"} <= set(summary["metrics"])
    assert summary["metrics"]["env_steps_total"] == [2048, 2048]
    assert stdout.count("mean return over the last 200") == 2  # one progress line per run
    manifest = Manifest.load(out)
    ferl_env = GymnasiumEnv(1, torch.Generator(), 0, id=CUE, kwargs=CUE_KWARGS, **CUE_SETTINGS)
    ferl_env.close()
    assert manifest.env["class"] == "ferl.envs.gymnasium_vector.GymnasiumEnv"
    task = {k: v for k, v in ferl_env.describe().items() if k not in VIEW_KEYS}
    assert {k: v for k, v in manifest.env.items() if k not in (*VIEW_KEYS, "class")} == task
    assert (manifest.task, manifest.actor["gamma"], manifest.env["n_actions"]) == ("gymnasium", CUE_GAMMA, 6)
    overrides = (out / ".hydra" / "overrides.yaml").read_text()
    assert "env.optimal_return=0.8" in overrides and "gamma=0.9" in overrides


def test_gymnasium_records_are_episodes_of_the_environment(cue):
    out, _ = cue
    ep = dict(np.load(out / "records" / "episodes.npz"))
    ret, steps = ep["return"], ep["steps"]
    assert ret.shape == steps.shape == ep["success"].shape == (2, ret.shape[1]) and ret.shape[1] > 200
    assert np.all(steps == 3) and set(np.unique(ep["terminal_reward"])) <= {-1.0, 1.0}
    np.testing.assert_allclose(ret, -0.2 + ep["terminal_reward"], atol=1e-6)  # raw rewards, undiscounted
    np.testing.assert_allclose(
        ep["discounted_return"], -0.1 - 0.1 * CUE_GAMMA + CUE_GAMMA**2 * ep["terminal_reward"], atol=1e-6
    )
    np.testing.assert_array_equal(ep["success"], ret > 0)
    assert float(ep["gamma"]) == CUE_GAMMA and np.isnan(ep["optimal_return"]) and np.isnan(ep["optimal_steps"])
    assert np.isnan(ep["td_abs_mean"]).all()
    metrics = json.loads((out / "summary.json").read_text())["metrics"]
    np.testing.assert_allclose(metrics["final_return"], ret[:, -200:].mean(1), rtol=1e-6)
    np.testing.assert_allclose(metrics["final_success_rate"], ep["success"][:, -200:].mean(1))


@pytest.mark.parametrize(
    "args, names",
    [
        (["--env-id", "Pendulum-v1"], "action space Box"),
        (["--env-id", "outside_env:Nope-v0"], "--env-id"),
        (["--env-id", "CartPole-v1", "--encoding", "onehot"], "--encoding"),  # a Box: no one-hot code
        (["--env-id", "ferl/TMaze-v0", "--optimal-return", "1"], "Gymnasium ids"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, args, names):
    out = tmp_path / "ppo"
    done = run_script(*args, "--steps", "100", "--out", str(out), env={**os.environ, "PYTHONPATH": str(TESTS)})
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and lines[0].startswith("recurrent_ppo.py: error:"), done.stderr
    assert names in lines[0] and not out.exists()
