"""``resume=true`` continues the same run (docs/reliability.md, "Checkpoints and resume").

The run's own config is the one its newest good checkpoint was written under (``RunIdentity``:
the checkpoint proves itself, and ``.hydra/`` of a run made before ferl/run/claim.py may have been
rewritten by a later launch). A resume starts
from that config and applies only the overrides given on its command line: a plain
``resume=true hydra.run.dir=DIR`` continues the run as it was configured, whatever the
experiment's defaults are now. An override that changes the value of a key (or a config-group
choice, ``experiment=…``) is refused, in one line listing every such key, old → new, unless the
key is in ``ALLOWED``: keys that cannot change what the run computes.
"""

from dataclasses import dataclass
from pathlib import Path
from typing import cast

import torch
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf

from ferl.config.params import ConfigError
from ferl.config.validate import resolved
from ferl.messages import warn
from ferl.run.checkpoint import Checkpoint, CheckpointError, RunIdentity, newest_good

# The keys a resume may change, and why none of them changes the run's numbers. Every other key
# is refused; among them, on purpose: compile (the compiled chunks round differently from the eager
# reference, docs/performance.md), trainer.log_every (the divergence guard checks the TD errors once
# per logging interval, so a run freezes at another step; on the digit floor it also sets the length
# of the chunks of TD steps, ferl/trainers/chunks.py), trainer.checkpoint_every (the same chunk
# length), trainer.error_every / td_sample_every / final_window (the records' shapes and the
# summary's windows), name (the summary's "experiment").
ALLOWED = {
    "resume": "the flag itself",
    "device": "auto or the device's own name, as long as it is the device the run ran on (checked apart: "
    "a generator's state and the kernels' rounding are the device's)",
    "cpu_threads": "torch's intra-op threads: the training step's reductions run within one thread "
    "(tested: a resume on 2 threads ends as the 1-thread run)",
    "memory_check": "whether the memory estimate is checked before the run starts",
    "optimized_metric": "which summary.json metric main() returns to a sweeper",
    "trainer.run.checkpoint_minutes": "checkpoints by the clock: a checkpoint at any step or episode leaves the numbers "
    "as they are (tests/test_train_cli.py, tests/test_tmaze_resume.py)",
    "trainer.phases.predictors.checkpoint_every_epochs": "the predictor phase's checkpoint interval, likewise",
    "preprocessor.cache_dir": "where fitted preprocessors are cached: a hit gives the weights a fit gives",
}
ABSENT = "(absent)"


@dataclass(frozen=True)
class Resumed:
    """The config a resume runs under, the checked checkpoint it continues, and what its own
    checkpoints will be written under."""

    config: DictConfig
    checkpoint: Checkpoint
    identity: RunIdentity


def current_choices() -> dict:
    """The config-group choices of this launch (``experiment``, ``actor``, …), Hydra's own left out."""
    try:
        choices = cast(dict, OmegaConf.to_container(HydraConfig.get().runtime.choices))
    except ValueError:  # no Hydra job (a trainer driven in process)
        return {}
    return {k: v for k, v in choices.items() if not k.startswith("hydra")}


def identity_of(cfg, device, choices: dict | None = None) -> RunIdentity:
    """What a new run's checkpoints are written under: ``cfg`` resolved, the choices, the device."""
    return RunIdentity(resolved(cfg), current_choices() if choices is None else choices, torch.device(device).type)


def resumed_run(run_path: Path, given: list[str], device_type) -> Resumed | None:
    """The config the run in ``run_path`` continues under with the ``given`` overrides (Hydra's
    task overrides of this launch), or None when the run holds no checkpoint yet (it starts from
    the beginning, under the given config). ConfigError, in one line: no checkpoint is good, or
    an override changes a key that ``ALLOWED`` does not hold. ``device_type`` maps a ``device``
    value to the device type it runs on."""
    try:
        chosen = newest_good(run_path / "checkpoints")
    except CheckpointError as e:
        raise ConfigError(f"cannot resume {run_path}: {e}") from None
    if chosen is None:
        warn(f"{run_path} holds no checkpoint yet: the run starts from the beginning")
        return None
    saved = chosen.identity
    if saved.config is None:
        raise ConfigError(f"cannot resume {run_path}: {chosen.path} carries no config to check the overrides against")
    config, changes = apply_overrides(saved, given)
    refused = [(key, old, new) for key, old, new in changes if key not in ALLOWED]
    if (now := device_type(config["device"])) != saved.device:
        refused.append(("device", saved.device, f"{now} (a run continues on the device it ran on)"))
    if refused:
        listed = ", ".join(f"{key}: {show(old)} → {show(new)}" for key, old, new in refused)
        raise ConfigError(
            f"resume=true continues the run in {run_path} under its own config, and these overrides "
            f"would change what it computes: {listed} (a resume may change only "
            f"{', '.join(ALLOWED)}; start a new run for other values)"
        )
    cfg = OmegaConf.create(config)
    OmegaConf.set_struct(cfg, True)
    return Resumed(cfg, chosen, RunIdentity(config, saved.choices, saved.device))


def apply_overrides(saved: RunIdentity, given: list[str]) -> tuple[dict, list]:
    """The saved config with the ``given`` overrides applied in order (a key given twice: the last
    wins, as in Hydra), and every key whose final value differs from the run's: (key, old, new).
    A config-group override (``experiment=…``) differs when it chooses another option than the
    run did; its keys are the run's, so it is not applied."""
    config = OmegaConf.create(saved.config)
    before: dict[str, object] = {}
    groups: dict[str, object] = {}
    for override in OverridesParser.create().parse_overrides(list(given)):
        key = override.key_or_group
        if key in saved.choices or "/" in key:  # a config group
            groups[key] = ABSENT if override.is_delete() else override.value()
            continue
        before.setdefault(key, value_at(config, key))
        if override.is_delete():
            parent, _, leaf = key.rpartition(".")
            node = OmegaConf.select(config, parent) if parent else config
            if isinstance(node, DictConfig) and leaf in node:
                del node[leaf]
        else:
            OmegaConf.update(config, key, override.value(), merge=False, force_add=True)
    changes = [
        (key, saved.choices.get(key, ABSENT), new)
        for key, new in groups.items()
        if saved.choices.get(key, ABSENT) != new
    ]
    changes += [(key, old, new) for key, old in before.items() if old != (new := value_at(config, key))]
    return cast(dict, OmegaConf.to_container(config, resolve=True)), changes


def value_at(config: DictConfig, key: str):
    """The plain value at a dotted ``key`` (ABSENT where there is none)."""
    value = OmegaConf.select(config, key, default=ABSENT)
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def show(value) -> str:
    """A value as one would write it in an override."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)
