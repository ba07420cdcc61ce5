"""One training job: the components built from the composed config, and the run it writes.

Data flows one way, and the components are built in that order from the config's groups: data
(when a component's constructor takes ``data``, or a preprocessor needs images to fit) →
environment → preprocessor → predictors → actor. Their sizes follow from what the modules
report, not from YAML keys: the predictors read the (processed) observation, the actor's state is
that observation followed by every predictor's memory, and what the environment decides (its
reward values, its observation size) reaches every constructor that takes it (``ferl.trainers.facts``).
Each component is checked against its protocol as soon as it is built, so that one lacking an
attribute is refused before anything is written. Run r of the batch uses seed + r; each
component's weights are drawn from seed + its offset + r (``ferl.rng``), so that they differ.

The job also holds what every phase of a trainer shares: the generator of the batch's random
stream, the divergence guard, the run directory and its TensorBoard writer, the progress that a
checkpoint saves (finished phases, the state of an unfinished one, what phases hand on:
``ferl.trainers.handoffs``)
and the summary's metrics.
"""

import time
from typing import Any

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from torch.utils.tensorboard import SummaryWriter

from ferl import rng
from ferl.compiled import compile_seconds, fast_path
from ferl.config.params import ConfigError, signature, target
from ferl.exploration import Exploration
from ferl.interfaces import Actor, Environment, EpisodicEnvironment, Predictor, Preprocessor
from ferl.rng import SeedOffsets
from ferl.run.directory import RunDir, StopRequest
from ferl.run.failures import Interrupted, where
from ferl.run.guard import DivergenceGuard
from ferl.trainers.facts import check_conforms, facts_for
from ferl.trainers.handoffs import PhaseOutputs, Prepared


def takes(node, name: str) -> bool:
    """Whether the constructor a config node names takes the argument ``name``."""
    return name in signature(target(node["_target_"]))[0]


def build(node, prefix: str = "", **runtime):
    """instantiate a component; a value that only the data reveal as impossible (a reservoir larger
    than a class's images) becomes a ConfigError naming it (``prefix``: the node's key and a dot,
    before the argument a constructor's message begins with)."""
    try:
        return instantiate(node, **runtime)
    except InstantiationException as e:
        cause = e.__cause__ or e
        if isinstance(cause, (ValueError, TypeError)):
            raise ConfigError(prefix + str(cause).splitlines()[0]) from None
        raise


def beta_facts(actor) -> dict:
    """The actor's inverse temperature at the start and the end of its schedule (monotone:
    ``ferl.schedules``), for records/run.json: β = 0 throughout is a uniformly random policy, an
    agent that analysis must not name like the one it would be with β > 0 (docs/records.md)."""
    start, end = actor.inverse_temperature(0.0), actor.inverse_temperature(1.0)  # every Actor has it
    return {"beta": {"start": float(start), "end": float(end)}}


class Job:
    """The components of one batch of runs and the run it writes (see the module docstring)."""

    # set by the trainer's fit, before any phase runs: the run directory, its TensorBoard writer
    # and the stop request (a signal) that checkpoints heed
    run: RunDir
    writer: SummaryWriter
    stop: StopRequest

    def __init__(self, cfg, device: torch.device, seeds: SeedOffsets, control, env_protocol: type = Environment):
        """``control``: the trainer's ``run`` node (``ferl.trainers.phased.RunControl``: logging,
        checkpoint intervals, divergence limit), which every phase reads; ``env_protocol``: what the
        trainer's phases need of the environment (an episodic one for Algorithms 1–2, a continuing
        one for online TD), checked as soon as it is built."""
        self.cfg, self.device, self.R, self.control = cfg, device, cfg.n_runs, control
        self.seeds = rng.run_seeds(cfg.seed, self.R)
        self.generator = rng.generator(cfg.seed, device)  # the batch's stream
        needs_data = takes(cfg.env, "data") or cfg.get("preprocessor") is not None
        self.data = build(cfg.data).load() if needs_data else None
        self.env_seed = cfg.seed + seeds.env
        self.env = self.make_env(self.R)
        check_conforms(self.env, env_protocol, "env")
        self.preprocessor = self.make_preprocessor(cfg.seed + seeds.preprocessor)
        self.n_obs = n_obs = (
            self.preprocessor.output_size if self.preprocessor is not None else self.env.observation_size
        )
        self.predictors = {
            name: self.make_part(
                p,
                f"predictor.{name}",
                Predictor,
                n_obs=n_obs,
                n_actions=self.env.n_actions,
                seed=cfg.seed + seeds.predictors * i,
            )
            for i, (name, p) in enumerate((cfg.get("predictor") or {}).items())
        }
        n_state = n_obs + sum(p.memory_size for p in self.predictors.values())
        self.actor = self.make_part(
            cfg.actor, "actor", Actor, n_state=n_state, n_actions=self.env.n_actions, seed=cfg.seed + seeds.actor
        )
        self.exploration = self.make_exploration(n_state, cfg.seed + seeds.exploration, env_protocol)
        self.guard = DivergenceGuard(self.R, control.divergence_limit, self.seeds, device)
        self.env.on_fault = self.guard.freeze  # an outside environment's failed run is frozen (ferl.envs.boundary)
        # what a checkpoint saves of the run's course: finished phases, an unfinished one's state,
        # data one phase hands the next, the summary's metrics so far, the acting phases' steps and time
        self.progress: dict[str, Any] = {
            "done": [],
            "partial": {},
            "shared": PhaseOutputs(),
            "metrics": {},
            "agent_steps": 0,
            "actor_time": 0.0,
        }
        self.prepared = Prepared()  # what phases prepare at every start (not saved: drawn again alike)
        self.unit = "step"  # what the guard reports a divergence in (a T-maze: "episode")
        self.fast = fast_path(cfg.compile, device)  # compile the phases' chunks of steps (ferl.compiled)
        self.compile_started = compile_seconds()  # a process may train several jobs (Hydra's joblib workers)
        self.started = time.perf_counter()  # this process's share of wall_time_s (the trainer may start it earlier)
        self.earlier_time = 0.0  # wall_time_s that earlier processes of the run spent, up to its checkpoint

    @property
    def outputs(self) -> PhaseOutputs:
        """What earlier phases handed on (``ferl.trainers.handoffs``)."""
        return self.progress["shared"]

    @property
    def metrics(self) -> dict:
        return self.progress["metrics"]

    def count_agent_steps(self, steps: int, seconds: float) -> None:
        """Environment steps summed over runs, and the wall time of the phase that took them
        (summary.json's ``agent_steps_per_s``)."""
        self.progress["agent_steps"] += steps
        self.progress["actor_time"] += seconds

    def make_part(self, node, key: str, protocol: type, **sizes):
        """A batch of R runs of the component ``node`` (config key ``key``), given the sizes the job
        computed and the environment's facts it takes (``ferl.trainers.facts``), on the job's device,
        checked against ``protocol``."""
        part = build(node, f"{key}.", n_runs=self.R, **sizes, **facts_for(node, key, self.env)).to(self.device)
        check_conforms(part, protocol, key)
        return part

    def make_preprocessor(self, seed: int):
        """The config's preprocessor (None without one). It fits on the data's training images
        (N, P) and then transforms the environment's observations (R, O): P and O must agree."""
        node = self.cfg.get("preprocessor")
        if node is None:
            return None
        if self.env.discovers_observations:  # before the sizes: they agree by construction (n_visible = O)
            raise ConfigError(
                f"preprocessor: it fits on the data's images and processes the table of every observation once, "
                f"and {self.env.task} environments discover their observations as they run: use ~preprocessor"
            )
        part = self.make_part(node, "preprocessor", Preprocessor, seed=seed)
        assert self.data is not None  # loaded whenever the config has a preprocessor
        pixels, size = self.data.train_images.shape[-1], self.env.observation_size
        if part.input_size != size or pixels != size:  # name the size that differs from the observations'
            differs = [f"takes {part.input_size} inputs"] * (part.input_size != size) + [
                f"fits on the data's images of {pixels} pixels"
            ] * (pixels != size)
            raise ConfigError(
                f"preprocessor: it {' and '.join(differs)}, but the environment's observations have {size} values"
            )
        return part

    def make_exploration(self, n_state: int, seed: int, env_protocol: type):
        """The config's directed exploration (``ferl.exploration``; ``none`` when the config has no
        ``exploration`` node), given the sizes its constructor takes; refused with a continuing
        trainer (it acts in episodes) and with an actor it cannot work with."""
        node = self.cfg.get("exploration") or {"_target_": "ferl.exploration.NoExploration"}
        given = {"n_state": n_state, "n_actions": self.env.n_actions, "seed": seed}
        part = self.make_part(node, "exploration", Exploration, **{k: v for k, v in given.items() if takes(node, k)})
        if part.active and env_protocol is not EpisodicEnvironment:
            raise ConfigError(
                f"exploration={part.describe()['kind']} acts in episodes, and this trainer's environment "
                "is continuing: use exploration=none"
            )
        part.check_actor(self.actor)
        return part

    def make_env(self, n_runs: int):
        """A batch of ``n_runs`` environments of the config on the job's generator."""
        extra: dict[str, Any] = {"data": self.data} if takes(self.cfg.env, "data") else {}
        if takes(self.cfg.env, "seed"):
            extra["seed"] = self.env_seed
        return build(self.cfg.env, n_runs=n_runs, generator=self.generator, device=self.device, **extra)

    def components(self) -> dict:
        """Every component (each has state, ``Checkpointed``), by the name its checkpoint entry has."""
        parts = {
            "env": self.env,
            "preprocessor": self.preprocessor,
            "actor": self.actor,
            "exploration": self.exploration if self.exploration.active else None,  # its counts
            **{f"predictor_{name}": p for name, p in self.predictors.items()},
        }
        return {name: part for name, part in parts.items() if part is not None}

    def describe(self) -> dict:
        """What produced the run (``records/run.json``): each component's own description."""

        def entry(part):
            return {"class": f"{type(part).__module__}.{type(part).__qualname__}", **part.describe()}

        return {
            "env": entry(self.env),
            "preprocessor": entry(self.preprocessor) if self.preprocessor else None,
            "predictors": {name: entry(p) for name, p in self.predictors.items()},
            "actor": {**entry(self.actor), **beta_facts(self.actor)},
            **({"exploration": entry(self.exploration)} if self.exploration.active else {}),
        }

    # ---- checkpoints ----------------------------------------------------------------------------
    def checkpoint(self, phase: str | None = None, state=None) -> None:
        """Write everything a resumed run needs (atomically): the progress (with ``state`` as the
        unfinished ``phase``'s), the generator, the guard and every component's state. Then exit
        if a signal asked the run to stop."""
        if phase is not None:
            self.progress["partial"][phase] = state
        self.progress["wall_time_s"] = self.wall_time()
        self.run.save_checkpoint(
            {
                "progress": self.progress,
                "generator": self.generator.get_state(),
                "guard": self.guard.state_dict(),
                **{name: part.state_dict() for name, part in self.components().items()},
            },
            self.writer,
        )
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
