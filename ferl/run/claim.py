"""What train.py does before a run touches its directory: check, lock, check again, write ``.hydra/``.

Why train.py writes ``.hydra/`` itself (``hydra.output_subdir: null`` in conf/config.yaml): Hydra
1.3's ``run_job`` writes ``.hydra/{config,hydra,overrides}.yaml`` before it calls main() and before
any ``on_job_start`` callback, so a launch that is then refused (a run already there, another
process at work in the directory) would already have rewritten the run's record of its own config.
A callback at ``on_run_start`` / ``on_multirun_start`` runs early enough for a single run, but for
a sweep it runs in the launching process, not in the joblib / submitit / ray worker that owns each
job's directory. Here, in main(), every launcher's job passes the same gate: nothing is written
before the checks and the lock have passed. The files are Hydra's own YAML (``_save_config``), with
``hydra.output_subdir`` as Hydra's default (``.hydra``) would have written it, made as one folder
renamed into place. A resume keeps the run's own ``.hydra/`` (put back from ``checkpoints/hydra/``
where a launch before this design rewrote it).

Order: a cheap check that writes nothing (a finished run, a resume without checkpoints), the lock
(``ferl.run.lock``), the same check again (the process that held the lock may have finished the
run meanwhile), then the leftovers of killed writes are removed and ``.hydra/`` is written.
"""

import copy
from contextlib import contextmanager
from pathlib import Path
from typing import cast

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from ferl.config.params import ConfigError
from ferl.messages import warn
from ferl.run.directory import atomic_dir, check_run_dir, remove_leftovers, restore_hydra_files
from ferl.run.lock import LOCK_FILE, RunLock, holder

HYDRA_DIR = ".hydra"  # Hydra's default hydra.output_subdir


@contextmanager
def owned_run_dir(run_path: Path):
    """Yield ``claim(cfg)``, which makes this process the owner of ``run_path`` (ConfigError, in
    one line, when it cannot be); the lock is let go when the block ends, however it ends."""
    lock = RunLock(run_path)
    try:
        yield lambda cfg: claim(Path(run_path), cfg, lock)
    finally:
        lock.release()


def claim(run_path: Path, cfg: DictConfig, lock: RunLock) -> None:
    """Check, lock, check again; then the run directory is this process's to write."""
    refuse_if_unfit(run_path, cfg.resume)
    if not lock.acquire():
        raise ConfigError(busy(run_path, holder(run_path)))
    if lock.left_by is not None:
        warn(f"{run_path}: took over the lock that {lock.left_by} left ({LOCK_FILE}; that process is gone)")
    refuse_if_unfit(run_path, cfg.resume)
    remove_leftovers(run_path)
    if cfg.resume:
        restore_hydra_files(run_path)
    if not (cfg.resume and (run_path / HYDRA_DIR).is_dir()):
        write_hydra_files(run_path, cfg)


def refuse_if_unfit(run_path: Path, resume: bool) -> None:
    """ConfigError when the directory cannot take this launch (``check_run_dir``); when a live
    process holds it, the line names that process instead. Writes nothing."""
    if (problem := check_run_dir(run_path, resume)) is not None:
        raise ConfigError(busy(run_path, who) if (who := holder(run_path)) else problem)


def busy(run_path: Path, who: str | None) -> str:
    return (
        f"hydra.run.dir={run_path} is in use by {who or 'another process (it has just let go)'} "
        f"(lock {run_path / LOCK_FILE}): one process per run directory; wait for it to end, "
        f"or pass another directory"
    )


def write_hydra_files(run_path: Path, cfg: DictConfig) -> None:
    """``.hydra/`` as Hydra's ``run_job`` writes it, unless Hydra wrote it itself (a launch that
    set ``hydra.output_subdir``)."""
    if HydraConfig.get().output_subdir is not None:
        return
    with atomic_dir(run_path / HYDRA_DIR) as tmp:
        for name, text in hydra_files(cfg).items():
            (tmp / name).write_text(text, encoding="utf-8")


def hydra_files(cfg: DictConfig) -> dict[str, str]:
    """The three files of ``.hydra/`` (hydra/core/utils.py: ``run_job``, ``_save_config``): the
    job's config, Hydra's (with its default ``output_subdir``, ``.hydra``), the task overrides."""
    hydra_cfg = cast(DictConfig, copy.deepcopy(HydraConfig.instance().cfg))  # set: a Hydra job runs
    with read_write(hydra_cfg.hydra), open_dict(hydra_cfg.hydra):
        hydra_cfg.hydra.output_subdir = HYDRA_DIR
    return {
        "config.yaml": OmegaConf.to_yaml(cfg),
        "hydra.yaml": OmegaConf.to_yaml(hydra_cfg),
        "overrides.yaml": OmegaConf.to_yaml(HydraConfig.get().overrides.task),
    }
