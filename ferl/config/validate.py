"""The composed config checked before any work (docs/reliability.md): one line naming the key and what is allowed.

The root keys are ``RunSettings``; every other node with a ``_target_`` (``env``, ``actor`` and its
schedules, each ``predictor.<name>``, ``preprocessor``, ``data``, ``trainer``) is checked against
the constructor it names (``ferl.config.params``): unknown keys, types, ranges and the class's own
cross-key rules. A group the user swapped after an experiment keeps the experiment's values its
option takes (``ferl.config.swaps``); what still does not fit, and a trainer whose kind of task
(episodic or continuing) is not the environment's, is refused naming the pair. What involves two
built components (a preprocessor's input size against the environment's observations,
``optimized_metric`` against what the trainer writes) is checked by the trainer's ``setup``, once
the components exist and before anything is trained.
"""

import re
from dataclasses import dataclass, fields
from typing import Annotated, Literal, cast

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from ferl.config.params import (
    Allowed,
    ConfigError,
    NonNegativeInt,
    PositiveInt,
    check_arguments,
    check_node,
    describe,
    signature,
    target,
)
from ferl.config.swaps import (
    check_fit,
    check_settings,
    drop_foreign_keys,
    hydra_node,
    pair,
    setting_named,
    swapped_groups,
    typed_values,
)

Device = Literal["auto", "cpu", "cuda"]


@dataclass(frozen=True)
class RunSettings:
    """The root keys of conf/config.yaml (what each means is commented there)."""

    name: str
    seed: NonNegativeInt
    n_runs: PositiveInt
    device: Device
    cpu_threads: PositiveInt
    resume: bool
    compile: bool
    memory_check: bool
    optimized_metric: Annotated[str, Allowed(bool, "(a summary.json metric name)")] | None


ROOT_KEYS = tuple(f.name for f in fields(RunSettings))


def validate(cfg: DictConfig) -> None:
    """Raise ConfigError for the first thing the config breaks; first drop the experiment's keys
    that a group the user swapped does not take (``cfg`` is changed in place)."""
    drop_foreign_keys(cfg)
    hydra = hydra_node(cfg)
    values = resolved(cfg)
    if values.get("name") is None and hydra is not None and hydra.runtime.choices.get("experiment") is None:
        raise ConfigError(
            "~experiment is not allowed: a run is named by its experiment; experiment=none runs without one"
        )
    check_arguments(RunSettings, {k: values[k] for k in ROOT_KEYS if k in values})
    try:
        for key, node in values.items():
            if key not in ROOT_KEYS:
                check_settings(cfg, key)
                check_tree(node, key)
    except ConfigError as e:
        raise blamed_on_swap(setting_named(e, cfg), hydra) from None
    check_fit(values, hydra)
    if values.get("device") == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device=cuda but no CUDA device is available: use device=auto or device=cpu")


def blamed_on_swap(error: ConfigError, hydra) -> ConfigError:
    """A key the user did not type that fails after a group swap came with the swapped option (or an
    experiment value it cannot take): the error names the pair first."""
    swapped = swapped_groups(hydra) if hydra is not None else []
    key = tuple(re.split(r"[^\w.]", str(error), maxsplit=1)[0].split("."))  # the leading dotted key
    typed = typed_values(hydra) if hydra is not None else set()
    if not swapped or any(key[:i] in typed for i in range(1, len(key) + 1)):
        return error
    at_fault = [g for g in swapped if key[0] == g] or swapped
    return ConfigError(f"{pair(hydra, at_fault)}: {error}")


def resolved(cfg: DictConfig) -> dict:
    """The job's config as plain values (Hydra's own node left out); a key without a value
    (``???``) is a ConfigError naming it and what it takes."""
    job = {k: cfg[k] for k in cfg if k != "hydra"}
    try:
        return cast(dict, OmegaConf.to_container(OmegaConf.create(job), resolve=True, throw_on_missing=True))
    except MissingMandatoryValue as e:
        key = cast(str, e.full_key)  # the missing value's dotted path
        parent, _, name = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else None
        hints = signature(target(node["_target_"]))[1] if isinstance(node, DictConfig) and "_target_" in node else {}
        expected = f": expected {describe(hints[name])}" if name in hints else ""
        raise ConfigError(f"{key} is required{expected}") from None


def check_tree(node, path: str) -> None:
    """A node with a ``_target_`` is a component; a map without one holds components (``predictor``)."""
    if isinstance(node, dict) and "_target_" in node:
        check_node(node, f"{path}.")
    elif isinstance(node, dict):
        for key, value in node.items():
            check_tree(value, f"{path}.{key}")
    else:
        raise ConfigError(f"{path}={node!r} is not allowed: expected a component (a node with a _target_)")
