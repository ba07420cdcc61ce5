"""The run directory of CONTRACT §2: tb/, summary.json, checkpoints/, records/.

Every file is written atomically (temporary file + rename), so an interruption never
leaves a half-written checkpoint or summary behind. Checkpoints check themselves before they are
used and the last two are kept (``ferl.run.checkpoint``). A checkpoint also remembers how long each
TensorBoard event file was when it was written; resuming cuts the files back to that, so the
points a resumed run logs again appear once, not twice.
"""
import json
import os
import shutil
import signal
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ferl.run import checkpoint
from ferl.run.checkpoint import Checkpoint, RunIdentity
from ferl.run.failures import writing

TB_EVENTS = "events.out.tfevents.*"  # the run's own event files (tb/analysis/ is analyze.py's)
HYDRA_OWN = {".hydra", "train.log"}  # what Hydra writes into a run directory before main()
HYDRA_FILES = ("config.yaml", "hydra.yaml", "overrides.yaml")  # .hydra/'s, rewritten by Hydra at every launch
HYDRA_COPY = Path("checkpoints") / "hydra"  # the run's own .hydra/ files, put back when it is resumed


def check_run_dir(path: Path, resume: bool) -> str | None:
    """Why ``path`` cannot take this run (None if it can): a new run never writes into a
    directory that already holds one, and a resumed one needs its checkpoints."""
    holds_run = any((path / p).exists() for p in ("summary.json", "checkpoints"))
    if resume and not (path / "checkpoints").exists():
        return f"resume=true but {path} holds no checkpoints/: pass hydra.run.dir=<an earlier run>"
    if holds_run and not resume:
        return f"hydra.run.dir={path} already holds a run: pass resume=true to continue it, or another directory"
    return None


def discard_if_new(path: Path) -> None:
    """Remove a run directory that holds only Hydra's own files and empty folders (a config that failed)."""
    if path.is_dir() and all(p.name in HYDRA_OWN or (p.is_dir() and not any(p.iterdir())) for p in path.iterdir()):
        shutil.rmtree(path, ignore_errors=True)
        if path.parent.is_dir() and not any(path.parent.iterdir()):
            path.parent.rmdir()


@contextmanager
def atomic_path(path: Path):
    """Yield a temporary path beside ``path``; rename it over ``path`` on success."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    os.chmod(tmp, 0o644)  # mkstemp creates 0600; results are meant to be shared
    try:
        with writing(path):  # a failing write() names no file: the error line names this one
            yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def restore_hydra_files(path: Path) -> None:
    """Put the run's own ``.hydra/`` files back: Hydra rewrote them for this launch (a resume's
    overrides), before main() could look; the copies were taken at the run's first checkpoint."""
    for name in HYDRA_FILES:
        if (path / HYDRA_COPY / name).is_file():
            with atomic_path(path / ".hydra" / name) as tmp:
                shutil.copyfile(path / HYDRA_COPY / name, tmp)


class RunDir:
    """``identity``: what its checkpoints are written under (train.py's config; a trainer fills
    it in from its own config when none was given); ``resume_from``: the checked checkpoint that
    ``resume`` continues (train.py chose it before the run was set up), else the newest good one."""

    def __init__(self, path, identity: RunIdentity | None = None, resume_from: Checkpoint | None = None):
        self.path = Path(path)
        self.identity, self.resume_from = identity, resume_from
        for sub in ("tb", "checkpoints", "records"):
            (self.path / sub).mkdir(parents=True, exist_ok=True)

    @property
    def checkpoints(self) -> Path:
        return self.path / "checkpoints"

    @property
    def tb(self) -> Path:
        return self.path / "tb"

    def save_records(self, name: str, runs: int, **arrays) -> None:
        """``records/<name>.npz``; its ``per_run`` names the arrays whose first axis is the run
        (``runs`` long), so that the analysis can tell a file of another run apart (docs/records.md)."""
        per_run = np.array(sorted(k for k, a in arrays.items() if np.ndim(a) and np.shape(a)[0] == runs), dtype=str)
        with atomic_path(self.path / "records" / f"{name}.npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **arrays, per_run=per_run)

    def save_json(self, name: str, content: dict) -> None:
        """``records/<name>.json``."""
        with atomic_path(self.path / "records" / f"{name}.json") as tmp:
            tmp.write_text(json.dumps(content, indent=2) + "\n")

    def save_checkpoint(self, state: dict, writer=None) -> None:
        """Write ``state``; with the run's SummaryWriter, flush it first and record the length
        of every event file, the point ``resume`` rolls the log back to."""
        if writer is not None:
            writer.flush()
            state = {**state, "tb_sizes": {p.name: p.stat().st_size for p in self.tb.glob(TB_EVENTS)}}
        self.keep_hydra_files()
        checkpoint.write(self.checkpoints, state, self.identity)

    def keep_hydra_files(self) -> None:
        """Copy ``.hydra/``'s files once, at the run's first checkpoint (``restore_hydra_files``)."""
        if (self.path / ".hydra").is_dir() and not (self.path / HYDRA_COPY).exists():
            for name in HYDRA_FILES:
                if (self.path / ".hydra" / name).is_file():
                    with atomic_path(self.path / HYDRA_COPY / name) as tmp:
                        shutil.copyfile(self.path / ".hydra" / name, tmp)

    def resume(self):
        """The newest good checkpoint's state (None if the run has none; CheckpointError if
        none is good), with ``tb/`` rolled back to the moment it was written: event files are cut
        to their recorded lengths, and files started after it (or, without a checkpoint, every
        event file) are removed, because the resumed run logs everything from that moment on
        again. A damaged ``last.pt`` passed over is kept as ``last.pt.damaged``, so that the
        next checkpoint does not turn it into ``previous.pt``."""
        chosen = self.resume_from or checkpoint.newest_good(self.checkpoints)
        saved = chosen.state() if chosen is not None else None
        if chosen is not None and chosen.path.name != checkpoint.LAST and (self.checkpoints / checkpoint.LAST).exists():
            os.replace(self.checkpoints / checkpoint.LAST,
                       self.checkpoints / (checkpoint.LAST + checkpoint.DAMAGED_SUFFIX))
        for stale in checkpoint.stale_temporary_files(self.checkpoints):
            stale.unlink()
        sizes = (saved or {}).pop("tb_sizes", {})
        for path in self.tb.glob(TB_EVENTS):
            if path.name in sizes:
                if path.stat().st_size > sizes[path.name]:  # never lengthened (with zeros)
                    os.truncate(path, sizes[path.name])
            else:
                path.unlink()
        return saved

    def write_summary(self, summary: dict) -> None:
        with atomic_path(self.path / "summary.json") as tmp:
            tmp.write_text(json.dumps(summary, indent=2) + "\n")


class CheckpointTimer:
    """Due once every ``minutes`` of wall time (0: never), so that a long phase is checkpointed
    by the clock as well as by its step count; a due call starts the next period."""

    def __init__(self, minutes: float):
        self.period = 60.0 * minutes
        self.next = time.monotonic() + self.period

    def due(self) -> bool:
        if self.period <= 0 or time.monotonic() < self.next:
            return False
        self.next = time.monotonic() + self.period
        return True


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR2, signal.SIGHUP)  # USR2: submitit's time-limit / pre-emption signal; HUP: a closed terminal (an ssh drop)


class StopRequest:
    """Turns SIGINT / SIGTERM / SIGUSR2 into a flag that the step loop polls between steps, so the
    run can write a consistent checkpoint before it exits (CONTRACT §2, interruption)."""

    def __init__(self):
        self.signal = None

    def __enter__(self):
        self._previous = {s: signal.signal(s, self._handle) for s in STOP_SIGNALS}
        return self

    def _handle(self, signum, frame):
        self.signal = signum

    def __exit__(self, *exc):
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    @property
    def requested(self) -> bool:
        return self.signal is not None
