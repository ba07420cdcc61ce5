"""The third-party suites (issue 5/8; `make suites`): every experiment trains a few episodes on the
real POPGym and MiniGrid environments, and every job of the suites' table composes to the agent
it names and passes train.py's checks."""

import importlib.util

import numpy as np
import pytest

from conftest import ROOT, compose_config, train_job, validated_config

SUITES = [
    "popgym_repeat_previous_easy",
    "popgym_count_recall_easy",
    "popgym_autoencode_easy",
    "popgym_minesweeper_easy",
    "minigrid_memory_s7",
]


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "baselines" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("experiment", SUITES)
def test_each_experiment_trains_on_the_real_environment_reproducibly(tmp_path, experiment):
    overrides = [f"experiment={experiment}", "n_runs=2", "trainer.n_episodes=3", "trainer.log_every=1"]
    summary, again = (train_job(compose_config(overrides), tmp_path / name) for name in ("run", "again"))
    metrics = summary["metrics"]
    assert again["metrics"] == metrics  # same seed, same numbers
    assert summary["task"] == "gymnasium"
    assert len(metrics["final_return"]) == 2 and all(np.isfinite(metrics["best_return"]))
    if experiment.startswith("popgym"):  # POPGym scales every episode's return into [−1, 1]
        assert all(-1 - 1e-6 <= r <= 1 + 1e-6 for r in metrics["final_return"]) and "solved" in metrics
    else:
        assert "final_success_rate" in metrics and "solved" not in metrics


def test_every_job_of_make_suites_composes_and_validates(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "baselines"))
    suites = load("suites")
    jobs = suites.train_jobs()
    expected = {"ferl": "FERLActor", "memoryless": "FERLActor", "mlp_q": "MLPQActor", "drqn": "RecurrentQActor"}
    assert {name.split("/")[0] for name in jobs} == {e.split("_", 1)[1] for e in SUITES}
    assert set(suites.EPISODES) == set(SUITES)
    for name, overrides in jobs.items():
        cfg = validated_config(overrides)
        agent = name.split("/")[1]
        assert cfg.actor._target_.endswith(expected[agent]), name
        assert (not cfg.get("predictor")) == (agent in ("memoryless", "drqn")), name
        assert cfg.trainer.n_episodes == suites.EPISODES[cfg.name][0], name
    ppo = suites.ppo_jobs()
    assert {name.split("/")[1] for name in ppo} == {e.split("_", 1)[1] for e in SUITES}
    for name, args in ppo.items():
        episodes, steps = suites.EPISODES[args[args.index("--experiment") + 1]]
        assert int(args[args.index("--steps") + 1]) == episodes * steps, name
