"""The composed config checked before any work (CONTRACT §6): one line naming the key and what is allowed.

The root keys are ``RunSettings``; every other node with a ``_target_`` (``env``, ``actor`` and its
schedules, each ``predictor.<name>``, ``preprocessor``, ``data``, ``trainer``) is checked against
the constructor it names (``ferl.config.params``): unknown keys, types, ranges and the class's own
cross-key rules. What involves two components (a preprocessor's input size against the
environment's observations, ``optimized_metric`` against what the trainer writes) is checked by
the trainer's ``setup``, once the components exist and before anything is trained.
"""
from dataclasses import dataclass, fields
from typing import Annotated, Literal

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from ferl.config.params import (Allowed, ConfigError, NonNegativeInt, PositiveInt, check_arguments, check_node,
                                describe, signature, target)

DEVICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class RunSettings:
    """The root keys of conf/config.yaml (what each means is commented there)."""
    name: str
    seed: NonNegativeInt
    n_runs: PositiveInt
    device: Literal[DEVICES]
    cpu_threads: PositiveInt
    resume: bool
    compile: bool
    memory_check: bool
    optimized_metric: Annotated[str, Allowed(bool, "(a summary.json metric name)")] | None


ROOT_KEYS = tuple(f.name for f in fields(RunSettings))


def validate(cfg: DictConfig) -> None:
    """Raise ConfigError for the first thing the config breaks."""
    values = resolved(cfg)
    check_arguments(RunSettings, {k: values[k] for k in ROOT_KEYS if k in values})
    for key, node in values.items():
        if key not in ROOT_KEYS:
            check_tree(node, key)
    if values.get("device") == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device=cuda but no CUDA device is available: use device=auto or device=cpu")


def resolved(cfg: DictConfig) -> dict:
    """The job's config as plain values (Hydra's own node left out); a key without a value
    (``???``) is a ConfigError naming it and what it takes."""
    job = {k: cfg[k] for k in cfg if k != "hydra"}
    try:
        return OmegaConf.to_container(OmegaConf.create(job), resolve=True, throw_on_missing=True)
    except MissingMandatoryValue as e:
        key = e.full_key
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
