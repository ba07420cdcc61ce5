"""ferl.run.together: several multiruns at once, each sweep's output in its log, its ``ferl:`` lines
named, failures reported. A stand-in for train.py (a small script) plays the sweeps."""

import sys
from pathlib import Path

import pytest

from ferl.run import together

# A stand-in for ``train.py -m ...``: prints a progress bar, a ferl line drawn over it and its
# arguments; waits until every sweep has started (a file per sweep), so that sweeps run one after
# another would never end (the test's timeout); exits with the code its first override names.
FAKE_TRAIN = r"""
import sys, time
from pathlib import Path
assert sys.argv[1] == "-m"
args = sys.argv[2:]
sweep_dir = Path(next(a.split("=", 1)[1] for a in args if a.startswith("hydra.sweep.dir=")))
(sweep_dir / "started").write_text("")
n = int(args[1].split("=")[1])
deadline = time.monotonic() + 20
while len(list(sweep_dir.parent.glob("*/started"))) < n:
    if time.monotonic() > deadline:
        sys.exit(9)
    time.sleep(0.01)
sys.stderr.write("predictors:  40%|####      |\r")
sys.stderr.write("predictors: 100%|##########|\rferl: 1/1 jobs done (0_x, 1 s)\n")
print("[HYDRA] a line of Hydra's own")
print("args:", *args)
sys.exit(int(args[0].split("=")[1]))
"""


@pytest.fixture
def fake(tmp_path: Path) -> tuple[str, ...]:
    script = tmp_path / "fake_train.py"
    script.write_text(FAKE_TRAIN)
    return (sys.executable, str(script))


def test_shown_is_the_text_after_the_last_carriage_return_of_a_ferl_line():
    assert together.shown(b"bar 10%|#\rbar 100%|##\rferl: 3/9 jobs done\n") == "3/9 jobs done"
    assert together.shown(b"ferl: error: phase 'actor': ...\r\n") == "error: phase 'actor': ..."
    assert together.shown(b"ferl: 1/2 jobs done\rbar 50%|#\n") is None  # the bar drawn over it
    assert together.shown(b"[HYDRA] Launching 9 jobs\n") is None
    # one job's line after the other job's unfinished bar (both jobs of a sweep write to one pipe)
    assert together.shown(b"\ractor:  40%|####  | 4/10 [00:01<00:01]ferl: x done in 3 s\n") == "x done in 3 s"


def test_parse_names_what_is_wrong():
    assert together.Sweep.parse("noise 2 experiment=ch3_floor 'env.noise=0.0,0.5'") == together.Sweep(
        "noise", 2, ("experiment=ch3_floor", "env.noise=0.0,0.5")
    )
    assert together.Sweep.parse("curve/corridor_5 1 x=1").name == "curve/corridor_5"  # a folder in a folder
    bad = [("noise 2", "expected"), ("../b 2 x=1", "NAME"), ("a//b 2 x=1", "NAME"), ("/a 2 x=1", "NAME")]
    for text, part in [*bad, ("noise 0 x=1", "JOBS"), ("n two x=1", "JOBS")]:
        with pytest.raises(ValueError, match=part):
            together.Sweep.parse(text)


def test_sweeps_run_at_once_each_logged_and_named(tmp_path: Path, fake, capsys):
    sweeps = [together.Sweep(name, jobs, ("code=0", "n=3")) for name, jobs in [("a", 2), ("b", 1), ("c", 1)]]
    assert together.run_together(tmp_path / "sweep", sweeps, train=fake) == 0
    out = capsys.readouterr().out.splitlines()
    for s in sweeps:
        assert f"ferl: {s.name}: 1/1 jobs done (0_x, 1 s)" in out
        assert any(line.startswith(f"ferl: {s.name}: sweep done after") for line in out)
        log = (tmp_path / "sweep" / s.name / together.LOG).read_text()
        assert "[HYDRA] a line of Hydra's own" in log and "predictors:  40%" in log  # everything, bars too
        sweep_dir = tmp_path / "sweep" / s.name
        assert (
            f"args: code=0 n=3 hydra/launcher=joblib hydra.launcher.n_jobs={s.jobs} hydra.sweep.dir={sweep_dir}\n"
            in log
        )
    assert not any("HYDRA" in line for line in out)  # the terminal gets the ferl lines only


def test_a_failed_sweep_is_named_with_its_log_and_the_others_finish(tmp_path: Path, fake, capsys):
    sweeps = [together.Sweep("ok", 1, ("code=0", "n=2")), together.Sweep("bad", 1, ("code=3", "n=2"))]
    assert together.run_together(tmp_path, sweeps, train=fake) == 1
    captured = capsys.readouterr()
    assert "ferl: ok: sweep done after" in captured.out
    assert "ferl: bad: sweep failed (exit 3) after" in captured.out
    assert captured.err.strip() == f"ferl: error: sweep bad failed; its output: {tmp_path / 'bad' / together.LOG}"


# A stand-in for one job (``train.py OVERRIDE ... hydra.run.dir=DIR``, as --lanes runs each): notes
# its start and end in a shared file, and exits with the code its first override names.
FAKE_JOB = r"""
import sys, time
from pathlib import Path
args = sys.argv[1:]
run_dir = next(a.split("=", 1)[1] for a in args if a.startswith("hydra.run.dir="))
notes = Path(sys.argv[0]).parent / "notes.txt"
with open(notes, "a") as f: f.write(f"start {run_dir}\n")
time.sleep(0.3)
with open(notes, "a") as f: f.write(f"end {run_dir}\n")
print("job", *args)
sys.exit(int(args[0].split("=")[1]))
"""


def test_lanes_run_every_sweeps_jobs_in_one_queue(tmp_path: Path, capsys):
    """``--lanes 2``: the three sweeps' six jobs each run once, in the order given, never more
    than two at once (and two at once while jobs wait), each one's output in its sweep's folder;
    a failed job is named with its log, and the status is 1."""
    script = tmp_path / "job" / "train.py"
    script.parent.mkdir()
    script.write_text(FAKE_JOB)
    sweeps = [
        together.Sweep("curve/corridor_5", 9, ("code=0", "seed=0,1")),
        together.Sweep("curve/corridor_3", 9, ("code=0", "seed=2")),
        together.Sweep("other", 9, ("code=0,4", "seed=3")),
    ]
    out = tmp_path / "sweep"
    assert together.pooled(out, sweeps, 2, False, train=(sys.executable, str(script))) == 1
    notes = (script.parent / "notes.txt").read_text().splitlines()
    starts = [line.split(" ", 1)[1] for line in notes if line.startswith("start")]
    expected = [str(d) for s in sweeps for d in jobs_of(out, s)]
    assert sorted(starts) == sorted(expected) and len(starts) == 5
    running, most = 0, 0
    for line in notes:
        running += 1 if line.startswith("start") else -1
        most = max(most, running)
    assert most == 2
    assert set(starts[:2]) == set(expected[:2])  # the queue's head, in the order given
    for run_dir in expected:
        assert Path(run_dir + ".log").read_text().startswith("job ")
    captured = capsys.readouterr()
    assert "3 sweeps, 5 jobs to do, 2 at a time" in captured.out
    failed = jobs_of(out, sweeps[2])[1]
    assert captured.err.strip() == f"ferl: error: job other/{failed.name} failed; its output: {failed}.log"


def jobs_of(sweep_dir: Path, sweep: together.Sweep) -> list[Path]:
    """The run directories of a sweep's jobs, as a resumed or pooled sweep names them."""
    from ferl.run.jobs import job_dir, sweep_jobs

    return [job_dir(sweep_dir / sweep.name, i, job) for i, job in enumerate(sweep_jobs(sweep.overrides))]


def test_main_refuses_bad_arguments_in_one_line(tmp_path: Path, capsys):
    assert together.main([str(tmp_path), "a 1 x=1", "a 2 y=1"]) == 2
    assert capsys.readouterr().err.strip() == "ferl: error: two sweeps share a NAME: a a"
    assert together.main([str(tmp_path), "a x=1"]) == 2
    assert "expected 'NAME JOBS OVERRIDE ...'" in capsys.readouterr().err
    assert together.main(["--lanes", "0", str(tmp_path), "a 1 x=1"]) == 2
    assert capsys.readouterr().err.strip() == "ferl: error: --lanes takes a whole number ≥ 1, got 0"
    assert not any(tmp_path.iterdir())  # refused before anything was written


def test_a_progress_bar_reaches_the_log_before_its_line_ends(tmp_path: Path, capsys):
    """``tail -f sweep.log`` shows a job's bar as it is drawn, not when the job ends."""
    import os
    import threading
    import time

    read_end, write_end = os.pipe()
    log_path = tmp_path / together.LOG
    with open(read_end, "rb") as pipe, open(log_path, "wb") as log:
        relay = threading.Thread(target=together._relay, args=("s", pipe, log, threading.Lock()), daemon=True)
        relay.start()
        try:
            os.write(write_end, b"actor:  10%|#\r")
            deadline = time.monotonic() + 10
            while log_path.read_bytes() != b"actor:  10%|#\r" and time.monotonic() < deadline:
                time.sleep(0.01)
            assert log_path.read_bytes() == b"actor:  10%|#\r"
            os.write(write_end, b"actor: 100%|##\rferl: 1/1 jobs done\n")
        finally:
            os.close(write_end)
            relay.join(timeout=10)
    assert capsys.readouterr().out == "ferl: s: 1/1 jobs done\n"


def test_a_stopped_queue_says_how_to_continue_it_with_its_lanes(tmp_path: Path):
    import signal

    line = together.stopped_line(signal.SIGHUP, tmp_path, [together.Sweep("a/b", 1, ("x=1",))], lanes=2)
    assert line.startswith("ferl: interrupted (SIGHUP): what the jobs wrote is kept")
    assert line.endswith(f"python -m ferl.run.together --resume --lanes 2 {tmp_path} 'a/b 1 x=1'")
