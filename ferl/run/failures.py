"""One line for a run that a full disk, an unwritable directory or a signal stopped.

A write that fails for want of space (ENOSPC, EDQUOT), on a read-only file system (EROFS) or
beyond the file-size limit (EFBIG, ``ulimit -f``) is not a bug of the run: its line says what
happened, which file could not be written, that the last good checkpoint is kept and how to go
on. It is printed before anything else is tried (the run's own log may be on the same full disk;
docs/reliability.md). A signal that stopped a run (``ferl.run.directory.StopRequest``) after its
checkpoint is written ends it with ``Interrupted`` and a line that says where it stopped.
"""

import errno
import os
import re
import signal
from contextlib import contextmanager
from pathlib import Path
from typing import cast

DISK = {
    errno.ENOSPC: ("no space left on device", "free space"),
    errno.EDQUOT: ("disk quota exceeded", "free space"),
    errno.EROFS: ("read-only file system", "make it writable"),
    errno.EFBIG: ("file larger than the file-size limit (ulimit -f)", "raise the limit"),
}
NOT_A_DIRECTORY = (errno.ENOTDIR, errno.EEXIST)  # a file stands where a directory should be
TEMPORARY = re.compile(r"^\.(?P<name>.+)\.[^.]+\.tmp$")  # atomic writes' ``.<name>.<random>.tmp``
UNITS = ("step", "episode", "epoch")  # what a phase's checkpoint state counts its progress in


class Interrupted(SystemExit):
    """A stop signal ended the run once its checkpoint was written; exit code 128 + signal,
    the shell's convention (130 for SIGINT, 129 for SIGHUP, 143 for SIGTERM)."""

    def __init__(self, signum: int, where: str):
        super().__init__(128 + signum)
        self.signum, self.where = signum, where

    def __reduce__(self):
        # A joblib worker's job hands it to the launching process pickled; the default rebuilds
        # it from ``args`` (the exit code alone), which this __init__ does not take.
        return (type(self), (self.signum, self.where))


@contextmanager
def writing(path):
    """Name ``path`` in an OSError raised inside that names no file (a failing ``write()`` on an
    open file does not), so that the error line can say which file could not be written."""
    try:
        yield
    except OSError as e:
        if e.filename is None:
            e.filename = str(path)
        raise


def disk_error(e: BaseException) -> OSError | None:
    """The first OSError of a full disk, a read-only file system or the file-size limit behind
    ``e`` (itself, its cause or its context: the write that failed first, not the writer
    flushed on the way out that failed after it; the first that names its file), else None."""
    seen: set[int] = set()
    found: list[OSError] = []
    link: BaseException | None = e
    while link is not None and id(link) not in seen:
        if isinstance(link, OSError) and link.errno in DISK:
            found.append(link)
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    named = [f for f in found if f.filename is not None]  # a library's own first try may name none
    return (named or found)[-1] if found else None


def written_file(e: OSError, shown=str) -> str:
    """The file the failing write was for: an atomic write's temporary file is named as the
    file it was to become."""
    name = e.filename if e.filename is not None else _file_in_traceback(e)
    if name is None:
        return "a file"
    path = Path(name)
    if match := TEMPORARY.match(path.name):
        path = path.with_name(match["name"])
    return shown(path)


def _file_in_traceback(e: BaseException) -> str | None:
    """The file name the innermost frame that knows one held (TensorBoard's writer thread
    writes its event file by ``filename``; its error is raised again in the run's thread)."""
    tb, frames = e.__traceback__, []
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    for frame in reversed(frames):
        for key in FILE_LOCALS:
            if isinstance(value := frame.f_locals.get(key), (str, bytes, Path)):  # TensorBoard's: bytes
                return os.fsdecode(value)
    return None


FILE_LOCALS = ("filename", "file_name", "tmp", "path")


def disk_line(e: OSError, run_path: Path, shown=str) -> str:
    """``no space left on device writing runs/x/checkpoints/last.pt (errno ENOSPC); the last good
    checkpoint is kept: free space, then resume=true hydra.run.dir=runs/x``."""
    code = cast(int, e.errno)  # disk_error's: one of DISK
    what, remedy = DISK[code]
    head = f"{what} writing {written_file(e, shown)} (errno {errno.errorcode[code]})"
    if (Path(run_path) / "checkpoints" / "last.pt").is_file():
        return f"{head}; the last good checkpoint is kept: {remedy}, then resume=true hydra.run.dir={shown(run_path)}"
    return f"{head}; no checkpoint was written yet: {remedy}, then run the command again"


HYDRA_OS_ERROR = re.compile(r"^(?P<kind>\w+Error): \[Errno (?P<no>\d+)\] (?P<why>[^:']+)(: '(?P<path>.*)')?$")


def hydra_os_error(report: str) -> str | None:
    """The one line for Hydra's report of an OSError it met before main() ran — creating the
    run directory or writing ``.hydra/`` into it: the path and the reason, not the traceback."""
    lines = [ln.strip() for ln in report.splitlines() if ln.strip()]
    if not any(ln.startswith("Traceback") for ln in lines):
        return None
    match = next((m for ln in reversed(lines) if (m := HYDRA_OS_ERROR.match(ln))), None)
    if match is None:
        return None
    no, path = int(match["no"]), match["path"] or "the run directory's .hydra/ files"
    name = errno.errorcode.get(no, match["no"])
    if no in DISK:
        what, remedy = DISK[no]
        return f"{what} writing {path} (errno {name}); nothing of the run was written: {remedy}, then run it again"
    if no in NOT_A_DIRECTORY:
        return (
            f"cannot create the run directory {path}: a file stands where a directory should be "
            f"(errno {name}); choose another hydra.run.dir / hydra.sweep.dir"
        )
    return f"cannot create the run directory {path}: {match['why']} (errno {name}); choose another hydra.run.dir"


def where(phase: str | None, state, done: list) -> str:
    """Where a run stopped: ``phase 'actor', episode 200`` (the unfinished phase's progress in its
    checkpoint state), or ``the end of phase 'predictors'``."""
    if phase is None:
        return f"the end of phase {done[-1]!r}" if done else "the start"
    count = _count(state) if isinstance(state, dict) else None
    return f"phase {phase!r}" + (f", {count[0]} {count[1]}" if count else "")


def _count(state: dict):
    """(unit, value) of the first progress counter in ``state`` or one level below it."""
    for node in (state, *(v for v in state.values() if isinstance(v, dict))):
        for unit in UNITS:
            if isinstance(node.get(unit), int):
                return unit, node[unit]
    return None


def interrupted_line(signum: int, at: str, run_path: Path, shown=str) -> str:
    """``interrupted by SIGINT at phase 'actor', episode 200: checkpoint written to runs/x/checkpoints;
    resume=true hydra.run.dir=runs/x continues``."""
    return (
        f"interrupted by {signal.Signals(signum).name} at {at}: checkpoint written to "
        f"{shown(Path(run_path) / 'checkpoints')}; resume=true hydra.run.dir={shown(run_path)} continues"
    )


def quiet_disk_errors_in_threads() -> None:
    """A disk error in a writer thread (TensorBoard's) prints no traceback: the thread hands it
    to the run's thread, whose line reports it. Other thread errors are printed as before."""
    import threading

    previous = threading.excepthook

    def hook(args):
        if disk_error(args.exc_value) is None:
            previous(args)

    threading.excepthook = hook
