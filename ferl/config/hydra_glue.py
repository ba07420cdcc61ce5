"""Hydra glue of train.py: the joblib launcher's job count, one-line composition errors, one line
for any other error of a run (its phase), the device, the metric that main() returns to a
sweeper, and the final summary table.

Imported by train.py; joblib's worker processes import it too (main() refers to it), so the
resolver and the warning filter below are in place wherever a job's config is composed.
"""
import io
import logging
import os
import sys
import traceback
import warnings
from contextlib import contextmanager
from pathlib import Path

import torch
from omegaconf import OmegaConf

from ferl.config.params import ConfigError
from ferl.stats import flat_metrics, mean_sd

# conf/hydra/launcher/{joblib,submitit_local,submitit_slurm,ray}.yaml set our defaults on top of the plugins' configs
# of the same name, which Hydra merges with a deprecation notice meant for configs one owns.
warnings.filterwarnings("ignore", message=r"\s*'hydra/launcher/\w+' is validated against ConfigStore schema")


def jobs_per_machine(cpu_threads) -> int:
    """Parallel jobs that fit this machine: cores // cpu_threads (at least 1), so that
    cpu_threads × n_jobs never exceeds the cores this process may run on."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // max(1, int(cpu_threads)))


# conf/hydra/launcher/joblib.yaml: n_jobs: ${ferl.jobs_per_machine:${cpu_threads}}
OmegaConf.register_new_resolver("ferl.jobs_per_machine", jobs_per_machine, replace=True)


def resolve_device(name: str) -> torch.device:
    """``auto``: CUDA when present, else the CPU."""
    return torch.device("cuda" if name == "auto" and torch.cuda.is_available() else ("cpu" if name == "auto" else name))


@contextmanager
def one_line_errors():
    """Hydra reports a bad override or group choice on several lines before main() runs;
    condense that report into one line (CONTRACT §6) unless HYDRA_FULL_ERROR=1."""
    if os.environ.get("HYDRA_FULL_ERROR") == "1":
        yield
        return
    real, sys.stderr = sys.stderr, io.StringIO()
    try:
        yield
    except SystemExit as e:
        captured, sys.stderr = sys.stderr, real
        if e.code and isinstance(captured, io.StringIO):
            print("ferl: error: " + condense_hydra_error(captured.getvalue()), file=sys.stderr)
        raise
    finally:
        if isinstance(sys.stderr, io.StringIO):
            sys.stderr = real


@contextmanager
def reported_by_phase(run_path: Path, phase):
    """An exception of the run (not a bad input, which ``fail`` reports) ends it with one line
    naming the phase (``phase()``: the trainer's current one) and the run directory, and exit
    code 1; its traceback goes to the run's ``train.log`` (Hydra's job log), and to the terminal
    too with HYDRA_FULL_ERROR=1. The checkpoints are left as they are: the last one written
    before the error is the one ``resume=true`` continues from."""
    try:
        yield
    except Exception as e:  # noqa: BLE001 — every failure of a run is reported this way
        name = phase()
        log = log_traceback(run_path, f"phase {name!r} failed")
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            traceback.print_exc()
        message = (str(e).strip().splitlines() or [""])[0]
        print(f"ferl: error: phase {name!r} of {shown(run_path)}: {type(e).__name__}: {message} "
              f"(traceback in {shown(log)}; HYDRA_FULL_ERROR=1 shows it here)", file=sys.stderr)
        sys.exit(1)


def log_traceback(run_path: Path, message: str) -> Path:
    """The exception being handled, with ``message``, into the run's log files only (Hydra's job
    logging also prints to the terminal): its file handlers, else ``run_path/train.log``."""
    files = [h for h in logging.getLogger().handlers if isinstance(h, logging.FileHandler)]
    if not files:
        path = Path(run_path) / "train.log"
        with open(path, "a") as f:
            f.write(f"{message}\n{traceback.format_exc()}")
        return path
    record = logging.getLogger(__name__).makeRecord(__name__, logging.ERROR, __file__, 0, message, None,
                                                   sys.exc_info())
    for handler in files:
        handler.handle(record)
        handler.flush()
    return Path(files[0].baseFilename)


def shown(path: Path) -> str:
    """``path`` relative to the working directory where it lies below it (as the user typed it)."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def release_stderr() -> None:
    """Hand stderr back once Hydra has composed the config (progress bars and errors go there)."""
    sys.stderr = sys.__stderr__


def condense_hydra_error(report: str) -> str:
    """Hydra's multi-line composition error as one line that starts with the full key when the
    error names one:
    ``env.noise: Value 'abc' of type 'str' could not be converted to Float | Error merging override env.noise=abc``."""
    lines = [ln.strip() for ln in report.split("Config search path:")[0].splitlines()
             if ln.strip() and "HYDRA_FULL_ERROR" not in ln]
    key = next((ln.partition(":")[2].strip() for ln in lines if ln.startswith("full_key:")), "")
    rest = [ln for ln in lines if not ln.startswith(("full_key:", "object_type=", "reference_type="))]
    if key:  # the cause first, then which override or file it came from
        rest = [ln for ln in rest if not ln.startswith(("Error merging", "In '"))] + \
               [ln for ln in rest if ln.startswith(("Error merging", "In '"))]
    return (f"{key}: " if key else "") + " | ".join(rest)


def optimized_value(summary: dict, metric: str | None) -> float | None:
    """What main() returns to a sweeper: the mean over runs of summary.json's ``metric``
    (None without one)."""
    if metric is None:
        return None
    flat = flat_metrics(summary["metrics"])
    if metric not in flat:
        raise ConfigError(f"optimized_metric={metric!r} is not allowed: this run's summary.json "
                          f"metrics are {', '.join(flat)}")
    return mean_sd(flat[metric])[0]


def summary_table(summary: dict) -> str:
    """The run's metrics, mean ± s.d. over runs (``ferl.stats``), one line each; a metric's ``<name>_before``
    twin (the same test before training) goes into a second column."""
    flat = flat_metrics(summary["metrics"])
    before = {}
    for name in list(flat):
        head, _, level = name.partition("/")
        if head.endswith("_before") and (twin := head[: -len("_before")] + (f"/{level}" if level else "")) in flat:
            before[twin] = flat.pop(name)

    def cell(values):
        mean, sd, n = mean_sd(values)
        return "n/a" if n == 0 else f"{mean:.3f}" + (f" ± {sd:.3f}" if n > 1 else "")

    n_runs = len(summary["seeds"])
    rows = [(f"metric ({n_runs} run{'s' if n_runs != 1 else ''})", "mean ± s.d.", "before training" if before else "")]
    rows += [(name, cell(values), cell(before[name]) if name in before else "") for name, values in flat.items()]
    w0, w1 = (max(len(r[i]) for r in rows) for i in (0, 1))
    lines = [f"  {a:<{w0}}  {b:<{w1}}  {c}".rstrip() for a, b, c in rows]
    optimal = ", ".join(f"{k} {v:.4g}" for k, v in summary.get("optimal", {}).items())
    return "\n".join(lines + ([f"  optimal: {optimal}"] if optimal else []))
