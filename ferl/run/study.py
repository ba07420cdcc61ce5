"""An Optuna study run as a Hydra multirun, kept in a database that outlives the process
(docs/sweeps.md, "The study database"); ``hydra_plugins.ferl_optuna_sweeper`` hands it Hydra's launcher.

Every trial is one train.py job in ``<sweep dir>/<trial number>_<experiment>``; main() returns the
value to optimise. What this module adds to a plain ask-and-tell loop:

* **resuming**: a process that ran the same command into the same sweep directory before left its
  finished trials in the study; they are kept. A RUNNING trial whose process is dead (its worker
  file's flock is free, ``ferl.run.study_storage.Worker``) is marked FAIL, ``ferl_interrupted``, and
  enqueued again with the same parameters; a trial this process was running when it got a signal
  or an exception is treated the same way before the process ends.
* **slots**: each trial takes one of ``n_trials`` slots (user attribute ``ferl_slot``), claimed under
  the study's claims lock, so that any number of worker processes (several ``train.py -m`` on one
  storage, SLURM array tasks) fill one study with ``n_trials`` trials in all, none twice. An
  interrupted trial gives its slot to its retry.
* **determinism**: Optuna's TPESampler(seed) draws from one random stream for the whole process; a
  fresh process, resuming, restarts that stream at the seed, so its next suggestions differ from those
  an uninterrupted study would have made (checked: from the first trial after the restart on, and the
  best value with them). Here each slot's suggestion comes from a new sampler seeded by
  ``(seed, slot)``: given the same finished trials, slot k gets the same parameters in any process,
  so a resumed study ends as the uninterrupted one does. TPE ignores FAIL trials, so the interrupted
  ones change nothing.
"""

import math
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import optuna
from hydra.core.utils import JobReturn, JobStatus
from hydra.utils import instantiate
from omegaconf import OmegaConf
from optuna.storages import BaseStorage
from optuna.trial import FrozenTrial, Trial, TrialState

from ferl.run.study_space import SearchSpace, search_space, suggest
from ferl.run.study_storage import Location, StudyError, Worker, claims, location, open_storage, open_study

SLOT = "ferl_slot"  # which of the n_trials slots a trial fills
WORKER = "ferl_worker"  # the worker process that runs it (study_storage.Worker.name)
INTERRUPTED = "ferl_interrupted"  # a FAIL trial whose process ended before it did: retried, its slot freed
RETRY_OF = "ferl_retry_of"  # on a retry: the number of the interrupted trial it runs again
RESULTS = "optimization_results.yaml"


@dataclass
class Settings:
    """``hydra.sweeper``'s keys (hydra_plugins.ferl_optuna_sweeper registers their defaults)."""

    study_name: str
    direction: str = "maximize"
    storage: str | None = "sqlite"
    n_trials: int = 20
    n_jobs: int = 1
    sampler: dict = field(default_factory=lambda: {"_target_": "optuna.samplers.TPESampler", "seed": None})
    params: dict = field(default_factory=dict)

    @classmethod
    def of(cls, keys: dict) -> "Settings":
        """The settings of ``hydra.sweeper``'s keys; a key this sweeper does not know is refused in one
        line (e.g. hydra-optuna-sweeper's ``max_failure_rate``)."""
        unknown = sorted(set(keys) - {f.name for f in fields(cls)})
        if unknown:
            known = ", ".join(f.name for f in fields(cls))
            raise StudyError(f"hydra.sweeper.{unknown[0]} is not a key of ferl's Optuna sweeper ({known})")
        return cls(**keys)


@dataclass
class Jobs:
    """The Hydra side: ``launch(overrides of each job, number of the first)`` runs jobs through the
    launcher; ``validate`` composes them first; ``save_config`` writes multirun.yaml."""

    sweep_dir: Path
    launch: Callable[[list[list[str]], int], Sequence[JobReturn]]
    validate: Callable[[list[list[str]]], None]
    save_config: Callable[[Path], None]


@dataclass
class Session:
    """One process's part in a study."""

    settings: Settings
    space: SearchSpace
    where: Location
    storage: BaseStorage
    study: optuna.Study
    worker: Worker


def run_study(settings: Settings, arguments: list[str], jobs: Jobs) -> None:
    """Open (or continue) the study, then claim, run and tell trials until its slots are taken."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # our own lines say what happens
    if settings.direction not in ("maximize", "minimize"):
        raise StudyError(f"hydra.sweeper.direction={settings.direction} is not allowed: maximize or minimize")
    space = search_space(settings.params, arguments)
    if not space.distributions:
        raise StudyError("nothing to search: give hydra.sweeper.params or a key=interval(…)/choice(…) override")
    where = location(settings.storage, jobs.sweep_dir)
    with claims(where):
        storage = open_storage(where, settings.study_name)
        study = open_study(storage, where, settings.study_name, settings.direction, space.identity())
        session = Session(settings, space, where, storage, study, Worker(where.workers_dir))
        requeued = requeue_stale(session)
    try:
        jobs.sweep_dir.mkdir(parents=True, exist_ok=True)
        jobs.save_config(jobs.sweep_dir / "multirun.yaml")
        print(start_line(session, requeued, jobs.sweep_dir), flush=True)
        while batch := claim_batch(session):
            run_batch(session, batch, jobs)
        with claims(where):
            written = finished(session) and write_results(session, jobs.sweep_dir)
    finally:
        session.worker.close()
    print(end_line(session, jobs.sweep_dir if written else None), flush=True)


def requeue_stale(session: Session) -> int:
    """Mark the RUNNING trials of dead workers interrupted and enqueue them again (under the claims
    lock); returns how many."""
    trials = session.study.get_trials(deepcopy=False)
    stale = [t for t in trials if t.state == TrialState.RUNNING and not session.worker.alive(t.user_attrs.get(WORKER))]
    for trial in stale:
        requeue(session, trial, trials)
    return len(stale)


def requeue(session: Session, trial: FrozenTrial, trials: list[FrozenTrial]) -> None:
    """``trial`` interrupted: FAIL with ``ferl_interrupted``, and a WAITING retry with its parameters
    (those it had drawn; a retry samples any others from the same slot's seed) and its slot. Each
    step can be repeated, so a process that dies half way leaves nothing the next one cannot finish."""
    session.storage.set_trial_user_attr(trial._trial_id, INTERRUPTED, True)
    if SLOT in trial.user_attrs and all(t.user_attrs.get(RETRY_OF) != trial.number for t in trials):
        session.study.enqueue_trial(trial.params, user_attrs={SLOT: trial.user_attrs[SLOT], RETRY_OF: trial.number})
    session.study.tell(trial.number, state=TrialState.FAIL)


def claim_batch(session: Session) -> list[Trial]:
    """Up to ``n_jobs`` trials for this process, each with its slot and parameters; [] when every
    slot is taken (by finished trials, or by trials other workers run)."""
    batch: list[Trial] = []
    with claims(session.where):
        requeue_stale(session)
        while len(batch) < max(1, session.settings.n_jobs) and (trial := claim(session)) is not None:
            batch.append(trial)
    return batch


def claim(session: Session) -> Trial | None:
    """The next trial: a waiting retry first (Optuna's ask takes the oldest WAITING trial), else a
    new one in the lowest free slot; its parameters drawn by the slot's own sampler."""
    trials = session.study.get_trials(deepcopy=False)
    waiting = [t for t in trials if t.state == TrialState.WAITING]
    slot = waiting[0].user_attrs.get(SLOT) if waiting else None
    if slot is None:
        slot = free_slot(trials, session.settings.n_trials)
        if slot is None:
            return None
    session.study.sampler = slot_sampler(session.settings.sampler, slot)
    trial = session.study.ask()
    trial.set_user_attr(SLOT, slot)
    trial.set_user_attr(WORKER, session.worker.name)
    for name, dist in session.space.distributions.items():
        suggest(trial, name, dist)
    return trial


def free_slot(trials: list[FrozenTrial], n_trials: int) -> int | None:
    """The lowest slot that no trial holds (an interrupted one holds none), or None."""
    taken = {t.user_attrs.get(SLOT) for t in trials if not t.user_attrs.get(INTERRUPTED)}
    return next((slot for slot in range(n_trials) if slot not in taken), None)


def slot_seed(seed: int, slot: int) -> int:
    """The sampler seed of one slot: independent streams for every (seed, slot)."""
    return int(np.random.SeedSequence([int(seed), slot]).generate_state(1)[0])


def slot_sampler(config: dict, slot: int) -> optuna.samplers.BaseSampler:
    """``hydra.sweeper.sampler`` instantiated for one slot (its seed made the slot's; no seed: unseeded)."""
    config = dict(config)
    if config.get("seed") is not None:
        config["seed"] = slot_seed(config["seed"], slot)
    return instantiate(config)


def run_batch(session: Session, batch: list[Trial], jobs: Jobs) -> None:
    """Run the batch's jobs and tell the study their values; a job that raised ends the sweep
    after its trial is told FAIL (as Hydra's basic sweeper ends on it). Any exit on the way (a
    signal, Ctrl-C, the launcher's error) first requeues the batch's trials for the next process."""
    overrides = [session.space.overrides(trial.params) for trial in batch]
    try:
        jobs.validate(overrides)
        returns: list[JobReturn] = []
        for first, size in consecutive([t.number for t in batch]):
            returns += jobs.launch(overrides[len(returns) : len(returns) + size], first)
    except BaseException:
        with claims(session.where):
            trials = session.study.get_trials(deepcopy=False)
            by_number = {t.number: t for t in trials}
            for trial in batch:
                requeue(session, by_number[trial.number], trials)
        raise
    problems = [tell(session.study, trial, ret) for trial, ret in zip(batch, returns)]
    for trial, ret, problem in zip(batch, returns, problems):
        if ret.status == JobStatus.FAILED:
            _ = ret.return_value  # raises the job's own exception, with its traceback
        if problem:
            raise StudyError(f"trial {trial.number}: {problem}")


def consecutive(numbers: list[int]) -> list[tuple[int, int]]:
    """Runs of consecutive trial numbers as (first, length): the launcher numbers a launch's jobs
    first, first + 1, …, and each job's folder must carry its own trial's number."""
    runs: list[tuple[int, int]] = []
    for number in numbers:
        if runs and runs[-1][0] + runs[-1][1] == number:
            runs[-1] = (runs[-1][0], runs[-1][1] + 1)
        else:
            runs.append((number, 1))
    return runs


def tell(study: optuna.Study, trial: Trial, ret: JobReturn) -> str | None:
    """Tell the study one job's value (FAIL for a job that raised or returned NaN); returns what
    stops the sweep: a value that is no number (None: train.py without ``optimized_metric``)."""
    if ret.status != JobStatus.COMPLETED:
        study.tell(trial, state=TrialState.FAIL)
        return None
    try:
        value = float(ret.return_value)
    except (TypeError, ValueError):
        study.tell(trial, state=TrialState.FAIL)
        return f"its job returned {ret.return_value!r}, not a number to optimise (set optimized_metric)"
    if math.isnan(value):
        study.tell(trial, state=TrialState.FAIL)  # a diverged run: failed, the search goes on
    else:
        study.tell(trial, value)
    return None


def finished(session: Session) -> bool:
    """Every slot taken and no trial left running or waiting: the study is over."""
    trials = session.study.get_trials(deepcopy=False)
    return free_slot(trials, session.settings.n_trials) is None and all(t.state.is_finished() for t in trials)


def write_results(session: Session, sweep_dir: Path) -> bool:
    """``<sweep dir>/optimization_results.yaml`` of a finished study: its best trial (the keys of
    hydra-optuna-sweeper's file, best_params and best_value, and where it came from), written whole
    or not at all; only at the end, so that the file says the study is over (baselines/family.py
    skips such a study). False when no trial finished with a value."""
    complete = session.study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    if not complete:
        return False
    best = session.study.best_trial
    results = {
        "name": "optuna",
        "best_params": dict(best.params),
        "best_value": best.value,
        "best_trial": best.number,
        "study_name": session.study.study_name,
        "storage": session.where.shown(),
        "n_complete": len(complete),
    }
    path = sweep_dir / RESULTS
    part = path.with_name(f".{RESULTS}.{os.getpid()}")
    part.write_text(OmegaConf.to_yaml(OmegaConf.create(results)))
    os.replace(part, path)
    return True


def counts(session: Session) -> dict[str, int]:
    """The study's trials by what they are to this process."""
    trials = session.study.get_trials(deepcopy=False)
    return {
        "done": sum(t.state == TrialState.COMPLETE for t in trials),
        "failed": sum(t.state == TrialState.FAIL and not t.user_attrs.get(INTERRUPTED) for t in trials),
        "running": sum(t.state == TrialState.RUNNING for t in trials),
        "retry": sum(t.state == TrialState.WAITING for t in trials),
    }


def start_line(session: Session, requeued: int, sweep_dir: Path) -> str:
    """Where the study lives and where it stands, and how to continue it."""
    n = counts(session)
    kind = {"sqlite": "SQLite", "journal": "journal file"}.get(session.where.kind, "database")
    parts = [f"{n['done']}/{session.settings.n_trials} trials done"]
    if n["failed"]:
        parts.append(f"{n['failed']} failed")
    if n["retry"]:
        parts.append(f"{n['retry']} interrupted to run again" + (f" ({requeued} found just now)" if requeued else ""))
    if n["running"]:
        parts.append(f"{n['running']} running in other workers")
    return (
        f"ferl: study '{session.study.study_name}' in {session.where.shown()} ({kind}): "
        f"{', '.join(parts)}; continue it with the same command and hydra.sweep.dir={sweep_dir}"
    )


def end_line(session: Session, sweep_dir: Path | None) -> str:
    """This worker's last line: the best trial so far, and where the results are (``sweep_dir``:
    written by this process)."""
    n = counts(session)
    head = f"ferl: study '{session.study.study_name}': {n['done']}/{session.settings.n_trials} trials done"
    if n["running"]:
        head += f", {n['running']} still running in other workers"
    if not n["done"]:
        return head
    best = session.study.best_trial
    values = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in best.params.items())
    if sweep_dir is None:
        return f"{head}; best so far {best.value:.4g} (trial {best.number}: {values})"
    return f"{head}; best {best.value:.4g} (trial {best.number}: {values}) in {sweep_dir / RESULTS}"


def main_error(e: Exception) -> None:
    """The one line of a refused study, on the terminal's stderr, and exit code 2."""
    sys.stderr = sys.__stderr__  # train.py's one_line_errors holds Hydra's stderr until main() runs
    print(f"ferl: error: {e}", file=sys.stderr, flush=True)
    raise SystemExit(2)
