"""A sweep's jobs one by one (docs/sweeps.md, "Resuming a sweep"): the jobs of a multirun, which of
them a resumed sweep keeps, continues or starts, and commands run a few at a time.

A job's state, from its run directory: **done** when it holds a ``summary.json`` that reads as one
(a dict with ``metrics``) and whose ``.hydra/overrides.yaml`` holds the job's overrides (``resume=…``
aside): it is kept; **resumed** when it holds ``checkpoints/`` and no summary: ``resume=true``
continues it; **to do** otherwise (no folder, or one whose run stopped before its first checkpoint).
A summary that does not read, or that of other overrides, is another run's: ``JobError``, and
nothing is run into it.
"""

from __future__ import annotations

import functools
import json
import subprocess
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import ExitStack
from pathlib import Path

from hydra._internal.config_loader_impl import get_overrides_dirname
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf

from ferl.run.progress import duration
from ferl.run.subdir import job_folder

ROOT = Path(__file__).resolve().parents[2]
DONE, RESUMED, TODO = "done", "resumed", "to do"


class JobError(ValueError):
    """A job's directory holds what a resumed sweep must not run into (the message is one line)."""


def sweep_jobs(overrides: list[str] | tuple[str, ...]) -> list[list[str]]:
    """The jobs of ``train.py -m OVERRIDES`` in Hydra's basic sweeper's order (job ``i`` is
    ``hydra.job.num`` = i), each as its task overrides (Hydra's own, ``hydra…``, left out)."""
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    (jobs,) = BasicSweeper.split_arguments(parsed, None)
    return [[o for o in job if not o.startswith(("hydra.", "hydra/"))] for job in jobs]


@functools.cache
def _config_yaml() -> DictConfig:
    """conf/config.yaml, read once per process (every job's folder name reads it)."""
    config = OmegaConf.load(ROOT / "conf" / "config.yaml")
    assert isinstance(config, DictConfig)
    return config


def default_choice(group: str) -> str:
    """conf/config.yaml's default option of a config group (``experiment``, ``env``)."""
    defaults = _config_yaml().defaults
    return next(str(d[group]) for d in defaults if isinstance(d, DictConfig) and group in d)


def default_experiment() -> str:
    """conf/config.yaml's ``experiment`` default."""
    return default_choice("experiment")


def _choice(job: list[str], group: str) -> str:
    return next((o.split("=", 1)[1] for o in job if o.startswith(f"{group}=")), None) or default_choice(group)


def override_dirname(job: list[str]) -> str:
    """``hydra.job.override_dirname`` of a job with these overrides, as Hydra writes it with
    conf/config.yaml's separators and excluded keys (Hydra's own function on the same parse)."""
    settings = _config_yaml().hydra.job.config.override_dirname
    parsed = OverridesParser.create().parse_overrides(list(job))
    return get_overrides_dirname(parsed, list(settings.exclude_keys), settings.item_sep, settings.kv_sep)


def job_dir(sweep_dir: Path, number: int, job: list[str]) -> Path:
    """The job's run directory, as conf/config.yaml's ``hydra.sweep.subdir`` names it:
    ``<job number>_<experiment>+<overrides>`` (``ferl.run.subdir``; ``experiment=none``: the env's
    name). A sweep launched before the overrides were in the name has ``<job number>_<experiment>``:
    where only that folder exists, it is the job's, so that such a sweep still resumes."""
    experiment = _choice(job, "experiment")
    name = _choice(job, "env") if experiment == "none" else experiment  # conf/experiment/none.yaml
    named = sweep_dir / job_folder(number, name, override_dirname(job))
    earlier = sweep_dir / job_folder(number, name)
    return earlier if not named.exists() and earlier.is_dir() else named


def _without_resume(overrides) -> list[str]:
    return sorted(str(o) for o in overrides if not str(o).startswith("resume="))


def job_state(run_dir: Path, overrides: list[str] | None = None) -> str:
    """``DONE``, ``RESUMED`` or ``TODO`` (module doc); ``overrides`` None: the summary alone is
    checked (a run whose ``.hydra/`` holds other settings than its command line, RecurrentPPO's)."""
    summary = run_dir / "summary.json"
    if not summary.exists():
        return RESUMED if (run_dir / "checkpoints").is_dir() else TODO
    try:
        ok = isinstance(data := json.loads(summary.read_text()), dict) and "metrics" in data
    except (OSError, ValueError):
        ok = False
    if not ok:
        raise JobError(f"{summary} does not read as a run's summary: not resumed; move that run away first")
    if overrides is not None:
        saved_file = run_dir / ".hydra" / "overrides.yaml"
        saved = OmegaConf.to_container(OmegaConf.load(saved_file)) if saved_file.is_file() else None
        saved = saved if isinstance(saved, list) else None
        if saved is None or _without_resume(saved) != _without_resume(overrides):
            raise JobError(
                f"{run_dir} holds a finished run of other overrides ({' '.join(saved or ['none recorded'])}), "
                f"not this sweep's job ({' '.join(overrides)}): is this the sweep of the same command?"
            )
    return DONE


def states_line(states: list[str]) -> str:
    """``3 jobs done (kept), 2 to do, 1 of them resumed from its checkpoint``."""
    done, todo = states.count(DONE), len(states) - states.count(DONE)
    return f"{done} jobs done (kept), {todo} to do, {states.count(RESUMED)} of them resumed from their checkpoints"


# Set by a launcher that a signal stopped (``ferl.run.together``): no queued job starts after it
STOPPING = threading.Event()


def _started(cmd: list[str], **kwargs) -> subprocess.CompletedProcess | None:
    """``subprocess.run(cmd)``, or None where the launcher was stopped before the job's turn came."""
    return None if STOPPING.is_set() else subprocess.run(cmd, **kwargs)


def run_commands(
    todo: dict[str, list[str]],
    logs: Path,
    jobs: int,
    what: str = "jobs",
    label: str = "",
    cwd: Path = ROOT,
    nested: bool = False,
) -> list[str]:
    """Run every named command, ``jobs`` at a time, in the order given, each one's output in
    ``logs/<name>.log`` (``/`` as ``_``; ``nested``: a name's folders as folders under ``logs``);
    one progress line as each ends (``label`` before it). Returns the names of those that failed.
    Once ``STOPPING`` is set, the jobs not yet started are skipped."""
    logs.mkdir(parents=True, exist_ok=True)
    paths = {n: logs / f"{n if nested else n.replace('/', '_')}.log" for n in todo}
    for path in paths.values():
        path.parent.mkdir(parents=True, exist_ok=True)
    started, failed = time.monotonic(), []
    with ExitStack() as logs_open, ThreadPoolExecutor(jobs) as pool:  # the jobs end before their logs close
        files = {n: logs_open.enter_context(open(path, "w")) for n, path in paths.items()}
        futures = {
            pool.submit(_started, cmd, cwd=cwd, stdout=files[n], stderr=subprocess.STDOUT): n for n, cmd in todo.items()
        }
        for count, future in enumerate(as_completed(futures), 1):
            name, elapsed, done = futures[future], time.monotonic() - started, future.result()
            if done is None:  # stopped before it started: the launcher's line says how to go on
                continue
            if done.returncode != 0:
                failed.append(name)
            left = elapsed / count * (len(todo) - count)  # the jobs so far, `jobs` at a time
            n_failed = f", {len(failed)} failed" if failed else ""
            eta = f"about {duration(left)} left" if count < len(todo) else f"sweep took {duration(elapsed)}"
            print(
                f"ferl: {label}{count}/{len(todo)} {what} done{n_failed} ({name}{' failed' if name in failed else ''}, "
                f"{duration(elapsed)} in all); {eta}",
                flush=True,
            )
    if failed:
        print(f"ferl: {label}failed: {', '.join(failed)} (logs: {logs}/<name>.log)", flush=True)
    return failed
