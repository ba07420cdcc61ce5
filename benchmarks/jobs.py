"""A trainer set up from the real configs, with a run directory that writes no checkpoints: what the
benchmarks time, phase by phase, without the disk; and a whole ``train.py`` job in a subprocess,
read back from its ``summary.json``."""

import json
import subprocess
import tempfile
from contextlib import contextmanager
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from torch.utils.tensorboard import SummaryWriter

from ferl.run.directory import RunDir, StopRequest

ROOT = Path(__file__).resolve().parents[1]


@contextmanager
def bench_job(overrides: list, device: str):
    """(trainer, job) of ``config`` with ``overrides``, set up on ``device``, its run in a
    temporary directory whose checkpoints are not written (time the arithmetic, not the disk)."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    cfg.name = "bench"
    trainer = instantiate(cfg.trainer)
    trainer.setup(cfg, torch.device(device))
    job = trainer.job
    with tempfile.TemporaryDirectory() as tmp, SummaryWriter(str(Path(tmp) / "tb")) as writer, StopRequest() as stop:
        job.run, job.writer, job.stop = RunDir(tmp), writer, stop
        job.run.save_checkpoint = lambda state, writer=None: None
        yield trainer, job


def phase(trainer, name: str):
    """The trainer's phase of that name."""
    return next(p for p in trainer.phases if p.name == name)


# The recurrent Q-learner (GRU core, linear head) on the passive T-maze: the agent whose compile
# time the benchmarks follow against T_max (bench_compile.py, bench_chunks.py)
PASSIVE_Q = [
    "experiment=passive_tmaze",
    "trainer=algorithm1",
    "actor=recurrent_q",
    "predictor=none",
    "actor.head=linear",
    "actor.memory=gru",
]


def train_summary(
    command: list[str], out: Path, what: str, env: dict | None = None, stderr: list | None = None
) -> dict:
    """Run one ``train.py`` job (``command``, its run directory ``out``) and return its summary;
    a failed job ends the benchmark in one line naming ``what`` and its last error line. The
    job's standard error is appended to ``stderr`` if given."""
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        tail = done.stderr.strip().splitlines()[-1:] or ["no output"]
        raise SystemExit(f"{what} failed: {tail[0]}")
    if stderr is not None:
        stderr.append(done.stderr)
    return json.loads((out / "summary.json").read_text())
