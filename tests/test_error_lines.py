"""Errors survive the failure they report (docs/reliability.md): a full disk, a read-only file
system, the file-size limit, an unwritable run directory and a stop signal each end train.py
with exactly one stderr line that names the file or directory, no traceback, no
``--- Logging error ---``, and an exit code ≠ 0; the run then resumes to the uninterrupted
run's numbers. analyze.py names the sweep members it cannot analyse.

Disk faults are injected into the train.py subprocess by ``tests/faults/sitecustomize.py``:
once a chosen file is opened for writing, every write() under the run directory fails with
the errno and no file name, as on a real full disk (train.log included).
"""

import errno
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import ROOT, eager, run_train
from test_fault_injection import TMAZE, assert_same_run, stderr_lines, whole  # noqa: F401 — the fixture
from test_train_cli import checkpointed_step

FAULTS = ROOT / "tests" / "faults"


def faulty(run_dir: Path, name: str, glob: str, skip: int = 0) -> dict:
    """The environment of a train.py whose disk fails (``name``: errno) once more than ``skip``
    files matching ``glob`` were opened for writing under ``run_dir``."""
    return {**os.environ, "PYTHONPATH": str(FAULTS), "FERL_FAULT": f"{name}:{run_dir}:{glob}:{skip}"}


def assert_one_clean_line(result, code: int) -> str:
    assert result.returncode == code, result.stderr[-3000:]
    lines = stderr_lines(result)
    assert len(lines) == 1, result.stderr[-3000:]
    assert "Traceback" not in result.stderr and "Logging error" not in result.stderr
    assert "HYDRA_FULL_ERROR=1" not in result.stderr or "shows it here" in lines[0]
    return lines[0]


# the file whose write fills the disk, how many such writes succeed first, the phase, the file named
FULL_DISK = {
    "checkpoint": (".last.pt.*.tmp", 1, "predictors", "checkpoints/last.pt"),
    "records": (".episodes.npz.*.tmp", 0, "actor", "records/episodes.npz"),
    "summary": (".summary.json.*.tmp", 0, "summary", "summary.json"),
    "tensorboard": ("events.out.tfevents.*", 12, None, "tb/events.out.tfevents."),
}


@pytest.mark.parametrize("case", FULL_DISK)
def test_full_disk_one_line_naming_the_file_then_resume_equals_uninterrupted(tmp_path, whole, case):  # noqa: F811
    glob, skip, phase, file = FULL_DISK[case]
    run_dir = tmp_path / "run"
    result = run_train(*TMAZE, f"hydra.run.dir={run_dir}", env=faulty(run_dir, "ENOSPC", glob, skip))
    line = assert_one_clean_line(result, 1)
    assert line.startswith(f"ferl: error: phase '{phase or ''}" if phase else "ferl: error: phase '"), line
    assert f"no space left on device writing {run_dir / file}" in line, line
    assert (
        "(errno ENOSPC); the last good checkpoint is kept: free space, then resume=true "
        f"hydra.run.dir={run_dir}" in line
    ), line
    assert "train.log" not in line  # it could not be written: the line does not claim it
    assert not (run_dir / "summary.json").exists()
    resumed = run_train("resume=true", f"hydra.run.dir={run_dir}")  # space freed
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert_same_run(run_dir, whole)


@pytest.mark.parametrize(
    "name, says", [("EROFS", "read-only file system"), ("EFBIG", "file larger than the file-size limit (ulimit -f)")]
)
def test_read_only_and_file_size_limit_lines(tmp_path, name, says):
    run_dir = tmp_path / "run"
    result = run_train(*TMAZE, f"hydra.run.dir={run_dir}", env=faulty(run_dir, name, ".last.pt.*.tmp", 1))
    line = assert_one_clean_line(result, 1)
    assert line.startswith(
        f"ferl: error: phase 'predictors': {says} writing {run_dir / 'checkpoints/last.pt'} "
        f"(errno {name}); the last good checkpoint is kept: "
    ), line


def test_a_file_where_the_run_directory_should_be(tmp_path):
    (tmp_path / "taken").write_text("a file\n")
    for run_dir, code in ((tmp_path / "taken", "EEXIST"), (tmp_path / "taken" / "run", "ENOTDIR")):
        line = assert_one_clean_line(run_train(*TMAZE, f"hydra.run.dir={run_dir}"), 1)
        assert line == (
            f"ferl: error: cannot create the run directory {run_dir}: a file stands where a directory "
            f"should be (errno {code}); choose another hydra.run.dir / hydra.sweep.dir"
        )
    assert (tmp_path / "taken").read_text() == "a file\n"


def test_a_read_only_run_directory_at_the_first_write(tmp_path):
    """The run's first write (.hydra/, which train.py writes once the directory is its own) fails:
    one line naming it, not a flattened traceback."""
    run_dir = tmp_path / "run"
    line = assert_one_clean_line(run_train(*TMAZE, f"hydra.run.dir={run_dir}", env=faulty(run_dir, "EROFS", "*")), 1)
    assert line.startswith(
        f"ferl: error: phase 'setup': read-only file system writing {run_dir / '.hydra'} "
        "(errno EROFS); no checkpoint was written yet"
    ), line
    assert 'File "' not in line and " | " not in line


# ---- signals ---------------------------------------------------------------------------------------
FLOOR = [
    "n_runs=2",
    "trainer.steps=8000",
    "trainer.checkpoint_every=500",
    "trainer.log_every=500",
    "trainer.test_per_class=8",
    "trainer.test_noise_levels=[0.0,0.125]",
]


@pytest.fixture(scope="module")
def floor_whole(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("floor") / "whole"
    assert run_train(*FLOOR, f"hydra.run.dir={run_dir}").returncode == 0
    return run_dir


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGHUP])
def test_signal_checkpoints_one_line_and_resumes(tmp_path, floor_whole, sig):
    cut = tmp_path / "cut"
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *eager(FLOOR), f"hydra.run.dir={cut}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    deadline = time.time() + 120
    while checkpointed_step(cut) == 0 and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + sig, err[-3000:]
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip() and "%|" not in ln]
    assert len(lines) == 1 and "Traceback" not in err, err[-3000:]
    step = checkpointed_step(cut)
    assert 0 < step < 8000
    assert lines[0] == (
        f"ferl: interrupted by {signal.Signals(sig).name} at phase 'continuing_td', step {step}: checkpoint "
        f"written to {cut / 'checkpoints'}; resume=true hydra.run.dir={cut} continues"
    )
    result = run_train(*FLOOR, "resume=true", f"hydra.run.dir={cut}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert (cut / "summary.json").read_text().split('"wall_time_s"')[0] == (
        floor_whole / "summary.json"
    ).read_text().split('"wall_time_s"')[0]


@pytest.mark.parametrize("script, module, prog", [("train.py", "hydra", "ferl"), ("analyze.py", "numpy", "analyze.py")])
def test_sigint_during_imports_one_line(tmp_path, script, module, prog):
    marker = tmp_path / "importing"
    env = {**os.environ, "PYTHONPATH": str(FAULTS), "FERL_SLOW_IMPORT": f"30:{module}:{marker}"}
    # a terminal's Ctrl-C: SIGINT at its default even when this test runs in a background job
    # (which inherits SIGINT ignored, and Python then installs no KeyboardInterrupt handler)
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / script), str(tmp_path)],
        env=env,
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.time() + 60
    while not marker.exists() and time.time() < deadline:
        time.sleep(0.02)
    assert marker.exists(), "the import never started"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.splitlines() == [f"{prog}: interrupted by SIGINT while starting: nothing was written"], err


# ---- analyze.py on a sweep with unfinished members -------------------------------------------------
def test_analyze_names_unfinished_members_and_a_missing_records_file(tmp_path, whole):  # noqa: F811
    sweep = tmp_path / "sweep"
    for name in ("0_done", "1_killed", "2_norecords", "3_early"):
        shutil.copytree(whole, sweep / name, ignore=shutil.ignore_patterns("analysis"))
    (sweep / "1_killed" / "summary.json").unlink()  # killed after its checkpoints
    (sweep / "2_norecords" / "records" / "episodes.npz").unlink()
    shutil.rmtree(sweep / "3_early" / "checkpoints")  # killed before its first checkpoint
    (sweep / "3_early" / "summary.json").unlink()
    result = subprocess.run(
        [sys.executable, str(ROOT / "analyze.py"), str(sweep)], capture_output=True, text=True, timeout=600, cwd=ROOT
    )
    assert result.returncode == 1, result.stderr[-3000:]
    assert "Traceback" not in result.stderr and "TypeError" not in result.stderr, result.stderr[-3000:]
    assert result.stderr.splitlines() == [
        f"analyze.py: skipped {sweep / '1_killed'}: no summary.json (unfinished or killed run: "
        f"resume=true hydra.run.dir={sweep / '1_killed'} continues it)",
        f"analyze.py: skipped {sweep / '3_early'}: no summary.json (unfinished or killed run: "
        "it ended before its first checkpoint)",
        f"analyze.py: error: {sweep / '2_norecords'}: FileNotFoundError: records/episodes.npz is missing: "
        "the analysis of this run needs it",
    ], result.stderr
    assert f"{sweep}: sweep of 2 runs; 2 skipped: 1_killed, 3_early, " in result.stdout, result.stdout
    assert (sweep / "0_done" / "analysis" / "report.md").is_file()
    assert "skipped: no summary.json" in (sweep / "analysis" / "report.md").read_text()


def test_a_running_member_is_named_by_its_lock(tmp_path):
    from ferl.analysis import members

    (tmp_path / "a" / ".hydra").mkdir(parents=True)
    (tmp_path / "a" / members.LOCK).touch()
    (tmp_path / "a" / "checkpoints" / "hydra").mkdir(parents=True)  # a run's copy of .hydra/: not a member
    assert members.unfinished(tmp_path) == [
        (tmp_path / "a", "no summary.json yet (it holds .ferl.lock: still running, or killed while it held it)")
    ]


def test_a_write_error_without_a_file_name_is_named():
    """A failing write() names no file; ``writing`` adds the file, a temporary one is named as its target."""
    from ferl.run.failures import disk_line, writing

    with pytest.raises(OSError) as caught, writing(Path("/r/checkpoints/last.pt")):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert disk_line(caught.value, Path("/r")).startswith(
        "no space left on device writing /r/checkpoints/last.pt (errno ENOSPC); no checkpoint was written yet"
    )
    temporary = OSError(errno.EFBIG, "File too large", "/r/records/.episodes.npz.ab12cd.tmp")
    assert "writing /r/records/episodes.npz (errno EFBIG)" in disk_line(temporary, Path("/r"))


def test_a_stopped_job_crosses_a_process_boundary():
    """A joblib worker's job that a signal stopped hands ``Interrupted`` to the launching process
    pickled: it must arrive whole (it failed to unpickle, and the sweep ended in a traceback)."""
    import pickle

    from ferl.run.failures import Interrupted

    where = "phase 'actor', episode 3"
    back = pickle.loads(pickle.dumps(Interrupted(signal.SIGINT, where)))
    assert (type(back), back.code, back.signum, back.where) == (Interrupted, 130, signal.SIGINT, where)


def test_sighup_before_the_step_loop_one_line(tmp_path):
    """SIGHUP while the run is being set up (the lock is held: the directory is the run's; the
    MNIST floor is not yet stepping): one line saying what is left to resume from, exit 129, not
    the signal's silent default. Sent once the lock file appears, it may land in the first steps
    instead: then the step loop's line, exit 129 too."""
    run_dir = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *eager(FLOOR), f"hydra.run.dir={run_dir}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    deadline = time.time() + 120
    while not (run_dir / ".ferl.lock").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.005)
    proc.send_signal(signal.SIGHUP)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGHUP, err[-3000:]
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip() and "%|" not in ln]
    assert len(lines) == 1 and "Traceback" not in err, err[-3000:]
    assert lines[0].startswith("ferl: interrupted by SIGHUP "), lines[0]
    if " during " in lines[0]:
        assert lines[0].endswith("no checkpoint was written yet: run the command again"), lines[0]
