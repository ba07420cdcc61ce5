"""A run's analysis kept while nothing it was made from has changed.

A run's ``analysis/`` is a function of the run's ``summary.json``, its ``records/``, the code
that analyses them (ferl and every registered plug-in package, e.g. ``reproduction``) and what the
plug-ins registered (``ferl.analysis.dispatch.REGISTRY``), and of nothing else. ``inputs_digest`` hashes all of these (SHA-256 of every file's name and bytes); the
analysis writes it last, as ``analysis/.inputs.sha256``, beside ``analysis/.outcome.json`` (the
run's line of a sweep report and the files it wrote). A later ``analyze.py`` finds the same digest
and every file it listed, and no other, and keeps the folder as it is: a sweep analysed again
redoes only the runs whose records changed (``--force``: every run). An analysis cut short
writes no digest, so it is done again; so is one whose folder was touched since.
"""

from __future__ import annotations

import hashlib
import importlib
import json
from collections.abc import Callable, Iterable, Sequence
from functools import cache
from pathlib import Path

import matplotlib
import numpy as np

from ferl.analysis.claims import Claim, ClaimResult, Measured
from ferl.analysis.dispatch import Registry
from ferl.analysis.report import RunOutcome

DIGEST = ".inputs.sha256"
OUTCOME = ".outcome.json"
CLAIMS = "claims.json"  # the run's judged claims, as the analysis writes them
CODE_PACKAGES = ("ferl",)  # besides the plug-ins: the package whose code draws every figure


def _hash_files(h, paths: Iterable[Path], root: Path) -> None:
    for path in paths:
        h.update(str(path.relative_to(root)).encode() + b"\0")
        h.update(hashlib.sha256(path.read_bytes()).digest())


@cache
def code_digest(plugins: tuple[str, ...]) -> str:
    """SHA-256 of the source of ferl and of each plug-in's package (every ``*.py`` below it), and
    of the versions of the libraries that draw and compute (matplotlib, NumPy)."""
    h = hashlib.sha256(f"matplotlib {matplotlib.__version__} numpy {np.__version__}".encode())
    for name in (*CODE_PACKAGES, *plugins):
        module = importlib.import_module(name.split(".")[0])
        root = Path(module.__file__ or "").parent
        _hash_files(h, sorted(root.rglob("*.py")), root.parent)
    return h.hexdigest()


def registry_key(registry: Registry) -> str:
    """What is registered, in words: the reference, each chapter's model and claims, the analysed
    environment kinds and the plug-in modules (a run analysed under another registry is redrawn)."""
    return json.dumps(
        [
            registry.reference,
            [(c.model, [(claim.source, claim.text) for claim in c.claims]) for c in registry.chapters],
            sorted(registry.environments),
            list(registry.modules),
        ]
    )


def inputs_digest(run_dir: Path, registry: Registry) -> str:
    """SHA-256 of what the run's analysis is made from: summary.json, every file of records/, the
    code (``code_digest``) and what is registered (``registry_key``)."""
    h = hashlib.sha256(code_digest(tuple(registry.modules)).encode() + registry_key(registry).encode())
    records = run_dir / "records"
    files = [run_dir / "summary.json", *sorted(p for p in records.rglob("*") if p.is_file())]
    _hash_files(h, [p for p in files if p.is_file()], run_dir)
    return h.hexdigest()


def _files(out: Path) -> list[str]:
    """What the analysis folder holds (its two bookkeeping files aside), relative to it."""
    return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and p.name not in (DIGEST, OUTCOME))


def save(out: Path, outcome: RunOutcome, digest: str, tb_files: list[str]) -> None:
    """Record what the analysis in ``out`` wrote, then its digest (last: a folder without one is
    an analysis that did not finish). ``tb_files``: its TensorBoard log's files."""
    record = {
        "experiment": outcome.experiment,
        "task": outcome.task,
        "verdicts": outcome.verdicts,
        "figures": outcome.figures,
        "files": _files(out),
        "tb_files": tb_files,
    }
    (out / OUTCOME).write_text(json.dumps(record, indent=1))
    (out / DIGEST).write_text(digest + "\n")


def load(
    run_dir: Path, out: Path, digest: Callable[[], str], tb_dir: Path, claims: Sequence[Claim]
) -> RunOutcome | None:
    """The run's outcome as its kept analysis recorded it, or None when the analysis must be made
    again: none kept, another digest, a file missing or added, a TensorBoard log changed, or a
    judged claim that no registered chapter holds any more (``claims``: every registered claim).
    ``digest`` gives the inputs' digest (``inputs_digest``); it is asked only where a digest was
    kept to compare it with, since hashing the records is what a run never analysed need not pay."""
    try:
        kept_digest = (out / DIGEST).read_text().strip()
    except (OSError, ValueError):
        return None
    if kept_digest != digest():
        return None
    try:
        record = json.loads((out / OUTCOME).read_text())
        judged = json.loads((out / CLAIMS).read_text())
    except (OSError, ValueError):
        return None
    tb_files = sorted(p.name for p in tb_dir.glob("*")) if tb_dir.is_dir() else []
    if record.get("files") != _files(out) or record.get("tb_files") != tb_files:
        return None
    by_key = {c.key: c for c in claims}
    found = [by_key.get((j["claim"], j["source"])) for j in judged]
    if any(c is None for c in found):
        return None
    # the sweep reads a run's claims by their text and verdict, never the measured value again
    results = [ClaimResult(c, Measured(None, j["measured"]), j["verdict"]) for c, j in zip(found, judged) if c]
    figures = [(str(name), str(caption)) for name, caption in record["figures"]]
    return RunOutcome(run_dir, record["experiment"], record["task"], "analyzed", record["verdicts"], results, figures)
