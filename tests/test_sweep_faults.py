"""Fault injection on a whole sweep (docs/sweeps.md, "Resuming a sweep"): a reduced ``make
reproduce``, its two stages and four sweep kinds at tiny budgets, killed by SIGKILL at random
moments in turn (the process group: a pre-empted node, a reboot) and resumed each time with
``--resume``, ends with every job's metrics equal to those of the same recipe left to run; no job
is started again once it has finished (every job's starts are counted, across processes, by
``tests/job_starts/sitecustomize.py``, and its ``summary.json`` is never rewritten), and a SIGINT
or SIGHUP stop says in one line how to go on.

The recipe is ``make reproduce``'s: first the experiments (two experiments, two jobs at a time,
Hydra's joblib workers), then the noise grid (two jobs at a time), the hidden sizes and the long
corridor (one at a time each) at once, by ``ferl.run.together``; a launcher process stands where
``make`` does. The sweeps' analysis (``analyze.py``: the report.md and every figure CSV) is
compared too, each file with its lines of time measures (wall time, agent-steps/s, compile time),
which no two runs share, left out and the sweep's own path written as SWEEP.

FERL_SWEEP_KILLS sets the number of moments (default 3, to keep ``make test`` short) and
FERL_SWEEP_STEPS the floor jobs' length (default 1 000; a longer sweep leaves room for more kills).
The moments are drawn from a seeded generator over the uninterrupted sweep's wall time, so a
failure can be replayed."""

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import ROOT, TINY, TINY_ALGORITHM1
from ferl.run.jobs import DONE, job_dir, job_state, sweep_jobs
from ferl.run.together import Sweep

KILLS = int(os.environ.get("FERL_SWEEP_KILLS", "3"))
STEPS = int(os.environ.get("FERL_SWEEP_STEPS", "1000"))  # each floor job's; longer sweeps take more kills
# the moments, as shares of the uninterrupted sweep's wall time: with few kills, late enough that
# each lands among the jobs rather than while the processes start; with many, early enough that
# most land before the sweep ends
SHARE = (0.3, 0.6) if KILLS <= 5 else (0.1, 0.35)
# floor jobs checkpointed every 250 steps and T-maze jobs checkpointed after their phases: short
# jobs, every one with a checkpoint to resume from
FLOOR = [a for a in TINY if not a.startswith(("trainer.steps=", "trainer.checkpoint_every="))]
FLOOR += [f"trainer.steps={STEPS}", "trainer.checkpoint_every=250", "compile=false", "device=cpu"]
TMAZE = ["n_runs=2", *TINY_ALGORITHM1, "trainer.checkpoint_every=25", "compile=false", "device=cpu"]
# the long corridor, as make reproduce runs it, with enough random episodes to balance its lengths
LONG = [a for a in TMAZE if not a.startswith("trainer.n_sample=")] + ["trainer.n_sample=100000"]
# make reproduce's stages: the experiments, then the other three sweeps together
STAGES = (
    (" ".join(["experiments 2 experiment=ch3_floor,ch3_coding_cw", *FLOOR]),),
    (
        " ".join(["noise_grid 2 experiment=ch3_floor env.noise=0.0,0.5", *FLOOR]),
        " ".join(["hidden_sizes 1 experiment=ch3_coding_cw actor.n_hidden=10,40", *FLOOR]),
        " ".join(["long_corridor 1 experiment=table4_1_regular env.corridor_length=6", *LONG]),
    ),
)
SWEEPS = [line for stage in STAGES for line in stage]
# where make stands: each stage in turn, stopping at the first that fails; a stop by signal is the
# stage's to report (its exit code, 128 + the signal, is passed on), as make passes a recipe's on
RECIPE = """
import json, signal, subprocess, sys
for signum in (signal.SIGINT, signal.SIGHUP):
    signal.signal(signum, lambda *_: None)
for stage in json.loads(sys.argv[1]):
    code = subprocess.call(stage)
    if code:
        sys.exit(code)
"""
STARTS = "FERL_JOB_STARTS"  # tests/job_starts/sitecustomize.py appends each job's start to this file


def launch(sweep_dir: Path, resume: bool) -> subprocess.Popen:
    """The recipe, each stage ``python -m ferl.run.together [--resume] SWEEP_DIR SWEEP ...``, in a
    session of its own, so that a signal to its process group reaches every job, as a terminal's or
    a scheduler's does; every job's start is appended to ``starts_file(sweep_dir)``."""
    stages = [
        [sys.executable, "-m", "ferl.run.together", *(["--resume"] if resume else []), str(sweep_dir), *stage]
        for stage in STAGES
    ]
    path = os.pathsep.join([str(Path(__file__).parent / "job_starts"), os.environ.get("PYTHONPATH", "")])
    return subprocess.Popen(
        [sys.executable, "-c", RECIPE, json.dumps(stages)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": path, STARTS: str(starts_file(sweep_dir))},
        start_new_session=True,
    )


def starts_file(sweep_dir: Path) -> Path:
    return sweep_dir.parent / f"{sweep_dir.name}.starts"


def starts(sweep_dir: Path) -> list[str]:
    """The job folders started so far, in order, one entry per start."""
    path = starts_file(sweep_dir)
    return path.read_text().splitlines() if path.exists() else []


def jobs(sweep_dir: Path) -> list[tuple[Path, list[str]]]:
    """Every job's folder and overrides, as Hydra numbers and names them."""
    out = []
    for line in SWEEPS:
        sweep = Sweep.parse(line)
        out += [(job_dir(sweep_dir / sweep.name, i, job), job) for i, job in enumerate(sweep_jobs(sweep.overrides))]
    return out


def metrics(sweep_dir: Path) -> dict:
    return {
        str(run_dir.relative_to(sweep_dir)): json.loads((run_dir / "summary.json").read_text())["metrics"]
        for run_dir, _ in jobs(sweep_dir)
    }


def finished_summaries(sweep_dir: Path) -> dict:
    """The finished jobs' summary.json by job folder: bytes and modification time, to show that none
    is written twice."""
    out = {}
    for run_dir, job in jobs(sweep_dir):
        if run_dir.exists() and job_state(run_dir, job) == DONE:
            summary = run_dir / "summary.json"
            out[str(run_dir)] = (summary.read_bytes(), summary.stat().st_mtime_ns)
    return out


TIMES = ("wall_time", "wall time", "agent_steps_per_s", "compile_time", "phase_time")


def analysis(sweep_dir: Path) -> dict[str, list[str]]:
    """analyze.py's reports and figure CSVs of the sweeps: path → lines, times left out (module docstring)."""
    done = subprocess.run([sys.executable, "analyze.py", str(sweep_dir)], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    files = [p for p in sweep_dir.rglob("*") if "analysis" in p.parts and p.suffix in (".csv", ".md")]
    return {str(p.relative_to(sweep_dir)): timeless(p.read_text().replace(str(sweep_dir), "SWEEP")) for p in files}


def timeless(text: str) -> list[str]:
    """The lines of ``text`` without time measures: a line that names one is left out, and so is a
    Markdown table's column whose header names one, in every row of that table."""
    out, dropped = [], None  # the columns of the current table to leave out
    for line in text.splitlines():
        if not line.startswith("| "):
            dropped = None
        else:
            cells = line.split(" | ")
            if dropped is None:  # a table's header
                dropped = {i for i, cell in enumerate(cells) if any(t in cell for t in TIMES)}
            line = " | ".join(c for i, c in enumerate(cells) if i not in dropped)
        if not any(t in line for t in TIMES):  # a line, or a table's row, of a time measure
            out.append(line)
    return out


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> tuple[Path, float]:
    sweep_dir = tmp_path_factory.mktemp("whole") / "sweep"
    started = time.monotonic()
    proc = launch(sweep_dir, resume=False)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err.decode()[-3000:]
    assert sorted(starts(sweep_dir)) == sorted(str(d) for d, _ in jobs(sweep_dir))  # each job, once
    return sweep_dir, time.monotonic() - started


def test_killed_at_random_moments_and_resumed_equals_the_uninterrupted_sweep(tmp_path, uninterrupted):
    """KILLS times: the launch (the first, then each --resume) killed at a moment drawn from
    SHARE of the uninterrupted sweep's wall time (some while the processes start, most while jobs
    run and write), unless the sweep ends first; then one last --resume runs to the end."""
    whole, seconds = uninterrupted
    sweep_dir, moments = tmp_path / "sweep", random.Random(62)
    kept: dict = {}
    for kill in range(KILLS):
        before = len(starts(sweep_dir))
        proc = launch(sweep_dir, resume=kill > 0)
        try:
            proc.wait(timeout=moments.uniform(*SHARE) * seconds)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            print(f"kill {kill + 1}:", [job_state(d, job) if d.exists() else "absent" for d, job in jobs(sweep_dir)])
        else:  # the sweep ended before this moment
            assert proc.returncode == 0, proc.stderr.read().decode()[-3000:] if proc.stderr else ""
            break
        assert_kept(sweep_dir, kept, starts(sweep_dir)[before:])
        kept = finished_summaries(sweep_dir)
    assert kill > 0, "the sweep ended before the first kill"
    before = len(starts(sweep_dir))
    proc = launch(sweep_dir, resume=True)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err.decode()[-3000:]
    assert_kept(sweep_dir, kept, starts(sweep_dir)[before:])
    assert set(starts(sweep_dir)) == {str(d) for d, _ in jobs(sweep_dir)}  # every job started
    assert metrics(sweep_dir) == metrics(whole)
    assert_same_analysis(sweep_dir, whole)


def assert_same_analysis(sweep_dir: Path, whole: Path) -> None:
    """analyze.py's reports and figure CSVs of both sweeps, line by line (times left out)."""
    resumed, ran = analysis(sweep_dir), analysis(whole)
    assert resumed.keys() == ran.keys() and any(k.endswith(".csv") for k in ran)
    for path, lines in ran.items():
        assert resumed[path] == lines, path


def assert_kept(sweep_dir: Path, kept: dict, started: list[str]) -> None:
    """The jobs finished before a launch (``kept``: their summaries) were not started by it
    (``started``: its starts) and their summary.json is as it was."""
    now = finished_summaries(sweep_dir)
    for folder, done in kept.items():
        assert folder not in started, f"{folder} finished, then started again"
        assert now.get(folder) == done, folder


def stop_after_a_checkpoint(sweep_dir: Path, resume: bool, sig: int) -> str:
    """A launch stopped by ``sig`` to its process group, as Ctrl-C or a closed terminal sends it,
    once a job has written a checkpoint after the launch: its one line that says how to go on."""
    since = time.time()
    proc = launch(sweep_dir, resume)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not any(
        p.stat().st_mtime > since for p in sweep_dir.glob("*/*/checkpoints/*.pt")
    ):
        time.sleep(0.05)
    os.killpg(proc.pid, sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + sig, err.decode()[-3000:]
    lines = [line for line in err.decode().splitlines() if line.startswith("ferl: interrupted")]
    assert len(lines) == 1, err.decode()[-3000:]
    return lines[0]


def test_a_stop_by_signal_says_how_to_resume_and_resumes_to_the_same_metrics(tmp_path, uninterrupted):
    """SIGINT stops the launch, SIGHUP the --resume after it, each in one line naming the command
    that continues (this command with --resume: the folder has no make target's sweep.json); the
    last --resume ends with the uninterrupted sweep's metrics, reports and figure CSVs."""
    whole, _ = uninterrupted
    sweep_dir = tmp_path / "sweep"
    for sig, resume in ((signal.SIGINT, False), (signal.SIGHUP, True)):
        line = stop_after_a_checkpoint(sweep_dir, resume, sig)
        name = signal.Signals(sig).name
        assert line.startswith(f"ferl: interrupted ({name}): what the jobs wrote is kept; continue with: "), line
        assert f"python -m ferl.run.together --resume {sweep_dir} " in line, line
    again = launch(sweep_dir, resume=True)
    _, err = again.communicate(timeout=600)
    assert again.returncode == 0, err.decode()[-3000:]
    assert metrics(sweep_dir) == metrics(whole)
    assert_same_analysis(sweep_dir, whole)


def test_analyze_a_sweep_being_written_reads_the_finished_jobs_and_names_the_others(tmp_path, uninterrupted):
    """analyze.py on the sweeps while they run, frozen (SIGSTOP to the process group) at a moment
    when some jobs have finished and others have not, so that whatever a job was writing stays
    half-written while the analysis reads: it ends with exit 0, analyses the finished jobs and
    names each unfinished one in one line; the sweeps, let go (SIGCONT), end as uninterrupted."""
    whole, _ = uninterrupted
    sweep_dir = tmp_path / "sweep"
    proc = launch(sweep_dir, resume=False)
    all_jobs = jobs(sweep_dir)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        done = [d for d, _ in all_jobs if (d / "summary.json").exists()]
        if done and any((d / ".hydra").is_dir() and d not in done for d, _ in all_jobs):
            break
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGSTOP)
    try:
        started = {d for d, _ in all_jobs if (d / ".hydra").is_dir()}
        done = {d for d in started if (d / "summary.json").exists()}
        analysed = subprocess.run(
            [sys.executable, "analyze.py", str(sweep_dir)], cwd=ROOT, capture_output=True, text=True, timeout=300
        )
    finally:
        os.killpg(proc.pid, signal.SIGCONT)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err.decode()[-3000:]
    assert done and started - done, "the sweeps were not caught between jobs"
    assert analysed.returncode == 0, analysed.stderr[-3000:]
    said = analysed.stdout + analysed.stderr
    for run_dir in started - done:
        assert sum(str(run_dir) in line for line in said.splitlines()) == 1, (run_dir, said[-3000:])
    assert metrics(sweep_dir) == metrics(whole)
