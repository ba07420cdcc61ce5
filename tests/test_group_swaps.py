"""Every experiment × every trainer, predictor and actor option: the swap composes and validates, or is
refused in one line that names the pair (ferl/config/swaps.py). Composition only: nothing is built."""

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig

from conftest import EXPERIMENTS, ROOT, compose_config
from ferl.config.params import ConfigError
from ferl.config.validate import validate

OPTIONS = {g: sorted(p.stem for p in (ROOT / "conf" / g).glob("*.yaml")) for g in ("trainer", "predictor", "actor")}
CONTINUING_ENVS = {"digit_floor", "large_action"}
EPISODIC_TRAINERS = {"algorithm1", "algorithm1_digit", "algorithm2_pixel", "online", "online_long"}


def outcome(overrides) -> str:
    """ "" when the config composes and validates, else the refusal's line."""
    cfg = compose("config", overrides=[*overrides, "compile=false"], return_hydra_config=True)
    HydraConfig.instance().set_config(cfg)
    try:
        validate(cfg)
    except ConfigError as e:
        return str(e)
    return ""


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_swap_validates_or_names_the_pair(experiment):
    """A swap is accepted, or refused in one line that starts by naming the option and the experiment;
    the refused ones are exactly the misfits: an episodic trainer on a continuing task or the other way
    round, and the oracle where the environment has no true-state view."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        env = compose(
            "config", overrides=[f"experiment={experiment}"], return_hydra_config=True
        ).hydra.runtime.choices.env
        refused = {}
        for group, options in OPTIONS.items():
            for option in options:
                line = outcome([f"experiment={experiment}", f"{group}={option}"])
                if line:
                    base = f"experiment={experiment}" if experiment != "none" else f"env={env}"
                    assert line.startswith(f"{group}={option} does not fit {base}: ") and "\n" not in line, line
                    refused[f"{group}={option}"] = line
    episodic = env not in CONTINUING_ENVS
    expected = {f"trainer={t}" for t in OPTIONS["trainer"] if (t in EPISODIC_TRAINERS) != episodic}
    if env not in ("tmaze", "digit_tmaze", "digit_floor"):  # the environments with a true-state view
        expected.add("actor=oracle")
    assert set(refused) == expected, refused


@pytest.mark.parametrize(
    "overrides,group,kept,dropped",
    [
        # the experiment's trainer.steps holds for a trainer that takes steps, and goes with one that does not
        (["experiment=ch3_coding_cw", "trainer=online_td"], "trainer", {"steps": 30000}, ()),
        (["experiment=table4_1_matching", "trainer=online"], "trainer", {"n_episodes": 10000}, ("n_sample", "n_epoch")),
        # a card game's short horizon holds for every actor; its values for the FERL actor's nodes go
        (["experiment=popgym_repeat_previous_easy", "actor=drqn"], "actor", {"gamma": 0.5}, ()),
        (
            ["experiment=large_action", "actor=mlp_q"],
            "actor",
            {"gamma": 0.0, "n_hidden": 13},
            ("action_code", "action_selection", "gibbs_sweeps"),
        ),
        # the experiment's predictor.joint values go with the joint predictor
        (["experiment=table4_2_digit", "predictor=separate"], "predictor", {}, ("joint",)),
        (["experiment=table4_2_digit", "predictor=none"], "predictor", {}, ("joint",)),
    ],
)
def test_a_swap_keeps_the_experiments_values_the_option_takes(overrides, group, kept, dropped):
    cfg = compose_config(overrides)
    HydraConfig.instance().set_config(cfg)
    validate(cfg)
    node = cfg[group]
    assert {k: node[k] for k in kept} == kept
    assert not set(dropped) & set(node), dropped


def test_a_swapped_schedule_is_the_experiments():
    """large_action chooses an exponential learning rate: under actor=mlp_q that schedule is kept
    whole, not mixed with the constant rate's ``value``."""
    cfg = compose_config(["experiment=large_action", "actor=mlp_q"])
    HydraConfig.instance().set_config(cfg)
    validate(cfg)
    assert dict(cfg.actor.lr) == {"_target_": "ferl.schedules.Exponential", "start": 0.1, "end": 0.01}


@pytest.mark.parametrize(
    "overrides,message",
    [
        # a key the user typed is never dropped: refused as without a swap, naming the key
        (
            ["experiment=ch3_floor", "trainer=online_td", "+trainer.n_sample=5"],
            "trainer.n_sample is not allowed: no phase reads it; trainer takes checkpoint_every, compile_group_runs, ",
        ),
        (
            ["experiment=table4_2_digit", "predictor=separate", "predictor.joint.c_y=0.5"],
            "predictor.joint.c_y=0.5 is not allowed: expected a component",
        ),
    ],
)
def test_typed_keys_are_never_dropped(overrides, message):
    cfg = compose_config(overrides)
    HydraConfig.instance().set_config(cfg)
    with pytest.raises(ConfigError) as e:
        validate(cfg)
    assert str(e.value).startswith(message), str(e.value)


@pytest.mark.parametrize("trainer", ["online", "online_long"])
def test_a_refusal_names_the_trainer_the_user_chose(trainer):
    """The online trainer's refusal of TD into a memory it lacks names the option chosen, not the stock one."""
    import torch
    from hydra.utils import instantiate

    cfg = compose_config(
        ["experiment=table4_1_matching", f"trainer={trainer}", "predictor=none", "trainer.td_to_memory=1", "n_runs=2"]
    )
    HydraConfig.instance().set_config(cfg)
    validate(cfg)
    with pytest.raises(ConfigError) as e:
        instantiate(cfg.trainer).setup(cfg, torch.device("cpu"))
    line = f"trainer.td_to_memory=1 is not allowed with predictor=none: trainer={trainer} has no memory"
    assert str(e.value).startswith(line), str(e.value)


@pytest.mark.parametrize(
    "overrides,line",
    [
        (
            ["experiment=null"],
            "ferl: error: experiment=null is not allowed: a group's option cannot be null; "
            "experiment=none runs without an experiment",
        ),
        (
            ["~experiment"],
            "ferl: error: ~experiment is not allowed: a run is named by its experiment; "
            "experiment=none runs without one",
        ),
        (
            ["experiment=ch3_floor", "trainer=online"],
            "ferl: error: trainer=online does not fit experiment=ch3_floor: its phases train on episodes, "
            "and env=digit_floor (DigitFloor) is a continuing task",
        ),
    ],
)
def test_train_py_refuses_in_one_line(tmp_path, overrides, line):
    """Through train.py: exactly one line on stderr, exit status ≠ 0, no run directory."""
    from conftest import run_train

    result = run_train(*overrides, f"hydra.run.dir={tmp_path / 'run'}", timeout=120)
    assert result.returncode != 0
    assert result.stderr.strip().splitlines() == [line], result.stderr
    assert not (tmp_path / "run").exists()
