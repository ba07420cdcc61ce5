"""Golden numbers: each of the nine reproduction experiments (CONTRACT §3) at reduced scale gives
exactly the summary.json metrics of tests/golden/reduced_scale.json, with seed 3, on CPU.

The file was written by the code of commit 1357315 (before the architecture of issue 1/8), so this
test also shows that the restructured code computes the reproduction's numbers bit for bit. A
change to any of them is a decision, not an accident: state it, then rewrite the file with

    python tests/test_golden.py --write

Rewritten once since, by issue 2/8, to add the T-mazes' new metrics (``env_steps_total``,
``env_steps_to_solve``, ``episodes_to_solve``); every metric of 1357315 kept its value. Re-based once more when the
per-episode discounted return became a float64 sum in step order (it was a float32 BLAS product
whose summation order, and so its ninth digit, differed between Intel and AMD CPUs):
``final_discounted_return`` moved by < 1e-6 relative, every other metric kept its value.

The digit mazes' numbers depend on how the CPU rounds 784-pixel sums (AVX-512 or not); the file
holds this project's machines' numbers. Each run is a separate process from the one that wrote
the file, so equality is also the determinism of CONTRACT §2 (same config and seed → same metrics).
"""

import json
import sys
from pathlib import Path

import pytest

from conftest import SHORT_ALGORITHM1, train_job

GOLDEN = Path(__file__).parent / "golden" / "reduced_scale.json"
FLOOR = [
    "n_runs=2",
    "trainer.steps=300",
    "trainer.test_per_class=5",
    "trainer.log_every=100",
    "trainer.checkpoint_every=100",
    "trainer.test_noise_levels=[0.0,0.5]",
]
MAZE = [
    "n_runs=2",
    *SHORT_ALGORITHM1,
]
REDUCED = {
    "ch3_floor": FLOOR,
    "ch3_coding_cw": FLOOR,
    "ch3_coding_ccw": FLOOR,
    "ch3_coding_noreward": FLOOR,
    "table4_1_regular": MAZE,
    "table4_1_matching": MAZE,
    "table4_2_digit": MAZE,
    "table5_1_bit": MAZE,
    "table5_1_pixel": [*MAZE, "preprocessor.sweeps=2", "env.reservoir_size=5"],
}


def overrides(experiment: str) -> list[str]:
    return [f"experiment={experiment}", "seed=3", *REDUCED[experiment]]


def run(compose_cfg, tmp_path: Path, experiment: str) -> dict:
    # a cache of its own: the RBM is fitted, not loaded
    cache = [f"preprocessor.cache_dir={tmp_path / 'cache'}"] if experiment == "table5_1_pixel" else []
    return train_job(compose_cfg([*overrides(experiment), *cache]), tmp_path / experiment)


@pytest.mark.parametrize("experiment", list(REDUCED))
def test_reduced_scale_metrics_equal_the_golden_ones(compose_cfg, tmp_path, experiment):
    golden = json.loads(GOLDEN.read_text())[experiment]
    assert golden["overrides"] == overrides(experiment)
    summary = run(compose_cfg, tmp_path, experiment)
    assert summary["metrics"] == golden["metrics"]
    assert summary["seeds"] == [3, 4]


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    import tempfile

    from conftest import compose_config

    with tempfile.TemporaryDirectory() as tmp:
        GOLDEN.write_text(
            json.dumps(
                {
                    e: {"overrides": overrides(e), "metrics": run(compose_config, Path(tmp), e)["metrics"]}
                    for e in REDUCED
                },
                indent=1,
            )
            + "\n"
        )
    print(f"wrote {GOLDEN}")
