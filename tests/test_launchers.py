"""Scale-out on the engines themselves (issue 7/8): train.py -m through a real submitit job array on
this machine (job pickles, folders, logs, results), submitit's timeout signal → checkpoint → the
job re-submitted with resume=true, and Ray (the optional `.[ray]` extra). Each launched job is
compared with the same job run directly, without a launcher (docs/sweeps.md)."""

import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT, TINY, assert_same_tb_log, eager, run_train
from ferl.run import checkpoint
from ferl.run.jobs import job_dir, sweep_jobs

# our conf/hydra/launcher/*.yaml extend the plugins' configs of the same name (see tests/test_sweeps.py)
pytestmark = pytest.mark.filterwarnings(
    r"ignore:\s*'hydra/launcher/\w+' is validated against ConfigStore schema:UserWarning"
)

SEEDS = (0, 1)
# the default experiment (ch3_floor) at TINY's size, 3000 steps: long enough to measure the speed
# that sizes the timeout test; device=cpu: every comparison on the CPU, whatever the machine
JOB = [*(a for a in TINY if not a.startswith("trainer.steps=")), "trainer.steps=3000", "cpu_threads=1", "device=cpu"]
SIGNAL_S = 30  # submitit's local controller signals a job 30 s (its signal_delay_s) before timeout_min=1


def summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def start(out: Path, *overrides: str, env: dict | None = None) -> subprocess.Popen:
    """train.py in the background (eager), its output in ``out``.log."""
    with open(out.with_suffix(".log"), "w") as log:  # the child keeps its own descriptor
        proc = subprocess.Popen(
            [sys.executable, str(ROOT / "train.py"), *eager(overrides)],
            cwd=ROOT,
            env={**(env or os.environ), "PYTHONUNBUFFERED": "1"},
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    proc.log = out.with_suffix(".log")
    return proc


def stop(proc: subprocess.Popen) -> None:
    """A background run killed (if it still runs): a failed test leaves none behind."""
    proc.kill()
    proc.wait()


def finish(proc: subprocess.Popen, timeout: float = 300) -> None:
    code = proc.wait(timeout=timeout)
    assert code == 0, proc.log.read_text()[-3000:]


@pytest.fixture(scope="module")
def direct(tmp_path_factory) -> dict:
    """The two jobs of the sweeps below run directly, without a launcher (both at once): seed → summary."""
    root = tmp_path_factory.mktemp("direct")
    procs = {
        seed: start(root / f"seed{seed}", *JOB, f"seed={seed}", f"hydra.run.dir={root / f'seed{seed}'}")
        for seed in SEEDS
    }
    for proc in procs.values():
        proc.wait(timeout=300)
    for proc in procs.values():
        finish(proc)
    summaries = {seed: summary(root / f"seed{seed}") for seed in SEEDS}
    assert summaries[0]["metrics"] != summaries[1]["metrics"]  # so that equality below says which job is which
    return summaries


def launched_jobs(sweep: Path, *overrides: str) -> list[Path]:
    """The folders Hydra names the jobs of ``train.py -m OVERRIDES`` (compile=false added, as
    run_train does): ``<job number>_ch3_floor+<overrides>`` (ferl.run.subdir)."""
    return [job_dir(sweep, n, job) for n, job in enumerate(sweep_jobs(eager(overrides)))]


def assert_jobs_are_the_direct_runs(sweep: Path, direct: dict) -> None:
    jobs = sorted(sweep.glob("*_ch3_floor*"))
    # the folders the launcher's workers named are the ones a resumed sweep looks for
    assert jobs == launched_jobs(sweep, *JOB, f"seed={','.join(map(str, SEEDS))}")
    assert [j.name.split("+")[0] for j in jobs] == [f"{n}_ch3_floor" for n in range(len(SEEDS))]
    for job, seed in zip(jobs, SEEDS):
        got = summary(job)
        assert got["seeds"] == [seed, seed + 1]
        assert set(got["metrics"]) == {"reward_per_step_last10pct", "greedy_accuracy", "greedy_accuracy_before"}
        assert got["metrics"] == direct[seed]["metrics"], job.name


def test_submitit_local_job_array(tmp_path, direct):
    """Two jobs as a submitit job array on this machine: each job's summary.json is the direct run's,
    and submitit's folder holds each job's pickled call, its pickled result and its logs."""
    sweep = tmp_path / "sweep"
    result = run_train(
        "-m",
        "hydra/launcher=submitit_local",
        *JOB,
        f"seed={','.join(map(str, SEEDS))}",
        f"hydra.sweep.dir={sweep}",
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    output = result.stdout + result.stderr
    assert "Submitit 'local' sweep output dir" in output and "ConfigStore schema" not in output
    assert_jobs_are_the_direct_runs(sweep, direct)

    folders = sorted(p for p in (sweep / ".submitit").iterdir() if p.name != "%j")  # %j: before ids exist
    assert len(folders) == len(SEEDS)
    done = set()
    for folder in folders:
        job_id = folder.name  # the job's process id: also the job's hydra.job.id
        assert (folder / f"{job_id}_submitted.pkl").stat().st_size > 0
        with open(folder / f"{job_id}_0_result.pkl", "rb") as f:
            outcome, job_return = pickle.load(f)
        assert outcome == "success" and job_return.status.name == "COMPLETED"
        run_dir = Path(job_return.hydra_cfg.hydra.runtime.output_dir)
        assert run_dir.parent == sweep and job_return.hydra_cfg.hydra.job.id == job_id
        log = (folder / f"{job_id}_0_log.out").read_text()
        assert f"summary:     {run_dir / 'summary.json'}" in log and "Job completed successfully" in log
        assert "continuing_td: 100%" in (folder / f"{job_id}_0_log.err").read_text()  # the progress bar
        done.add(run_dir)
    assert done == set(launched_jobs(sweep, *JOB, f"seed={','.join(map(str, SEEDS))}"))


def checkpointed_step(run_dir: Path) -> int:
    progress = checkpoint.read(run_dir / "checkpoints" / "last.pt").state()["progress"]
    return (progress["partial"].get("continuing_td") or {}).get("step", 0)


def test_submitit_timeout_checkpoints_and_the_resubmitted_job_ends_as_uninterrupted(tmp_path, direct):
    """submitit_local with timeout_min=1 signals the job 30 s after it starts: submitit's own
    USR2 (its time-limit and pre-emption signal), on which the run writes its checkpoint and exits; the same
    sweep re-submitted with resume=true continues the job in its directory and ends with the summary and
    TensorBoard log of the same job run uninterrupted (beside it, directly). The job's length comes from
    the direct runs' speed, which 3000 steps measure short (CI's job ended 79 000 steps before the
    signal): a job that ends before the signal is run again at the speed it measured itself."""

    def training_steps(done: dict) -> int:  # ≈ 60 s of training at the speed a run measured: cut after ≈ 26 s
        per_s = done["agent_steps_per_s"] / len(done["seeds"])
        return int(min(max(per_s * 60, 20000), 1_000_000)) // 1000 * 1000

    steps = training_steps(direct[0])
    whole, sweep = tmp_path / "whole", tmp_path / "sweep"
    reference = None
    try:
        for attempt in range(3):
            args = [
                *(
                    a
                    for a in JOB
                    if not a.startswith(("trainer.steps=", "trainer.checkpoint_every=", "trainer.log_every="))
                ),
                f"trainer.steps={steps}",
                "trainer.log_every=1000",
                f"trainer.checkpoint_every={steps}",
            ]  # no periodic checkpoint inside training: only the signal's
            (job,) = launched_jobs(sweep, *args)
            reference = start(whole, *args, f"hydra.run.dir={whole}")  # meanwhile, beside the submitit job
            cut = run_train(
                "-m",
                "hydra/launcher=submitit_local",
                "hydra.launcher.timeout_min=1",
                *args,
                f"hydra.sweep.dir={sweep}",
                timeout=300,
            )
            if not (job / "summary.json").exists():
                break
            stop(reference)  # the job ended before submitit's signal: again, at least twice as long
            assert attempt < 2, f"the job ended before submitit's signal three times, the last with {steps} steps"
            steps = max(training_steps(summary(job)), 2 * steps)
            shutil.rmtree(whole, ignore_errors=True), shutil.rmtree(sweep)
        assert cut.returncode != 0 and "has not produced any output" in cut.stdout + cut.stderr, cut.stderr[-3000:]
        assert 0 < checkpointed_step(job) < steps
        (folder,) = (p for p in (sweep / ".submitit").iterdir() if p.name != "%j")
        taken = (job / "checkpoints" / "last.pt").stat().st_mtime - (
            folder / f"{folder.name}_submitted.pkl"
        ).stat().st_mtime
        assert SIGNAL_S - 5 < taken < 60, f"checkpoint {taken:.0f} s after submission: not submitit's signal"

        resumed = run_train(
            "-m",
            "hydra/launcher=submitit_local",
            "resume=true",
            *args,
            f"hydra.sweep.dir={sweep}",
            f"hydra.sweep.subdir={job.name}",
            timeout=300,
        )
        assert resumed.returncode == 0, resumed.stderr[-3000:]
    except BaseException:
        if reference is not None:
            stop(reference)
        raise
    finish(reference)
    assert summary(job)["metrics"] == summary(whole)["metrics"]
    assert_same_tb_log(job, whole)
    assert len([p for p in (sweep / ".submitit").iterdir() if p.name != "%j"]) == 2  # two submissions


def test_ray_launcher_two_jobs(tmp_path, direct):
    """Two jobs through hydra-ray-launcher on a Ray instance started for the sweep (address local:
    in the launching process, stopped when it exits); each job's summary.json is the direct run's."""
    pytest.importorskip("ray", reason="the ray extra is not installed: pip install -e '.[ray]'")
    pytest.importorskip(
        "hydra_plugins.hydra_ray_launcher", reason="the ray extra is not installed: pip install -e '.[ray]'"
    )
    sweep = tmp_path / "sweep"
    result = run_train(
        "-m",
        "hydra/launcher=ray",
        "+hydra.launcher.ray.init.num_cpus=2",
        "+hydra.launcher.ray.init.include_dashboard=false",
        *JOB,
        f"seed={','.join(map(str, SEEDS))}",
        f"hydra.sweep.dir={sweep}",
        timeout=300,
        env={**os.environ, "RAY_DEDUP_LOGS": "0"},
    )  # every worker's lines, even when alike
    assert result.returncode == 0, result.stderr[-3000:]
    output = result.stdout + result.stderr
    assert "Ray Launcher is launching 2 jobs" in output and "ConfigStore schema" not in output
    assert_jobs_are_the_direct_runs(sweep, direct)
    # each job ran in a Ray worker process, whose output Ray forwards with its task name and pid
    workers = [line for line in output.splitlines() if "(_run_job pid=" in line and "ferl: ch3_floor done" in line]
    assert len(workers) == len(SEEDS)


def test_ray_launcher_config(compose_cfg):
    """Our ray.yaml on the plugin's config: one CPU a thread for each job, no retries, and no object
    store size, which ray.init() refuses when it joins a running cluster."""
    pytest.importorskip(
        "hydra_plugins.hydra_ray_launcher", reason="the ray extra is not installed: pip install -e '.[ray]'"
    )
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    launcher = instantiate(compose_cfg(["hydra/launcher=ray", "cpu_threads=3"]).hydra.launcher)
    assert type(launcher).__name__ == "RayLauncher"
    assert OmegaConf.to_container(launcher.ray_cfg, resolve=True) == {
        "init": {"address": "local", "object_store_memory": None},
        "remote": {"num_cpus": 3, "max_retries": 0},
    }
