"""Several multiruns at once, their jobs sharing the machine's cores (``make reproduce``).

    python -m ferl.run.together [--resume] [--lanes N] SWEEP_DIR "NAME JOBS OVERRIDE ..." ["NAME JOBS OVERRIDE ..." ...]

runs ``train.py -m OVERRIDE ... hydra/launcher=joblib hydra.launcher.n_jobs=JOBS
hydra.sweep.dir=SWEEP_DIR/NAME`` for every NAME, all at once. One sweep after another leaves cores
idle: while a sweep's last job runs alone, and all through a sweep of one job. Started together,
the sweeps' jobs fill each other's gaps (docs/performance.md, "Sweeps at once").

Each sweep's whole output (Hydra's lines, the jobs' progress bars) goes to
``SWEEP_DIR/NAME/sweep.log``; the terminal gets each sweep's ``ferl:`` lines (the jobs done and
the time left, ``ferl.run.progress``; a job's errors), named by the sweep, and one line when a
sweep ends. Exit 0 when every sweep succeeded; else one line per failed sweep naming its log,
and 1. Ctrl-C or a closed terminal (SIGINT, SIGHUP) reaches every job (they share its process
group); the jobs stop as a single run does (docs/reliability.md), and this says in one line how
to continue (``make TARGET RESUME=SWEEP_DIR`` where ``ferl.run.sweepdir`` made the folder, else
this command with ``--resume``) and exits 128 + the signal.

``--lanes N`` puts every sweep's jobs in one queue, in the order given (the longest sweeps first
packs best), N at a time in all (a sweep's JOBS is not used then): no core waits while a sweep
ends with fewer jobs left than its JOBS, where many short sweeps follow each other (``make
beyond``'s curves). Each job runs as ``--resume`` runs it (below), its output in
``SWEEP_DIR/NAME/<job folder>.log``, with one line as each ends.

``--resume`` continues the sweeps of an earlier, interrupted launch into the same SWEEP_DIR
(docs/sweeps.md, "Resuming a sweep"): each sweep's jobs, numbered as Hydra numbers them, are kept
where done, resumed from their checkpoints where interrupted, started where not
(``ferl.run.jobs``), each as ``train.py OVERRIDE ... [resume=true] hydra.run.dir=<its job folder>``,
JOBS at a time, its output in ``SWEEP_DIR/NAME/<job folder>.log``; one line per sweep says how many
jobs are done, to do and resumed, then one per finished job. A job folder that holds another run
stops everything before any job starts (one line, exit 2).
"""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from ferl.run.jobs import (
    DONE,
    RESUMED,
    STOPPING,
    JobError,
    job_dir,
    job_state,
    run_commands,
    states_line,
    sweep_jobs,
)
from ferl.run.progress import duration
from ferl.run.sweepdir import target_of

PREFIX = "ferl: "
LOG = "sweep.log"
TRAIN = (sys.executable, "train.py")  # run from the repository's root, as the make targets are
STOP_GRACE_S = 60.0  # after Ctrl-C, how long the jobs may take to write their checkpoints


class Stopped(KeyboardInterrupt):
    """SIGINT or SIGHUP reached the launcher (``main`` installs the handler): which one."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def stopped(e: KeyboardInterrupt, sweep_dir: Path, sweeps: list[Sweep], lanes: int | None = None) -> int:
    """After a stop: its one line (what is kept, the command that continues the sweep) on stderr;
    the exit status, 128 + the signal (a plain KeyboardInterrupt is SIGINT's)."""
    signum = e.signum if isinstance(e, Stopped) else signal.SIGINT
    print(stopped_line(signum, sweep_dir, sweeps, lanes), file=sys.stderr)
    return 128 + signum


def stopped_line(signum: int, sweep_dir: Path, sweeps: list[Sweep], lanes: int | None = None) -> str:
    """The one line after a stop: what is kept and the command that continues the sweep."""
    target = target_of(sweep_dir)
    if target is not None:
        again = f"make {target} RESUME={sweep_dir}"
    else:
        specs = " ".join(shlex.quote(f"{s.name} {s.jobs} {shlex.join(s.overrides)}") for s in sweeps)
        pool = f" --lanes {lanes}" if lanes else ""
        again = f"python -m ferl.run.together --resume{pool} {shlex.quote(str(sweep_dir))} {specs}"
    name = signal.Signals(signum).name
    return f"{PREFIX}interrupted ({name}): what the jobs wrote is kept; continue with: {again}"


@dataclass(frozen=True)
class Sweep:
    """One multirun: its directory's name under the sweep directory, jobs at a time, overrides."""

    name: str
    jobs: int
    overrides: tuple[str, ...]

    @classmethod
    def parse(cls, text: str) -> Sweep:
        """``"NAME JOBS OVERRIDE ..."``; ValueError naming what is wrong."""
        words = shlex.split(text)
        if len(words) < 3:
            raise ValueError(f"{text!r}: expected 'NAME JOBS OVERRIDE ...'")
        name, jobs, *overrides = words
        if any(not part or part.startswith(".") for part in name.split("/")):
            raise ValueError(f"{text!r}: NAME must be a relative folder (a/b) without . or .. parts, got {name!r}")
        if not jobs.isdigit() or int(jobs) < 1:
            raise ValueError(f"{text!r}: JOBS must be a whole number ≥ 1, got {jobs!r}")
        return cls(name, int(jobs), tuple(overrides))

    def command(self, train: tuple[str, ...], sweep_dir: Path) -> list[str]:
        return [
            *train,
            "-m",
            *self.overrides,
            "hydra/launcher=joblib",
            f"hydra.launcher.n_jobs={self.jobs}",
            f"hydra.sweep.dir={sweep_dir / self.name}",
        ]


def shown(line: bytes) -> str | None:
    """What a terminal would show of one line of output, if it is a ``ferl:`` line: the text after
    its last carriage return (a progress bar redraws itself with ``\\r``, and a line printed while
    a bar is drawn follows the bar's last state), from its ``ferl:`` on (a sweep's two jobs share
    one pipe: one job's line can follow the other's unfinished bar); None for any other line."""
    text = line.decode(errors="replace").rstrip("\r\n").rsplit("\r", 1)[-1]
    start = text.find(PREFIX)
    return None if start < 0 else text[start + len(PREFIX) :]


def _relay(name: str, pipe: IO[bytes], log: IO[bytes], lock: threading.Lock) -> None:
    """Copy a sweep's output to its log as it comes (a progress bar's redraws too, which end in no
    newline), and its ``ferl:`` lines to the terminal with its name."""
    pending = b""  # the unfinished line, from its last carriage return on (all ``shown`` reads)
    while chunk := pipe.read1(1 << 16):  # type: ignore[attr-defined]  # a BufferedReader (Popen.stdout)
        log.write(chunk)
        log.flush()
        *lines, pending = (pending + chunk).split(b"\n")
        pending = pending[pending.rfind(b"\r") + 1 :]
        for line in lines:
            text = shown(line)
            if text is not None:
                with lock:
                    print(f"{PREFIX}{name}: {text}", flush=True)


def run_together(sweep_dir: Path, sweeps: list[Sweep], train: tuple[str, ...] = TRAIN) -> int:
    """Start every sweep, relay their output until all have ended; the exit status (module doc)."""
    lock, start = threading.Lock(), time.monotonic()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}  # a job's lines reach its log as they are printed
    running = []
    for sweep in sweeps:
        out = sweep_dir / sweep.name
        out.mkdir(parents=True, exist_ok=True)
        log = open(out / LOG, "wb")  # noqa: SIM115 — closed when its sweep has ended
        proc = subprocess.Popen(
            sweep.command(train, sweep_dir), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env
        )
        assert proc.stdout is not None
        relay = threading.Thread(target=_relay, args=(sweep.name, proc.stdout, log, lock), daemon=True)
        relay.start()
        running.append((sweep, proc, relay, log))
    if len(sweeps) == 1:
        head = f"sweep {sweeps[0].name} ({sweeps[0].jobs} jobs at a time); its whole output: {sweep_dir}/{sweeps[0].name}/{LOG}"
    else:
        shares = ", ".join(f"{s.name} ({s.jobs} at a time)" for s in sweeps)
        head = f"{len(sweeps)} sweeps at once, sharing the cores: {shares}; each one's whole output: {sweep_dir}/NAME/{LOG}"
    print(PREFIX + head, flush=True)
    codes: dict[str, int] = {}
    try:
        while len(codes) < len(running):
            for sweep, proc, relay, log in running:
                if sweep.name in codes or proc.poll() is None:
                    continue
                relay.join()
                log.close()
                codes[sweep.name] = proc.returncode
                how = "done" if proc.returncode == 0 else f"failed (exit {proc.returncode})"
                with lock:
                    print(f"{PREFIX}{sweep.name}: sweep {how} after {duration(time.monotonic() - start)}", flush=True)
            time.sleep(0.2)
    except KeyboardInterrupt as e:
        _stop([proc for _, proc, _, _ in running])
        return stopped(e, sweep_dir, sweeps)
    failed = [s for s in sweeps if codes[s.name] != 0]
    for s in failed:
        print(f"{PREFIX}error: sweep {s.name} failed; its output: {sweep_dir / s.name / LOG}", file=sys.stderr)
    return 1 if failed else 0


def resume_commands(sweep_dir: Path, sweep: Sweep, train: tuple[str, ...] = TRAIN) -> tuple[dict, list[str]]:
    """The commands of the sweep's jobs not done yet (job folder name → command) and every job's
    state; JobError where a job folder holds another run."""
    todo, states = {}, []
    for number, job in enumerate(sweep_jobs(sweep.overrides)):
        run_dir = job_dir(sweep_dir / sweep.name, number, job)
        states.append(state := job_state(run_dir, job))
        if state != DONE:
            todo[run_dir.name] = [
                *train,
                *job,
                *(["resume=true"] if state == RESUMED else []),
                f"hydra.run.dir={run_dir}",
            ]
    return todo, states


def planned(sweep_dir: Path, sweeps: list[Sweep], resuming: bool, train: tuple[str, ...]) -> list | None:
    """Each sweep with its jobs' commands not done yet and every job's state (``resume_commands``);
    with ``resuming``, one line per sweep says what it keeps. None after a JobError's line."""
    try:
        plans = [(sweep, *resume_commands(sweep_dir, sweep, train)) for sweep in sweeps]
    except JobError as e:
        print(f"{PREFIX}error: {e}", file=sys.stderr)
        return None
    for sweep, _, states in plans if resuming else ():
        print(f"{PREFIX}{sweep.name}: resuming {sweep_dir / sweep.name}: {states_line(states)}", flush=True)
    return plans


def until_done(threads: list[threading.Thread]) -> None:
    """Start the queues' threads and wait for them in this one, which a signal reaches: then no
    queued job starts (``STOPPING``; the running ones got the same signal and stop as a run does)
    and the KeyboardInterrupt goes on to the caller."""
    try:
        for thread in threads:
            thread.start()
        for thread in threads:
            while thread.is_alive():
                thread.join(0.2)
    except KeyboardInterrupt:
        STOPPING.set()
        raise


def resume_together(sweep_dir: Path, sweeps: list[Sweep], train: tuple[str, ...] = TRAIN) -> int:
    """``--resume``: every sweep's remaining jobs, the sweeps at once (module doc); the exit status."""
    plans = planned(sweep_dir, sweeps, True, train)
    if plans is None:
        return 2
    failed: dict[str, list[str]] = {}
    threads = [
        threading.Thread(
            target=lambda s=sweep, t=todo: failed.update(
                {s.name: run_commands(t, sweep_dir / s.name, s.jobs, label=f"{s.name}: ")}
            ),
            daemon=True,
        )
        for sweep, todo, _ in plans
        if todo
    ]
    try:
        until_done(threads)
    except KeyboardInterrupt as e:
        return stopped(e, sweep_dir, sweeps)
    for name, names in failed.items():
        for job in names:
            print(
                f"{PREFIX}error: sweep {name}: job {job} failed; its output: {sweep_dir / name / job}.log",
                file=sys.stderr,
            )
    return 1 if any(failed.values()) else 0


def pooled(sweep_dir: Path, sweeps: list[Sweep], lanes: int, resuming: bool, train: tuple[str, ...] = TRAIN) -> int:
    """``--lanes``: every sweep's jobs not done yet in one queue, ``lanes`` at a time (module doc);
    with ``resuming``, one line per sweep first says what it keeps. The exit status."""
    plans = planned(sweep_dir, sweeps, resuming, train)
    if plans is None:
        return 2
    todo = {f"{sweep.name}/{job}": command for sweep, commands, _ in plans for job, command in commands.items()}
    print(
        f"{PREFIX}{len(sweeps)} sweeps, {len(todo)} jobs to do, {lanes} at a time; each job's output: "
        f"{sweep_dir}/NAME/<job folder>.log",
        flush=True,
    )
    ran: list[list[str]] = []
    try:
        until_done(
            [
                threading.Thread(
                    target=lambda: ran.append(run_commands(todo, sweep_dir, lanes, nested=True)), daemon=True
                )
            ]
        )
    except KeyboardInterrupt as e:
        return stopped(e, sweep_dir, sweeps, lanes)
    failed = ran[0] if ran else list(todo)  # nothing returned: the queue itself failed
    for job in failed:
        print(f"{PREFIX}error: job {job} failed; its output: {sweep_dir / job}.log", file=sys.stderr)
    return 1 if failed else 0


def _stop(procs: list[subprocess.Popen]) -> None:
    """After Ctrl-C: the jobs got the same SIGINT; wait for them to stop, then terminate the rest."""
    deadline = time.monotonic() + STOP_GRACE_S
    for proc in procs:
        try:
            proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            proc.terminate()


def _raise_stopped(signum: int, frame) -> None:
    raise Stopped(signum)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    resume = bool(args) and args[0] == "--resume"
    args = args[1:] if resume else args
    lanes = None
    if args and args[0] == "--lanes":
        if len(args) < 2 or not args[1].isdigit() or int(args[1]) < 1:
            print(
                f"{PREFIX}error: --lanes takes a whole number ≥ 1, got {' '.join(args[1:2]) or 'nothing'}",
                file=sys.stderr,
            )
            return 2
        lanes, args = int(args[1]), args[2:]
    if len(args) < 2:
        usage = "usage: python -m ferl.run.together [--resume] [--lanes N] SWEEP_DIR 'NAME JOBS OVERRIDE ...' ..."
        print(usage, file=sys.stderr)
        return 2
    try:
        sweeps = [Sweep.parse(a) for a in args[1:]]
    except ValueError as e:
        print(f"{PREFIX}error: {e}", file=sys.stderr)
        return 2
    names = [s.name for s in sweeps]
    if len(set(names)) < len(names):
        print(f"{PREFIX}error: two sweeps share a NAME: {' '.join(names)}", file=sys.stderr)
        return 2
    # Ctrl-C or a closed terminal ends the sweeps' jobs (their own handlers) and this, also where a
    # script that started it in the background left SIGINT ignored (the jobs install theirs either way)
    for signum in (signal.SIGINT, signal.SIGHUP):
        signal.signal(signum, _raise_stopped)
    if lanes is not None:
        return pooled(Path(args[0]), sweeps, lanes, resume)
    return (resume_together if resume else run_together)(Path(args[0]), sweeps)


if __name__ == "__main__":
    sys.exit(main())
