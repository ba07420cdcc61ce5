"""One training job: the components built from the composed config, and the run it writes.

Data flows one way, and the components are built in that order from the config's groups: data
(when a component's constructor takes ``data``, or a preprocessor needs images to fit) →
environment → preprocessor → predictors → actor. Their sizes follow from what the modules
report, not from YAML keys: the predictors read the (processed) observation, the actor's state is
that observation followed by every predictor's memory. Run r of the batch uses seed + r; each
component's weights are drawn from seed + its offset + r (``SeedOffsets``), so that they differ.

The job also holds what every phase of a trainer shares: the generator of the batch's random
stream, the divergence guard, the run directory and its TensorBoard writer, the progress that a
checkpoint saves (finished phases, the state of an unfinished one, data passed between phases)
and the summary's metrics.
"""
import time
from dataclasses import dataclass

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate

from ferl.compiled import compile_seconds, fast_path
from ferl.config.params import ConfigError, signature, target
from ferl.run.failures import Interrupted, where
from ferl.run.guard import DivergenceGuard


@dataclass(frozen=True)
class SeedOffsets:
    """What is added to the run's seed for each component's initial weights."""
    actor: int = 0
    predictors: int = 10_000   # predictor i: + i × this
    preprocessor: int = 200_000
    env: int = 300_000         # an environment that draws its own task per run (``seed`` in its constructor)


def takes(node, name: str) -> bool:
    """Whether the constructor a config node names takes the argument ``name``."""
    return name in signature(target(node["_target_"]))[0]


def build(node, **runtime):
    """instantiate a component; a value that only the data reveal as impossible (a reservoir larger
    than a class's images) becomes a ConfigError naming it."""
    try:
        return instantiate(node, **runtime)
    except InstantiationException as e:
        cause = e.__cause__ or e
        if isinstance(cause, (ValueError, TypeError)):
            raise ConfigError(str(cause).splitlines()[0]) from None
        raise


class Job:
    """The components of one batch of runs and the run it writes (see the module docstring)."""

    def __init__(self, cfg, device: torch.device, seeds: SeedOffsets, divergence_limit: float):
        self.cfg, self.device, self.R = cfg, device, cfg.n_runs
        self.seeds = [cfg.seed + r for r in range(self.R)]
        self.generator = torch.Generator(device).manual_seed(cfg.seed)
        pre_cfg, predictor_cfg = cfg.get("preprocessor"), cfg.get("predictor") or {}
        needs_data = takes(cfg.env, "data") or pre_cfg is not None
        self.data = build(cfg.data).load() if needs_data else None
        self.env_seed = cfg.seed + seeds.env
        self.env = self.make_env(self.R)
        self.preprocessor = build(pre_cfg, n_runs=self.R, seed=cfg.seed + seeds.preprocessor).to(device) \
            if pre_cfg is not None else None
        if self.preprocessor is not None and self.preprocessor.input_size != self.env.observation_size:
            raise ConfigError(f"preprocessor takes {self.preprocessor.input_size} inputs, but the environment's "
                              f"observations have {self.env.observation_size} values")
        self.n_obs = n_obs = self.preprocessor.output_size if self.preprocessor is not None else self.env.observation_size
        self.predictors = {name: build(p, n_runs=self.R, n_obs=n_obs, n_actions=self.env.n_actions,
                                       seed=cfg.seed + seeds.predictors * i).to(device)
                           for i, (name, p) in enumerate(predictor_cfg.items())}
        n_state = n_obs + sum(p.memory_size for p in self.predictors.values())
        self.actor = build(cfg.actor, n_runs=self.R, n_state=n_state, n_actions=self.env.n_actions,
                           seed=cfg.seed + seeds.actor).to(device)
        self.guard = DivergenceGuard(self.R, divergence_limit, self.seeds, device)
        if hasattr(self.env, "on_fault"):  # an outside environment's failed run is frozen (ferl.envs.boundary)
            self.env.on_fault = self.guard.freeze
        self.run = self.writer = self.stop = None
        # what a checkpoint saves of the run's course: finished phases, an unfinished one's state,
        # data one phase hands the next, the summary's metrics so far, the acting phases' steps and time
        self.progress = {"done": [], "partial": {}, "shared": {}, "metrics": {}, "agent_steps": 0, "actor_time": 0.0}
        self.resources = {}  # what phases prepare at every start (not saved: drawn again alike)
        self.unit = "step"   # what the guard reports a divergence in (a T-maze: "episode")
        self.fast = fast_path(cfg.compile, device)  # compile the phases' chunks of steps (ferl.compiled)
        self.compile_started = compile_seconds()  # a process may train several jobs (Hydra's joblib workers)
        self.started = time.perf_counter()  # this process's share of wall_time_s (the trainer may start it earlier)
        self.earlier_time = 0.0  # wall_time_s that earlier processes of the run spent, up to its checkpoint

    @property
    def shared(self) -> dict:
        return self.progress["shared"]

    @property
    def metrics(self) -> dict:
        return self.progress["metrics"]

    def count_agent_steps(self, steps: int, seconds: float) -> None:
        """Environment steps summed over runs, and the wall time of the phase that took them
        (summary.json's ``agent_steps_per_s``)."""
        self.progress["agent_steps"] += steps
        self.progress["actor_time"] += seconds

    def make_env(self, n_runs: int):
        """A batch of ``n_runs`` environments of the config on the job's generator."""
        extra = {"data": self.data} if takes(self.cfg.env, "data") else {}
        if takes(self.cfg.env, "seed"):
            extra["seed"] = self.env_seed
        return build(self.cfg.env, n_runs=n_runs, generator=self.generator, device=self.device, **extra)

    def components(self) -> dict:
        """Every component that has parameters or state, by the name its checkpoint entry has."""
        parts = {"env": self.env, "preprocessor": self.preprocessor, "actor": self.actor,
                 **{f"predictor_{name}": p for name, p in self.predictors.items()}}
        return {name: part for name, part in parts.items() if part is not None and hasattr(part, "state_dict")}

    def describe(self) -> dict:
        """What produced the run (``records/run.json``): each component's own description."""
        def entry(part):
            return {"class": f"{type(part).__module__}.{type(part).__qualname__}", **part.describe()}
        return {"env": entry(self.env), "preprocessor": entry(self.preprocessor) if self.preprocessor else None,
                "predictors": {name: entry(p) for name, p in self.predictors.items()}, "actor": entry(self.actor)}

    # ---- checkpoints ----------------------------------------------------------------------------
    def checkpoint(self, phase: str | None = None, state=None) -> None:
        """Write everything a resumed run needs (atomically): the progress (with ``state`` as the
        unfinished ``phase``'s), the generator, the guard and every component's state. Then exit
        if a signal asked the run to stop."""
        if phase is not None:
            self.progress["partial"][phase] = state
        self.progress["wall_time_s"] = self.wall_time()
        self.run.save_checkpoint({
            "progress": self.progress, "generator": self.generator.get_state(), "guard": self.guard.state_dict(),
            **{name: part.state_dict() for name, part in self.components().items()}}, self.writer)
        if self.stop.requested:  # train.py prints where, and exits 128 + the signal
            raise Interrupted(self.stop.signal, where(phase, state, self.progress["done"]))

    def restore(self, saved: dict) -> None:
        """A checkpoint's progress, generator, guard and component states."""
        self.generator.set_state(saved["generator"])
        self.guard.load_state_dict(saved["guard"])
        for name, part in self.components().items():
            part.load_state_dict(saved[name])
        self.progress = saved["progress"]
        self.earlier_time = self.progress.get("wall_time_s", 0.0)  # absent from checkpoints written before it

    def wall_time(self) -> float:
        """summary.json's ``wall_time_s`` so far: every process of the run, a resumed one's
        predecessors up to the checkpoint it continues (their time after it is computed again)."""
        return self.earlier_time + time.perf_counter() - self.started
