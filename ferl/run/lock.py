"""One process owns a run directory at a time (docs/reliability.md, "One process per run directory").

The owner holds an advisory lock, ``fcntl.flock`` on ``DIR/.ferl.lock``, for as long as it works
in DIR, and writes its pid and host into the file, so that a second process is refused in one line
that names who holds it. Why flock: the kernel drops it when its process ends, however it ends
(kill -9 and a node that is re-queued included), so a lock file whose flock is free was left by a
process that is gone; it is stale, and the next process takes it over without anyone's help.

The owner removes the file when it lets go, so that a finished run holds no lock file. A process
that opened the file just before it was removed may win the flock of that removed file; it then
sees that the name no longer leads to the file it locked and starts again on the name (the lock is
the file the name leads to, never an inode someone still holds open).
"""

import fcntl
import json
import os
import socket
from pathlib import Path

LOCK_FILE = ".ferl.lock"

_HELD: dict[str, "RunLock"] = {}  # run directory (absolute) → the lock this process holds on it


class RunLock:
    """The lock of one run directory; ``acquire`` never waits, ``release`` is safe to repeat."""

    def __init__(self, run_path: str | Path) -> None:
        self.file = Path(os.path.abspath(run_path)) / LOCK_FILE
        self.fd: int | None = None
        self.left_by: str | None = None  # the holder a stale lock file named, when it was taken over

    def acquire(self) -> bool:
        """Take the lock (True), or find it held by another process (False)."""
        self.file.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.file, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                return False
            if names_file(self.file, fd):
                break
            os.close(fd)  # its holder removed the file we locked: lock the one the name leads to now
        self.fd = fd
        self.left_by = describe(read_text(fd))
        write_owner(fd)
        _HELD[str(self.file.parent)] = self
        return True

    def release(self) -> None:
        """Let go: remove the file (if it is still ours) while the flock is held, then drop the flock."""
        if self.fd is None:
            return
        if names_file(self.file, self.fd):
            self.file.unlink()
        os.close(self.fd)
        self.fd = None
        _HELD.pop(str(self.file.parent), None)


def held(run_path) -> RunLock | None:
    """The lock this process holds on ``run_path``, if any."""
    return _HELD.get(os.path.abspath(run_path))


def holder(run_path) -> str | None:
    """Who holds ``run_path``'s lock now ("pid N on host H"), or None when nobody does. Writes
    nothing: the file is opened read-only and never created. Used to name the holder in a refusal
    that is decided anyway; the shared flock it takes when the lock is free lasts microseconds."""
    try:
        fd = os.open(Path(run_path) / LOCK_FILE, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    try:
        return (
            (describe(read_text(fd)) or "another process (it has not written its name yet)")
            if flock_taken(fd)
            else None
        )
    finally:
        os.close(fd)


def flock_taken(fd: int) -> bool:
    """Whether a process holds an exclusive flock on the open file ``fd``: a shared non-blocking
    flock fails then; where it succeeds it is dropped at once (it lasts microseconds)."""
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    fcntl.flock(fd, fcntl.LOCK_UN)
    return False


def names_file(path: Path, fd: int) -> bool:
    """Whether ``path`` still leads to the open file ``fd``."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    own = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (own.st_dev, own.st_ino)


def write_owner(fd: int) -> None:
    """This process's pid and host, written over the file's content in place."""
    data = (json.dumps({"pid": os.getpid(), "host": socket.gethostname()}) + "\n").encode()
    os.pwrite(fd, data, 0)
    os.ftruncate(fd, len(data))


def read_text(fd: int) -> str:
    return os.pread(fd, 4096, 0).decode(errors="replace")


def describe(text: str) -> str | None:
    """ "pid N on host H" from a lock file's content (None when it names nobody)."""
    try:
        owner = json.loads(text)
        return f"pid {owner['pid']} on host {owner['host']}"
    except (ValueError, TypeError, KeyError):
        return None
