"""The free-energy family's comparison (baselines/family.py): every test job composes to the agent,
head, trainer and episodes it names and passes train.py's checks; each study searches the tuning
task, which is no test task, over the actor's own step-size range; the tuned values reach every
job of their agent, and a missing study is one line naming its file."""

import importlib.util

import pytest
import yaml
from hydra import compose, initialize_config_dir

from conftest import ROOT, validated_config


def load(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "baselines"))
    spec = importlib.util.spec_from_file_location("family", ROOT / "baselines" / "family.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_test_job_composes_to_the_agent_it_names(monkeypatch):
    family = load(monkeypatch)
    jobs = family.train_jobs()
    assert len(jobs) == len(family.TASKS) * len(family.AGENTS) == 8 * 6
    experiments = set()
    for name, overrides in jobs.items():
        task, agent = name.split("/")
        cfg = validated_config(overrides)
        experiments.add(cfg.name)
        assert cfg.trainer.n_episodes == family.TASKS[task][1], name
        if agent.startswith("rq_"):
            assert cfg.actor._target_.endswith("RecurrentQActor") and not cfg.get("predictor"), name
            assert cfg.actor.head == agent[3:] and cfg.hydra.runtime.choices.trainer == "algorithm1", name
        else:
            assert cfg.actor._target_.endswith("FERLActor") and cfg.get("predictor"), name
            assert cfg.trainer.get("td_to_memory", 0) == (family.TD_TO_MEMORY if agent == "ferl_td" else 0), name
    assert "passive_tmaze" in experiments and "table4_1_regular" not in experiments  # tuning task ≠ test tasks
    assert {f"experiment={e}" for e in experiments} == {o[0][0] for o in family.TASKS.values()}


def test_each_study_searches_the_tuning_task_in_its_own_range(monkeypatch, tmp_path):
    family = load(monkeypatch)
    for agent in family.AGENTS:
        command = family.tune_command(agent, tmp_path)
        assert command[2] == "-m" and f"hydra.sweep.dir={tmp_path / 'tune' / agent}" in command
        overrides = [o for o in command[3:] if "interval(" not in o]  # sweep ranges need a multirun
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            cfg = compose("config", overrides=overrides, return_hydra_config=True)
        assert (
            cfg.hydra.runtime.choices.experiment == "table4_1_regular"
            and cfg.env.corridor_length == 5
            and cfg.n_runs == 2
        )
        assert cfg.hydra.sweeper.n_trials == 24 and cfg.hydra.sweeper.sampler.seed == 0
        assert cfg.trainer.n_episodes == family.TUNE_EPISODES
        ranges = [o for o in command if "interval(" in o]
        assert ranges == ([family.ADAM_RANGE] if agent.startswith("rq_") else []), agent


def test_tuned_values_reach_every_job_of_their_agent(monkeypatch, tmp_path):
    family = load(monkeypatch)
    for i, agent in enumerate(family.AGENTS):
        study = tmp_path / "tune" / agent
        study.mkdir(parents=True)
        best = {"best_params": {"actor.lr.value": 0.001 * (i + 1), "actor.beta.end": 3.0 + i}, "best_value": 0.0}
        (study / "optimization_results.yaml").write_text(yaml.safe_dump(best))
    jobs = family.train_jobs(lambda agent: family.tuned(agent, tmp_path))
    for name, overrides in jobs.items():
        i = list(family.AGENTS).index(name.split("/")[1])
        cfg = validated_config(overrides)
        assert cfg.actor.lr.value == pytest.approx(0.001 * (i + 1)) and cfg.actor.beta.end == 3.0 + i, name
    (tmp_path / "tune" / "rq_linear" / "optimization_results.yaml").unlink()
    with pytest.raises(SystemExit, match=r"rq_linear/optimization_results\.yaml is missing"):
        family.tuned("rq_linear", tmp_path)


@pytest.mark.parametrize("left", [None, "train.log", "checkpoints"])
def test_a_job_run_again_is_one_that_train_py_accepts(monkeypatch, tmp_path, left):
    """A comparison run again in its folder resumes a job only where it left checkpoints: a job
    stopped before its first (its folder holds Hydra's log alone) starts anew, as the run
    directory's own check requires."""
    from ferl.run.directory import check_run_dir

    monkeypatch.syspath_prepend(str(ROOT / "baselines"))
    import side_by_side

    run_dir = tmp_path / "matching_ferl"
    if left is not None:
        run_dir.mkdir()
        (run_dir / left).mkdir() if left == "checkpoints" else (run_dir / left).write_text("")
    resume = "resume=true" in side_by_side.command("matching/ferl", ["experiment=table4_1_matching"], tmp_path, False)
    assert resume == (left == "checkpoints")
    assert check_run_dir(run_dir, resume) is None
