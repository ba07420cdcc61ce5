import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from ferl.schema import register_schemas

ROOT = Path(__file__).resolve().parents[1]
register_schemas()  # conf/ extends ferl/schema.py's schemas, as in train.py
EXPERIMENTS = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))


@pytest.fixture
def compose_cfg():
    """Compose the real configs as train.py does (hydra's runtime keys included)."""
    def _compose(overrides=()):
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            return compose("config", overrides=list(overrides), return_hydra_config=True)
    return _compose


def run_train(*overrides, cwd=ROOT, timeout=600, **popen):
    """Run train.py in a subprocess; returns the CompletedProcess."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run([sys.executable, str(ROOT / "train.py"), *overrides], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout, **popen)


TINY = ["n_runs=2", "trainer.steps=300", "trainer.log_every=100", "trainer.checkpoint_every=100",
        "trainer.test_per_class=8", "trainer.test_noise_levels=[0.0,0.125,0.5]"]
