"""Same config, seed and n_runs → bit-identical summary.json metrics on CPU, for every experiment
of CONTRACT §3 at reduced scale (issue 7/7). In-process, two fresh run directories each."""

import pytest
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import open_dict

from ferl.run_dir import RunDir
from ferl.trainers.digit_floor import train_digit_floor
from ferl.trainers.tmaze import train_tmaze
from test_configs import EXPERIMENTS

TRAINERS = {"digit_floor": train_digit_floor, "tmaze": train_tmaze}
TINY = {"digit_floor": ["n_runs=2", "trainer.steps=300", "trainer.test_per_class=5",
                        "trainer.log_every=100", "trainer.checkpoint_every=100",
                        "trainer.test_noise_levels=[0.0,0.5]"],
        "tmaze": ["n_runs=2", "trainer.n_sample=300", "trainer.n_epoch=2", "trainer.n_episodes=40",
                  "trainer.log_every=20", "trainer.td_sample_every=20", "trainer.final_window=20"]}


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_same_seed_gives_identical_metrics(compose_cfg, tmp_path, experiment):
    task = compose_cfg([f"experiment={experiment}"]).task
    overrides = [f"experiment={experiment}", "seed=3", *TINY[task]]
    if experiment == "table5_1_pixel":
        overrides += ["preprocessor.sweeps=2", "env.reservoir_size=5"]
    torch.set_num_threads(1)
    runs = []
    for name in ("first", "second"):  # a cache of its own each: both runs fit their RBM
        cfg = compose_cfg([*overrides, f"preprocessor.cache_dir={tmp_path / name / 'cache'}"]
                          if experiment == "table5_1_pixel" else overrides)
        HydraConfig.instance().set_config(cfg)
        with open_dict(cfg):  # what @hydra.main hands to train.py: the job's config only
            del cfg["hydra"]
        runs.append(TRAINERS[task](cfg, RunDir(tmp_path / name), torch.device("cpu")))
    first, second = runs
    assert first["metrics"] == second["metrics"]
    assert first["seeds"] == [3, 4]
