"""T-maze analysis of chapter 5 (Algorithm 2): figure numbers, the RBM preprocessor's PCA
(Figs. 5.15–5.16), the memories' separation by the initial signal (Figs. 5.7–5.8,
5.20–5.21) and the chapter-5 claims, on synthetic runs whose truth is known
(tests/synthetic_runs.py, `make_ch5_run`)."""

import csv
import json

import numpy as np

from ferl.analysis.claims import HELD, NOT_HELD
from reproduction.preprocessor import pcs_for_share
from synthetic_runs import DIGIT_CLASSES, assert_analysis_outputs, make_ch5_run
from test_analysis_tmaze import claim_verdicts, judge, load_maze
from test_analyze_cli import analyze

LAYERS = ("memory_observation", "memory_reward", "state", "hidden")
JUNCTION = [f"junction_{layer}_{kind}" for layer in LAYERS for kind in ("activations", "pca")]
FIGURES = [
    "prediction_errors_observation",
    "prediction_errors_reward",
    "learning_curves",
    "td_errors",
    *JUNCTION,
    "junction_state_pca3d",
]
PREPROCESSOR = ["preprocessor_raw_pca", "preprocessor_processed_pca", "preprocessor_reconstruction_error"]
DATA = [
    "summary.csv",
    "learning_curves.csv",
    "prediction_errors_observation.csv",
    "prediction_errors_reward.csv",
    "junction_separation.csv",
    "junction_explained_variance.csv",
    "claims.json",
]
PREPROCESSOR_DATA = [
    "preprocessor_explained_variance.csv",
    "preprocessor_reconstruction_error.csv",
    "preprocessor.json",
]
MEMORY_CLAIM = {"pixel": "§5.3.2, Figs. 5.20–5.21", "bit": "§5.3.1, Figs. 5.7–5.8"}
CLASS_CLAIM = "§5.3.2, Figs. 5.15(a)/5.16(a)"
# Where the report names each figure (its caption starts with the dissertation's number).
CAPTIONS = {
    "pixel": {
        "preprocessor_raw_pca": "Fig. 5.15",
        "preprocessor_processed_pca": "Fig. 5.16",
        "prediction_errors_observation": "Fig. 5.17(a): absolute error",
        "prediction_errors_reward": "Fig. 5.17(b): squared error",
        "learning_curves": "Figs. 5.18–5.19(a–b)",
        "td_errors": "Fig. 5.19(c–d)",
        "junction_memory_reward_pca": "Fig. 5.20(b)",
        "junction_memory_observation_pca": "Fig. 5.21(b)",
        "junction_state_pca3d": "Fig. 5.23(b)",
        "junction_hidden_pca": "Figs. 5.24(b)/5.25(b)",
    },
    "bit": {
        "prediction_errors_observation": "Fig. 5.2(a): absolute error",
        "prediction_errors_reward": "Fig. 5.2(b): squared error",
        "learning_curves": "Figs. 5.3–5.5",
        "td_errors": "Fig. 5.6",
        "junction_memory_reward_pca": "Fig. 5.7(b)",
        "junction_memory_observation_pca": "Fig. 5.8(b)",
        "junction_state_pca3d": "Fig. 5.10(b)",
        "junction_hidden_pca3d": "Fig. 5.13(b)",
    },
}


def separation_rows(run_dir) -> dict[tuple[str, str, str], float]:
    with (run_dir / "analysis" / "junction_separation.csv").open() as f:
        return {(r["layer"], r["labels"], r["phase"]): float(r["silhouette_mean"]) for r in csv.DictReader(f)}


def check_chapter5_report(run_dir, kind: str, figures, data) -> None:
    report = assert_analysis_outputs(run_dir, figures, data)
    for name, number in CAPTIONS[kind].items():
        assert f"[{name}.png]({name}.png) — {number}" in report, name
    assert "Fig. 4." not in report and "| criterion |" in report
    verdicts = claim_verdicts(run_dir)
    section = "§5.3.2" if kind == "pixel" else "§5.3.1"
    assert verdicts and all(source.startswith(section) for source in verdicts)
    assert verdicts[MEMORY_CLAIM[kind]] == HELD
    rows = separation_rows(run_dir)
    for phase in ("first", "last"):  # the score of both memory layers is in the CSV
        assert rows["memory_reward", "initial_signal", phase] > 0.7
        assert abs(rows["memory_observation", "initial_signal", phase]) < 0.1


def test_analyze_sweep_of_chapter5_pixel_and_bit_runs(tmp_path):
    sweep = tmp_path / "sweep"
    pixel, bit = make_ch5_run(sweep / "pixel"), make_ch5_run(sweep / "bit", pixel=False)
    result = analyze(sweep)  # one analyze.py call: its start-up dominates the time
    assert result.returncode == 0, result.stderr

    check_chapter5_report(pixel, "pixel", FIGURES + PREPROCESSOR, DATA + PREPROCESSOR_DATA)
    check_chapter5_report(bit, "bit", FIGURES + ["junction_hidden_pca3d"], DATA)
    assert not list((bit / "analysis").glob("preprocessor*"))
    assert (pixel / "analysis" / "report.md").read_text().startswith("# T-maze (digit matching)")
    assert "junction_hidden_pca3d" not in (pixel / "analysis" / "report.md").read_text()

    numbers = json.loads((pixel / "analysis" / "preprocessor.json").read_text())
    silhouette = numbers["class_silhouette_pc1_3"]
    assert silhouette["raw"] > 0.5 and silhouette["processed_mean"] > 0.5
    held_out = numbers["held_out_reconstruction_error"]
    assert held_out["after"]["mean"] < 0.2 * held_out["before"]["mean"]
    assert numbers["classes"] == ["0", "1", "2", "3", "4"] and numbers["images_per_class"] == 20
    verdicts = claim_verdicts(pixel)
    assert verdicts[CLASS_CLAIM] == HELD
    assert verdicts["§5.3.2, Observation preprocessor"] == HELD


def test_swapped_memories_fail_the_claim(tmp_path):
    run = load_maze(make_ch5_run(tmp_path / "run", signal_role="observation"))
    assert judge(run)[MEMORY_CLAIM["pixel"]] == NOT_HELD
    assert np.nanmean(run.separation["memory_observation", "initial_signal"]) > 0.7
    assert abs(np.nanmean(run.separation["memory_reward", "initial_signal"])) < 0.1


def test_distinct_images_are_one_reservoir_per_digit_class(tmp_path):
    k = 4
    pre = load_maze(make_ch5_run(tmp_path / "run", reservoir_size=k)).preprocessing
    names = list(DIGIT_CLASSES)
    assert pre.class_names == ["0", "1", "2", "3", "4"] and pre.reservoir_size == k
    first = [names.index(n) for n in ("start_0", "start_1", "corridor", "goal_left", "goal_right")]
    np.testing.assert_array_equal(pre.ids, np.concatenate([n * k + np.arange(k) for n in first]))
    np.testing.assert_array_equal(pre.labels, np.repeat(np.arange(5), k))
    raw = pre.records["raw_observations"]
    assert len(np.unique(raw, axis=0)) == len(pre.ids)  # the junction shows start images only
    assert pre.raw[1].shape == (784,) and pre.processed_ratios.shape == (2, 8)


def test_shuffled_codes_lose_the_class_structure(tmp_path):
    run = load_maze(make_ch5_run(tmp_path / "run", codes="shuffled"))
    raw, processed = run.preprocessing.silhouettes
    assert raw > 0.5 and np.abs(processed).max() < 0.2  # random labels: slightly negative
    assert judge(run)[CLASS_CLAIM] == NOT_HELD


def test_pcs_for_share():
    assert pcs_for_share(np.array([0.5, 0.3, 0.15, 0.05])) == 3
    assert pcs_for_share(np.array([0.6, 0.3, 0.1])) == 2  # exactly 90 %
    assert pcs_for_share(np.array([0.95, 0.05, 0.0])) == 1
