"""Hydra glue of train.py: the joblib launcher's job count, one-line composition errors, one line
for any other error of a run (its phase), the device, the metric that main() returns to a
sweeper, and the final summary table.

Imported by train.py; joblib's worker processes import it too (main() refers to it), so the
resolvers (below, and ``ferl.run.subdir``'s job folder) and the warning filter are in place
wherever a job's config is composed.
"""

import io
import logging
import os
import signal
import sys
import traceback
import warnings
from contextlib import contextmanager
from pathlib import Path

import torch
from omegaconf import OmegaConf

import ferl.run.subdir  # noqa: F401 — registers the resolver that names a multirun job's folder
from ferl.config.params import ConfigError
from ferl.run.failures import (
    Interrupted,
    disk_error,
    disk_line,
    hydra_os_error,
    interrupted_line,
    quiet_disk_errors_in_threads,
)
from ferl.stats import flat_metrics, mean_sd

# conf/hydra/launcher/{joblib,submitit_local,submitit_slurm,ray}.yaml set our defaults on top of the plugins' configs
# of the same name, which Hydra merges with a deprecation notice meant for configs one owns.
warnings.filterwarnings("ignore", message=r"\s*'hydra/launcher/\w+' is validated against ConfigStore schema")

quiet_disk_errors_in_threads()  # TensorBoard's writer thread on a full disk: the run's line reports it


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
    condense that report into one line (docs/reliability.md, "Bad input") unless HYDRA_FULL_ERROR=1. An OSError
    Hydra met creating the run directory or writing ``.hydra/`` is one line naming the path and
    the reason; Ctrl-C before the run started, one line and exit code 130."""
    if os.environ.get("HYDRA_FULL_ERROR") == "1":
        yield
        return
    real, sys.stderr = sys.stderr, io.StringIO()
    try:
        yield
    except SystemExit as e:
        captured, sys.stderr = sys.stderr, real
        if e.code and isinstance(captured, io.StringIO):
            print("ferl: error: " + hydra_report_line(captured.getvalue(), sys.argv[1:]), file=sys.stderr)
        raise
    except KeyboardInterrupt:
        sys.stderr = real
        print("ferl: interrupted by SIGINT before the run started: nothing to resume", file=sys.stderr)
        sys.exit(128 + signal.SIGINT)
    finally:
        if isinstance(sys.stderr, io.StringIO):
            sys.stderr = real


@contextmanager
def reported_by_phase(run_path: Path, phase):
    """An exception of the run (not a bad input, which ``fail`` reports) ends it with one line
    naming the phase (``phase()``: the trainer's current one) and the run directory, and exit
    code 1; its traceback goes to the run's ``train.log`` (Hydra's job log), and to the terminal
    too with HYDRA_FULL_ERROR=1. The checkpoints are left as they are: the last one written
    before the error is the one ``resume=true`` continues from. A full disk, a read-only file
    system or the file-size limit (``ferl.run.failures``) gets its own line, printed before the
    log is tried (it may be on the same disk); a stop signal, the line of where it stopped."""
    try:
        with stops_outside_the_loop():
            yield
    except Interrupted as stop:  # the checkpoint is written (ferl.trainers.job)
        # on a line of its own: the phase's progress bar is still open
        print(f"\nferl: {interrupted_line(stop.signum, stop.where, run_path, shown)}", file=sys.stderr)
        raise
    except (KeyboardInterrupt, Stopped) as stop:  # a signal outside a phase's step loop (set-up, the summary)
        signum = getattr(stop, "signum", signal.SIGINT)
        print(
            f"ferl: interrupted by {signal.Signals(signum).name} during {phase()} of {shown(run_path)}: "
            f"{kept(run_path)}",
            file=sys.stderr,
        )
        sys.exit(128 + signum)
    except Exception as e:  # noqa: BLE001 — every failure of a run is reported this way
        logging.raiseExceptions = False  # a log handler on a full disk fails silently, not with a traceback
        report_failure(e, run_path, phase())
        sys.exit(1)


class Stopped(BaseException):
    """SIGHUP (a closed terminal, an ssh drop) outside a phase's step loop, where ``StopRequest``
    does not poll: raised by the signal's handler, so that the run ends in one line (not silently,
    by the signal's default action) with what it leaves to resume from. A BaseException, as KeyboardInterrupt: no
    ``except Exception`` on the way takes it for an error of the run."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise_stopped(signum, frame):
    raise Stopped(signum)


@contextmanager
def stops_outside_the_loop():
    """SIGHUP raises ``Stopped`` while the block runs; a phase's ``StopRequest`` takes it over inside
    its step loop (and gives it back). SIGTERM keeps its handler outside the loop: a launcher may own
    it (submitit's lets SLURM's SIGTERM pass while the job checkpoints on SIGUSR2). Only the main
    thread can set handlers: elsewhere (a launcher's thread) the signal keeps its own."""
    previous = {}
    for signum in (signal.SIGHUP,):
        try:
            previous[signum] = signal.signal(signum, _raise_stopped)
        except ValueError:
            break
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def report_failure(e: Exception, run_path: Path, name: str) -> None:
    """The error's line on stderr and its traceback in the run's log, the line first for a disk
    error; the line says where the traceback is only where it could be written."""
    full = os.environ.get("HYDRA_FULL_ERROR") == "1"  # the traceback on the terminal too, the line last
    disk = disk_error(e)
    if disk is not None:
        print(f"ferl: error: phase {name!r}: {disk_line(disk, run_path, shown)}", file=sys.stderr)
        log_traceback(run_path, f"phase {name!r} failed")
        if full:
            traceback.print_exc()
        return
    log = log_traceback(run_path, f"phase {name!r} failed")
    if full:
        traceback.print_exc()
    message = (str(e).strip().splitlines() or [""])[0]
    where = f"traceback in {shown(log)}" if log is not None else "its traceback could not be written to train.log"
    print(
        f"ferl: error: phase {name!r} of {shown(run_path)}: {type(e).__name__}: {message} "
        f"({where}; HYDRA_FULL_ERROR=1 shows it here)",
        file=sys.stderr,
    )


def kept(run_path: Path) -> str:
    """What an interruption outside the step loop leaves to resume from."""
    if (Path(run_path) / "checkpoints" / "last.pt").is_file():
        return f"its last checkpoint is kept; resume=true hydra.run.dir={shown(run_path)} continues"
    return "no checkpoint was written yet: run the command again"


def log_traceback(run_path: Path, message: str) -> Path | None:
    """The exception being handled, with ``message``, into the run's log file only (Hydra's job
    logging also prints to the terminal): its file handler's, else ``run_path/train.log``. None
    where it could not be written (a full disk): that failure is swallowed, never a second traceback."""
    files = [h for h in logging.getLogger().handlers if isinstance(h, logging.FileHandler)]
    path = Path(files[0].baseFilename) if files else Path(run_path) / "train.log"
    record = logging.getLogger(__name__).makeRecord(__name__, logging.ERROR, __file__, 0, message, (), sys.exc_info())
    text = (files[0].format(record) if files else f"{message}\n{traceback.format_exc()}").rstrip("\n") + "\n"
    try:
        for handler in files:
            handler.flush()  # what the run logged before comes first
        with open(path, "a") as f:
            f.write(text)
    except Exception:  # noqa: BLE001 — the error line is out already; the log is a best effort
        return None
    return path


def shown(path: Path) -> str:
    """``path`` relative to the working directory where it lies below it (as the user typed it)."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def release_stderr() -> None:
    """Hand stderr back once Hydra has composed the config (progress bars and errors go there)."""
    sys.stderr = sys.__stderr__


def hydra_report_line(report: str, arguments: list[str]) -> str:
    """The one line of what Hydra printed on stderr before main() ran, given the command line's
    ``arguments`` (tests/test_hydra_versions.py checks it for every Hydra release the pin allows)."""
    return hydra_os_error(report) or null_group_choice(report, arguments) or condense_hydra_error(report)


def null_group_choice(report: str, arguments: list[str]) -> str | None:
    """``experiment=null``: Hydra refuses a null group choice with a traceback; one line naming the
    override and what is allowed instead (None for any other report)."""
    if "Config group override must be a string or a list. Got NoneType" not in report:
        return None
    typed = next((a for a in arguments if a.partition("=")[2] == "null" and "." not in a.partition("=")[0]), "")
    group = typed.partition("=")[0].lstrip("+~") or "a config group"
    instead = "experiment=none runs without an experiment" if group == "experiment" else f"~{group} removes it"
    return f"{typed or group + '=null'} is not allowed: a group's option cannot be null; {instead}"


def condense_hydra_error(report: str) -> str:
    """Hydra's multi-line composition error as one line that starts with the full key when the
    error names one:
    ``env.noise: Value 'abc' of type 'str' could not be converted to Float | Error merging override env.noise=abc``."""
    lines = [
        ln.strip()
        for ln in report.split("Config search path:")[0].splitlines()
        if ln.strip() and "HYDRA_FULL_ERROR" not in ln
    ]
    key = next((ln.partition(":")[2].strip() for ln in lines if ln.startswith("full_key:")), "")
    rest = [ln for ln in lines if not ln.startswith(("full_key:", "object_type=", "reference_type="))]
    if key:  # the cause first, then which override or file it came from
        rest = [ln for ln in rest if not ln.startswith(("Error merging", "In '"))] + [
            ln for ln in rest if ln.startswith(("Error merging", "In '"))
        ]
    return (f"{key}: " if key else "") + " | ".join(rest)


def optimized_value(summary: dict, metric: str | None) -> float | None:
    """What main() returns to a sweeper: the mean over runs of summary.json's ``metric``
    (None without one)."""
    if metric is None:
        return None
    flat = flat_metrics(summary["metrics"])
    if metric not in flat:
        raise ConfigError(
            f"optimized_metric={metric!r} is not allowed: this run's summary.json metrics are {', '.join(flat)}"
        )
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
