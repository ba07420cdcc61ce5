"""Fault injection (issue 24): every kind of file ferl writes — checkpoints, preprocessor cache
entries, records (records/*.npz, records/run.json), summary.json — damaged in three ways and the
outcome checked: cut short (``truncated``), its second half replaced by other bytes of the same
length (``other_bytes``), and a valid file of another shape (``other_shape``: a plain torch.save
checkpoint, an npz with one run fewer, a JSON array, another fit's cache entry).

| file                     | outcome expected                                                              |
| ------------------------ | ----------------------------------------------------------------------------- |
| checkpoints/last.pt      | resume: one warning line, falls back to previous.pt, ends as uninterrupted    |
| last.pt and previous.pt  | resume: one error line naming both and what is wrong, exit 2, run dir as was  |
| preprocessor cache entry | next run: one warning line, the entry removed and fitted again, same numbers  |
| records/*.npz, run.json  | analyze.py: one error line naming the run (and the file), exit 1, others done |
| summary.json             | analyze.py as above; resume=true writes it again from the last checkpoint     |

and an exception inside a phase: one line naming the phase and the run, the traceback in the run's
train.log, exit 1, and the last checkpoint resumes to the uninterrupted run's numbers.
"""

import hashlib
import json
import os
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import RESUMABLE_TMAZE, TINY_ALGORITHM1, assert_same_tb_log, run_train
from ferl.run import checkpoint
from ferl.run.checkpoint import CheckpointError, RunIdentity

TMAZE = RESUMABLE_TMAZE  # checkpoints after episodes 100 and 200 and after the actor phase
PIXEL = [
    "experiment=table5_1_pixel",
    "n_runs=2",
    "env.reservoir_size=5",
    "preprocessor.sweeps=20",
    *TINY_ALGORITHM1,
]
WAYS = ("truncated", "other_bytes", "other_shape")


# ---- damage ----------------------------------------------------------------------------------------
def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def other_bytes(path: Path) -> None:
    """The second half replaced by other bytes: the same length, the header (magic) intact."""
    data = path.read_bytes()
    half = len(data) // 2
    path.write_bytes(data[:half] + bytes((b + 1) % 256 for b in data[half:]))


def other_shape(path: Path) -> None:
    """A valid file of the same kind that is not what ferl wrote there."""
    if path.suffix == ".pt" and path.parent.name == "checkpoints":  # the format before checksums
        torch.save(checkpoint.read(path).state(), path)
    elif path.suffix == ".pt":  # the preprocessor cache: a good entry of another fit
        from ferl.preprocessors.cache import write_entry

        write_entry(path, "another fit", {"W": torch.zeros(3, 4)}, np.zeros((2, 5)))
    elif path.suffix == ".npz":  # the same arrays, one run fewer
        with np.load(path) as f:
            arrays = {k: f[k][:1] if f[k].ndim and f[k].shape[0] == 2 else f[k] for k in f.files}
        with open(path, "wb") as f:
            np.savez_compressed(f, **arrays)
    else:  # JSON: an array where an object was
        path.write_text("[]\n")


DAMAGE = {"truncated": truncate, "other_bytes": other_bytes, "other_shape": other_shape}


def snapshot(run_dir: Path) -> dict:
    """Every file under ``run_dir`` and a hash of its bytes."""
    return {
        p.relative_to(run_dir).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(run_dir.rglob("*"))
        if p.is_file()
    }


def records(run_dir: Path) -> dict:
    out = {}
    for path in sorted((run_dir / "records").glob("*.npz")):
        with np.load(path) as f:
            out |= {f"{path.stem}/{k}": f[k] for k in f.files}
    return out


def metrics(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())["metrics"]


def assert_same_run(got: Path, want: Path) -> None:
    assert metrics(got) == metrics(want)
    a, b = records(got), records(want)
    assert a.keys() == b.keys()
    for key in b:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert_same_tb_log(got, want)


def stderr_lines(result) -> list[str]:
    """stderr without progress bars (tqdm redraws with carriage returns)."""
    return [
        ln
        for ln in result.stderr.replace("\r", "\n").splitlines()
        if ln.strip() and "%|" not in ln and not ln.startswith("warning: Embedding dir exists")
    ]


# ---- the checkpoint format itself (in process) ---------------------------------------------------
IDENTITY = RunIdentity({"n_runs": 2, "seed": 0}, {"experiment": "x"}, "cpu")


def test_write_read_and_keep_the_last_two(tmp_path):
    for step in range(3):
        checkpoint.write(tmp_path, {"step": step, "w": torch.arange(4.0) * step}, IDENTITY)
    last, previous = checkpoint.read(tmp_path / "last.pt"), checkpoint.read(tmp_path / "previous.pt")
    assert last.state()["step"] == 2 and previous.state()["step"] == 1
    assert last.identity == IDENTITY
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt", "previous.pt"]  # no temporary left


@pytest.mark.parametrize(
    "damage, problem",
    [
        (lambda d: d[:10], "is truncated (10 bytes, shorter than its 56-byte header)"),
        (lambda d: d[:-1], "is truncated ("),
        (lambda d: b"", "is empty (0 bytes)"),
        (lambda d: d + b"x", "1 bytes beyond its recorded length"),
        (lambda d: d[:-5] + bytes(5), "checksum mismatch"),
        (lambda d: b"GARBAGE!" * 20, "is not a ferl checkpoint (it does not start with FERLCKPT)"),
        (
            lambda d: d[:8] + struct.pack("<I", 2) + d[12:],
            "has checkpoint format 2; this ferl reads format 1 (written by a newer ferl)",
        ),
    ],
)
def test_each_damage_is_named_before_anything_is_unpickled(tmp_path, monkeypatch, damage, problem):
    checkpoint.write(tmp_path, {"step": 1}, IDENTITY)
    path = tmp_path / "last.pt"
    path.write_bytes(damage(path.read_bytes()))
    monkeypatch.setattr(torch, "load", lambda *a, **k: pytest.fail("torch.load on a damaged checkpoint"))
    with pytest.raises(CheckpointError) as e:
        checkpoint.read(path, "checkpoints/last.pt")
    assert str(e.value).startswith("checkpoints/last.pt ") and problem in str(e.value)


def test_a_plain_torch_save_file_is_the_old_format(tmp_path):
    torch.save({"progress": {}}, tmp_path / "last.pt")
    with pytest.raises(CheckpointError, match=r"format from before format 1 .*plain torch.save"):
        checkpoint.read(tmp_path / "last.pt")


def test_newest_good_falls_back_with_one_warning_or_names_every_problem(tmp_path):
    checkpoint.write(tmp_path, {"step": 1}, IDENTITY)
    checkpoint.write(tmp_path, {"step": 2}, IDENTITY)
    truncate(tmp_path / "last.pt")
    warnings = []
    assert checkpoint.newest_good(tmp_path, warnings.append).state()["step"] == 1
    assert len(warnings) == 1 and "last.pt is truncated" in warnings[0] and "previous.pt" in warnings[0]
    other_bytes(tmp_path / "previous.pt")
    with pytest.raises(
        CheckpointError,
        match=r"no good checkpoint: .*last.pt is truncated .*; .*previous.pt is "
        r"damaged: checksum mismatch",
    ):
        checkpoint.newest_good(tmp_path)
    assert checkpoint.newest_good(tmp_path / "none") is None


# ---- checkpoints through train.py ----------------------------------------------------------------
@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> Path:
    """A tiny regular T-maze run, uninterrupted."""
    run_dir = tmp_path_factory.mktemp("whole") / "run"
    result = run_train(*TMAZE, f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert actor_episode(run_dir / "checkpoints" / "previous.pt") == 200
    return run_dir


def actor_episode(path: Path) -> int:
    """The actor episode a checkpoint was written at."""
    return checkpoint.read(path).state()["progress"]["partial"]["actor"]["episode"]


def cut_copy(whole: Path, dst: Path) -> Path:
    """``whole`` as it was when its last checkpoint was written, minus what only the end writes:
    no summary.json, and no records written after ``previous.pt`` (the resumed run must write
    them again)."""
    shutil.copytree(whole, dst, ignore=shutil.ignore_patterns("analysis"))
    (dst / "summary.json").unlink()
    before = (dst / "checkpoints" / "previous.pt").stat().st_mtime
    for path in (dst / "records").glob("*.npz"):
        if path.stat().st_mtime > before:
            path.unlink()
    return dst


@pytest.mark.parametrize("way", WAYS)
def test_damaged_last_checkpoint_falls_back_and_ends_as_uninterrupted(tmp_path, whole, way):
    run_dir = cut_copy(whole, tmp_path / "run")
    assert not (run_dir / "records" / "episodes.npz").exists()
    DAMAGE[way](run_dir / "checkpoints" / "last.pt")
    damaged = (run_dir / "checkpoints" / "last.pt").read_bytes()
    result = run_train("resume=true", f"hydra.run.dir={run_dir}")  # the run's own config: no other override
    assert result.returncode == 0, result.stderr[-2000:]
    warnings = [ln for ln in stderr_lines(result) if ln.startswith("ferl: warning:")]
    assert len(warnings) == 1, result.stderr
    assert warnings[0].startswith(f"ferl: warning: {run_dir}: checkpoints/last.pt ")
    assert warnings[0].endswith("; resuming from the checkpoint before it, checkpoints/previous.pt")
    assert {
        "truncated": "is truncated",
        "other_bytes": "checksum mismatch",
        "other_shape": "format from before format 1",
    }[way] in warnings[0]
    assert "Traceback" not in result.stderr
    assert_same_run(run_dir, whole)
    assert (run_dir / "checkpoints" / "last.pt.damaged").read_bytes() == damaged  # set aside, not lost
    checkpoint.read(run_dir / "checkpoints" / "last.pt")  # the resumed run's own, good


@pytest.mark.parametrize("way", [*WAYS, "newer_format"])
def test_no_good_checkpoint_one_line_and_the_run_dir_untouched(tmp_path, whole, way):
    run_dir = cut_copy(whole, tmp_path / "run")
    for name in ("last.pt", "previous.pt"):
        path = run_dir / "checkpoints" / name
        if way == "newer_format":
            data = path.read_bytes()
            path.write_bytes(data[:8] + struct.pack("<I", 2) + data[12:])
        else:
            DAMAGE[way](path)
    before = snapshot(run_dir)
    result = run_train("resume=true", f"hydra.run.dir={run_dir}")
    assert result.returncode == 2
    lines = stderr_lines(result)
    assert len(lines) == 1, result.stderr
    problem = {
        "truncated": "is truncated",
        "other_bytes": "checksum mismatch",
        "other_shape": "format from before format 1",
        "newer_format": "has checkpoint format 2",
    }[way]
    assert lines[0].startswith(f"ferl: error: cannot resume {run_dir}: no good checkpoint: checkpoints/last.pt ")
    assert "; checkpoints/previous.pt " in lines[0] and lines[0].count(problem) == 2
    assert snapshot(run_dir) == before  # tb/ not cut, .hydra/ as the run wrote it, nothing new


def test_summary_damaged_resume_writes_it_again(tmp_path, whole):
    """A finished run's summary.json damaged (each way): resume=true recomputes nothing and
    writes the summary again from the last checkpoint."""
    for way in WAYS:
        run_dir = tmp_path / way
        shutil.copytree(whole, run_dir, ignore=shutil.ignore_patterns("analysis"))
        DAMAGE[way](run_dir / "summary.json")
        result = run_train("resume=true", f"hydra.run.dir={run_dir}")
        assert result.returncode == 0, result.stderr[-2000:]
        assert "actor:" not in result.stderr  # no phase ran again
        assert_same_run(run_dir, whole)


# ---- any other exception during a run ------------------------------------------------------------
def test_an_error_in_a_phase_one_line_and_the_last_checkpoint_resumes(tmp_path, whole):
    """The actor phase cannot write its records (a directory stands where episodes.npz goes): one
    line naming the phase and the run, the traceback in train.log (and with HYDRA_FULL_ERROR=1 on
    the terminal), exit 1; with the obstacle gone, resume=true ends as the uninterrupted run."""
    run_dir = tmp_path / "run"
    (run_dir / "records" / "episodes.npz").mkdir(parents=True)
    result = run_train(*TMAZE, f"hydra.run.dir={run_dir}")
    assert result.returncode == 1
    lines = stderr_lines(result)
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert lines[0].startswith(f"ferl: error: phase 'actor' of {run_dir}: IsADirectoryError: ")
    assert lines[0].endswith(f"(traceback in {run_dir / 'train.log'}; HYDRA_FULL_ERROR=1 shows it here)")
    log = (run_dir / "train.log").read_text()
    assert "phase 'actor' failed" in log and "Traceback (most recent call last)" in log and "save_records" in log
    assert actor_episode(run_dir / "checkpoints" / "last.pt") == 200  # the last periodic one

    full = run_train("resume=true", f"hydra.run.dir={run_dir}", env={**os.environ, "HYDRA_FULL_ERROR": "1"})
    assert full.returncode == 1 and "Traceback (most recent call last)" in full.stderr
    assert stderr_lines(full)[-1].startswith(f"ferl: error: phase 'actor' of {run_dir}: IsADirectoryError")

    (run_dir / "records" / "episodes.npz").rmdir()
    result = run_train("resume=true", f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert_same_run(run_dir, whole)


# ---- records, run.json, summary.json through analyze.py -------------------------------------------
FILES = ("records/episodes.npz", "records/run.json", "summary.json")
CASES = [(f, w) for f in FILES for w in WAYS]


@pytest.fixture(scope="module")
def analysed(tmp_path_factory, whole) -> dict:
    """(file, way) → (exit status, stderr lines, run dir) of ``analyze.py RUN`` on a damaged copy
    of the run, in process (runner.main is analyze.py's body)."""
    import contextlib
    import io

    import reproduction  # noqa: F401 — as analyze.py does
    from ferl.analysis import runner

    root, out = tmp_path_factory.mktemp("analysed"), {}
    for i, (file, way) in enumerate(CASES):
        run_dir = root / f"case{i}"  # a name that does not name the file
        shutil.copytree(whole, run_dir, ignore=shutil.ignore_patterns("analysis"))
        DAMAGE[way](run_dir / file)
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                status = runner.main([run_dir])
            except Exception as e:  # noqa: BLE001 — a traceback on the terminal, as the test says
                status = f"raised {type(e).__name__}: {e}"
        out[file, way] = status, err.getvalue().splitlines(), run_dir
    return out


@pytest.mark.parametrize("file, way", CASES)
def test_analyze_a_damaged_file_fails_in_one_line(analysed, file, way):
    status, lines, run_dir = analysed[file, way]
    assert status == 1, status
    assert len(lines) == 1 and lines[0].startswith(f"analyze.py: error: {run_dir}: "), lines


@pytest.mark.parametrize("file, way", CASES)
def test_analyze_names_the_damaged_file(analysed, file, way):
    status, lines, _ = analysed[file, way]
    assert status == 1 and len(lines) == 1 and Path(file).name in lines[0], lines


# damaged runs that once stopped the sweep's own analysis (after every run's): a damaged run.json, a summary
# that is not a JSON object
SWEEP_STOPS = [("records/run.json", w) for w in WAYS] + [("summary.json", "other_shape")]


def test_analyze_a_sweep_with_damaged_runs_analyses_the_others(tmp_path, whole):
    """analyze.py SWEEP (the command line) with an intact run and a damaged one of every case
    that does not stop the sweep: each damaged run one line, exit 1, the intact run and the
    sweep's report written, no traceback."""
    import subprocess
    import sys

    from conftest import ROOT

    sweep = tmp_path / "sweep"
    shutil.copytree(whole, sweep / "good", ignore=shutil.ignore_patterns("analysis"))
    damaged = [case for case in CASES if case not in SWEEP_STOPS]
    for i, (file, way) in enumerate(damaged):
        shutil.copytree(whole, sweep / f"bad{i}", ignore=shutil.ignore_patterns("analysis"))
        DAMAGE[way](sweep / f"bad{i}" / file)
    result = subprocess.run(
        [sys.executable, str(ROOT / "analyze.py"), str(sweep)], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 1, result.stderr[-3000:]
    assert "Traceback" not in result.stderr, result.stderr[-3000:]
    errors = [ln for ln in result.stderr.splitlines() if ln.startswith("analyze.py: error:")]
    assert sorted(ln.split(":")[2].strip() for ln in errors) == [str(sweep / f"bad{i}") for i in range(len(damaged))], (
        result.stderr[-3000:]
    )
    assert (sweep / "good" / "analysis" / "report.md").is_file()
    assert (sweep / "analysis" / "report.md").is_file()


@pytest.mark.parametrize("file, way", SWEEP_STOPS)
def test_analyze_a_sweep_whose_damaged_run_stops_it(tmp_path, whole, file, way):
    import reproduction  # noqa: F401 — as analyze.py does
    from ferl.analysis import runner

    sweep = tmp_path / "sweep"
    for name in ("good", "bad"):
        shutil.copytree(whole, sweep / name, ignore=shutil.ignore_patterns("analysis"))
    DAMAGE[way](sweep / "bad" / file)
    assert runner.main([sweep]) == 1
    assert (sweep / "analysis" / "report.md").is_file()


# ---- the preprocessor cache (ferl/preprocessors/cache.py heals it) ------------------------------
@pytest.fixture(scope="module")
def pixel(tmp_path_factory) -> tuple[Path, Path]:
    """A tiny pixel T-maze run that fitted its RBM into a cache of its own: (run dir, cache entry)."""
    root = tmp_path_factory.mktemp("pixel")
    result = run_train(*PIXEL, f"hydra.run.dir={root / 'run'}", f"preprocessor.cache_dir={root / 'cache'}")
    assert result.returncode == 0, result.stderr[-2000:]
    (entry,) = (root / "cache").glob("*.pt")
    return root / "run", entry


@pytest.mark.parametrize("way", WAYS)
def test_damaged_cache_entry_warns_fits_again_and_heals(tmp_path, pixel, way):
    from ferl.preprocessors.cache import entry_header

    whole, entry = pixel
    cache = tmp_path / "cache"
    shutil.copytree(entry.parent, cache)
    DAMAGE[way](cache / entry.name)
    run_dir = tmp_path / "run"
    result = run_train(*PIXEL, f"hydra.run.dir={run_dir}", f"preprocessor.cache_dir={cache}")
    assert result.returncode == 0, result.stderr[-2000:]
    warnings = [ln for ln in stderr_lines(result) if ln.startswith("ferl: warning:")]
    assert len(warnings) == 1 and f"preprocessor cache {cache / entry.name} failed its check" in warnings[0], warnings
    assert "Traceback" not in result.stderr
    assert metrics(run_dir) == metrics(whole)
    assert (cache / entry.name).read_bytes() == entry.read_bytes()  # healed: the clean fit's entry again
    assert entry_header(cache / entry.name)["key"] == entry_header(entry)["key"]
