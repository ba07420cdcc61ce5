"""A full disk (or a read-only one, or the file-size limit) for train.py in a subprocess.

Put this folder on PYTHONPATH and set FERL_FAULT=ERRNO:ROOT:GLOB:SKIP, e.g.
``ENOSPC:/tmp/x/run:.last.pt.*.tmp:1``: once more than SKIP files whose name matches GLOB have
been opened for writing under ROOT, the disk is "full": every write() to a file under ROOT fails
with OSError(ERRNO) and no file name, as a real write() on a full disk does. The files are
opened as ever; only their writes fail (the run's train.log too).
FERL_SLOW_IMPORT=SECONDS:MODULE:MARKER instead makes ``import MODULE`` wait (after touching MARKER),
so that a test can send SIGINT while train.py's imports run.
"""

import builtins
import errno
import fnmatch
import io
import os
import time

FAULT = os.environ.get("FERL_FAULT")
SLOW = os.environ.get("FERL_SLOW_IMPORT")


class _Disk:
    full = False
    opened = 0


def _failing(file, name: str):
    """``file`` whose write() raises once the disk is full."""

    class Failing:
        def __init__(self, inner):
            self._inner = inner

        def write(self, data):
            if _Disk.full:
                raise OSError(_ERRNO, os.strerror(_ERRNO))
            return self._inner.write(data)

        def writelines(self, lines):
            for line in lines:
                self.write(line)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._inner.close()

        def __iter__(self):
            return iter(self._inner)

        def __getattr__(self, key):
            return getattr(self._inner, key)

    return Failing(file)


def _watch(path, mode) -> bool:
    """Count a write-open under ROOT; True when its writes are to be watched."""
    if not isinstance(path, (str, bytes, os.PathLike)) or not any(c in str(mode) for c in "wax+"):
        return False
    path = os.path.abspath(os.fsdecode(path))
    if not path.startswith(_ROOT):
        return False
    if fnmatch.fnmatch(os.path.basename(path), _GLOB):
        _Disk.opened += 1
        _Disk.full = _Disk.full or _Disk.opened > _SKIP
    return True


def _patched_open(real):
    def patched(file, mode="r", *args, **kwargs):
        f = real(file, mode, *args, **kwargs)
        return _failing(f, file) if _watch(file, mode) else f

    return patched


def _patched_fdopen(real):
    def patched(fd, mode="r", *args, **kwargs):
        f = real(fd, mode, *args, **kwargs)
        try:
            name = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            return f
        return _failing(f, name) if _watch(name, mode) else f

    return patched


if FAULT:
    _name, _ROOT, _GLOB, _skip = FAULT.split(":")
    _ERRNO, _ROOT, _SKIP = getattr(errno, _name), os.path.abspath(_ROOT), int(_skip)
    builtins.open = io.open = _patched_open(io.open)
    os.fdopen = _patched_fdopen(os.fdopen)

if SLOW:
    import importlib.abc
    import sys

    class _SlowHydra(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            seconds, module, marker = SLOW.split(":", 2)
            if name == module:
                open(marker, "w").close()
                time.sleep(float(seconds))
            return None

    sys.meta_path.insert(0, _SlowHydra())
