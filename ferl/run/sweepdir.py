"""The folder of a make target's sweep (docs/sweeps.md, "Resuming a sweep"): a new dated one, or the
one ``RESUME=`` names, checked to be a sweep of that target.

    python -m ferl.run.sweepdir TARGET [RESUME]

prints the folder. A new one is ``outputs/<target>/<date>_<time>/`` (``-`` in the target's name as
``_``) with its ``sweep.json``: the target, when it started (UTC) and the git commit (and whether
the work tree had uncommitted changes). Then one line on stderr names the newest unfinished sweep
of the target (one with no ``analysis/report.md``), if there is one, and how to continue it.

``RESUME=DIR``: ``DIR`` must be a folder whose ``sweep.json`` names this target, or, made before
``sweep.json`` was written, one inside ``outputs/<target>/``. Anything else: one line, exit 2.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

MARKER = "sweep.json"
NOTES = "report_notes.md"  # lines a launcher leaves for its sweep's report (ferl/analysis/runner.py)
REPORT = Path("analysis") / "report.md"


def folder_name(target: str) -> str:
    return target.replace("-", "_")


def git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", *args], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def new_sweep(target: str, outputs: Path) -> Path:
    """A new dated folder with its ``sweep.json``."""
    (outputs / folder_name(target)).mkdir(parents=True, exist_ok=True)
    while True:  # a sweep started in the same second has that name: never write into it
        now = time.gmtime()
        path = outputs / folder_name(target) / time.strftime("%Y-%m-%d_%H-%M-%S", now)
        try:
            path.mkdir()
            break
        except FileExistsError:
            time.sleep(0.5)
    status = git("status", "--porcelain", "--untracked-files=no")
    info = {
        "target": target,
        "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", now),
        "commit": git("rev-parse", "HEAD"),
        "dirty": bool(status) if status is not None else None,
    }
    (path / MARKER).write_text(json.dumps(info, indent=1) + "\n")
    return path


def target_of(path: Path) -> str | None:
    """The target a sweep folder's ``sweep.json`` names (None: none, or unreadable)."""
    try:
        return json.loads((path / MARKER).read_text())["target"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def check_resume(target: str, resume: str, outputs: Path) -> str | None:
    """Why ``resume`` is not a sweep of ``target`` (None when it is)."""
    path = Path(resume)
    how = f"RESUME={resume}"
    if not path.is_dir():
        return f"{how}: no such folder"
    named = target_of(path)
    if named is not None:
        return None if named == target else f"{how} is a sweep of `make {named}`, not of `make {target}`"
    if (path / MARKER).exists():
        return f"{how}: its {MARKER} does not read"
    if path.resolve().parent == (outputs / folder_name(target)).resolve():
        return None  # made before sweep.json was written
    return f"{how} is not a sweep of `make {target}` (no {MARKER}, not in {outputs / folder_name(target)}/)"


def unfinished(target: str, outputs: Path) -> Path | None:
    """The newest sweep of ``target`` with no report yet."""
    base = outputs / folder_name(target)
    found = sorted(p for p in base.glob("*") if p.is_dir() and not (p / REPORT).exists()) if base.is_dir() else []
    return found[-1] if found else None


def main(argv: list[str] | None = None, outputs: Path = Path("outputs")) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not 1 <= len(args) <= 2:
        print("usage: python -m ferl.run.sweepdir TARGET [RESUME]", file=sys.stderr)
        return 2
    target, resume = args[0], (args[1] if len(args) == 2 else "")
    if resume:
        if (problem := check_resume(target, resume, outputs)) is not None:
            print(f"ferl: error: {problem}", file=sys.stderr)
            return 2
        print(resume.rstrip("/"))
        return 0
    earlier = unfinished(target, outputs)
    if earlier is not None:
        print(
            f"ferl: {earlier} has no report yet (stopped?): `make {target} RESUME={earlier}` continues it; "
            f"starting a new sweep",
            file=sys.stderr,
        )
    print(new_sweep(target, outputs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
