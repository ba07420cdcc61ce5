"""Progress of a multirun (``train.py -m``): one line per finished job, with the jobs done of the
sweep's total and an estimate of the time left, e.g.

    ferl: 3/9 jobs done (2_table4_1_matching, 41 s); about 2 min left

A Hydra callback (conf/config.yaml ``hydra.callbacks.progress``), so every multirun has it, whatever
its launcher: ``on_multirun_start`` (the launching process) counts the jobs and starts
``<sweep dir>/progress.jsonl``; ``on_job_start`` and ``on_job_end`` (the process that runs the job:
a joblib worker, a SLURM task) append to it under a file lock; ``on_job_end`` prints the line.
A single run prints nothing extra. A job whose main() raises counts as done and says so ("failed").
"""

import fcntl
import heapq
import json
import math
import sys
import time
from pathlib import Path
from typing import cast

from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobStatus
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

import ferl.run.subdir  # noqa: F401 — the resolver of hydra.sweep.subdir, which job_name reads
from ferl.run.jsonio import strict_dumps

FILE = "progress.jsonl"  # one JSON object a line: the sweep's start, then each job's start and end
BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


def sweep_size(arguments: list[str], config_loader=None) -> int | None:
    """Jobs of Hydra's basic sweeper for these overrides: the cartesian product of every key's
    values, a key given twice counting once (its last value), as BasicSweeper.split_arguments
    enumerates them; None for a sweep it cannot count (``interval``). ``glob`` choices need the
    config loader."""
    sizes = {}
    for override in OverridesParser.create(config_loader=config_loader).parse_overrides(arguments):
        if override.is_sweep_override() and not override.is_discrete_sweep():
            return None
        sizes[override.get_key_element()] = (
            len(list(override.sweep_string_iterator())) if override.is_sweep_override() else 1
        )
    return math.prod(sizes.values())


def planned_jobs(config: DictConfig) -> int | None:
    """The sweep's number of jobs where its sweeper says it ahead: the basic sweeper's product of
    the command line's and ``hydra.sweeper.params``' values, a sweeper's ``n_trials`` (Optuna);
    else None."""
    sweeper = config.hydra.sweeper
    if OmegaConf.select(sweeper, "_target_") == BASIC_SWEEPER:
        params = OmegaConf.select(sweeper, "params") or {}
        arguments = [f"{k}={v}" for k, v in params.items()]
        arguments += cast(list, OmegaConf.to_container(config.hydra.overrides.task, resolve=False))
        loader = GlobalHydra.instance().config_loader() if GlobalHydra.instance().is_initialized() else None
        try:
            return sweep_size(arguments, loader)
        except Exception:  # noqa: BLE001 - Hydra reports a bad sweep itself; then no total
            return None
    trials = OmegaConf.select(sweeper, "n_trials")
    return trials if isinstance(trials, int) and trials > 0 else None


def time_left(durations: list[float], running: list[float], queued: int, lanes: int) -> float:
    """Seconds until the last job ends if every job takes the mean of ``durations`` (the finished
    jobs') and ``lanes`` jobs run at once: each running job (``running``: seconds it has run) ends
    when it reaches the mean (now if past it), each queued job starts on the first free lane."""
    mean = sum(durations) / len(durations)
    free = [max(mean - r, 0.0) for r in running] + [0.0] * max(lanes - len(running), 0)
    heapq.heapify(free)
    for _ in range(queued):
        heapq.heappush(free, heapq.heappop(free) + mean)
    return max(free, default=0.0)


def duration(seconds: float) -> str:
    return (
        f"{seconds:.0f} s"
        if seconds < 60
        else f"{seconds / 60:.0f} min"
        if seconds < 5400
        else f"{seconds / 3600:.1f} h"
    )


def progress_line(events: list[dict], now: float) -> str:
    """The line for the last event of ``events`` (a job's end), from the sweep's records so far."""
    total = next((e["jobs"] for e in events if e["event"] == "sweep"), None)
    began = next((e["time"] for e in events if e["event"] == "sweep"), None)
    running, lanes, ends = {}, 1, []
    for e in events:  # the most jobs that ran at once: the sweep's parallel lanes
        if e["event"] == "start":
            running[e["job"]] = e["time"]
            lanes = max(lanes, len(running))
        elif e["event"] == "end":
            running.pop(e["job"], None)
            ends.append(e)
    last, n_failed = ends[-1], sum(e["failed"] for e in ends)
    done = f"{len(ends)}/{total}" if total else f"{len(ends)}"
    failed = f", {n_failed} failed" if n_failed else ""
    job = (
        f"{last['job']} failed after {duration(last['seconds'])}"
        if last["failed"]
        else f"{last['job']}, {duration(last['seconds'])}"
    )
    line = f"ferl: {done} jobs done{failed} ({job})"
    if total is None:
        return line
    if len(ends) >= total:
        return line + (f"; sweep took {duration(now - began)}" if began is not None else "")
    durations = [e["seconds"] for e in ends if not e["failed"]] or [e["seconds"] for e in ends]
    queued = max(total - len(ends) - len(running), 0)
    left = time_left(durations, [now - t for t in running.values()], queued, lanes)
    return line + (f"; about {duration(left)} left" if left >= 60 else "; under a minute left")


def record(path: Path, event) -> list[dict]:
    """Append ``event(events so far)`` to the progress file under an exclusive lock; returns every
    event in it, the new one last."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            f.seek(0)
            events = [json.loads(line) for line in f if line.strip()]
            events.append(event(events))
            f.write(strict_dumps(events[-1]) + "\n")  # "a+": at the end, whatever the position
            f.flush()
            return events
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def sweep_file(config: DictConfig) -> Path:
    """``<sweep dir>/progress.jsonl``, a relative sweep dir taken from where train.py was started."""
    return Path(config.hydra.runtime.cwd) / str(config.hydra.sweep.dir) / FILE


def job_name(config: DictConfig) -> str:
    """The job's folder inside the sweep folder (``hydra.sweep.subdir``, e.g. ``2_table4_1_matching+actor.n_hidden-40``)."""
    return str(OmegaConf.select(config, "hydra.sweep.subdir", default=None) or config.hydra.job.num)


class SweepProgress(Callback):
    """conf/config.yaml's ``hydra.callbacks.progress``; stateless (joblib pickles it to every worker)."""

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        path = sweep_file(config)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(strict_dumps({"event": "sweep", "time": time.time(), "jobs": planned_jobs(config)}) + "\n")

    def on_job_start(self, config: DictConfig, **kwargs) -> None:
        if config.hydra.mode == RunMode.MULTIRUN:
            record(sweep_file(config), lambda _: {"event": "start", "job": job_name(config), "time": time.time()})

    def on_job_end(self, config: DictConfig, job_return, **kwargs) -> None:
        if config.hydra.mode != RunMode.MULTIRUN:
            return
        name, now = job_name(config), time.time()

        def end(events):
            began = max((e["time"] for e in events if e["event"] == "start" and e["job"] == name), default=now)
            return {
                "event": "end",
                "job": name,
                "time": now,
                "seconds": round(now - began, 3),
                "failed": job_return.status == JobStatus.FAILED,
            }

        line = progress_line(record(sweep_file(config), end), now)
        # on a terminal, first clear a progress bar that another job has left half-drawn on the line
        print(("\r\x1b[K" if sys.stdout.isatty() else "") + line, flush=True)
