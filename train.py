"""Train n_runs independent FERL runs at once (CONTRACT §2).

    python train.py [experiment=NAME] [group=option ...] [key=value ...]
    python train.py -m experiment=ch3_floor seed=0,10 env.noise=0.125,0.5
    python train.py -m hparams_search=matching_optuna      # Optuna: main() returns optimized_metric
"""
import io
import os
import shutil
import sys
from contextlib import contextmanager
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from ferl.data import DataError
from ferl.hydra_support import condense_hydra_error, optimized_value, summary_table  # also: the launcher resolver
from ferl.run_dir import RunDir
from ferl.schema import register_schemas
from ferl.trainers.digit_floor import train_digit_floor
from ferl.trainers.tmaze import train_tmaze
from ferl.validate import ConfigError, validate

register_schemas()  # conf/*/*.yaml extend these structured-config schemas (ferl/schema.py)

TRAINERS = {"digit_floor": train_digit_floor, "tmaze": train_tmaze}
HYDRA_OWN = {".hydra", "train.log"}  # what Hydra writes into a run directory before main()


def resolve_device(name: str) -> torch.device:
    return torch.device("cuda" if name == "auto" and torch.cuda.is_available() else ("cpu" if name == "auto" else name))


def check_run_dir(path: Path, resume: bool) -> None:
    """A new run never writes into a directory that already holds a run (unless resume)."""
    holds_run = any((path / p).exists() for p in ("summary.json", "checkpoints"))
    if resume and not (path / "checkpoints").exists():
        raise ConfigError(f"resume=true but {path} holds no checkpoints/: pass hydra.run.dir=<an earlier run>")
    if holds_run and not resume:
        raise ConfigError(f"hydra.run.dir={path} already holds a run: pass resume=true to continue it, or another directory")


def discard_if_new(path: Path) -> None:
    """Remove a run directory that holds only Hydra's own files and empty folders (a config that failed)."""
    if path.is_dir() and all(p.name in HYDRA_OWN or (p.is_dir() and not any(p.iterdir())) for p in path.iterdir()):
        shutil.rmtree(path, ignore_errors=True)
        if path.parent.is_dir() and not any(path.parent.iterdir()):
            path.parent.rmdir()


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


def release_stderr() -> None:
    """Hand stderr back once Hydra has composed the config (progress bars and errors go there)."""
    sys.stderr = sys.__stderr__


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    """One job; returns the mean over runs of summary.json's ``optimized_metric`` (None when
    that key is null), which Hydra's Optuna sweeper maximises or minimises."""
    release_stderr()
    run_path = Path(HydraConfig.get().runtime.output_dir)
    try:
        validate(cfg)
        check_run_dir(run_path, cfg.resume)
    except ConfigError as e:
        discard_if_new(run_path)
        print(f"ferl: error: {e}", file=sys.stderr)
        sys.exit(2)
    torch.set_num_threads(cfg.cpu_threads)
    run = RunDir(run_path)
    try:
        summary = TRAINERS[cfg.task](cfg, run, resolve_device(cfg.device))
    except (ConfigError, DataError) as e:  # a setting or input file that shows itself once data load
        discard_if_new(run_path)
        print(f"ferl: error: {e}", file=sys.stderr)
        sys.exit(2)
    run.write_summary(summary)
    try:
        value = optimized_value(summary, cfg.optimized_metric)
    except ConfigError as e:
        print(f"ferl: error: {e}", file=sys.stderr)
        sys.exit(2)
    print(f"ferl: {cfg.name} done in {summary['wall_time_s']:.1f} s "
          f"({summary['agent_steps_per_s']:.0f} agent-steps/s)\n"
          f"  summary:     {run_path / 'summary.json'}\n"
          f"  TensorBoard: tensorboard --logdir {run.tb}\n"
          f"  analysis:    python analyze.py {run_path}\n"
          f"{summary_table(summary)}"
          + (f"\n  {cfg.optimized_metric} (optimized_metric, mean over runs): {value:.4f}" if value is not None else ""))
    return value


if __name__ == "__main__":
    with one_line_errors():
        main()
