"""T-maze analysis (chapter 4): the numbers against direct re-implementations, and
analyze.py end to end on synthetic runs whose truth is known (tests/synthetic_runs.py)."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from ferl.analysis import coding, dispatch, generic
from ferl.analysis.claims import HELD, NOT_HELD, evaluate
from reproduction import ch5, tmaze
from reproduction.tmaze import TMazeRun
from synthetic_runs import assert_analysis_outputs, load_run, make_floor_run, make_tmaze_run
from test_analyze_cli import analyze, event_files

FIGURES = [
    "prediction_errors_joint",
    "learning_curves",
    "td_errors",
    *(f"junction_{layer}_{kind}" for layer in ("memory_joint", "state", "hidden") for kind in ("activations", "pca")),
    "junction_hidden_pca3d",
]
DATA = [
    "summary.csv",
    "learning_curves.csv",
    "prediction_errors_joint.csv",
    "junction_separation.csv",
    "junction_explained_variance.csv",
    "claims.json",
]
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
        s.append((b - a) / max(a, b) if max(a, b) > 0 else 0.0)
    return float(np.mean(s))


def test_silhouette_matches_direct_loop():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3)) + np.repeat(np.eye(3) * 2, [15, 15, 10], axis=0)
    labels = np.repeat([0, 1, 2], [15, 15, 10])
    labels[-1] = 7  # a singleton cluster scores 0
    assert coding.silhouette_score(x, labels) == pytest.approx(silhouette_loop(x, labels), abs=1e-12)


def test_silhouette_of_repeated_points_matches_direct_loop():
    """Repeated (point, label) pairs are scored once with their count: the same as every point."""
    rng = np.random.default_rng(5)
    states = rng.normal(size=(6, 3))
    visit = rng.integers(0, 6, 90)
    labels = np.where(visit < 3, 0, 1)
    labels[::7] = 2  # some states under two labels, one state visited once
    x = states[visit]
    assert len(np.unique(np.column_stack([x, labels]), axis=0)) < 20
    assert coding.silhouette_score(x, labels) == pytest.approx(silhouette_loop(x, labels), abs=1e-12)


def test_silhouette_of_points_equal_up_to_rounding_is_that_of_equal_points():
    """A converged memory visits a few states, the same state in two clusters: rounding noise in
    their projection must not decide the score ((b − a) / max(a, b) of two rounding errors)."""
    states = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.2]])
    labels = np.repeat([0, 1, 2], 20)
    exact = states[np.repeat([0, 0, 1], 20)]  # clusters 0 and 1 on one state: a = b = 0, s = 0
    rounded = exact + np.random.default_rng(4).normal(0, 1e-13, exact.shape)
    expected = silhouette_loop(exact, labels)
    assert expected == pytest.approx(1 / 3)  # cluster 2's points score 1, the others 0
    assert coding.silhouette_score(rounded, labels) == pytest.approx(expected, abs=1e-9)


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


def test_pca_scores_and_explained_variance():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(200, 2)) @ np.array([[3.0, 0, 0, 0], [0, 1.0, 0, 0]]) + 5
    scores, ratio = coding.pca(x)
    assert scores.shape == (200, 3) and ratio.shape == (4,)
    assert ratio.sum() == pytest.approx(1.0) and ratio[0] > 0.85 and ratio[2:].max() < 1e-20
    np.testing.assert_allclose(scores.var(axis=0) / x.var(axis=0).sum(), ratio[:3], atol=1e-12)


# ---- runs ------------------------------------------------------------------------


def load_maze(run_dir: Path) -> TMazeRun:
    return TMazeRun.load(load_run(run_dir))


def judge(maze: TMazeRun) -> dict[str, str]:
    """source → verdict of the claims of the chapter that the run's facts select."""
    chapter = dispatch.REGISTRY.chapter_of(maze.run.manifest)
    return {r.claim.source: r.verdict for r in evaluate(chapter.claims, maze)}


def claim_verdicts(run_dir: Path) -> dict[str, str]:
    return {c["source"]: c["verdict"] for c in json.loads((run_dir / "analysis" / "claims.json").read_text())}


def check_outputs(run_dir: Path) -> None:
    report = assert_analysis_outputs(run_dir, FIGURES, DATA)
    assert report.startswith("# T-maze (matching)")
    for name in [*FIGURES, *DATA]:
        assert f"]({name}" in report, name
    assert event_files(run_dir)


def check_synthetic_truth(run_dir: Path) -> None:
    verdicts = claim_verdicts(run_dir)
    assert verdicts[HIDDEN_CLAIM] == HELD
    assert verdicts["§4.3.2, Fig. 4.14; §4.3.3"] == HELD  # memory keeps the signal
    assert verdicts["§4.3.2, Fig. 4.11"] == HELD  # solved in all runs
    assert verdicts["§4.3.2, Fig. 4.10"] == HELD  # predictor learns, generalises
    assert not any(source.startswith("§4.3.1") for source in verdicts)  # regular-only claims
    with (run_dir / "analysis" / "junction_separation.csv").open() as f:
        rows = {(r["layer"], r["labels"], r["phase"]): float(r["silhouette_mean"]) for r in csv.DictReader(f)}
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
    run = load_maze(make_tmaze_run(tmp_path / "run", hidden="shuffled"))
    assert judge(run)[HIDDEN_CLAIM] == NOT_HELD
    assert abs(np.nanmean(run.separation["hidden", "condition"])) < 0.1


def test_a_run_recorded_with_the_old_name_junction_npz_is_still_read(tmp_path):
    run_dir = make_tmaze_run(tmp_path / "run")
    records = run_dir / "records"
    (records / "probe.npz").rename(records / "junction.npz")
    old = load_maze(run_dir)
    assert len(old.junction["run"]) > 0 and judge(old)[HIDDEN_CLAIM] == HELD


def test_regular_maze_gets_its_own_claims_and_steps_from_episodes(tmp_path):
    run = load_maze(make_tmaze_run(tmp_path / "run", matching=False, steps_to_goal=False))
    sources = set(judge(run))
    assert "§4.3.1, Fig. 4.6" in sources and HIDDEN_CLAIM not in sources
    j = run.junction
    np.testing.assert_array_equal(run.steps_to_goal, run.episodes["steps"][j["run"], j["episode"]])
    assert run.condition_names == ["0", "1"]


def test_chapter_5_figures_follow_the_predictors_roles_not_their_names(tmp_path):
    run = load_maze(
        make_tmaze_run(
            tmp_path / "run",
            predictors={"m_y": "observation", "m_r": "reward"},
            memory_keys=("memory_m_y", "memory_m_r"),
            signal_memories=("memory_m_r",),
        )
    )
    assert [p.name for p in run.run.predictors] == ["m_y", "m_r"]
    assert run.layers == ["memory_m_r", "memory_m_y", "state", "hidden"]
    assert {(m, "initial_signal") for m in ("memory_m_y", "memory_m_r")} <= set(run.separation)
    assert dispatch.REGISTRY.chapter_of(run.run.manifest) is ch5.CHAPTER
    num = ch5.CHAPTER.numbering(run.run.manifest)
    assert num is ch5.BIT
    figures = generic.analyze(run.run, num, tmp_path).figures | tmaze.make_figures(run, num)
    assert figures["prediction_errors_m_y"][1].startswith("Fig. 5.2(a): absolute error")
    assert figures["prediction_errors_m_r"][1].startswith("Fig. 5.2(b): squared error")
    assert figures["junction_memory_m_y_pca"][1].startswith("Fig. 5.8(b): observation-predictor")
    assert figures["junction_memory_m_r_pca"][1].startswith("Fig. 5.7(b): reward-predictor")
    verdicts = judge(run)  # chapter-5 claims only; m^r (named m_r) keeps the signal, m^y not
    assert verdicts and all(source.startswith("§5.3.1") for source in verdicts)
    assert verdicts["§5.3.1, Figs. 5.7–5.8"] == HELD


def test_a_maze_with_a_predictor_of_no_role_gets_no_claims_and_unnumbered_figures(tmp_path):
    run_dir = make_tmaze_run(tmp_path / "run", predictors={"world": "other"}, memory_keys=("memory_world",))
    result = analyze(run_dir)
    assert result.returncode == 0, result.stderr
    report = (run_dir / "analysis" / "report.md").read_text()
    assert "## Claims" not in report  # no chapter applies: no claims section
    assert "no chapter's model matches this run" in report  # the dissertation's task: its header says why
    assert (
        "[junction_memory_world_pca.png](junction_memory_world_pca.png) — predictor memory (world) at the T-junction"
    ) in report
    assert "Fig. " not in report
    assert json.loads((run_dir / "analysis" / "claims.json").read_text()) == []
    for name in (
        "learning_curves",
        "td_errors",
        "prediction_errors_world",
        "junction_memory_world_pca",
        "junction_hidden_pca",
    ):
        assert (run_dir / "analysis" / f"{name}.png").is_file(), name


@pytest.mark.parametrize("n, d", [(300, 6), (5, 12)])  # by XᵀX's eigenvectors; by SVD when n < d
def test_pca_equals_the_svd_of_the_centred_data(n, d):
    rng = np.random.default_rng(n)
    x = rng.normal(size=(n, d)) * np.linspace(3.0, 0.5, d) + 2.0
    scores, ratio = coding.pca(x, 3)
    u, s, vt = np.linalg.svd(x - x.mean(axis=0), full_matrices=False)
    largest = vt[np.arange(3), np.abs(vt[:3]).argmax(axis=1)]  # each PC's largest loading, made positive
    np.testing.assert_allclose(scores, u[:, :3] * s[:3] * np.sign(largest), atol=1e-9)
    np.testing.assert_allclose(ratio[: len(s)], s**2 / np.sum(s**2), atol=1e-12)
    assert ratio.shape == (d,) and not ratio[len(s) :].any()


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_nonfinite_rows_equals_isfinite_all(dtype):
    x = np.random.default_rng(0).normal(size=(50, 7)).astype(dtype)
    x[3, 2], x[9, 0], x[17, 6], x[20] = np.nan, np.inf, -np.inf, np.finfo(dtype).max  # a full row of max: finite
    x[30, 1], x[30, 2] = np.inf, -np.inf  # their sum is NaN: still non-finite
    expected = ~np.isfinite(x).all(axis=1)
    np.testing.assert_array_equal(coding.nonfinite_rows(x), expected)
    assert expected.sum() == 4
