"""Facts first (docs/architecture.md, "How a run is put together"): sizes come from the environment
through the Job, and a component is checked against its protocol when it is built.

* ``tests/five_arms.py`` (3 reward values, 5 actions, 6-bit observations) trains through train.py
  with the stock ``predictor=joint`` under Algorithm 1 and online, no size on the command line or
  in its YAML: the predictor's reward bits, inputs and the actor's actions are the environment's.
* A size stated against the environment, or an environment lacking what its protocol declares, is
  one ``ferl: error:`` line, exit ≠ 0, and no run directory left behind.
"""

import json
import os
import re
from pathlib import Path

import pytest
import torch

from conftest import run_train
from ferl.config.params import ConfigError
from ferl.conformance import missing_members, required_members
from ferl.interfaces import EpisodicEnvironment, EpisodicEnvironmentBase, TrainingBatch
from ferl.trainers.facts import check_conforms, facts_for
from five_arms import FiveArms, Forgetful

TESTS = Path(__file__).resolve().parent
ENV = {**os.environ, "PYTHONPATH": str(TESTS)}
# the recipe's command (docs/architecture.md, "Add an environment") on this environment, tiny
COMMAND = [
    f"hydra.searchpath=[file://{TESTS / 'toy' / 'conf'}]",
    "experiment=none",
    "env=five_arms",
    "predictor=joint",
    "actor=ferl_tmaze",
]
ALGORITHM1 = [
    "trainer=algorithm1",
    "n_runs=2",
    "trainer.n_sample=60",
    "trainer.n_epoch=3",
    "trainer.n_episodes=60",
    "trainer.log_every=20",
    "trainer.final_window=20",
    "trainer.l_training=1",
]
ONLINE = [
    "trainer=online",
    "n_runs=2",
    "trainer.n_episodes=40",
    "trainer.replay_sample=4",
    "trainer.log_every=20",
    "trainer.final_window=20",
]
ERROR = re.compile(r"ferl: error: [^\n]+")


def only_error_line(result) -> str:
    """The one line a refused run prints (stderr), after checking there is nothing else."""
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and ERROR.fullmatch(lines[0]), result.stderr[-2000:]
    return lines[0]


@pytest.mark.parametrize("trainer", [ALGORITHM1, ONLINE], ids=["algorithm1", "online"])
def test_an_environment_of_other_sizes_trains_with_the_stock_joint_predictor(tmp_path, trainer):
    overrides = [*COMMAND, *trainer]
    assert not any(key in o for o in overrides for key in ("n_reward", "n_obs", "n_actions", "observation_size"))
    run_dir = tmp_path / "run"
    result = run_train(*overrides, f"hydra.run.dir={run_dir}", env=ENV)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    manifest = json.loads((run_dir / "records" / "run.json").read_text())
    assert summary["task"] == "five_arms" and len(summary["metrics"]["final_correct_rate"]) == 2
    assert manifest["env"]["class"] == "five_arms.FiveArms"
    joint = manifest["predictors"]["joint"]
    assert joint["reward_output"] == "bits" and joint["reward_bits"] == 3  # one per reward value (-1, 0, 1)


def test_a_size_that_disagrees_with_the_environment_is_one_line_before_any_file(tmp_path):
    run_dir = tmp_path / "out" / "run"
    result = run_train(*COMMAND, *ALGORITHM1, "+predictor.joint.n_reward=4", f"hydra.run.dir={run_dir}", env=ENV)
    assert only_error_line(result) == (
        "ferl: error: predictor.joint.n_reward=4 disagrees with the environment: "
        "env=five_arms.FiveArms has 3 reward values (-1.0, 0.0, 1.0); leave it out"
    )
    assert not (tmp_path / "out").exists()


def test_the_same_size_stated_agrees_and_is_taken():
    env = FiveArms(2, torch.Generator().manual_seed(0))
    node = {"_target_": "ferl.predictors.recurrent.predictor", "memory": "elman", "n_reward": 3}
    assert facts_for(node, "predictor.joint", env) == {"n_reward": 3}
    assert facts_for({**node, "n_reward": None}, "predictor.joint", env) == {"n_reward": 3}
    with pytest.raises(ConfigError, match=r"^predictor\.joint\.n_reward=2 disagrees"):
        facts_for({**node, "n_reward": 2}, "predictor.joint", env)


def test_an_environment_without_reward_values_gives_no_reward_bits():
    """A third-party environment declares no reward values: bits cannot be built, in one line."""
    env = FiveArms(2, torch.Generator().manual_seed(0))
    env.reward_values = ()
    node = {"_target_": "ferl.predictors.recurrent.predictor", "memory": "gru"}
    assert facts_for(node, "predictor.joint", env) == {}
    from ferl.predictors.recurrent import predictor

    with pytest.raises(ValueError, match=r"^n_reward is required with reward_output=bits: .*reward_output=linear"):
        predictor(memory="gru", n_runs=1, n_obs=6, n_actions=5)


def test_a_missing_attribute_is_named_in_one_line_before_any_file(tmp_path):
    run_dir = tmp_path / "out" / "run"
    result = run_train(
        *[o.replace("env=five_arms", "env=forgetful") for o in COMMAND],
        *ALGORITHM1,
        f"hydra.run.dir={run_dir}",
        env=ENV,
    )
    assert only_error_line(result) == (
        "ferl: error: env: five_arms.Forgetful lacks max_steps, optimal_steps, observation_names "
        '(an episodic environment needs them: docs/architecture.md, "Add an environment")'
    )
    assert not (tmp_path / "out").exists()


def test_hooks_are_declared_and_the_base_gives_their_defaults():
    """A protocol declares its hooks as members; an environment that subclasses the base names
    none of them and gets the defaults; one that neither defines them nor subclasses the base is
    told which base gives them."""
    env = FiveArms(2, torch.Generator().manual_seed(0))
    assert "traceable_steps" not in vars(FiveArms) and "discovers_observations" not in vars(FiveArms)
    assert (env.traceable_steps, env.discovers_observations, env.on_fault) == (False, False, None)
    assert "keep_episodes" not in vars(FiveArms) and env.keep_episodes(3, "trainer.replay_episodes") is None
    assert "tables_generic" not in vars(FiveArms) and env.tables_generic(lambda t: 1 / 0) is None  # nothing passed
    check_conforms(env, EpisodicEnvironment, "env")  # no error
    hooks = {"traceable_steps", "discovers_observations", "keep_episodes", "tables_generic", "on_fault"}
    assert hooks <= set(required_members(EpisodicEnvironment))
    assert "fuse" in required_members(TrainingBatch)
    assert missing_members(Forgetful(2, torch.Generator()), EpisodicEnvironment) == [
        "max_steps",
        "optimal_steps",
        "observation_names",
    ]

    class Unbased:  # FiveArms' members copied onto a class outside the base
        pass

    bare = Unbased()
    bare.__dict__.update(
        {
            name: getattr(env, name)
            for name in required_members(EpisodicEnvironment)
            if name not in dir(EpisodicEnvironmentBase) and name != "probe"
        }
    )
    bare.probe = env.probe
    missing = ["on_fault", "traceable_steps", "discovers_observations", "keep_episodes", "tables_generic"]
    assert missing_members(bare, EpisodicEnvironment) == missing
    with pytest.raises(
        ConfigError,
        match=r"lacks on_fault, traceable_steps, discovers_observations, keep_episodes, tables_generic \(.*; "
        r"ferl\.interfaces\.EpisodicEnvironmentBase gives the defaults of on_fault, "
        r"traceable_steps, discovers_observations, keep_episodes, tables_generic\)$",
    ):
        check_conforms(bare, EpisodicEnvironment, "env")
