"""The Hydra face of ferl's Optuna sweeper; the study itself is ``ferl.run.study``.

Hydra instantiates a sweeper only from the ``hydra_plugins`` namespace package (hydra/core/plugins.py,
``is_in_toplevel_plugins_module``) and imports every public module of it at each start, sweep or
not: this module imports neither Optuna nor ferl's study code until a sweep begins. It registers
``hydra/sweeper=ferl_optuna`` and its samplers ``hydra/sweeper/sampler=tpe|random`` with Hydra's
ConfigStore, the keys the hydra-optuna-sweeper plugin had (study_name, direction, storage, n_trials,
n_jobs, sampler, params); ``storage`` now names where the study lives (ferl.run.study_storage).
"""

import sys
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

SWEEPER = {
    "defaults": [{"sampler": "tpe"}, "_self_"],
    "_target_": "hydra_plugins.ferl_optuna_sweeper.ferl_optuna_sweeper.FerlOptunaSweeper",
    "_recursive_": False,  # the sampler's config reaches the study as is: it builds one sampler per slot
    "study_name": "study",
    "direction": "maximize",  # or minimize: what to do with the value main() returns
    "storage": "sqlite",  # sqlite: <sweep dir>/study.db; journal: <sweep dir>/study.journal (NFS); or a database URL
    "n_trials": 20,  # the study's trials in all, over every process that works on it
    "n_jobs": 1,  # trials this process launches at once (in parallel with hydra/launcher=joblib)
    "params": None,  # key → Hydra sweep syntax: interval(a, b), tag(log, interval(a, b)), range(…), choice(…)
}
SAMPLERS = {
    "tpe": {"_target_": "optuna.samplers.TPESampler", "seed": None, "n_startup_trials": 10},
    "random": {"_target_": "optuna.samplers.RandomSampler", "seed": None},
}

store = ConfigStore.instance()
store.store(group="hydra/sweeper", name="ferl_optuna", node=SWEEPER, provider="ferl_optuna_sweeper")
for name, node in SAMPLERS.items():
    store.store(group="hydra/sweeper/sampler", name=name, node=node, provider="ferl_optuna_sweeper")


class FerlOptunaSweeper(Sweeper):
    """``hydra.sweeper``: each trial one job of the configured launcher, the study in a database."""

    def __init__(self, study_name: str, sampler: Any, params: Any = None, **settings: Any) -> None:
        self.settings = {"study_name": study_name, **settings}
        self.sampler = sampler
        self.params = params
        self.config: DictConfig | None = None
        self.hydra_context: HydraContext | None = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config = config
        self.hydra_context = hydra_context
        self.launcher = Plugins.instance().instantiate_launcher(
            config=config, hydra_context=hydra_context, task_function=task_function
        )

    def sweep(self, arguments: list[str]) -> None:
        from ferl.config.params import ConfigError

        try:
            from ferl.run.study import Jobs, Settings, main_error, run_study
        except ModuleNotFoundError as e:  # the sweepers extra is not installed
            if e.name != "optuna":
                raise
            sys.stderr = sys.__stderr__  # as ferl.run.study.main_error: Hydra's stderr is held until main() runs
            print("ferl: error: an Optuna search needs optuna>=4: pip install -e '.[sweepers]'", file=sys.stderr)
            raise SystemExit(2) from e

        assert self.config is not None and self.launcher is not None
        config, launcher = self.config, self.launcher
        jobs = Jobs(
            sweep_dir=Path(str(config.hydra.sweep.dir)),
            launch=lambda overrides, first: launcher.launch(overrides, initial_job_idx=first),
            validate=self.validate_batch_is_legal,
            save_config=lambda path: OmegaConf.save(config, path),
        )
        try:
            settings = Settings.of(
                {
                    **self.settings,
                    "sampler": container(self.sampler),
                    "params": {str(k): str(v) for k, v in (container(self.params) or {}).items()},
                }
            )
            run_study(settings, list(arguments), jobs)
        except ConfigError as e:  # a refused study or search space: one line
            main_error(e)


def container(node: Any) -> Any:
    """A config node as plain Python (it may arrive as a DictConfig or already as a dict)."""
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
