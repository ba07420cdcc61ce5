"""Resuming an interrupted sweep (docs/sweeps.md, "Resuming a sweep"): ferl.run.together --resume
keeps the finished jobs, resumes the interrupted ones, starts the others; ferl.run.sweepdir checks
RESUME; baselines' run_table keeps its finished jobs likewise."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from hydra.core.override_parser.overrides_parser import OverridesParser

from conftest import ROOT, TINY, eager
from ferl.run import sweepdir, together
from ferl.run.jobs import DONE, RESUMED, TODO, JobError, job_dir, job_state, sweep_jobs

# ch3_floor at a tiny size, 2 jobs (seeds 0 and 1); long enough to be stopped after a checkpoint
SWEEP = [*(a for a in TINY if not a.startswith(("trainer.steps=", "trainer.checkpoint_every="))), "compile=false"]
SWEEP += ["trainer.steps=3000", "trainer.checkpoint_every=250", "device=cpu"]


def finished(run_dir: Path, overrides: list[str]) -> None:
    """A finished job's files as a launch leaves them (the summary, .hydra/overrides.yaml)."""
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (run_dir / "summary.json").write_text(json.dumps({"metrics": {"x": [1.0]}}))


def test_jobs_are_numbered_as_hydra_numbers_them():
    jobs = sweep_jobs(["experiment=table4_1_regular", "seed=0,1", "actor.n_hidden=10,20", "hydra/launcher=joblib"])
    assert jobs == [
        ["experiment=table4_1_regular", "seed=0", "actor.n_hidden=10"],
        ["experiment=table4_1_regular", "seed=0", "actor.n_hidden=20"],
        ["experiment=table4_1_regular", "seed=1", "actor.n_hidden=10"],
        ["experiment=table4_1_regular", "seed=1", "actor.n_hidden=20"],
    ]
    # named by the overrides but the seed (conf/config.yaml's exclude_keys), numbered first
    assert job_dir(Path("s"), 3, jobs[3]) == Path("s/3_table4_1_regular+actor.n_hidden-20")
    assert job_dir(Path("s"), 0, ["seed=0"]) == Path("s/0_ch3_floor")  # conf/config.yaml's default


@pytest.mark.parametrize(
    "job",
    [
        ["experiment=table4_1_regular", "seed=3", "predictor.joint.memory=lstm", "resume=true"],
        ["experiment=none", "env=tmaze", "predictor=joint", "actor=ferl_tmaze", "trainer=algorithm1"],
        ["data=mnist_idx", "data.root=/data/mnist files", "env.noise=0.5", "trainer.test_noise_levels=[0.0,0.5]"],
        [  # more than 80 characters of overrides: cut, and ended by a digest of them
            "actor.n_hidden=39",
            "actor.gamma=0.8",
            "env.noise=0.25",
            "trainer.log_every=10",
            "trainer.steps=30000",
            "trainer.checkpoint_every=1000",
        ],
    ],
)
def test_a_jobs_folder_is_the_one_hydra_names(compose_cfg, job):
    """job_dir (what a resumed sweep looks for) is the folder Hydra's hydra.sweep.subdir gives the
    job: its number, experiment (`experiment=none`: its env) and overrides, every character one a
    folder name and Hydra's unquoted `hydra.run.dir=` take, and at most ~100 characters long."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict

    cfg = compose_cfg(job)
    with open_dict(cfg):
        cfg.hydra.job.num = 12
    HydraConfig.instance().set_config(cfg)
    name = str(cfg.hydra.sweep.subdir)
    assert job_dir(Path("s"), 12, eager(job)) == Path("s") / name
    assert re.fullmatch(r"12_[A-Za-z0-9_]+(\+[A-Za-z0-9._+-]+)?", name) and len(name) <= 100, name
    assert "seed" not in name and "resume" not in name and "compile" not in name
    OverridesParser.create().parse_overrides([f"hydra.run.dir=s/{name}"])  # the resumed job's own command


def test_a_sweep_launched_before_the_overrides_named_the_folders_still_resumes(tmp_path):
    """Its jobs' folders are `<number>_<experiment>`: where only such a folder exists, it is the job's."""
    job = ["experiment=ch3_floor", "env.noise=0.5"]
    (tmp_path / "0_ch3_floor").mkdir()
    assert job_dir(tmp_path, 0, job) == tmp_path / "0_ch3_floor"
    (tmp_path / "0_ch3_floor+env.noise-0.5").mkdir()
    assert job_dir(tmp_path, 0, job) == tmp_path / "0_ch3_floor+env.noise-0.5"


def test_each_job_is_kept_resumed_or_started(tmp_path):
    sweep = together.Sweep("s", 1, ("experiment=ch3_floor", "seed=0,1,2"))
    jobs = sweep_jobs(sweep.overrides)
    finished(tmp_path / "s" / "0_ch3_floor", jobs[0])
    (tmp_path / "s" / "1_ch3_floor" / "checkpoints").mkdir(parents=True)
    todo, states = together.resume_commands(tmp_path, sweep, ("train",))
    assert states == [DONE, RESUMED, TODO]
    assert todo == {
        "1_ch3_floor": ["train", *jobs[1], "resume=true", f"hydra.run.dir={tmp_path / 's' / '1_ch3_floor'}"],
        "2_ch3_floor": ["train", *jobs[2], f"hydra.run.dir={tmp_path / 's' / '2_ch3_floor'}"],
    }


def test_another_runs_folder_stops_the_resume_before_anything_runs(tmp_path, capsys):
    finished(tmp_path / "s" / "0_ch3_floor", ["experiment=ch3_floor", "seed=7"])
    before = sorted(p.name for p in (tmp_path / "s").rglob("*"))
    assert together.main(["--resume", str(tmp_path), "s 1 experiment=ch3_floor seed=0,1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds a finished run of other overrides" in err[0] and "seed=7" in err[0]
    assert sorted(p.name for p in (tmp_path / "s").rglob("*")) == before
    (tmp_path / "s" / "0_ch3_floor" / "summary.json").write_text("{not json")
    with pytest.raises(JobError, match="does not read"):
        job_state(tmp_path / "s" / "0_ch3_floor", ["experiment=ch3_floor", "seed=7"])


def test_resume_trains_only_the_interrupted_job(tmp_path, capsys):
    """Job 0 finished, job 1 stopped by SIGTERM after a checkpoint: the resumed sweep starts one
    process, job 1's, with resume=true; job 0's files are left byte for byte and unmodified."""
    sweep_dir, line = tmp_path / "sweep", f"s 1 {' '.join(SWEEP)} seed=0,1"
    jobs = sweep_jobs(together.Sweep.parse(line).overrides)
    first, second = (job_dir(sweep_dir / "s", i, job) for i, job in enumerate(jobs))
    finished(first, jobs[0])
    kept = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in first.rglob("*") if p.is_file()}

    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *eager(jobs[1]), f"hydra.run.dir={second}"],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    deadline = time.time() + 60
    while not list((second / "checkpoints").glob("*.pt")) and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 128 + signal.SIGTERM, "the job ended before it could be stopped"
    assert not (second / "summary.json").exists()

    starts = tmp_path / "starts.jsonl"  # train.py behind a script that notes each process start
    wrapper = tmp_path / "train.py"
    wrapper.write_text(
        f"import json, os, sys\nwith open({str(starts)!r}, 'a') as f: f.write(json.dumps(sys.argv[1:]) + '\\n')\n"
        f"os.execv(sys.executable, [sys.executable, {str(ROOT / 'train.py')!r}, *sys.argv[1:]])\n"
    )
    assert together.resume_together(sweep_dir, [together.Sweep.parse(line)], (sys.executable, str(wrapper))) == 0
    out = capsys.readouterr().out
    assert "s: resuming" in out and "1 jobs done (kept), 1 to do, 1 of them resumed" in out
    assert "s: 1/1 jobs done" in out
    assert [json.loads(x) for x in starts.read_text().splitlines()] == [
        [*jobs[1], "resume=true", f"hydra.run.dir={second}"]
    ]
    assert job_state(second, jobs[1]) == DONE  # its own .hydra/ kept: the overrides without resume=true
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in first.rglob("*") if p.is_file()} == kept


def test_sweepdir_makes_a_dated_sweep_and_checks_resume(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    outputs = tmp_path / "outputs"
    assert sweepdir.main(["beyond-full"], outputs) == 0
    made = Path(capsys.readouterr().out.strip())
    assert made.parent == outputs / "beyond_full"
    info = json.loads((made / "sweep.json").read_text())
    assert info["target"] == "beyond-full" and info["started"].endswith("UTC") and "commit" in info
    # a bare make names the newest sweep without a report, in one line
    assert sweepdir.main(["beyond-full"], outputs) == 0
    assert capsys.readouterr().err.count("\n") == 1
    assert sweepdir.main(["beyond-full", str(made)], outputs) == 0
    assert capsys.readouterr().out.strip() == str(made)
    for target, resume, part in [
        ("beyond", str(made), "is a sweep of `make beyond-full`, not of `make beyond`"),
        ("beyond", str(tmp_path / "nowhere"), "no such folder"),
        ("suites", str(tmp_path), "is not a sweep of `make suites`"),
    ]:
        assert sweepdir.main([target, resume], outputs) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and part in err[0], err
    old = outputs / "suites" / "2026-01-01_00-00-00"  # made before sweep.json was written
    old.mkdir(parents=True)
    assert sweepdir.main(["suites", str(old)], outputs) == 0


def test_run_table_keeps_finished_jobs_and_resumes_the_interrupted(tmp_path, monkeypatch, capsys):
    sys.path.insert(0, str(ROOT / "baselines"))
    import side_by_side

    trains = {"a/ferl": ["experiment=ch3_floor"], "b/ferl": ["experiment=table4_1_matching"], "c/x": ["seed=3"]}
    finished(tmp_path / "a_ferl", trains["a/ferl"])
    (tmp_path / "b_ferl" / "checkpoints").mkdir(parents=True)
    ran = {}
    monkeypatch.setattr(side_by_side, "run_commands", lambda todo, *a, **k: ran.update(todo) or [])
    monkeypatch.setattr(side_by_side.subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, 0))
    assert side_by_side.run_table(tmp_path, trains, {}, 1) == 0
    assert "1 jobs done (kept), 2 to do, 1 of them resumed" in capsys.readouterr().out
    assert sorted(ran) == ["b/ferl", "c/x"]
    assert "resume=true" in ran["b/ferl"] and "resume=true" not in ran["c/x"]
