"""A training procedure as a sequence of phases (``Phase``), run in order on one ``Job``.

Chapter 3's procedure is test → online TD training → test (§3.5); Algorithms 1 and 2 are
[preprocessor fit →] random collection → predictor training → actor training (§4.3.1, §5.2).
A phase does one thing to the job's components, may draw from the job's generator, writes its
own records and metrics, and checkpoints itself (``Job.checkpoint``) where it is long. After
every phase the job is checkpointed; ``resume`` skips the finished phases and hands an
unfinished one the state its last checkpoint saved, so a resumed run computes exactly what an
uninterrupted one does.
"""

import time
from dataclasses import dataclass
from typing import Literal, get_args

import torch
from torch.utils.tensorboard import SummaryWriter

from ferl import rng
from ferl.compiled import compile_seconds
from ferl.config.params import ConfigError, NonNegative, Positive, PositiveInt, checked, plain
from ferl.interfaces import ContinuingEnvironment, Environment, EpisodicEnvironment, TrainerBase
from ferl.run.directory import RunDir, StopRequest
from ferl.run.resume import identity_of
from ferl.run.tensorboard import log_hparams
from ferl.trainers.handoffs import PhaseOutputs
from ferl.trainers.job import Job

EnvironmentKind = Literal["episodic", "continuing", "any"]
ENVIRONMENTS: dict[str, type] = dict(
    zip(get_args(EnvironmentKind), (EpisodicEnvironment, ContinuingEnvironment, Environment))
)


@dataclass(frozen=True)
class RunControl:
    """The trainer's ``run`` node (conf/trainer/run/default.yaml): what every phase of a run shares
    for logging, checkpoints and the divergence guard. ``log_every``: steps or episodes between
    TensorBoard points (and the guard's checks); ``checkpoint_every``: steps or episodes between
    a long phase's checkpoints, and ``checkpoint_minutes`` of wall time between them (0: by count
    only); ``divergence_limit``: the |TD error| beyond which (or non-finite) a run is frozen and
    reported diverged (``ferl.run.guard``)."""

    log_every: PositiveInt
    checkpoint_every: PositiveInt
    checkpoint_minutes: NonNegative
    divergence_limit: Positive


class Phase:
    """One step of a training procedure, built from an entry of a trainer's ``phases`` (its
    ``_target_`` and its own keys); it is named by its key there, and implements ``run``."""

    name = ""
    last_step = 0  # the step or episode of its last TensorBoard points (0: it logs none of its own)

    def applies(self, job: Job) -> bool:
        """Whether the job's components call for this phase (a preprocessor's fit needs one)."""
        return True

    def prepare(self, job: Job) -> None:
        """What the phase needs before any phase runs (drawn in this order at every start, so a
        resumed run draws it again the same way): e.g. a test set, or nothing."""

    def start(self, job: Job) -> None:
        """What a fresh run logs before its first phase (nothing here)."""

    def metric_names(self, job: Job) -> list[str]:
        """The flat summary.json metrics it writes into ``job.metrics``."""
        return []

    def run(self, job: Job, state) -> None:
        """Do the phase, from ``state`` (what its last checkpoint saved) or from the start (None)."""
        raise NotImplementedError

    def fresh_state(self, job: Job):
        """What the phase allocates as it starts (records of every step or episode), as ``run``
        begins from it; the memory estimate counts it (``ferl.run.footprint``). None: nothing."""
        return None

    def run_bytes(self, job: Job) -> int:
        """The peak bytes ``run`` allocates beyond ``fresh_state``, including what earlier phases
        handed it (collected episodes, training batches): the memory estimate's hook."""
        return 0


class PhasedTrainer(TrainerBase):
    """A training procedure as written in conf/trainer/*.yaml: ``phases`` (name → phase), run in
    order on one ``Job``, and the ``run`` node they share (``RunControl``). ``kind``: what
    analysis calls the procedure (``phased``: Algorithms 1–2 and chapter 3's; ``online``: §5.4);
    ``environment``: the kind of task its phases step (checked when the environment is built and,
    against the environment's class, by the config's validation); ``seed_offsets``: the
    components' seed offsets, by the name ``ferl.rng`` gives them (``episodic``: Algorithms 1–2 and
    the online trainer; ``continuing``: chapter 3). ``settings``: the trainer's own keys that its
    phases read by interpolation (``${trainer.n_episodes}``), the names users override
    (``trainer.n_episodes=…``); kept in ``records/run.json``."""

    job: Job  # the components, built by setup
    phase = "setup"  # what the trainer is doing: setup, resume, a phase's name, summary (train.py's error line)

    @checked
    def __init__(
        self,
        phases: dict[str, Phase],
        run: RunControl,
        kind: Literal["phased", "online"],
        environment: EnvironmentKind,
        seed_offsets: rng.OffsetsName,
        **settings,
    ):
        for name, phase in phases.items():
            phase.name = name
        self.all_phases, self.control, self.kind = list(phases.values()), run, kind
        self.environment = ENVIRONMENTS[environment]
        self.seed_offsets = rng.NAMED_OFFSETS[seed_offsets]
        self.params = {k: plain(v) for k, v in settings.items()}  # for records/run.json
        self.last_step = max(phase.last_step for phase in self.all_phases)  # of the HParams session

    def setup(self, cfg, device: torch.device) -> None:
        """Build the components and what each phase prepares; check the run's optimized metric."""
        self.started = time.perf_counter()  # wall_time_s counts the building too
        self.job = Job(cfg, device, self.seed_offsets, self.control, self.environment)
        self.job.started = self.started
        self.phases = [phase for phase in self.all_phases if phase.applies(self.job)]
        for phase in self.phases:
            phase.prepare(self.job)
        metric = cfg.get("optimized_metric")
        if metric is not None and metric not in self.metric_names():
            raise ConfigError(
                f"optimized_metric={metric!r} is not allowed: expected null or a summary.json metric "
                f"of this run: {', '.join(self.metric_names())}"
            )

    def metric_names(self) -> list[str]:
        return [name for phase in self.phases for name in phase.metric_names(self.job)]

    def starting_state(self) -> list:
        """Every phase's ``fresh_state`` (``Trainer.starting_state``)."""
        return [phase.fresh_state(self.job) for phase in self.phases]

    def run_bytes(self) -> int:
        """The largest phase's ``run_bytes``: phases run one after another (``Trainer.run_bytes``)."""
        return max((int(phase.run_bytes(self.job)) for phase in self.phases), default=0)

    def describe(self) -> dict:
        return {
            "class": f"{type(self).__module__}.{type(self).__qualname__}",
            "kind": self.kind,
            "phases": [p.name for p in self.phases],
            **self.params,
        }

    def fit(self, run: RunDir, resume: bool) -> dict:
        """Every phase not yet done; returns the summary.json dict (docs/records.md)."""
        job = self.job
        job.run = run
        if run.identity is None:  # driven in process: the checkpoints carry the job's own config
            run.identity = identity_of(job.cfg, job.device)
        self.phase = "resume" if resume else "start"
        saved = run.resume() if resume else None
        if saved:
            job.restore(saved)
        self.write_manifest(run)
        with SummaryWriter(run.tb) as job.writer, StopRequest() as job.stop:
            if not job.progress["done"]:
                for phase in self.phases:
                    phase.start(job)
            for phase in self.phases:
                if phase.name in job.progress["done"]:
                    continue
                self.phase = phase.name
                started = time.perf_counter()
                phase.run(job, job.progress["partial"].pop(phase.name, None))
                times = job.progress.setdefault("phase_time_s", {})
                times[phase.name] = times.get(phase.name, 0.0) + time.perf_counter() - started
                job.progress["partial"].pop(phase.name, None)  # its in-phase checkpoints' state
                job.progress["done"].append(phase.name)
                if phase is self.phases[-1]:
                    job.stop = StopRequest()  # finished: a late signal no longer stops it
                    job.progress["shared"] = PhaseOutputs()  # the finished run keeps parameters, not the data
                job.checkpoint()
            self.phase = "summary"
            summary = self.summary(job, job.wall_time())  # over every process of the run
            log_hparams(job.writer, job.cfg, summary, self.last_step)
        return summary

    def write_manifest(self, run: RunDir) -> None:
        """``records/run.json``: what produced the run, for analysis to read (docs/records.md)."""
        manifest = {
            "task": self.job.env.task,
            "experiment": self.job.cfg.name,
            "trainer": self.describe(),
            **self.job.describe(),
        }
        run.save_json("run", manifest)

    def summary(self, job: Job, wall_time: float) -> dict:
        return {
            "experiment": job.cfg.name,
            "task": job.env.task,
            "seeds": job.seeds,
            "metrics": job.guard.void_failed_envs(job.metrics),
            "optimal": job.env.optimal(job.actor.gamma),
            "wall_time_s": wall_time,
            "agent_steps_per_s": job.progress["agent_steps"] / max(job.progress["actor_time"], 1e-9),
            "compile_time_s": compile_seconds() - job.compile_started,  # in wall_time_s, not in agent-steps/s
            "phase_time_s": job.progress.get("phase_time_s", {}),  # a phase cut by a stop: from its resume on
            "diverged": job.guard.report(job.unit),
        }
