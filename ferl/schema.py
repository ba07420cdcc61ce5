"""Structured-config schemas of every config group (Hydra's ConfigStore, CONTRACT §6).

Each option file of conf/ extends its schema (``defaults: [<option>_schema, _self_]``), so Hydra
checks types while it composes: ``n_runs=2.5``, ``env.noise=abc`` or ``actor.td_rule=td_lambda``
fail before any output exists, and a key that no schema names is rejected. The values themselves
stay in the YAML files (fields here are ``MISSING``: one place for every default); ranges and
cross-key rules (T_max ≥ T_min, state sizes, …) are checked by ``ferl.validate``.

A setting with a fixed set of values is a ``StrEnum`` built from the tuple of the module that
uses it (``ferl.actor.TD_RULES``, …): members equal their strings, so the code keeps comparing
and passing plain strings.
"""
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Dict, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING
from omegaconf.nodes import AnyNode, BooleanNode, EnumNode, IntegerNode, StringNode

from ferl.actor import ACTION_CODES, ACTION_SELECTIONS, LR_NORMS, TD_RULES
from ferl.envs.digit_floor import REWARD_CONDITIONS
from ferl.predictor import REWARD_OUTPUTS
from ferl.preprocessor import VISIBLE_MODES

SCHEMA_SUFFIX = "_schema"  # conf/<group>/<option>.yaml extends <group>/<option>_schema
TASKS = ("digit_floor", "tmaze")  # train.TRAINERS
DEVICES = ("auto", "cpu", "cuda")  # train.resolve_device


def _enum(name: str, values: tuple) -> type[StrEnum]:
    """A StrEnum whose members are named and valued by ``values`` (picklable: module-level)."""
    return StrEnum(name, {v: v for v in values}, module=__name__, qualname=name)


Task = _enum("Task", TASKS)
Device = _enum("Device", DEVICES)
TDRule = _enum("TDRule", TD_RULES)
LRNorm = _enum("LRNorm", LR_NORMS)
ActionCode = _enum("ActionCode", ACTION_CODES)
ActionSelection = _enum("ActionSelection", ACTION_SELECTIONS)
RewardCondition = _enum("RewardCondition", REWARD_CONDITIONS)
RewardOutput = _enum("RewardOutput", REWARD_OUTPUTS)
VisibleMode = _enum("VisibleMode", VISIBLE_MODES)


# ---- root (conf/config.yaml) -------------------------------------------------------------------
def root_schema() -> dict:
    """The root keys, typed. A map of typed value nodes rather than a dataclass: the optional groups
    (predictor, preprocessor) stay absent when null instead of becoming ``key: null``; Hydra still
    rejects unknown root keys (struct mode)."""
    return {
        "name": StringNode(MISSING),
        "task": EnumNode(Task, MISSING),
        "seed": IntegerNode(MISSING),
        "n_runs": IntegerNode(MISSING),
        "device": EnumNode(Device, MISSING),
        "cpu_threads": IntegerNode(MISSING),
        "resume": BooleanNode(MISSING),
        "compile": BooleanNode(MISSING),
        # untyped: ferl.validate names the metrics of the task (and rejects a number such as 1)
        "optimized_metric": AnyNode(MISSING),
    }


# ---- data --------------------------------------------------------------------------------------
@dataclass
class MnistEmbeddedSchema:
    _target_: str = MISSING
    test_per_class: int = MISSING
    split_seed: int = MISSING


@dataclass
class MnistIDXSchema:
    _target_: str = MISSING
    root: str = MISSING


# ---- env ---------------------------------------------------------------------------------------
@dataclass
class DigitFloorSchema:
    _target_: str = MISSING
    patches: int = MISSING
    arrangement: List[List[str]] = MISSING
    noise: float = MISSING
    reward_condition: RewardCondition = MISSING
    goal_reward: float = MISSING
    boundary_reward: float = MISSING
    other_reward: float = MISSING
    noise_tile: Optional[str] = MISSING


@dataclass
class TMazeSchema:
    _target_: str = MISSING
    corridor_length: int = MISSING
    max_steps: int = MISSING
    matching: bool = MISSING
    goal_reward: float = MISSING
    wall_reward: float = MISSING
    step_reward: float = MISSING


@dataclass
class DigitTMazeSchema(TMazeSchema):
    digit_classes: Dict[str, int] = MISSING  # a free map observation name → digit class
    image_index: int = MISSING
    reservoir_size: int = MISSING
    binarize_threshold: Optional[float] = MISSING


# ---- actor -------------------------------------------------------------------------------------
@dataclass
class FERLActorSchema:
    _target_: str = MISSING
    n_hidden: int = MISSING
    td_rule: TDRule = MISSING
    gamma: float = MISSING
    lr: Any = MISSING      # a ferl.schedules node; its keys differ by class (value | start, end)
    lr_norm: LRNorm = MISSING
    beta: Any = MISSING    # likewise
    init_std: float = MISSING
    bias_init_std: float = MISSING
    action_code: ActionCode = MISSING
    action_selection: ActionSelection = MISSING
    gibbs_sweeps: int = MISSING
    td_fresh: bool = MISSING


# ---- predictor: the group maps predictor name → ElmanPredictor ----------------------------------
@dataclass
class ElmanSchema:
    _target_: str = MISSING
    n_memory: int = MISSING
    reward_output: RewardOutput = MISSING
    lr: float = MISSING
    init_std: float = MISSING
    time_average: bool = MISSING
    batch_size: int = MISSING


@dataclass
class JointElmanSchema(ElmanSchema):
    """Chapter 4: observations and the encoded reward, with input scalings, gains and error weights."""
    n_reward: int = MISSING
    c_y: float = MISSING
    c_a: float = MISSING
    beta_m: float = MISSING
    beta_y: float = MISSING
    beta_r: float = MISSING
    rho_y: float = MISSING
    rho_r: float = MISSING


@dataclass
class RewardElmanSchema(ElmanSchema):
    """Chapter 5's scalar-reward predictor (Table 5.1 drops ρ, c and the gains)."""
    predict_obs: bool = MISSING


@dataclass
class JointPredictorSchema:
    joint: JointElmanSchema = MISSING


@dataclass
class SeparatePredictorSchema:
    observation: ElmanSchema = MISSING
    reward: RewardElmanSchema = MISSING


# ---- preprocessor ------------------------------------------------------------------------------
@dataclass
class RBMSchema:
    _target_: str = MISSING
    n_visible: int = MISSING
    n_hidden: int = MISSING
    cd_k: int = MISSING
    sweeps: int = MISSING
    persistent: bool = MISSING
    lr: float = MISSING
    momentum: float = MISSING
    initial_momentum: float = MISSING
    initial_momentum_sweeps: int = MISSING
    weight_decay: float = MISSING
    batch_size: int = MISSING
    init_std: float = MISSING
    visible: VisibleMode = MISSING
    cache_dir: str = MISSING


# ---- trainer -----------------------------------------------------------------------------------
@dataclass
class DigitFloorTrainerSchema:
    steps: int = MISSING
    log_every: int = MISSING
    checkpoint_every: int = MISSING
    test_per_class: int = MISSING
    test_noise_levels: List[float] = MISSING
    checkpoint_minutes: float = MISSING
    divergence_limit: float = MISSING
    compile_group_runs: int = MISSING
    prefetch: int = MISSING


@dataclass
class Algorithm1TrainerSchema:
    n_sample: int = MISSING
    collect_batch: int = MISSING
    train_fraction: float = MISSING
    l_training: int = MISSING
    n_epoch: int = MISSING
    error_every: int = MISSING
    n_episodes: int = MISSING
    actor_obs_scale: float = MISSING
    log_every: int = MISSING
    td_sample_every: int = MISSING
    final_window: int = MISSING
    checkpoint_every_epochs: int = MISSING
    checkpoint_every: int = MISSING
    checkpoint_minutes: float = MISSING
    divergence_limit: float = MISSING


# (group, option) → schema; conf/<group>/<option>.yaml lists ``<option>_schema`` in its defaults
SCHEMAS = {
    ("data", "mnist_embedded"): MnistEmbeddedSchema,
    ("data", "mnist_idx"): MnistIDXSchema,
    ("env", "digit_floor"): DigitFloorSchema,
    ("env", "tmaze"): TMazeSchema,
    ("env", "digit_tmaze"): DigitTMazeSchema,
    ("actor", "ferl"): FERLActorSchema,
    ("actor", "ferl_tmaze"): FERLActorSchema,
    ("predictor", "joint"): JointPredictorSchema,
    ("predictor", "separate"): SeparatePredictorSchema,
    ("preprocessor", "rbm"): RBMSchema,
    ("trainer", "digit_floor"): DigitFloorTrainerSchema,
    ("trainer", "algorithm1"): Algorithm1TrainerSchema,
}


def register_schemas() -> None:
    """Store every schema in Hydra's ConfigStore (idempotent: storing again replaces the node).
    Called at import of train.py and of ferl.hydra_support (which joblib's workers import)."""
    cs = ConfigStore.instance()
    for (group, option), node in SCHEMAS.items():
        cs.store(group=group, name=f"{option}{SCHEMA_SUFFIX}", node=node)
    cs.store(name=f"config{SCHEMA_SUFFIX}", node=root_schema())
