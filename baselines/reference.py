"""RecurrentPPO's reference for `make suites` (docs/beyond.md, "Outside POMDPs"): `make
suites-reference` trains it into ``outputs/suites_reference/<date>_<time>/`` (its ``sweep.json``:
when it started, at which commit; ``ferl.run.sweepdir``); `make suites` trains ferl's agents only
and, before its analysis, copies the newest reference's finished PPO jobs into its sweep and
leaves one line for its report (``report_notes.md``, printed above its "Agents side by side"
section) naming the reference folder, its date and commit, or saying that there is none.

``suites_reference.json`` in the suites sweep names the reference whose jobs were copied in; a later
run of the same sweep (``RESUME=``) with a newer reference replaces those copies, and never a
sweep's own PPO jobs (a sweep made before the reference had its own target).
"""

import json
import shutil
from pathlib import Path

from ferl.run.jobs import DONE, JobError, job_state
from ferl.run.sweepdir import MARKER, NOTES

COPIED = "suites_reference.json"  # in the suites sweep: the reference folder and the job folders copied from it


def finished_ppo_jobs(reference: Path) -> list[Path]:
    """The reference's PPO job folders that hold a finished run."""
    jobs = []
    for path in sorted(reference.glob("ppo_*")):
        try:
            if path.is_dir() and job_state(path) == DONE:
                jobs.append(path)
        except JobError:
            continue  # a damaged summary: not a result
    return jobs


def newest(references: Path) -> Path | None:
    """The newest reference folder (by the start its ``sweep.json`` records) with a finished PPO job."""
    found = []
    for marker in references.glob(f"*/{MARKER}"):
        try:
            started = json.loads(marker.read_text())["started"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if finished_ppo_jobs(marker.parent):
            found.append((started, marker.parent.name, marker.parent))
    return max(found)[2] if found else None


def described(reference: Path) -> str:
    """``<folder> (started <date>, commit <sha>)``."""
    info = json.loads((reference / MARKER).read_text())
    dirty = " with uncommitted changes" if info.get("dirty") else ""
    return f"{reference} (started {info['started']}, commit {info.get('commit') or 'unknown'}{dirty})"


def copy_newest(out: Path, references: Path) -> str:
    """Copy the newest reference's finished PPO jobs into the sweep ``out`` (module doc); write and
    return the report's line about it."""
    reference = newest(references)
    record = out / COPIED
    earlier = json.loads(record.read_text()) if record.is_file() else None
    own = [p.name for p in out.glob("ppo_*") if p.is_dir() and p.name not in (earlier or {}).get("jobs", [])]
    if own:
        line = f"RecurrentPPO: this sweep's own jobs ({', '.join(sorted(own))}), no reference copied in."
    elif reference is None:
        line = f"RecurrentPPO: no reference in {references} (make suites-reference): no RecurrentPPO row."
    else:
        if earlier is not None and earlier["reference"] != str(reference):
            for name in earlier["jobs"]:
                shutil.rmtree(out / name, ignore_errors=True)
            record.unlink()
        jobs = finished_ppo_jobs(reference)
        for job in jobs:
            if not (out / job.name).exists():
                shutil.copytree(job, out / job.name, symlinks=True)
        record.write_text(json.dumps({"reference": str(reference), "jobs": [j.name for j in jobs]}, indent=1) + "\n")
        line = f"RecurrentPPO: the reference {described(reference)}, its jobs {', '.join(j.name for j in jobs)}."
    (out / NOTES).write_text(line + "\n")
    print(f"ferl: {line}", flush=True)
    return line
