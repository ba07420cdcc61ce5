"""Checkpoint files that prove themselves before they are used (docs/reliability.md).

A checkpoint file is a fixed header, a JSON header and the payload (``torch.save`` of the state),
with everything after the fixed header covered by one SHA-256::

    bytes  0–7    magic  b"FERLCKPT"
    bytes  8–11   format version, uint32 little-endian (FORMAT)
    bytes 12–15   length H of the JSON header, uint32 little-endian
    bytes 16–23   length P of the payload, uint64 little-endian
    bytes 24–55   SHA-256 of the JSON header and the payload
    bytes 56–     the JSON header (UTF-8), then the P bytes of the payload

The JSON header holds what the checkpoint was written under (``RunIdentity``): the run's resolved
job config, its config-group choices (``experiment``, ``actor``, …) and the device it ran on. A
file is read whole, and its length and checksum are checked before ``torch.load`` sees a byte of
the payload, so a truncated or overwritten file is named as such and never unpickled.

The run keeps two: ``last.pt`` and the one before it, ``previous.pt`` (a hard link to the old
``last.pt`` is made ``previous.pt`` before the new one replaces ``last.pt``: at every moment both
names hold a complete checkpoint). Resuming takes the newest good one (``newest_good``).
"""

import hashlib
import io
import json
import os
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ferl import messages
from ferl.run.failures import writing
from ferl.run.jsonio import strict_dumps

MAGIC = b"FERLCKPT"
FORMAT = 1
FIXED = struct.Struct("<8sIIQ32s")  # magic, format, header length, payload length, sha256
LAST, PREVIOUS = "last.pt", "previous.pt"
DAMAGED_SUFFIX = ".damaged"  # a damaged last.pt set aside when the run resumes from previous.pt
OLD_FORMAT = (b"PK\x03\x04", b"\x80")  # torch.save's zip file and its legacy pickle: ferl before FORMAT 1


class CheckpointError(Exception):
    """A checkpoint file that cannot be used; the message says which and why, in one line."""


@dataclass(frozen=True)
class RunIdentity:
    """What a checkpoint was written under: the resolved job config, the config-group choices
    (``hydra.runtime.choices``) and the device the run ran on (``cpu``, ``cuda``)."""

    config: dict
    choices: dict = field(default_factory=dict)
    device: str = "cpu"


@dataclass
class Checkpoint:
    """A checkpoint whose length and checksum were checked: its header and its payload's bytes."""

    path: Path
    identity: RunIdentity
    payload: bytes

    def state(self) -> dict:
        """The payload deserialised (only ever called on a checked file)."""
        return torch.load(io.BytesIO(self.payload), map_location="cpu", weights_only=False)


def encode(state: dict, identity: RunIdentity | None) -> tuple[bytes, memoryview]:
    """The file's bytes in two pieces: the fixed and the JSON header, then the payload. The payload
    is torch.save's buffer itself, hashed and written where it lies: a run's records can make it
    hundreds of MB, and each copy of it costs as much as writing it."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    payload = buffer.getbuffer()
    header = strict_dumps(
        {
            "format": FORMAT,
            "config": identity.config if identity else None,
            "choices": identity.choices if identity else {},
            "device": identity.device if identity else None,
        }
    ).encode()
    digest = hashlib.sha256(header)
    digest.update(payload)
    return FIXED.pack(MAGIC, FORMAT, len(header), len(payload), digest.digest()) + header, payload


def decode(path: Path, data: bytes, name: str | None = None) -> Checkpoint:
    """Check ``data`` (the bytes of ``path``, called ``name`` in messages) before anything of it
    is deserialised; raise CheckpointError saying what is wrong."""
    name = name or str(path)
    if not data:
        raise CheckpointError(f"{name} is empty (0 bytes)")
    if data.startswith(OLD_FORMAT):
        raise CheckpointError(
            f"{name} is in ferl's checkpoint format from before format {FORMAT} (a plain torch.save "
            f"file, without checksum or config), which cannot be checked and is not read"
        )
    if not (data.startswith(MAGIC) or MAGIC.startswith(data)):
        raise CheckpointError(f"{name} is not a ferl checkpoint (it does not start with {MAGIC.decode()})")
    if len(data) < FIXED.size:
        raise CheckpointError(f"{name} is truncated ({len(data)} bytes, shorter than its {FIXED.size}-byte header)")
    _, version, h, p, digest = FIXED.unpack_from(data)
    if version != FORMAT:
        raise CheckpointError(
            f"{name} has checkpoint format {version}; this ferl reads format {FORMAT}"
            + (" (written by a newer ferl)" if version > FORMAT else "")
        )
    expected = FIXED.size + h + p
    if len(data) < expected:
        raise CheckpointError(f"{name} is truncated ({len(data)} of {expected} bytes)")
    if len(data) > expected:
        raise CheckpointError(
            f"{name} is damaged: {len(data) - expected} bytes beyond its recorded length of {expected}"
        )
    if hashlib.sha256(data[FIXED.size :]).digest() != digest:
        raise CheckpointError(f"{name} is damaged: checksum mismatch (its bytes changed after it was written)")
    header = json.loads(data[FIXED.size : FIXED.size + h])
    identity = RunIdentity(header["config"], header.get("choices") or {}, header.get("device"))
    return Checkpoint(path, identity, data[FIXED.size + h :])


def read(path: Path, name: str | None = None) -> Checkpoint:
    """The checked checkpoint at ``path`` (CheckpointError when it is missing or damaged)."""
    name = name or str(path)
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise CheckpointError(f"{name} is missing") from None
    except OSError as e:
        raise CheckpointError(f"{name} cannot be read: {e.strerror or e}") from None
    return decode(Path(path), data, name)


def exists(directory: Path) -> bool:
    """Whether ``directory`` holds a checkpoint file (good or not)."""
    return any((Path(directory) / name).exists() for name in (LAST, PREVIOUS))


def newest_good(directory: Path, warn=None) -> Checkpoint | None:
    """The newest checkpoint of ``directory`` that passes its checks: ``last.pt``, else
    ``previous.pt`` (with one warning line naming what is wrong with ``last.pt``); None when the
    directory holds neither file; CheckpointError naming every file's problem when none is good."""
    directory = Path(directory)
    if not exists(directory):
        return None
    problems = []
    for name in (LAST, PREVIOUS):
        try:
            found = read(directory / name, f"{directory.name}/{name}")
        except CheckpointError as e:
            problems.append(str(e))
            continue
        if problems:
            (warn or messages.warn)(
                f"{directory.parent}: {problems[0]}; resuming from the checkpoint before it, "
                f"{directory.name}/{PREVIOUS}"
            )
        return found
    raise CheckpointError("no good checkpoint: " + "; ".join(problems))


def write(directory: Path, state: dict, identity: RunIdentity | None) -> None:
    """Write ``state`` as ``last.pt``, the former ``last.pt`` kept as ``previous.pt``. The new
    file is complete on disk (flushed and synced) before any name changes, so an interruption
    or a full disk leaves both earlier checkpoints as they were."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    head, payload = encode(state, identity)
    last, previous = directory / LAST, directory / PREVIOUS
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{LAST}.", suffix=".tmp")
    try:
        with writing(last), os.fdopen(fd, "wb") as f:  # a full disk's error names last.pt
            f.write(head)
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        if last.exists():
            keep_as_previous(last, previous)
        os.replace(tmp, last)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def keep_as_previous(last: Path, previous: Path) -> None:
    """``previous`` becomes the file ``last`` is, atomically: a hard link renamed over it (both
    names stay complete throughout); where links are not supported, ``last`` is renamed."""
    link = previous.with_name(f".{previous.name}.link")
    try:
        if link.exists():
            link.unlink()
        os.link(last, link)
        os.replace(link, previous)
    except OSError:
        os.replace(last, previous)


def stale_temporary_files(directory: Path) -> list[Path]:
    """What an interrupted ``write`` (kill -9) left behind."""
    return [*Path(directory).glob(f".{LAST}.*.tmp"), *Path(directory).glob(f".{PREVIOUS}.link")]
