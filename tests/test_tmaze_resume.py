"""T-maze runs interrupted in each phase and resumed (CONTRACT §2; issue 7/7): SIGTERM writes a
checkpoint and exits 143, kill -9 falls back to the last periodic checkpoint, and `resume=true`
finishes with the same summary and records as an uninterrupted run, without redoing a phase."""

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_same_tb_log, eager
from ferl.run import checkpoint
from test_train_cli import summary

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "experiment=table4_1_matching",
    "n_runs=2",
    "trainer.n_sample=200",
    "trainer.n_epoch=60",
    "trainer.error_every=5",
    "trainer.phases.predictors.checkpoint_every_epochs=5",
    "trainer.n_episodes=1500",
    "trainer.checkpoint_every=100",
    "trainer.log_every=100",
]


def train(*args: str, stderr=subprocess.PIPE) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *eager([*TINY, *args])],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=stderr,
        text=True,
    )


def progress(run_dir: Path) -> dict | None:
    try:
        return checkpoint.read(run_dir / "checkpoints" / "last.pt").state()["progress"]
    except checkpoint.CheckpointError:  # not written yet
        return None


def interrupt_when(run_dir: Path, ready, sig: int, *args: str) -> dict:
    """Start a run (with `args`), send `sig` once its checkpoint satisfies `ready`, wait; return the progress."""
    proc = train(*args, f"hydra.run.dir={run_dir}", stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        found = progress(run_dir)
        if found is not None and ready(found):
            break
        time.sleep(0.02)
    proc.send_signal(sig)
    code = proc.wait(timeout=240)
    assert code in (128 + sig, -sig), f"the run ended ({code}) before it could be interrupted"
    assert not (run_dir / "summary.json").exists()
    return progress(run_dir)


def records(run_dir: Path, name: str) -> dict:
    with np.load(run_dir / "records" / f"{name}.npz") as data:
        return {k: data[k] for k in data.files}


@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("whole") / "run"
    proc = train(f"hydra.run.dir={run_dir}")
    assert proc.wait(timeout=300) == 0, proc.stderr.read()[-2000:]
    return run_dir


def assert_same_as_uninterrupted(run_dir: Path, whole: Path) -> None:
    proc = train("resume=true", f"hydra.run.dir={run_dir}")
    assert proc.wait(timeout=300) == 0, proc.stderr.read()[-2000:]
    assert summary(run_dir)["metrics"] == summary(whole)["metrics"]
    assert_same_records(run_dir, whole, ("predictor", "episodes", "probe"))
    assert_same_tb_log(run_dir, whole)


def assert_same_records(run_dir: Path, whole: Path, names) -> None:
    for name in names:
        got, want = records(run_dir, name), records(whole, name)
        assert got.keys() == want.keys()
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=f"{name}.npz {key}")


def mid(phase: str):
    """Ready once a periodic checkpoint inside the phase exists: a signal that lands between an
    earlier phase's checkpoint and the flag check after it would end the run right there."""
    return lambda p: p["partial"].get(phase) is not None


@pytest.mark.parametrize("phase", ["predictors", "actor"])
def test_sigterm_in_each_phase_then_resume_equals_uninterrupted(tmp_path, whole, phase):
    run_dir = tmp_path / "cut"
    saved = interrupt_when(run_dir, mid(phase), signal.SIGTERM)
    # the last checkpoint lies inside the phase, so the resumed run continues mid-phase
    assert saved["partial"].get(phase) is not None, f"no mid-{phase} checkpoint: {saved['done']}"
    assert phase not in saved["done"] and "collect" in saved["done"]
    assert_same_as_uninterrupted(run_dir, whole)


def test_kill_9_mid_actor_resumes_from_the_last_periodic_checkpoint(tmp_path, whole):
    run_dir = tmp_path / "killed"
    saved = interrupt_when(
        run_dir, lambda p: (p["partial"].get("actor") or {}).get("episode", 0) >= 300, signal.SIGKILL
    )
    assert saved is not None, "the last checkpoint is unreadable"
    assert saved["partial"]["actor"]["episode"] % 100 == 0  # a periodic one: nothing ran a handler
    assert_same_as_uninterrupted(run_dir, whole)


def test_a_finished_phase_is_not_recomputed(tmp_path, whole):
    run_dir = tmp_path / "cut"
    interrupt_when(run_dir, lambda p: "predictors" in p["done"], signal.SIGTERM)
    proc = train("resume=true", f"hydra.run.dir={run_dir}")
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-2000:]
    assert "predictor joint" not in err  # no predictor epoch ran again (its progress bar)
    assert "actor" in err
    assert summary(run_dir)["metrics"] == summary(whole)["metrics"]


PIXEL = [
    "experiment=table5_1_pixel",
    "n_runs=2",
    "env.reservoir_size=5",
    "preprocessor.sweeps=60",
    "trainer.n_sample=300",
    "trainer.n_epoch=3",
    "trainer.n_episodes=100",
    "trainer.log_every=50",
    "trainer.td_sample_every=50",
    "trainer.final_window=50",
]


def train_pixel(run_dir: Path, *args: str, stderr=subprocess.PIPE) -> subprocess.Popen:
    # a cache of its own per run directory: every run fits its RBM (no shortcut through the cache)
    return subprocess.Popen(
        [
            sys.executable,
            str(ROOT / "train.py"),
            *eager([*PIXEL, *args]),
            f"hydra.run.dir={run_dir}",
            f"preprocessor.cache_dir={run_dir.parent / (run_dir.name + '_cache')}",
        ],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=stderr,
        text=True,
    )


def test_sigterm_in_the_preprocessor_phase_then_resume(tmp_path):
    """SIGTERM while the RBM preprocessor trains: the fit stops after the sweep it is in, is
    checkpointed, the run exits; the resumed run continues the fit from that sweep and ends as an
    uninterrupted one (tests/test_fit_resume.py holds the sweep exactly, in process)."""
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    proc = train_pixel(whole)
    assert proc.wait(timeout=300) == 0, proc.stderr.read()[-2000:]

    proc = train_pixel(cut, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not list((cut / "tb").glob("events.out.tfevents.*")) and time.time() < deadline:
        time.sleep(0.02)
    time.sleep(0.5)  # the signal handler is installed right after the TensorBoard writer
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=240) == 128 + signal.SIGTERM
    stopped = progress(cut)
    assert stopped["done"] == [], "the fit ended before the signal: nothing was tested"
    sweep = stopped["partial"]["preprocessor"]["fit"]["sweep"]
    assert 0 < sweep < 60

    proc = train_pixel(cut, "resume=true")
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-2000:]
    assert "preprocessor:   0%|" not in err and f"| {sweep}/60 [" in err  # the fit went on from its sweep
    assert summary(cut)["metrics"] == summary(whole)["metrics"]
    assert_same_records(cut, whole, ("preprocessor", "predictor", "episodes"))


@pytest.mark.parametrize(
    "agent",
    [
        ("actor=drqn", "predictor=none"),
        ("actor=recurrent_q", "actor.head=free_energy", "actor.memory=lstm", "predictor=none"),
        ("actor=drqn", "predictor=none", "compile=true"),
    ],
)
def test_drqn_resumes_mid_actor_equal_to_uninterrupted(tmp_path, agent):
    """The recurrent Q-learner's checkpoint (its replay, Adam's moments, the target network, each
    run's generator) continues the run exactly: DRQN, and an RBM head on an LSTM core; DRQN on
    the fast path too (its compiled episodes and replay steps are deterministic: the resumed
    process, which loads the graphs, computes bit for bit what the uninterrupted one did)."""
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    agent = (*agent, "trainer.n_episodes=600")  # stopped after its checkpoint at episode 300
    proc = train(*agent, f"hydra.run.dir={whole}")
    assert proc.wait(timeout=300) == 0, proc.stderr.read()[-2000:]
    saved = interrupt_when(
        cut, lambda p: (p["partial"].get("actor") or {}).get("episode", 0) >= 300, signal.SIGTERM, *agent
    )
    assert 0 < saved["partial"]["actor"]["episode"] < 600
    proc = train(*agent, "resume=true", f"hydra.run.dir={cut}")
    assert proc.wait(timeout=300) == 0, proc.stderr.read()[-2000:]
    assert summary(cut)["metrics"] == summary(whole)["metrics"]
    got, want = records(cut, "episodes"), records(whole, "episodes")
    for key in want:
        np.testing.assert_array_equal(got[key], want[key], err_msg=f"episodes.npz {key}")
