"""Analyze finished runs: figures, their numbers and a claims-vs-measurements report.

    python analyze.py RUN_OR_SWEEP_DIR [more dirs ...]

A directory holding `summary.json` is a run: its `analysis/` folder is rebuilt
(PNG figures, CSV/JSON data, `report.md`) and the figures are appended to its
TensorBoard log `tb/` under `analysis/<name>`. Any other directory is a sweep:
every run below it is analyzed and `DIR/analysis/report.md` links their reports.
The analysis is chosen by the run's `task` (CONTRACT.md §4); tasks without one
are skipped with a message.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

PROG = "analyze.py"


def _analyzers() -> dict:
    """task → analyze(run_dir, out_dir) -> RunAnalysis; imported only when needed."""
    from ferl.analysis import floor, tmaze
    return {floor.TASK: floor.analyze, tmaze.TASK: tmaze.analyze}


def _publish_figures(figures: dict, out: Path, tb_dir: Path) -> None:
    """Save every figure as PNG and log it to TensorBoard under `analysis/<name>`.

    Each figure is rendered once by the Agg canvas and the same pixels go to both,
    which is what `SummaryWriter.add_figure` logs, without drawing it twice more.
    """
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.image import imsave
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(str(tb_dir)) as writer:
        for name, (fig, _) in figures.items():
            canvas = FigureCanvasAgg(fig)
            canvas.draw()
            rgba = np.asarray(canvas.buffer_rgba())
            imsave(out / f"{name}.png", rgba)
            writer.add_image(f"analysis/{name}", rgba[..., :3], global_step=0, dataformats="HWC")


def _write_claims_json(path: Path, results) -> None:
    path.write_text(json.dumps([{"claim": r.claim.text, "source": r.claim.source,
                                 "measured": r.measured.text, "criterion": r.claim.criterion,
                                 "verdict": r.verdict}
                                for r in results], indent=2, ensure_ascii=False) + "\n")


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
    _publish_figures(analysis.figures, out, run_dir / "tb")
    _write_claims_json(out / "claims.json", analysis.results)
    analysis.data_files.append("claims.json")
    write_run_report(out / "report.md", analysis)

    verdicts = {v: sum(r.verdict == v for r in analysis.results) for v in VERDICTS}
    print(f"{run_dir}: {len(analysis.figures)} figures, {len(analysis.results)} claims "
          f"({', '.join(f'{n} {v}' for v, n in verdicts.items())}) -> {out / 'report.md'}")
    return RunOutcome(run_dir, experiment, task, "analyzed", verdicts)


def _safe_analyze_run(run_dir: Path):
    """One failing run must not stop a sweep: report it in one line and go on."""
    from ferl.analysis.report import RunOutcome

    try:
        return analyze_run(run_dir)
    except Exception as exc:  # noqa: BLE001 — any failure is reported per run
        print(f"{PROG}: error: {run_dir}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return RunOutcome(run_dir, "?", "?", f"failed: {type(exc).__name__}: {exc}")


def analyze_sweep(sweep_dir: Path) -> list:
    from ferl.analysis.report import write_sweep_report

    runs = sorted(p.parent for p in sweep_dir.rglob("summary.json")
                  if "analysis" not in p.relative_to(sweep_dir).parts)
    outcomes = [_safe_analyze_run(r) for r in runs]
    out = sweep_dir / "analysis"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    write_sweep_report(out / "report.md", sweep_dir, outcomes)
    print(f"{sweep_dir}: sweep of {len(runs)} runs -> {out / 'report.md'}")
    return outcomes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, metavar="RUN_OR_SWEEP_DIR",
                        help="a run directory (holds summary.json) or a directory of runs")
    args = parser.parse_args(argv)

    missing = [str(d) for d in args.dirs if not d.is_dir()]
    if missing:
        print(f"{PROG}: error: no such directory: {', '.join(missing)}", file=sys.stderr)
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
            outcomes = analyze_sweep(d)
        if any(o.status.startswith("failed") for o in outcomes):
            status = max(status, 1)
    return status


if __name__ == "__main__":
    sys.exit(main())
