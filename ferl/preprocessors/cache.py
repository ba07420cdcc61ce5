"""Fitted preprocessors kept on disk, so that only the first run of a setting pays for the fit.

A fit is a pure function of the preprocessor's constructor arguments (its ``hparams``: sizes,
n_runs and seed included: every run trains on its own stream from seed + r) and the training
images, so those two are the key. Files are written atomically: concurrent jobs filling the same
cache both train and the last rename wins, with identical contents.

An entry proves itself before anything of it is deserialised. The file ``<class>-<hash>.pt`` is

    ferl-preprocessor-cache 1\\n
    {"key": …, "sha256": …, "bytes": …, "shapes": {name: [sizes], …}}\\n      (one line of JSON)
    <payload: torch.save of {"state_dict", "errors"}, exactly "bytes" long>

and it is used only when the magic line matches, the key is the fit's own, the payload has its
length and sha256, and the shapes are those of the preprocessor and its errors; only then does
``torch.load`` (weights only) read the payload. Any other file there (cut short, other bytes, a fit
of other settings, one written before this format, one that cannot be read) is reported in one
warning line, removed, and the fit is computed again.
"""

import hashlib
import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np
import torch

from ferl.messages import warn
from ferl.run.jsonio import strict_dumps

MAGIC = b"ferl-preprocessor-cache 1\n"


class DamagedEntry(Exception):
    """A cache entry that failed its check: ``reason`` says which, ``identity`` (device, inode) is
    the file that was read (None: it could not be opened)."""

    def __init__(self, reason: str, identity: tuple | None = None):
        super().__init__(reason)
        self.reason, self.identity = reason, identity


def tensor_digest(x: torch.Tensor) -> str:
    """sha256 of a tensor's shape, dtype and values."""
    digest = hashlib.sha256(f"{tuple(x.shape)} {x.dtype}".encode())
    digest.update(x.detach().cpu().contiguous().numpy().data)
    return digest.hexdigest()


def cache_key(preprocessor, images: torch.Tensor) -> str:
    return strict_dumps({"hparams": preprocessor.hparams, "images": tensor_digest(images)}, sort_keys=True, default=str)


def entry_path(preprocessor, key: str, cache_dir) -> Path:
    name = type(preprocessor).__name__.lower()
    return Path(cache_dir) / f"{name}-{hashlib.sha256(key.encode()).hexdigest()[:16]}.pt"


def load_or_fit(preprocessor, images: torch.Tensor, cache_dir, writer=None, **train) -> tuple[np.ndarray, bool]:
    """``preprocessor.train(images)`` (its own streams; ``train``: its further arguments), or the
    state that the same hparams and images saved in ``cache_dir`` before (None: no cache). The file
    is ``<class>-<sha256[:16]>.pt`` (module docstring). Returns (the training errors (R, sweeps),
    whether cached)."""
    if cache_dir is None:
        return preprocessor.train(images, None, writer, **train), False
    key = cache_key(preprocessor, images)
    path = entry_path(preprocessor, key, cache_dir)
    expected = {name: list(x.shape) for name, x in preprocessor.state_dict().items()}
    try:
        state, errors = read_entry(path, key, expected)
    except (FileNotFoundError, NotADirectoryError):  # no entry (yet)
        pass
    except DamagedEntry as e:
        warn(f"preprocessor cache {path} failed its check ({e.reason}): {discard(path, e.identity)}, fitting again")
    else:
        preprocessor.load_state_dict(state)
        return errors.numpy(), True
    errors = preprocessor.train(images, None, writer, **train)
    try:
        write_entry(path, key, preprocessor.state_dict(), errors)
    except OSError as e:  # a full disk, a read-only cache: the fit is done, the next run fits again
        warn(f"preprocessor cache {path} could not be written ({e.strerror or e}): the fit is not kept")
    return errors, False


def write_entry(path: Path, key: str, state_dict: dict, errors: np.ndarray) -> None:
    """The entry (module docstring), atomically: readers never see a half-written file."""
    buffer = io.BytesIO()
    torch.save(
        {
            "state_dict": {k: v.detach().cpu() for k, v in state_dict.items()},
            "errors": torch.from_numpy(np.ascontiguousarray(errors)),
        },
        buffer,
    )
    payload = buffer.getvalue()
    shapes = {**{name: list(x.shape) for name, x in state_dict.items()}, "errors": list(errors.shape)}
    header = strict_dumps(
        {"key": key, "sha256": hashlib.sha256(payload).hexdigest(), "bytes": len(payload), "shapes": shapes},
        sort_keys=True,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(MAGIC + header.encode() + b"\n" + payload)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; caches are meant to be shared
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def entry_header(path) -> dict:
    """The header of the entry at ``path`` (its key, sha256, payload length, shapes), unchecked:
    for looking at a cache, not for loading from it."""
    with open(path, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise ValueError(f"{path} is not a ferl preprocessor cache entry")
        return json.loads(f.readline())


def read_entry(path: Path, key: str, expected: dict) -> tuple[dict, torch.Tensor]:
    """(state_dict, errors) of a checked entry; FileNotFoundError when there is none, DamagedEntry
    (reason, the file's identity) when it fails a check. The payload is deserialised only after
    its length and sha256 match the header."""
    try:
        with open(path, "rb") as f:
            opened = os.fstat(f.fileno())
            raw = f.read()
    except (FileNotFoundError, NotADirectoryError):
        raise
    except OSError as e:
        raise DamagedEntry(f"unreadable: {e.strerror or e}") from None
    identity = (opened.st_dev, opened.st_ino)
    if not raw.startswith(MAGIC):
        raise DamagedEntry("not a ferl cache entry, or one written before entries carried a checksum", identity)
    line, newline, payload = raw[len(MAGIC) :].partition(b"\n")
    try:
        header = json.loads(line) if newline else None
    except ValueError:
        header = None
    if (
        not isinstance(header, dict)
        or not {"key", "sha256", "bytes", "shapes"} <= header.keys()
        or not isinstance(header["shapes"], dict)
    ):
        raise DamagedEntry("its header is cut short or unreadable", identity)
    if header["key"] != key:
        raise DamagedEntry("it holds the fit of other settings or images", identity)
    if len(payload) != header["bytes"]:
        raise DamagedEntry(f"{len(payload)} bytes of payload, its header announces {header['bytes']}", identity)
    if hashlib.sha256(payload).hexdigest() != header["sha256"]:
        raise DamagedEntry("its payload does not match its sha256", identity)
    shapes = header["shapes"]
    if differ := [k for k in {*shapes, *expected} - {"errors"} if shapes.get(k) != expected.get(k)]:
        raise DamagedEntry(
            ", ".join(f"{k} of shape {shapes.get(k)}, the preprocessor's {expected.get(k)}" for k in sorted(differ)),
            identity,
        )
    try:
        saved = torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
        state, errors = saved["state_dict"], saved["errors"]
        loaded = {k: list(v.shape) for k, v in state.items()}, list(errors.shape)
    except Exception as e:  # noqa: BLE001 — a payload that hashes right but does not load: still damaged
        raise DamagedEntry(
            f"its payload does not load: {str(e).splitlines()[0] if str(e) else type(e).__name__}", identity
        ) from None
    if loaded != (expected, shapes.get("errors")):
        raise DamagedEntry("its payload's shapes differ from its header's", identity)
    return state, errors


def discard(path: Path, identity: tuple | None) -> str:
    """Remove a damaged entry — unless another job has meanwhile replaced it by a good one (then
    that one stays). Returns what happened, for the warning."""
    try:
        now = os.stat(path)
        if identity is None or (now.st_dev, now.st_ino) == identity:
            os.remove(path)
    except FileNotFoundError:
        pass
    except OSError as e:
        return f"not removed ({e.strerror or e})"
    return "removed"
