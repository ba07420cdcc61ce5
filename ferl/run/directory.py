"""The run directory (docs/records.md): tb/, summary.json, checkpoints/, records/.

Every file is written atomically (temporary file + rename), so an interruption never
leaves a half-written checkpoint or summary behind. Checkpoints check themselves before they are
used and the last two are kept (``ferl.run.checkpoint``). A checkpoint also remembers how long each
TensorBoard event file was when it was written; resuming cuts the files back to that, so the
points a resumed run logs again appear once, not twice.
"""

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
from ferl.run.jsonio import strict_dumps
from ferl.run.lock import LOCK_FILE, RunLock, held

TB_EVENTS = "events.out.tfevents.*"  # the run's own event files (tb/analysis/ is analyze.py's)
HYDRA_OWN = {".hydra", "train.log"}  # what a launch writes into a run directory before its run starts
HYDRA_FILES = ("config.yaml", "hydra.yaml", "overrides.yaml")  # .hydra/'s (ferl/run/claim.py writes them)
HYDRA_COPY = Path("checkpoints") / "hydra"  # the run's own .hydra/ files, kept at its first checkpoint


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
    """Remove a run directory that holds only Hydra's own files and empty folders (a config that
    failed), under its lock: a fresh run directory that another process holds (it has not written
    more than that yet) is that process's, and is left alone."""
    if not is_new(path):
        return
    lock = held(path) or RunLock(path)
    if lock.fd is None and not lock.acquire():
        return
    try:
        if is_new(path):
            shutil.rmtree(path, ignore_errors=True)
            if path.parent.is_dir() and not any(path.parent.iterdir()):
                path.parent.rmdir()
    finally:
        lock.release()


def is_new(path: Path) -> bool:
    """Whether ``path`` is a directory that holds only Hydra's files, a lock and empty folders."""
    own = HYDRA_OWN | {LOCK_FILE}
    return path.is_dir() and all(p.name in own or (p.is_dir() and not any(p.iterdir())) for p in path.iterdir())


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


@contextmanager
def atomic_dir(path: Path):
    """Yield a temporary folder beside ``path``; on success it becomes ``path`` as a whole (a
    folder already there is replaced), so an interruption never leaves part of it under its name."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        yield tmp
        os.chmod(tmp, 0o755)  # mkdtemp creates 0700; results are meant to be shared
        if path.exists():  # renamed aside first: a folder cannot be renamed over a full one
            old = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
            os.replace(path, old / path.name)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def remove_leftovers(path: Path) -> list[Path]:
    """Remove what ``atomic_path`` and ``atomic_dir`` left in the run directory ``path`` when a
    process was killed mid-write (``.<name>.*.tmp``): called once its owner holds the run's lock,
    so none of them is being written. The checkpoints' own leftovers are ``RunDir.resume``'s."""
    found = [
        p
        for folder in (path, path / "records", path / ".hydra", path / HYDRA_COPY)
        if folder.is_dir()
        for p in folder.glob(".*.tmp")
        if p.is_file()
    ]
    found += [p for folder in (path, path / "checkpoints") for p in folder.glob(".*hydra.*.tmp") if p.is_dir()]
    for p in found:
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    return found


def restore_hydra_files(path: Path) -> None:
    """Put the run's own ``.hydra/`` files back from the copy taken at its first checkpoint, where
    they differ: runs made before train.py wrote ``.hydra/`` itself (ferl/run/claim.py) had it
    rewritten by Hydra at every launch, a refused one included."""
    for name in HYDRA_FILES:
        kept, own = path / HYDRA_COPY / name, path / ".hydra" / name
        if kept.is_file() and not (own.is_file() and own.read_bytes() == kept.read_bytes()):
            with atomic_path(own) as tmp:
                shutil.copyfile(kept, tmp)


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
        with atomic_path(self.path / "records" / f"{name}.npz") as tmp, open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays, per_run=per_run)

    def save_json(self, name: str, content: dict) -> None:
        """``records/<name>.json``."""
        with atomic_path(self.path / "records" / f"{name}.json") as tmp:
            tmp.write_text(strict_dumps(content, indent=2) + "\n")

    def save_checkpoint(self, state: dict, writer=None) -> None:
        """Write ``state``; with the run's SummaryWriter, flush it first and record the length
        of every event file, the point ``resume`` rolls the log back to."""
        if writer is not None:
            writer.flush()
            state = {**state, "tb_sizes": {p.name: p.stat().st_size for p in self.tb.glob(TB_EVENTS)}}
        self.keep_hydra_files()
        checkpoint.write(self.checkpoints, state, self.identity)

    def keep_hydra_files(self) -> None:
        """Copy ``.hydra/``'s files at the run's first checkpoint (``restore_hydra_files``), as one
        folder renamed into place: a copy cut short by a kill (made before that) is made again."""
        source, copy = self.path / ".hydra", self.path / HYDRA_COPY
        names = [name for name in HYDRA_FILES if (source / name).is_file()]
        if names and not all((copy / name).is_file() for name in names):
            with atomic_dir(copy) as tmp:
                for name in names:
                    shutil.copyfile(source / name, tmp / name)

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
            os.replace(
                self.checkpoints / checkpoint.LAST, self.checkpoints / (checkpoint.LAST + checkpoint.DAMAGED_SUFFIX)
            )
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
            tmp.write_text(strict_dumps(summary, indent=2) + "\n")


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


STOP_SIGNALS = (
    signal.SIGINT,
    signal.SIGTERM,
    signal.SIGUSR2,
    signal.SIGHUP,
)  # USR2: submitit's time-limit / pre-emption signal; HUP: a closed terminal (an ssh drop)


class StopRequest:
    """Turns SIGINT / SIGTERM / SIGUSR2 into a flag that the step loop polls between steps, so the
    run can write a consistent checkpoint before it exits (docs/reliability.md, interruption)."""

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
