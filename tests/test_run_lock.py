"""One process per run directory (ferl/run/lock.py, ferl/run/claim.py; docs/reliability.md): a
refused launch leaves an existing run byte-identical, two launches or two resumes into one
directory leave one run (its .hydra/, summary.json and TensorBoard agree), a stale lock is taken
over; wall_time_s adds up over resumes; leftovers of killed writes are removed and an interrupted
copy of .hydra/ is made again."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from conftest import ROOT, TINY, eager, run_train, tb_scalars
from ferl.run import checkpoint
from ferl.run.directory import HYDRA_COPY, HYDRA_FILES, RunDir
from ferl.run.lock import LOCK_FILE, RunLock
from test_fault_injection import snapshot, stderr_lines
from test_train_cli import checkpointed_step, summary

HOST = socket.gethostname()
LONG = [*TINY, "trainer.steps=6000", "trainer.checkpoint_every=500", "trainer.log_every=500"]


def launch(run_dir: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *eager([*args, f"hydra.run.dir={run_dir}"])],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def together(run_dir: Path, *variants: list) -> list[tuple]:
    """Start one train.py per variant into ``run_dir`` at once; (process, exit code, stderr) each."""
    procs = [launch(run_dir, *args) for args in variants]
    return [(p, p.wait(timeout=300), p.stderr.read()) for p in procs]


def hydra_seed(run_dir: Path) -> int:
    return yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())["seed"]


def assert_refused_by(stderr: str, run_dir: Path, pid: int) -> None:
    lines = stderr_lines(SimpleNamespace(stderr=stderr))
    assert len(lines) == 1, stderr
    assert lines[0].startswith(
        f"ferl: error: hydra.run.dir={run_dir} is in use by pid {pid} on host {HOST} (lock {run_dir / LOCK_FILE}): "
    ), lines[0]


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("finished") / "run"
    result = run_train(*TINY, f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert not (run_dir / LOCK_FILE).exists()  # let go at the end
    return run_dir


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory) -> Path:
    """A digit-floor run stopped by SIGTERM inside its actor phase (a checkpoint, no summary)."""
    run_dir = tmp_path_factory.mktemp("interrupted") / "run"
    proc = launch(run_dir, *LONG)
    deadline = time.time() + 120
    while checkpointed_step(run_dir) == 0 and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=120) == 128 + signal.SIGTERM, "the run ended before it could be interrupted"
    assert 0 < checkpointed_step(run_dir) < 6000 and not (run_dir / LOCK_FILE).exists()
    return run_dir


def copy_of(run_dir: Path, dst: Path) -> Path:
    shutil.copytree(run_dir, dst)
    return dst


# ---- a refused launch writes nothing ---------------------------------------------------------------
def test_a_refused_launch_leaves_a_finished_run_byte_identical(tmp_path, finished):
    run_dir = copy_of(finished, tmp_path / "run")
    before = snapshot(run_dir)
    result = run_train(*TINY, "experiment=ch3_coding_ccw", "seed=5", "actor.n_hidden=7", f"hydra.run.dir={run_dir}")
    assert result.returncode == 2
    assert stderr_lines(result) == [
        f"ferl: error: hydra.run.dir={run_dir} already holds a run: pass resume=true "
        f"to continue it, or another directory"
    ]
    assert snapshot(run_dir) == before  # .hydra/ and train.log included: Hydra wrote nothing either


def test_a_held_directory_is_refused_naming_the_holder_and_left_as_it_was(tmp_path, interrupted):
    """The test process holds the lock (a run at work): a new launch into its fresh directory and
    a resume of an interrupted run are refused in one line naming pid and host, and nothing
    there changes: the fresh directory (only train.log and the lock so far) is not discarded."""
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / "train.log").write_text("")
    resumable = copy_of(interrupted, tmp_path / "resumable")
    for run_dir, args in ((fresh, TINY), (resumable, [*LONG, "resume=true"])):
        lock = RunLock(run_dir)
        assert lock.acquire()
        try:
            before = snapshot(run_dir)
            result = run_train(*args, f"hydra.run.dir={run_dir}")
            assert result.returncode == 2
            assert_refused_by(result.stderr, run_dir, os.getpid())
            assert snapshot(run_dir) == before
        finally:
            lock.release()
        assert not (run_dir / LOCK_FILE).exists()


# ---- two processes, one directory -------------------------------------------------------------------
def test_two_launches_together_leave_one_run(tmp_path):
    run_dir = tmp_path / "run"
    results = together(run_dir, [*TINY, "seed=0"], [*TINY, "seed=7"])
    assert sorted(code for _, code, _ in results) == [0, 2], [err[-2000:] for _, _, err in results]
    (winner, _, _), (_, _, refused) = sorted(results, key=lambda r: r[1])
    if "already holds a run" not in refused:  # else the winner had finished before the other looked
        assert_refused_by(refused, run_dir, winner.pid)
    seed = hydra_seed(run_dir)
    assert summary(run_dir)["seeds"] == [seed, seed + 1]
    assert len(list((run_dir / "tb").glob("events.out.tfevents.*"))) == 1
    assert not (run_dir / LOCK_FILE).exists()


def test_two_resumes_together_leave_each_point_once(tmp_path, interrupted):
    run_dir = copy_of(interrupted, tmp_path / "run")
    results = together(run_dir, [*LONG, "resume=true"], [*LONG, "resume=true"])
    assert sorted(code for _, code, _ in results) == [0, 2], [err[-2000:] for _, _, err in results]
    (winner, _, _), (_, _, refused) = sorted(results, key=lambda r: r[1])
    assert_refused_by(refused, run_dir, winner.pid)
    scalars = tb_scalars(run_dir)
    assert [s for s, _ in scalars["actor/reward_ma100"]] == list(range(500, 6001, 500))
    for tag, points in scalars.items():
        steps = [s for s, _ in points]
        assert len(steps) == len(set(steps)), tag
    assert summary(run_dir)["seeds"] == [hydra_seed(run_dir), hydra_seed(run_dir) + 1]


def test_a_stale_lock_is_taken_over(tmp_path):
    """A lock file left by a process that is gone (kill -9: its flock went with it)."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / LOCK_FILE).write_text(json.dumps({"pid": gone.pid, "host": HOST}) + "\n")
    result = run_train(*TINY, f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert (
        f"ferl: warning: {run_dir}: took over the lock that pid {gone.pid} on host {HOST} left "
        f"({LOCK_FILE}; that process is gone)"
    ) in stderr_lines(result)
    assert (run_dir / "summary.json").is_file() and not (run_dir / LOCK_FILE).exists()


def test_lock_in_process_refuses_a_second_holder_and_names_the_first(tmp_path):
    first, second = RunLock(tmp_path), RunLock(tmp_path)
    assert first.acquire() and not second.acquire()
    assert json.loads((tmp_path / LOCK_FILE).read_text()) == {"pid": os.getpid(), "host": HOST}
    first.release()
    assert not (tmp_path / LOCK_FILE).exists()
    assert second.acquire() and second.left_by is None  # a lock let go leaves no file to take over
    second.release()


# ---- wall time, leftovers, the .hydra copy --------------------------------------------------------
def test_resumed_wall_time_adds_every_process(tmp_path, interrupted):
    """summary.json's wall_time_s = the first process's (as its checkpoint recorded it) + the
    resuming process's own: at least the time of the phases it ran, at most its life."""
    run_dir = copy_of(interrupted, tmp_path / "run")
    first = checkpoint.read(run_dir / "checkpoints" / "last.pt").state()["progress"]
    assert first["wall_time_s"] > 0
    started = time.perf_counter()
    result = run_train(*LONG, "resume=true", f"hydra.run.dir={run_dir}")
    lifetime = time.perf_counter() - started
    assert result.returncode == 0, result.stderr[-2000:]
    phases = {name: t for name, t in summary(run_dir)["phase_time_s"].items() if name not in first["done"]}
    assert phases  # the phases this process ran (a cut phase counts from its resume on)
    own = summary(run_dir)["wall_time_s"] - first["wall_time_s"]
    assert sum(phases.values()) <= own <= lifetime


def test_leftovers_are_removed_and_an_interrupted_hydra_copy_is_made_again(tmp_path, interrupted):
    run_dir = copy_of(interrupted, tmp_path / "run")
    leftovers = [
        run_dir / ".summary.json.k2j4x9_a.tmp",
        run_dir / "records" / ".steps.npz.a8f3kq0z.tmp",
        run_dir / ".hydra" / ".config.yaml.zz81kd7e.tmp",
    ]
    for path in leftovers:
        path.write_bytes(b"half a write")
    cut_copy = run_dir / "checkpoints" / ".hydra.w8x1m2qa.tmp"  # a kill inside keep_hydra_files
    cut_copy.mkdir()
    (cut_copy / "config.yaml").write_text("half")
    shutil.rmtree(run_dir / HYDRA_COPY)
    (run_dir / HYDRA_COPY).mkdir()  # a copy cut short the way it was made before: file by file
    shutil.copyfile(run_dir / ".hydra" / "config.yaml", run_dir / HYDRA_COPY / "config.yaml")
    result = run_train(*LONG, "resume=true", f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert not any(p.exists() for p in [*leftovers, cut_copy])
    for name in HYDRA_FILES:
        assert (run_dir / HYDRA_COPY / name).read_bytes() == (run_dir / ".hydra" / name).read_bytes(), name


def test_a_failed_hydra_copy_leaves_no_copy_and_is_made_at_the_next_checkpoint(tmp_path, monkeypatch):
    run = RunDir(tmp_path)
    (tmp_path / ".hydra").mkdir()
    for name in HYDRA_FILES:
        (tmp_path / ".hydra" / name).write_text(f"{name}\n")
    real, copied = shutil.copyfile, []

    def cut_short(src, dst):
        if copied:
            raise KeyboardInterrupt  # interrupted after the first file
        copied.append(real(src, dst))

    monkeypatch.setattr(shutil, "copyfile", cut_short)
    with pytest.raises(KeyboardInterrupt):
        run.keep_hydra_files()
    assert not (tmp_path / HYDRA_COPY).exists()
    monkeypatch.setattr(shutil, "copyfile", real)
    run.keep_hydra_files()
    assert sorted(p.name for p in (tmp_path / HYDRA_COPY).iterdir()) == sorted(HYDRA_FILES)
