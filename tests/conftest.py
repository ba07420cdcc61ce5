import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))


def eager(overrides) -> list:
    """Tests run the eager reference path unless they choose: compiling every tiny configuration
    of the suite would take most of its time. tests/test_fast_path.py holds the compiled path to it."""
    overrides = list(overrides)
    return overrides if any(o.startswith("compile=") for o in overrides) else [*overrides, "compile=false"]


def compose_config(overrides=()):
    """Compose the real configs as train.py does (hydra's runtime keys included), eager by default."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=eager(overrides), return_hydra_config=True)


def validated_config(overrides=()):
    """A composed config that has passed train.py's checks before any work (``ferl.config.validate``)."""
    from hydra.core.hydra_config import HydraConfig

    from ferl.config.validate import validate

    cfg = compose_config(overrides)
    HydraConfig.instance().set_config(cfg)
    validate(cfg)
    return cfg


@pytest.fixture
def compose_cfg():
    return compose_config


def train_job(cfg, run_dir, resume: bool = False) -> dict:
    """What train.py does with a composed config, in process on the CPU: the trainer of
    ``cfg.trainer`` set up and fitted into ``run_dir``; returns the summary."""
    import torch
    from hydra.core.hydra_config import HydraConfig
    from hydra.utils import instantiate
    from omegaconf import open_dict

    from ferl.run.directory import RunDir

    if "hydra" in cfg:
        HydraConfig.instance().set_config(cfg)
        with open_dict(cfg):  # what @hydra.main hands to train.py: the job's config only
            del cfg["hydra"]
    torch.set_num_threads(1)
    trainer = instantiate(cfg.trainer)
    trainer.setup(cfg, torch.device("cpu"))
    return trainer.fit(RunDir(run_dir), resume)


def train_sweep(root: Path, jobs: dict) -> dict:
    """A sweep directory as train.py -m leaves it: job name → overrides, each trained in process
    into ``root/name`` with its summary.json written, then the sweep analysed; returns the summaries."""
    import reproduction  # noqa: F401 — registers the dissertation's analyses, as analyze.py does
    from ferl.analysis import runner
    from ferl.run.directory import RunDir

    summaries = {}
    for name, overrides in jobs.items():
        run = RunDir(root / name)
        summaries[name] = train_job(compose_config(overrides), run.path)
        run.write_summary(summaries[name])
    runner.analyze_sweep(root)
    return summaries


def run_train(*overrides, cwd=ROOT, timeout=600, env=None, **popen):
    """Run train.py in a subprocess (in ``env``, by default this one's); returns the CompletedProcess."""
    env = {**(env or os.environ), "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *eager(overrides)],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        **popen,
    )


# Algorithm 1 (or 2) at a size a test affords: a few random episodes, two predictor epochs, 40 actor episodes
SHORT_ALGORITHM1 = [
    "trainer.n_sample=300",
    "trainer.n_epoch=2",
    "trainer.n_episodes=40",
    "trainer.log_every=20",
    "trainer.td_sample_every=20",
    "trainer.final_window=20",
]
# Algorithm 1 at a tiny scale, logged and windowed every 25 actor episodes
TINY_ALGORITHM1 = [
    "trainer.n_sample=200",
    "trainer.n_epoch=2",
    "trainer.n_episodes=50",
    "trainer.log_every=25",
    "trainer.td_sample_every=25",
    "trainer.final_window=25",
]
# the regular maze, checkpointed after actor episodes 100 and 200 and after every phase
RESUMABLE_TMAZE = [
    "experiment=table4_1_regular",
    "n_runs=2",
    "trainer.n_sample=200",
    "trainer.n_epoch=20",
    "trainer.phases.predictors.checkpoint_every_epochs=5",
    "trainer.n_episodes=300",
    "trainer.checkpoint_every=100",
    "trainer.log_every=100",
]

TINY = [
    "n_runs=2",
    "trainer.steps=300",
    "trainer.log_every=100",
    "trainer.checkpoint_every=100",
    "trainer.test_per_class=8",
    "trainer.test_noise_levels=[0.0,0.125,0.5]",
]


def tb_scalars(run_dir: Path) -> dict:
    """Every scalar a run logged to tb/ (its event files in order): tag → [(step, value)]."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(Path(run_dir) / "tb"), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def assert_same_tb_log(resumed: Path, whole: Path) -> None:
    """A resumed run's scalars are the uninterrupted run's: every point once, at the same step
    with the same value (the hparam/ metrics include the timing, so only their steps)."""
    import numpy as np

    got, want = tb_scalars(resumed), tb_scalars(whole)
    assert got.keys() == want.keys()
    for tag in want:
        assert [s for s, _ in got[tag]] == [s for s, _ in want[tag]], tag
        if not tag.startswith("hparam/"):  # NaN == NaN here: a diverged run's statistics are NaN
            np.testing.assert_array_equal([v for _, v in got[tag]], [v for _, v in want[tag]], err_msg=tag)
