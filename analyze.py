"""Analyze finished runs: figures, their numbers and a claims-vs-measurements report.

    python analyze.py RUN_OR_SWEEP_DIR [more dirs ...]

    python analyze.py SWEEP_DIR --readme README.md   # also paste the claims table into README

A directory holding `summary.json` is a run: its `analysis/` folder is rebuilt
(PNG figures, CSV/JSON data, `report.md`) and the figures are logged to its
TensorBoard under `tb/analysis/` (replaced on every analysis). Any other directory is
a sweep: every run below it is analyzed, and `DIR/analysis/` gets the sweep's
aggregate tables, the Fig. 3.6 noise grid and the reproduction report
(`ferl.analysis.sweep`), its figures also logged to `DIR/analysis/tb/`.
The analysis is chosen by the run's `task` (CONTRACT.md §4); tasks without one
are skipped with a message.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

PROG = "analyze.py"


def _analyzers() -> dict:
    """task → analyze(run_dir, out_dir) -> RunAnalysis; imported only when needed."""
    from ferl.analysis import floor, tmaze
    return {floor.TASK: floor.analyze, tmaze.TASK: tmaze.analyze}


def _publish_figures(figures: dict, out: Path, tb_dir: Path) -> None:
    """Save every figure as PNG and log it to a fresh TensorBoard log `tb_dir` under
    `analysis/<name>`.

    Each figure is rendered once by the Agg canvas and the same pixels go to both,
    which is what `SummaryWriter.add_figure` logs, without drawing it twice more.
    """
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.image import imsave
    from torch.utils.tensorboard import SummaryWriter

    shutil.rmtree(tb_dir, ignore_errors=True)
    with SummaryWriter(str(tb_dir)) as writer:
        for name, (fig, _) in figures.items():
            canvas = FigureCanvasAgg(fig)
            canvas.draw()
            rgba = np.asarray(canvas.buffer_rgba())
            imsave(out / f"{name}.png", rgba)
            writer.add_image(f"analysis/{name}", rgba[..., :3], global_step=0, dataformats="HWC")


def _claim_json(r, **where) -> dict:
    return {"claim": r.claim.text, "source": r.claim.source, "measured": r.measured.text,
            "criterion": r.claim.criterion, "verdict": r.verdict, **where}


def _write_json(path: Path, items: list) -> None:
    path.write_text(json.dumps(items, indent=2, ensure_ascii=False) + "\n")


def analyze_run(run_dir: Path):
    """Rebuild `run_dir/analysis/`; return the run's line of a sweep report."""
    from ferl.analysis.report import VERDICTS, RunOutcome, write_run_report

    summary = json.loads((run_dir / "summary.json").read_text())
    task, experiment = str(summary.get("task")), str(summary.get("experiment", "?"))
    analyzer = _analyzers().get(task)
    if analyzer is None:
        print(f"{run_dir}: skipped, no analysis for task {task!r} yet")
        return RunOutcome(run_dir, experiment, task, f"skipped: no analysis for task {task!r}")

    out = run_dir / "analysis"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    analysis = analyzer(run_dir, out)
    _publish_figures(analysis.figures, out, run_dir / "tb" / "analysis")
    _write_json(out / "claims.json", [_claim_json(r) for r in analysis.results])
    analysis.data_files.append("claims.json")
    write_run_report(out / "report.md", analysis)

    verdicts = {v: sum(r.verdict == v for r in analysis.results) for v in VERDICTS}
    print(f"{run_dir}: {len(analysis.figures)} figures, {len(analysis.results)} claims "
          f"({', '.join(f'{n} {v}' for v, n in verdicts.items())}) -> {out / 'report.md'}")
    return RunOutcome(run_dir, experiment, task, "analyzed", verdicts, analysis.results,
                      [(name, caption) for name, (_, caption) in analysis.figures.items()])


def _safe_analyze_run(run_dir: Path):
    """One failing run must not stop a sweep: report it in one line and go on."""
    from ferl.analysis.report import RunOutcome

    try:
        return analyze_run(run_dir)
    except Exception as exc:  # noqa: BLE001 — any failure is reported per run
        print(f"{PROG}: error: {run_dir}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return RunOutcome(run_dir, "?", "?", f"failed: {type(exc).__name__}: {exc}")


def _read_summary(run_dir: Path) -> dict | None:
    """A run's summary for the sweep tables, also where its own analysis failed; None if unreadable."""
    from ferl.runs import load_summary

    try:
        return load_summary(run_dir)
    except (OSError, ValueError):
        return None


def analyze_sweep(sweep_dir: Path, readme: Path | None = None) -> list:
    """Analyze every run below `sweep_dir`, then the sweep as a whole (ferl.analysis.sweep)."""
    from ferl.analysis import sweep as sw
    from ferl.analysis.report import jobs_table

    from ferl.runs import find_runs

    start = time.perf_counter()
    runs = find_runs(sweep_dir)
    outcomes = [_safe_analyze_run(r) for r in runs]
    jobs = [sw.Job(o, summary) for o in outcomes
            if (summary := _read_summary(o.run_dir)) is not None]
    sweep = sw.Sweep(sweep_dir, jobs)
    out = sweep_dir / "analysis"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    analysis, rows = sw.analyze_sweep(sweep, out)
    _publish_figures(analysis.figures, out, out / "tb")
    _write_json(out / "claims.json",
                [_claim_json(r.result, job=None if r.job is None else str(r.job.run_dir),
                             variant=None if r.job is None else r.job.variant) for r in rows])
    analysis.data_files.append("claims.json")

    wall = {}
    train_wall = sweep_dir / sw.TRAIN_WALL_TIME
    if train_wall.is_file():
        wall["training wall time (make reproduce)"] = float(train_wall.read_text())
    wall["sum of the jobs' wall_time_s"] = sum(float(j.summary.get("wall_time_s", 0)) for j in jobs)
    wall["analysis wall time"] = time.perf_counter() - start
    lines = sw.report_lines(sweep, analysis, rows, out, wall)
    lines += ["", "## Jobs", ""] + jobs_table(sweep_dir, out, outcomes)
    (out / "report.md").write_text("\n".join(lines) + "\n")
    if readme is not None:
        sw.update_readme(readme, rows, wall, out / "report.md")
        print(f"{readme}: reproduction table updated")
    print(f"{sweep_dir}: sweep of {len(runs)} runs, {len(rows)} claims "
          f"({sw.verdict_counts(rows)}) -> {out / 'report.md'}")
    return outcomes


def _has_readme_block(path: Path) -> bool:
    from ferl.analysis.sweep import README_BEGIN, README_END
    text = path.read_text() if path.is_file() else ""
    return README_BEGIN in text and README_END in text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, metavar="RUN_OR_SWEEP_DIR",
                        help="a run directory (holds summary.json) or a directory of runs")
    parser.add_argument("--readme", type=Path, metavar="README.md",
                        help="paste a sweep's claims table into this file, between its "
                             "reproduction-report markers")
    args = parser.parse_args(argv)

    missing = [str(d) for d in args.dirs if not d.is_dir()]
    if missing:
        print(f"{PROG}: error: no such directory: {', '.join(missing)}", file=sys.stderr)
        return 2
    runs = [str(d) for d in args.dirs if (d / "summary.json").is_file()]
    if args.readme is not None and runs:
        print(f"{PROG}: error: --readme takes sweep directories only, not the run "
              f"{', '.join(runs)}", file=sys.stderr)
        return 2
    if args.readme is not None and not _has_readme_block(args.readme):
        from ferl.analysis.sweep import README_BEGIN, README_END
        print(f"{PROG}: error: --readme {args.readme}: needs a file with the lines "
              f"{README_BEGIN!r} and {README_END!r}", file=sys.stderr)
        return 2

    status = 0
    for d in args.dirs:
        if (d / "summary.json").is_file():
            outcomes = [_safe_analyze_run(d)]
        elif not any(d.rglob("summary.json")):
            print(f"{PROG}: error: {d}: no run (summary.json) found below it", file=sys.stderr)
            status = 2
            continue
        else:
            outcomes = analyze_sweep(d, args.readme)
        if any(o.status.startswith("failed") for o in outcomes):
            status = max(status, 1)
    return status


if __name__ == "__main__":
    sys.exit(main())
