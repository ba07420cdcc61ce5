"""Train n_runs independent runs at once (docs/usage.md, "Training"): compose, check, set up, train, report.

    python train.py [experiment=NAME] [group=option ...] [key=value ...]
    python train.py -m experiment=ch3_floor seed=0,10 env.noise=0.125,0.5
    python train.py -m hparams_search=matching_optuna      # Optuna: main() returns optimized_metric

The trainer is the config's ``trainer`` node (``_target_``); it builds the components of the other
groups and trains them (ferl/trainers/, docs/architecture.md).
"""

import sys

try:  # Ctrl-C while torch loads: one line, not importlib's traceback (docs/reliability.md)
    from pathlib import Path

    import hydra
    import torch
    from hydra.core.hydra_config import HydraConfig
    from hydra.utils import instantiate
    from omegaconf import DictConfig

    # importing hydra_glue also registers the launcher resolver
    from ferl.config.hydra_glue import (
        one_line_errors,
        optimized_value,
        release_stderr,
        reported_by_phase,
        resolve_device,
        summary_table,
    )
    from ferl.config.params import ConfigError
    from ferl.config.validate import validate
    from ferl.data import DataError
    from ferl.run.claim import owned_run_dir
    from ferl.run.directory import RunDir, discard_if_new
    from ferl.run.footprint import check_memory
    from ferl.run.resume import identity_of, resumed_run
except KeyboardInterrupt:
    print("ferl: interrupted by SIGINT while starting: nothing was written", file=sys.stderr)
    sys.exit(130)


def fail(message: str, run_path: Path) -> None:
    """One line, exit code 2, and no run directory left behind (docs/reliability.md)."""
    discard_if_new(run_path)
    print(f"ferl: error: {message}", file=sys.stderr)
    sys.exit(2)


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    """One job; returns the mean over runs of summary.json's ``optimized_metric`` (None when
    that key is null), which Hydra's Optuna sweeper maximises or minimises."""
    release_stderr()
    hydra_cfg = HydraConfig.get()
    run_path = Path(hydra_cfg.runtime.output_dir)
    trainer = resumed = None
    # any other exception: one line naming the phase, the traceback in the run's train.log
    with (
        reported_by_phase(run_path, lambda: getattr(trainer, "phase", None) or "setup"),
        owned_run_dir(run_path) as claim,
    ):  # one process per run directory, for the whole run
        try:
            validate(cfg)
            claim(cfg)  # check, lock, check again, then .hydra/ (ferl/run/claim.py): before anything is written
            if cfg.resume:  # the run's own config (its checkpoint's) with the overrides given now
                resumed = resumed_run(run_path, list(hydra_cfg.overrides.task), lambda d: resolve_device(d).type)
                if resumed is not None:
                    cfg = resumed.config
                    validate(cfg)
            check_memory(cfg)  # before any of the run's tensors exists: refused when it would not fit
            torch.set_num_threads(cfg.cpu_threads)
            device = resolve_device(cfg.device)
            trainer = instantiate(cfg.trainer)
            trainer.setup(cfg, device)
        except (ConfigError, DataError) as e:  # DataError: an input file that shows itself once data load
            fail(str(e), run_path)
        run = RunDir(
            run_path, resumed.identity if resumed else identity_of(cfg, device), resumed.checkpoint if resumed else None
        )
        summary = trainer.fit(run, cfg.resume)
        run.write_summary(summary)
    value = optimized_value(summary, cfg.optimized_metric)
    print(
        f"ferl: {cfg.name} done in {summary['wall_time_s']:.1f} s "
        f"({summary['agent_steps_per_s']:.0f} agent-steps/s)\n"
        f"  summary:     {run_path / 'summary.json'}\n"
        f"  TensorBoard: tensorboard --logdir {run.tb}\n"
        f"  analysis:    python analyze.py {run_path}\n"
        f"{summary_table(summary)}"
        + (f"\n  {cfg.optimized_metric} (optimized_metric, mean over runs): {value:.4f}" if value is not None else "")
    )
    return value


if __name__ == "__main__":
    with one_line_errors():
        main()
