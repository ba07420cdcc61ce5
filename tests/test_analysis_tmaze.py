"""T-maze analysis (chapter 4): the numbers against direct re-implementations, and
analyze.py end to end on synthetic runs whose truth is known (tests/synthetic_runs.py)."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from ferl.analysis import coding, tmaze
from ferl.analysis.report import HELD, NOT_HELD, TMAZE_CLAIMS, evaluate
from synthetic_runs import assert_analysis_outputs, make_floor_run, make_tmaze_run
from test_analyze_cli import analyze, event_files

FIGURES = ["prediction_errors_joint", "learning_curves", "td_errors",
           *(f"junction_{layer}_{kind}" for layer in ("memory_joint", "state", "hidden")
             for kind in ("activations", "pca")), "junction_hidden_pca3d"]
DATA = ["learning_curves.csv", "prediction_errors_joint.csv", "junction_separation.csv",
        "junction_explained_variance.csv", "claims.json"]
HIDDEN_CLAIM = "§4.3.2, Figs. 4.17–4.19"


# ---- numbers -------------------------------------------------------------------

def silhouette_loop(x: np.ndarray, labels: np.ndarray) -> float:
    """Rousseeuw's definition, one point at a time."""
    s = []
    for i in range(len(x)):
        d = np.linalg.norm(x - x[i], axis=1)
        own = (labels == labels[i]) & (np.arange(len(x)) != i)
        if not own.any():
            s.append(0.0)
            continue
        a = d[own].mean()
        b = min(d[labels == c].mean() for c in set(labels.tolist()) if c != labels[i])
        s.append((b - a) / max(a, b))
    return float(np.mean(s))


def test_silhouette_matches_direct_loop():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3)) + np.repeat(np.eye(3) * 2, [15, 15, 10], axis=0)
    labels = np.repeat([0, 1, 2], [15, 15, 10])
    labels[-1] = 7  # a singleton cluster scores 0
    assert coding.silhouette_score(x, labels) == pytest.approx(silhouette_loop(x, labels), abs=1e-12)


def test_silhouette_known_cases():
    rng = np.random.default_rng(1)
    labels = np.repeat([0, 1, 2, 3], 100)
    centres = 10 * np.eye(4)[:, :3]
    separated = centres[labels] + rng.normal(0, 0.1, (400, 3))
    assert coding.silhouette_score(separated, labels) > 0.95
    same = rng.normal(size=(400, 3))
    assert abs(coding.silhouette_score(same, labels)) < 0.05
    assert np.isnan(coding.silhouette_score(same, np.zeros(400)))
    assert coding.silhouette_score(np.zeros((4, 2)), [0, 0, 1, 1]) == 0.0


def test_moving_average_curve_matches_loop():
    values = np.random.default_rng(2).normal(size=(3, 50))
    episodes, mean, sem = tmaze.curve(values, window=7)
    ma = np.array([[values[r, k - 7:k].mean() for k in range(7, 51)] for r in range(3)])
    np.testing.assert_array_equal(episodes, np.arange(7, 51))
    np.testing.assert_allclose(mean, ma.mean(axis=0))
    np.testing.assert_allclose(sem, ma.std(axis=0, ddof=1) / np.sqrt(3))


def test_pca_scores_and_explained_variance():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(200, 2)) @ np.array([[3.0, 0, 0, 0], [0, 1.0, 0, 0]]) + 5
    scores, ratio = coding.pca(x)
    assert scores.shape == (200, 3) and ratio.shape == (4,)
    assert ratio.sum() == pytest.approx(1.0) and ratio[0] > 0.85 and ratio[2:].max() < 1e-20
    np.testing.assert_allclose(scores.var(axis=0) / x.var(axis=0).sum(), ratio[:3], atol=1e-12)


# ---- runs ------------------------------------------------------------------------

def claim_verdicts(run_dir: Path) -> dict[str, str]:
    return {c["source"]: c["verdict"]
            for c in json.loads((run_dir / "analysis" / "claims.json").read_text())}


def check_outputs(run_dir: Path) -> None:
    report = assert_analysis_outputs(run_dir, FIGURES, DATA)
    assert report.startswith("# T-maze (matching)")
    for name in [*FIGURES, *DATA]:
        assert f"]({name}" in report, name
    assert event_files(run_dir)


def check_synthetic_truth(run_dir: Path) -> None:
    verdicts = claim_verdicts(run_dir)
    assert verdicts[HIDDEN_CLAIM] == HELD
    assert verdicts["§4.3.2, Fig. 4.14; §4.3.3"] == HELD       # memory keeps the signal
    assert verdicts["§4.3.2, Fig. 4.11"] == HELD               # solved in all runs
    assert verdicts["§4.3.2, Fig. 4.10"] == HELD               # predictor learns, generalises
    assert not any(source.startswith("§4.3.1") for source in verdicts)  # regular-only claims
    with (run_dir / "analysis" / "junction_separation.csv").open() as f:
        rows = {(r["layer"], r["labels"], r["phase"]): float(r["silhouette_mean"])
                for r in csv.DictReader(f)}
    assert rows["hidden", "condition", "first"] < 0.1 < 0.7 < rows["hidden", "condition", "last"]
    assert rows["memory_joint", "initial_signal", "first"] > 0.7
    with (run_dir / "analysis" / "learning_curves.csv").open() as f:
        last = list(csv.DictReader(f))[-1]
    assert float(last["discounted_return_ma200_mean"]) == pytest.approx(4.3175, abs=1e-3)


def test_analyze_sweep_of_a_floor_and_a_tmaze_run(tmp_path):
    # One analyze.py call, as its start-up dominates the time.
    sweep = tmp_path / "sweep"
    runs = [make_floor_run(sweep / "floor"), make_tmaze_run(sweep / "nested" / "tmaze")]
    result = analyze(sweep)
    assert result.returncode == 0, result.stderr
    top = (sweep / "analysis" / "report.md").read_text()
    for run in runs:
        assert f"]({Path('..', run.relative_to(sweep), 'analysis', 'report.md')})" in top
    assert "| tmaze | analyzed |" in top and "| digit_floor | analyzed |" in top
    check_outputs(runs[1])
    check_synthetic_truth(runs[1])


def test_shuffled_hidden_activations_do_not_separate(tmp_path):
    run = tmaze.TMazeRun.load(make_tmaze_run(tmp_path / "run", hidden="shuffled"))
    verdicts = {r.claim.source: r.verdict for r in evaluate(TMAZE_CLAIMS, run)}
    assert verdicts[HIDDEN_CLAIM] == NOT_HELD
    assert abs(np.nanmean(run.separation["hidden", "condition"])) < 0.1


def test_regular_maze_gets_its_own_claims_and_steps_from_episodes(tmp_path):
    run = tmaze.TMazeRun.load(make_tmaze_run(tmp_path / "run", matching=False,
                                             steps_to_goal=False))
    sources = {r.claim.source for r in evaluate(TMAZE_CLAIMS, run)}
    assert "§4.3.1, Fig. 4.6" in sources and HIDDEN_CLAIM not in sources
    j = run.junction
    np.testing.assert_array_equal(run.steps_to_goal, run.episodes["steps"][j["run"], j["episode"]])
    assert run.condition_names == ["0", "1"]


def test_two_predictors_and_memories_of_chapter_5(tmp_path):
    run = tmaze.TMazeRun.load(make_tmaze_run(tmp_path / "run", predictors=("obs", "reward"),
                                             memory_keys=("memory_obs", "memory_reward")))
    assert run.predictors == ["obs", "reward"]
    assert run.layers == ["memory_obs", "memory_reward", "state", "hidden"]
    assert {(m, "initial_signal") for m in ("memory_obs", "memory_reward")} <= set(run.separation)
    figures = tmaze.make_figures(run)
    assert {"prediction_errors_obs", "prediction_errors_reward",
            "junction_memory_reward_pca"} <= set(figures)
    # Chapter-5 figure numbers; names the dissertation does not use get the whole figure.
    assert run.numbering is tmaze.CH5_BIT
    assert figures["prediction_errors_obs"][1].startswith("Fig. 5.2: ")
    assert figures["prediction_errors_reward"][1].startswith("Fig. 5.2(b): squared error")
    assert figures["junction_memory_obs_pca"][1].startswith("Figs. 5.7–5.8(b): ")
    # chapter-4 claims are about the joint predictor
    assert not any(r.claim.source.startswith("§4") for r in evaluate(TMAZE_CLAIMS, run))
