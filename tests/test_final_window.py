"""``trainer.final_window`` is the one window of a run's final metrics: a tiny T-maze run trained
with ``final_window=5`` through train.py and analysed by analyze.py uses 5 episodes everywhere:
the summary's metrics, the records, the TensorBoard moving averages and the analysis's learning
curves and claims. Each is checked against a direct NumPy computation from the recorded episodes."""

import csv
import json

import numpy as np
import pytest

from conftest import run_train
from ferl import runs
from test_analyze_cli import analyze

W, N = 5, 40  # the window, and episodes per run: both far from the default window of 200
TINY = [
    "experiment=table4_1_matching",
    "n_runs=2",
    "trainer.n_sample=300",
    "trainer.n_epoch=2",
    f"trainer.n_episodes={N}",
    "trainer.log_every=10",
    "trainer.td_sample_every=10",
    f"trainer.final_window={W}",
]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp("window") / "run"
    done = run_train(*TINY, "compile=false", f"hydra.run.dir={path}")
    assert done.returncode == 0, done.stderr[-2000:]
    done = analyze(path)
    assert done.returncode == 0, done.stderr[-2000:]
    return path


@pytest.fixture(scope="module")
def episodes(run_dir) -> dict:
    with np.load(run_dir / "records" / "episodes.npz") as f:
        return dict(f)


def first_solved_window(returns: np.ndarray, correct: np.ndarray, optimum: float) -> int | None:
    """The 0-based last episode of the first window of W episodes with return ≥ 0.95 × optimum and
    correct-goal rate ≥ 0.95, by a plain loop."""
    for k in range(W - 1, len(returns)):
        window = slice(k - W + 1, k + 1)
        if returns[window].mean() >= 0.95 * optimum and correct[window].mean() >= 0.95:
            return k
    return None


def test_the_window_is_recorded(run_dir, episodes):
    assert int(episodes["final_window"]) == W
    assert json.loads((run_dir / "records" / "run.json").read_text())["trainer"]["final_window"] == W


def test_summary_metrics_are_over_the_last_w_episodes(run_dir, episodes):
    metrics = json.loads((run_dir / "summary.json").read_text())["metrics"]
    ret = episodes["discounted_return"].astype(np.float64)
    correct = episodes["correct_goal"].astype(np.float64)
    np.testing.assert_allclose(metrics["final_discounted_return"], ret[:, -W:].mean(1), rtol=1e-12)
    np.testing.assert_allclose(metrics["final_steps_to_goal"], episodes["steps"][:, -W:].mean(1), rtol=1e-12)
    np.testing.assert_allclose(metrics["final_correct_goal_rate"], correct[:, -W:].mean(1), rtol=1e-12)
    optimum = float(episodes["optimal_return"])
    solved = (ret[:, -W:].mean(1) >= 0.95 * optimum) & (correct[:, -W:].mean(1) >= 0.95)
    assert metrics["solved"] == solved.astype(int).tolist()
    for r in range(ret.shape[0]):
        k = first_solved_window(ret[r], correct[r], optimum)
        assert metrics["episodes_to_solve"][r] == (None if k is None else k + 1)
    # the test tells the windows apart: this run's last 5 episodes differ from its last 20 and all 40
    assert not np.allclose(ret[:, -W:].mean(1), ret[:, -20:].mean(1))


def test_tensorboard_moving_averages_are_over_w_episodes(run_dir, episodes):
    logged = runs.scalars(run_dir, tags=[f"actor/discounted_return_ma{W}", "actor/discounted_return_ma200"])
    assert set(logged["tag"]) == {f"actor/discounted_return_ma{W}"}
    by_step = logged.set_index("step")["value"]
    for done in range(10, N + 1, 10):
        want = episodes["discounted_return"][:, done - W : done].astype(np.float64).mean()
        assert by_step[done] == pytest.approx(want, rel=1e-6)


def test_analysis_curves_and_claims_use_the_recorded_window(run_dir, episodes):
    with (run_dir / "analysis" / "learning_curves.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["episode"]) for r in rows] == list(range(W, N + 1))
    ret = episodes["discounted_return"].astype(np.float64)
    for r in rows:
        k = int(r["episode"])
        assert float(r[f"discounted_return_ma{W}_mean"]) == pytest.approx(ret[:, k - W : k].mean(), rel=1e-5)
    td = episodes["td_abs_mean"].astype(np.float64)
    worst = (td[:, -W:].mean(1) / td[:, :W].mean(1)).max()
    claims = json.loads((run_dir / "analysis" / "claims.json").read_text())
    measured = [c["measured"] for c in claims if c["claim"].startswith("The TD error decreases")]
    assert len(measured) == 1
    assert f"over the first {W} episodes" in measured[0] and f"over the last {W} " in measured[0]
    assert measured[0].endswith(f"last ÷ first in the worst run {worst:.3f}")
