"""The members of a sweep that analyze.py cannot analyse: run directories without summary.json.

Hydra creates a job's directory (``.hydra/``) before the job runs, and a run writes
``checkpoints/`` as it trains and ``summary.json`` only when it ends; a directory that holds the
first but not the last is a run that is still training, or one that was killed or failed. The
sweep's analysis goes on without it, but names it (docs/records.md, "Analysis"), so that a sweep
of ten jobs with two missing never reads as a sweep of eight.
"""

from __future__ import annotations

from pathlib import Path

from ferl import runs

RUN_MARKS = (".hydra", "checkpoints")  # what a run directory holds before it has a summary
LOCK = ".ferl.lock"  # held by a training run while it writes into its directory
OUTSIDE = ("analysis",)  # analyze.py's own folders: never a run


def unfinished(sweep_dir: Path) -> list[tuple[Path, str]]:
    """(run directory, why it has no analysis) for every directory below ``sweep_dir`` that
    Hydra or a run started but that holds no summary.json, sorted by path."""
    sweep_dir = Path(sweep_dir)
    found = {}
    for mark in RUN_MARKS:
        for path in sweep_dir.rglob(mark):
            run_dir = path.parent
            if path.is_dir() and not _excluded(run_dir, sweep_dir) and not (run_dir / runs.SUMMARY).exists():
                found[run_dir] = reason(run_dir)
    return sorted(found.items())


def _excluded(run_dir: Path, sweep_dir: Path) -> bool:
    """A folder inside another run (its checkpoints' copy of .hydra/) or inside an analysis."""
    parts = run_dir.relative_to(sweep_dir).parts
    return any(p in OUTSIDE or p in RUN_MARKS for p in parts)


def reason(run_dir: Path) -> str:
    """Why ``run_dir`` has no summary.json, as far as its files tell."""
    if (run_dir / LOCK).exists():
        return f"no {runs.SUMMARY} yet (it holds {LOCK}: still running, or killed while it held it)"
    if (run_dir / "checkpoints").is_dir():
        return f"no {runs.SUMMARY} (unfinished or killed run: resume=true hydra.run.dir={run_dir} continues it)"
    return f"no {runs.SUMMARY} (unfinished or killed run: it ended before its first checkpoint)"
