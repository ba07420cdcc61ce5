"""A multirun's progress (ferl/run/progress.py): the sweep's job count, the time-left estimate, the
line of each finished job (a failed one too), nothing extra for a single run, and a real joblib
multirun whose worker processes print their lines."""

import itertools
import json

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import JobReturn, JobStatus
from hydra.types import RunMode
from omegaconf import open_dict

from conftest import EXPERIMENTS, ROOT, eager, run_train
from ferl.run.progress import FILE, SweepProgress, planned_jobs, progress_line, sweep_size, time_left

pytestmark = pytest.mark.filterwarnings(
    r"ignore:\s*'hydra/launcher/\w+' is validated against ConfigStore schema:UserWarning"
)


def test_sweep_size_is_the_cartesian_product_of_the_values():
    arguments = [
        "experiment=ch3_floor,table4_1_matching",
        "env.noise=0.0,0.5,1.0",
        "n_runs=2",
        "seed=range(0,40,10)",
        "hydra/launcher=joblib",
        "actor.n_hidden=5,6",
        "actor.n_hidden=10,20,40",
    ]
    values = [
        ["ch3_floor", "table4_1_matching"],
        ["0.0", "0.5", "1.0"],
        ["2"],
        [0, 10, 20, 30],
        ["joblib"],
        ["10", "20", "40"],
    ]  # a key given twice: its last values
    assert sweep_size(arguments) == len(list(itertools.product(*values))) == 72
    assert sweep_size(["n_runs=2"]) == 1
    assert sweep_size(["env.noise=interval(0.0,1.0)"]) is None  # the basic sweeper cannot run it


def test_planned_jobs_of_the_basic_and_the_optuna_sweeper(compose_cfg):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=eager(["n_runs=2"]), return_hydra_config=True)
        with open_dict(cfg):  # what train.py -m ... leaves there (compose itself refuses sweeps)
            cfg.hydra.overrides.task = ["experiment=glob(*)", "seed=0,10", "n_runs=2"]
            cfg.hydra.sweeper.params = {"env.noise": "0.0,0.5,1.0"}
        assert GlobalHydra.instance().is_initialized()  # glob(*) is listed by the config loader
        assert planned_jobs(cfg) == len(list(itertools.product(EXPERIMENTS, [0, 10], [2], [0.0, 0.5, 1.0])))
    assert planned_jobs(compose_cfg(["hparams_search=matching_optuna", "hydra.sweeper.n_trials=5"])) == 5


def test_time_left_schedules_the_mean_job_on_the_lanes():
    assert time_left([10.0, 20.0], [], queued=3, lanes=1) == pytest.approx(45.0)  # one after the other
    # two lanes, mean 10: the running job (4 s in) ends at 6; queued ones start at 0, 6, 10 → end at 20
    assert time_left([10.0], [4.0], queued=3, lanes=2) == pytest.approx(20.0)
    assert time_left([10.0], [30.0], queued=0, lanes=2) == 0.0  # the last job has overrun the mean
    assert time_left([10.0], [], queued=4, lanes=4) == pytest.approx(10.0)


def test_progress_line():
    events = [
        {"event": "sweep", "time": 0.0, "jobs": 4},
        {"event": "start", "job": "0_a", "time": 0.0},
        {"event": "start", "job": "1_b", "time": 0.0},
        {"event": "end", "job": "0_a", "time": 600.0, "seconds": 600.0, "failed": False},
    ]
    # 2 lanes (both ran at once), mean 600 s: 1_b ends now, 2_ and 3_ take 600 s side by side
    assert progress_line(events, 600.0) == "ferl: 1/4 jobs done (0_a, 10 min); about 10 min left"
    # a failed job counts, and only the jobs that succeeded give the mean
    events += [{"event": "end", "job": "1_b", "time": 660.0, "seconds": 660.0, "failed": True}]
    assert progress_line(events, 660.0) == "ferl: 2/4 jobs done, 1 failed (1_b failed after 11 min); about 10 min left"
    events += [
        {"event": "start", "job": "2_c", "time": 660.0},
        {"event": "end", "job": "2_c", "time": 700.0, "seconds": 40.0, "failed": False},
        {"event": "start", "job": "3_d", "time": 700.0},
        {"event": "end", "job": "3_d", "time": 7900.0, "seconds": 7200.0, "failed": False},
    ]
    assert progress_line(events, 7900.0) == "ferl: 4/4 jobs done, 1 failed (3_d, 2.0 h); sweep took 2.2 h"
    unknown = [{"event": "sweep", "time": 0.0, "jobs": None}, *events[1:4]]  # a sweeper that does not say
    assert progress_line(unknown, 600.0) == "ferl: 1 jobs done (0_a, 10 min)"


def hydra_job(compose_cfg, sweep, mode, num):
    cfg = compose_cfg(["experiment=ch3_floor", f"hydra.sweep.dir={sweep}"])
    with open_dict(cfg):
        cfg.hydra.mode, cfg.hydra.job.num = mode, num
        cfg.hydra.overrides.task = ["experiment=ch3_floor", "seed=0,10"]
    HydraConfig.instance().set_config(cfg)  # hydra.sweep.subdir reads ${hydra:runtime.choices.experiment}
    return cfg


def test_callback_counts_a_failed_job_and_leaves_single_runs_alone(compose_cfg, tmp_path, capsys):
    progress = SweepProgress()
    single = hydra_job(compose_cfg, tmp_path / "single", RunMode.RUN, 0)
    progress.on_job_start(single, task_function=None)
    progress.on_job_end(single, JobReturn(status=JobStatus.COMPLETED))
    assert capsys.readouterr().out == "" and not (tmp_path / "single").exists()

    first = hydra_job(compose_cfg, tmp_path, RunMode.MULTIRUN, 0)
    progress.on_multirun_start(first)
    progress.on_job_start(first, task_function=None)
    progress.on_job_end(first, JobReturn(status=JobStatus.FAILED))
    assert capsys.readouterr().out.startswith("ferl: 1/2 jobs done, 1 failed (0_ch3_floor failed after 0 s);")
    events = [json.loads(line) for line in (tmp_path / FILE).read_text().splitlines()]
    assert [e["event"] for e in events] == ["sweep", "start", "end"] and events[0]["jobs"] == 2
    assert events[-1]["failed"] is True


def test_joblib_multirun_prints_one_line_per_job(tmp_path):
    sweep = tmp_path / "sweep"
    result = run_train(
        "-m",
        "experiment=ch3_coding_cw",
        "seed=0,10",
        "n_runs=2",
        "trainer.steps=300",
        "trainer.log_every=100",
        "trainer.checkpoint_every=100",
        "trainer.test_per_class=8",
        "trainer.test_noise_levels=[0.0]",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        f"hydra.sweep.dir={sweep}",
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    lines = [line for line in result.stdout.splitlines() if " jobs done " in line]
    assert len(lines) == 2, result.stdout
    assert lines[0].startswith("ferl: 1/2 jobs done (") and lines[0].endswith(" left")
    assert lines[1].startswith("ferl: 2/2 jobs done (") and "; sweep took " in lines[1]
    # each line names the job's folder: its number, experiment and overrides (ferl.run.subdir)
    named = {line.split("(")[1].split(",")[0] for line in lines}
    assert {name.split("+")[0] for name in named} == {"0_ch3_coding_cw", "1_ch3_coding_cw"}
    assert named == {p.name for p in sweep.glob("*_ch3_coding_cw+*")}
    events = [json.loads(line) for line in (sweep / FILE).read_text().splitlines()]
    assert [e["event"] for e in events].count("end") == 2 and events[0]["jobs"] == 2
