"""analyze.py end to end on synthetic digit-floor runs (docs/records.md, CONTRACT.md §4)."""

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from synthetic_runs import assert_analysis_outputs, load_run, make_floor_run

REPO = Path(__file__).resolve().parents[1]
FIGURES = [
    "learning_curves",
    "td_errors",
    "fig3_5_weights",
    "fig3_6a_greedy_before",
    "fig3_6b_greedy_after",
    "fig3_6_accuracy_vs_noise",
    "fig3_7_outlier",
    "fig3_10_median_activation",
    "fig3_11_dendrogram_run0",
    "fig3_11_dendrogram_all_runs",
    "fig3_12_mutual_information",
]
DATA = [
    "greedy_accuracy.csv",
    "mfr_run0.csv",
    "mfr_run1.csv",
    "pair_clusters.json",
    "mutual_information.csv",
    "learning_curves.csv",
    "summary.csv",
    "claims.json",
]


def analyze(*dirs: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(REPO / "analyze.py"), *map(str, dirs)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )


def snapshot(run_dir: Path, skip=("analysis", "tb")) -> dict[str, tuple[str, int]]:
    """Content hash and mtime of every file outside the given top-level folders."""
    return {
        str(p.relative_to(run_dir)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        for p in sorted(run_dir.rglob("*"))
        if p.is_file() and p.relative_to(run_dir).parts[0] not in skip
    }


def event_files(run_dir: Path) -> list[Path]:
    """The analysis figures' TensorBoard log (CONTRACT §4), rewritten by every analysis."""
    return sorted((run_dir / "tb" / "analysis").glob("events.out.tfevents.*"))


@pytest.fixture(scope="module")
def analyzed_run(tmp_path_factory):
    run_dir = make_floor_run(tmp_path_factory.mktemp("single") / "run")
    before = snapshot(run_dir)
    result = analyze(run_dir)
    return run_dir, before, result


def test_single_run_writes_figures_data_and_report(analyzed_run):
    run_dir, _, result = analyzed_run
    assert result.returncode == 0, result.stderr
    report = assert_analysis_outputs(run_dir, FIGURES, DATA)
    claim_rows = [line for line in report.splitlines() if line.startswith("| ") and line.rstrip().endswith("** |")]
    assert claim_rows, report
    for name in FIGURES:
        assert f"]({name}.png)" in report
    assert "[learning_curves.png](learning_curves.png) — Fig. 3.4: " in report
    assert report.startswith("# Digit floor (chapter 3)")
    assert event_files(run_dir)


def test_single_run_results_reflect_the_synthetic_truth(analyzed_run):
    run_dir, _, _ = analyzed_run
    # The synthetic hidden activations cluster by optimal action in every run.
    pairs = json.loads((run_dir / "analysis" / "pair_clusters.json").read_text())
    found = {tuple(p["pair"]): p["runs_forming_cluster"] for p in pairs["same_action_pairs"]}
    assert found == {("0", "3"): 2, ("1", "2"): 2, ("5", "8"): 2, ("6", "7"): 2}
    claims = {c["source"]: c["verdict"] for c in json.loads((run_dir / "analysis" / "claims.json").read_text())}
    assert claims["§3.5.3, Figs. 3.11(a)/(b), 3.13"] == "held"
    assert claims["§3.5.1, Fig. 3.6(b)"] == "held"
    assert not any(
        "without reward" in c["claim"].lower() for c in json.loads((run_dir / "analysis" / "claims.json").read_text())
    )


def test_tensorboard_holds_every_figure_as_the_png_file_s_bytes(analyzed_run):
    """Each figure is encoded once: TensorBoard's image is the PNG file, byte for byte, and its
    size is the PNG's own (decoded independently by PIL)."""
    from PIL import Image
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_dir, _, result = analyzed_run
    assert result.returncode == 0, result.stderr
    acc = EventAccumulator(str(run_dir / "tb" / "analysis"), size_guidance={"images": 0})
    acc.Reload()
    assert sorted(acc.Tags()["images"]) == sorted(f"analysis/{name}" for name in FIGURES)
    for name in FIGURES:
        (event,) = acc.Images(f"analysis/{name}")
        png = (run_dir / "analysis" / f"{name}.png").read_bytes()
        assert event.encoded_image_string == png
        with Image.open(run_dir / "analysis" / f"{name}.png") as image:
            assert (event.width, event.height) == image.size and image.mode == "RGBA"


def test_rerun_overwrites_only_analysis_and_its_tb_log(analyzed_run):
    run_dir, before, _ = analyzed_run
    stale = run_dir / "analysis" / "stale.txt"
    stale.write_text("left over from an older analysis")
    old_events = event_files(run_dir)
    training_log = run_dir / "tb" / "events.out.tfevents.training"
    training_log.write_text("the training phase's own log")

    result = analyze(run_dir)
    assert result.returncode == 0, result.stderr
    assert not stale.exists()
    assert (run_dir / "analysis" / "report.md").is_file()
    new_events = event_files(run_dir)
    assert len(new_events) == 1 and not set(new_events) & set(old_events)
    assert training_log.read_text() == "the training phase's own log"
    training_log.unlink()
    assert snapshot(run_dir) == before


def test_sweep_analyzes_every_run_and_links_them(tmp_path):
    sweep = tmp_path / "sweep"
    runs = [
        make_floor_run(sweep / "0", seed=1),
        make_floor_run(sweep / "nested" / "1", classes=[*"01234N678"], reward=False, seed=2),
    ]
    older = sweep / "run_without_manifest"  # written before records/run.json existed
    older.mkdir()
    (older / "summary.json").write_text(json.dumps({"task": "tmaze", "experiment": "t"}))

    result = analyze(sweep)
    assert result.returncode == 0, result.stderr
    top = (sweep / "analysis" / "report.md").read_text()
    for run in runs:
        assert (run / "analysis" / "report.md").is_file()
        assert (run / "analysis" / "fig3_12_mutual_information.png").is_file()
        assert f"]({Path('..', run.relative_to(sweep), 'analysis', 'report.md')})" in top
    assert "| skipped: no records/run.json |" in top and not (older / "analysis").exists()
    assert "Without reward" in (runs[1] / "analysis" / "report.md").read_text()


def test_missing_directory_is_one_line_error(tmp_path):
    result = analyze(tmp_path / "does_not_exist")
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1
    assert "does_not_exist" in result.stderr


def test_a_diverged_run_is_left_out_of_the_clustering(tmp_path):
    """A run whose weights diverged has NaN activations: its dendrogram is skipped, not fatal."""
    import numpy as np

    from reproduction.floor import FloorRun

    run_dir = make_floor_run(tmp_path / "run", n_runs=3)
    path = run_dir / "records" / "floor_test.npz"
    with np.load(path) as data:
        test = {k: data[k] for k in data.files}
    for key in ("hidden_after", "hidden_marginal_after"):
        test[key][1] = np.nan
    np.savez(path, **test)
    run = FloorRun.load(load_run(run_dir))
    assert run.mfr_linkages[1] is None and run.mfr_linkages[0] is not None
    assert all(len(run.cluster_hits(i, j)) == 2 for i, j in run.same_action_pairs)
    result = analyze(run_dir)
    assert result.returncode == 0, result.stderr
    assert ": 2/2 runs" in (run_dir / "analysis" / "report.md").read_text()  # the healthy runs


def test_a_page_without_generated_blocks_is_refused_before_any_analysis(tmp_path):
    run = make_floor_run(tmp_path / "sweep" / "0_run")
    page = tmp_path / "README.md"
    page.write_text("# no markers here\n")
    result = subprocess.run(
        [sys.executable, str(REPO / "analyze.py"), str(tmp_path / "sweep"), "--readme", str(page)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and not (run / "analysis").exists()
    (line,) = result.stderr.strip().splitlines()
    assert f"--readme {page}: needs a file with the marker lines" in line and "reproduction-scorecard:begin" in line
    assert page.read_text() == "# no markers here\n"
