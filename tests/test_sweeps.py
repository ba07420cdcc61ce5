"""Hydra launchers and sweepers (issue 6/7): the joblib launcher runs multirun jobs in parallel,
the SLURM launcher config composes without a cluster, the Optuna search composes and optimises the
metric that train.py's main() returns; the final summary table."""

import json
import math

import pytest
import torch
import yaml
from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

from conftest import TINY, eager, run_train
from ferl.config.hydra_glue import jobs_per_machine, optimized_value, summary_table
from ferl.config.params import ConfigError
from ferl.config.validate import validate
from ferl.run.jobs import job_dir, sweep_jobs

# our conf/hydra/launcher/*.yaml extend the plugins' configs of the same name (ferl.config.hydra_glue
# silences Hydra's notice about that; pytest resets warning filters for each test)
pytestmark = pytest.mark.filterwarnings(
    r"ignore:\s*'hydra/launcher/\w+' is validated against ConfigStore schema:UserWarning"
)

TMAZE_TINY = [
    "n_runs=2",
    "trainer.n_sample=200",
    "trainer.n_epoch=3",
    "trainer.n_episodes=60",
    "trainer.log_every=20",
    "trainer.td_sample_every=20",
    "trainer.final_window=20",
]


def fake_summary(task="digit_floor"):
    metrics = (
        {
            "reward_per_step_last10pct": [5.0, 7.0],
            "greedy_accuracy": {"0": [0.5, 1.0], "0.125": [0.25, None]},
            "greedy_accuracy_before": {"0": [0.25, 0.25], "0.125": [None, None]},
        }
        if task == "digit_floor"
        else {
            "final_discounted_return": [4.0, 3.0, 2.0],
            "final_steps_to_goal": [3.0, 3.0, 4.0],
            "final_correct_goal_rate": [1.0, 1.0, 0.5],
            "solved": [1, 1, 0],
        }
    )
    return {
        "experiment": "x",
        "task": task,
        "seeds": list(range(len(next(iter(metrics.values()))))),
        "metrics": metrics,
        "optimal": {"reward_per_step": 8.0},
    }


def test_joblib_multirun_runs_both_jobs(tmp_path):
    sweep = tmp_path / "sweep"
    result = run_train(
        "-m",
        *TINY,
        "experiment=ch3_coding_cw",
        "seed=0,10",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        f"hydra.sweep.dir={sweep}",
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "Joblib.Parallel(n_jobs=2" in result.stdout + result.stderr
    assert "ConfigStore schema" not in result.stderr  # our launcher config on top of the plugin's, quietly
    jobs = sorted(sweep.glob("*_ch3_coding_cw*"))
    # named by their overrides (the seed aside), as ferl.run.jobs finds them to resume the sweep
    named = sweep_jobs(eager([*TINY, "experiment=ch3_coding_cw", "seed=0,10"]))
    assert jobs == [job_dir(sweep, n, job) for n, job in enumerate(named)]
    assert jobs[0].name.startswith("0_ch3_coding_cw+n_runs-2+trainer.") and "seed" not in jobs[0].name
    assert jobs[0].name.split("+", 1)[1] == jobs[1].name.split("+", 1)[1]
    seeds = [json.loads((j / "summary.json").read_text())["seeds"] for j in jobs]
    assert seeds == [[0, 1], [10, 11]]
    assert result.stdout.count("mean ± s.d.") == 2 and "greedy_accuracy/0.125" in result.stdout


def test_joblib_launcher_fits_jobs_to_the_cores(compose_cfg):
    cores = jobs_per_machine(1)
    for threads in (1, 2, 64):
        cfg = compose_cfg(["hydra/launcher=joblib", f"cpu_threads={threads}"])
        n_jobs = cfg.hydra.launcher.n_jobs
        assert n_jobs == max(1, cores // threads) and (n_jobs * threads <= cores or n_jobs == 1)
    assert compose_cfg(["hydra/launcher=joblib", "hydra.launcher.n_jobs=3"]).hydra.launcher.n_jobs == 3


def test_submitit_slurm_launcher_composes(compose_cfg):
    cfg = compose_cfg(["hydra/launcher=submitit_slurm", "cpu_threads=4", "experiment=table4_1_matching"])
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("SlurmLauncher") and get_class(launcher._target_)
    assert launcher.partition is None and launcher.cpus_per_task == 4
    assert launcher.timeout_min > 0 and launcher.mem_gb > 0 and launcher.array_parallelism > 0
    assert launcher.max_num_timeout == 0
    assert OmegaConf.to_container(launcher, resolve=True)  # every interpolation resolves
    HydraConfig.instance().set_config(cfg)
    validate(cfg)


def test_optuna_search_config_composes(compose_cfg):
    cfg = compose_cfg(["hparams_search=matching_optuna"])
    sweeper = cfg.hydra.sweeper
    assert cfg.hydra.runtime.choices.experiment == "table4_1_matching" and cfg.hydra.runtime.choices.env == "tmaze"
    assert sweeper._target_.endswith("FerlOptunaSweeper") and sweeper.direction == "maximize"
    assert get_class(sweeper._target_) and get_class(sweeper.sampler._target_)  # Optuna ≥ 4 installed
    assert sweeper.sampler.seed is not None and sweeper.n_trials > 0
    assert sweeper.storage == "sqlite"  # the study in <sweep dir>/study.db (tests/test_study_storage.py)
    assert cfg.optimized_metric == "final_discounted_return"
    for key in sweeper.params:  # the search space names keys that the experiment has
        assert OmegaConf.select(cfg, key) is not None, key
    assert set(sweeper.params) == {"actor.lr.value", "actor.beta.end"}
    HydraConfig.instance().set_config(cfg)
    validate(cfg)
    assert compose_cfg([]).get("optimized_metric") is None


def test_optuna_sweep_maximises_main_return_value(tmp_path):
    sweep = tmp_path / "optuna"
    result = run_train(
        "-m",
        "hparams_search=matching_optuna",
        "hydra.sweeper.n_trials=2",
        *TMAZE_TINY,
        f"hydra.sweep.dir={sweep}",
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    jobs = [next(sweep.glob(f"{i}_table4_1_matching*")) for i in range(2)]  # the folder may name overrides
    means = [
        sum(m) / len(m)
        for m in (json.loads((job / "summary.json").read_text())["metrics"]["final_discounted_return"] for job in jobs)
    ]
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert best["best_value"] == pytest.approx(max(means), rel=1e-6)
    assert set(best["best_params"]) == {"actor.lr.value", "actor.beta.end"}
    assert best["n_complete"] == 2 and (sweep / "study.db").is_file()


def test_optimized_value_is_the_mean_over_runs():
    floor, maze = fake_summary(), fake_summary("tmaze")
    assert optimized_value(floor, None) is None
    assert optimized_value(floor, "reward_per_step_last10pct") == pytest.approx(6.0)
    assert optimized_value(floor, "greedy_accuracy/0") == pytest.approx(0.75)
    assert optimized_value(floor, "greedy_accuracy/0.125") == pytest.approx(0.25)  # null runs skipped
    assert math.isnan(optimized_value(floor, "greedy_accuracy_before/0.125"))
    assert optimized_value(maze, "final_discounted_return") == pytest.approx(3.0)
    assert optimized_value(maze, "solved") == pytest.approx(2 / 3)
    with pytest.raises(ConfigError, match="optimized_metric"):
        optimized_value(maze, "greedy_accuracy/0")


def test_summary_table():
    lines = summary_table(fake_summary()).splitlines()
    assert lines[0].split() == ["metric", "(2", "runs)", "mean", "±", "s.d.", "before", "training"]
    rows = {line.split()[0]: line.split()[1:] for line in lines[1:]}
    assert rows["reward_per_step_last10pct"] == ["6.000", "±", "1.414"]
    assert rows["greedy_accuracy/0"] == ["0.750", "±", "0.354", "0.250", "±", "0.000"]
    assert rows["greedy_accuracy/0.125"] == ["0.250", "n/a"]  # one run: no s.d. (ferl.stats)
    assert not any(name.startswith("greedy_accuracy_before") for name in rows)
    assert lines[-1] == "  optimal: reward_per_step 8"
    maze = summary_table(fake_summary("tmaze")).splitlines()
    assert maze[0].split()[:3] == ["metric", "(3", "runs)"] and "before" not in maze[0]
    assert maze[1].split() == ["final_discounted_return", "3.000", "±", "1.000"]


def check_before_work(cfg) -> None:
    """What train.py checks before any training: the config, then the trainer's setup, which
    knows the metrics its run will write."""
    HydraConfig.instance().set_config(cfg)
    validate(cfg)
    instantiate(cfg.trainer).setup(cfg, torch.device("cpu"))


@pytest.mark.parametrize(
    "overrides,message",
    [
        (["optimized_metric=reward"], "optimized_metric='reward' is not allowed"),
        (["optimized_metric=1"], "optimized_metric=1 is not allowed"),
        # the metrics of this run are named: a T-maze's, or the floor's at its own test levels
        (["experiment=table4_1_matching", "optimized_metric=greedy_accuracy/0"], "final_discounted_return"),
        (["optimized_metric=greedy_accuracy/0.3"], "greedy_accuracy/0.125"),
    ],
)
def test_optimized_metric_is_validated(compose_cfg, overrides, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")) as e:
        check_before_work(compose_cfg([*overrides, "n_runs=1"]))
    assert "\n" not in str(e.value)


def test_optimized_metric_accepts_every_task_metric(compose_cfg):
    for overrides in (
        ["optimized_metric=greedy_accuracy/0.125"],
        ["optimized_metric=greedy_accuracy_before/1"],
        ["optimized_metric=reward_per_step_last10pct"],
        ["experiment=table5_1_bit", "optimized_metric=final_correct_goal_rate"],
    ):
        check_before_work(compose_cfg([*overrides, "n_runs=1"]))
