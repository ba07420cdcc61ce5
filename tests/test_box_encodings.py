"""A Box's thresholds derived per entry (``env.thresholds: auto``, ferl/envs/derived.py).

The derived lists are held to NumPy computed here: the sample replayed by a loop of this file,
the bounds cut by ``numpy.linspace``, the quantiles by ``numpy.quantile``; every bit is checked to
move on the sample; the sources are the ones each entry was built to have; and the whole path runs
through train.py on the stateless CartPole of issue 61 (tests/stateless_cartpole.py).
"""

import json
import os

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium import spaces

from conftest import ROOT, run_train
from ferl.config.params import ConfigError
from ferl.envs.derived import SAMPLE_SEED, random_policy_sample
from ferl.envs.encodings import encoder_for
from ferl.envs.gymnasium_vector import GymnasiumEnv

ENV = {**os.environ, "PYTHONPATH": str(ROOT / "tests")}
STATELESS = "stateless_cartpole:StatelessCartPole-v0"


class Mixed(gymnasium.Env):
    """Five entries, each built for one case of ferl/envs/derived.py: 0 uniform over its finite
    bounds (→ bounds), 1 normal inside bounds of ±10⁶ (→ sample: the bounds are huge), 2 a random
    walk with infinite bounds (→ sample), 3 constant (→ no bits), 4 three integer values (→ sample,
    its repeated quantiles once)."""

    observation_space = spaces.Box(
        np.array([0.0, -1e6, -np.inf, -np.inf, -np.inf]), np.array([1.0, 1e6, np.inf, np.inf, np.inf]), dtype=np.float64
    )
    action_space = spaces.Discrete(2)

    def observe(self):
        r = self.np_random
        return np.array([r.uniform(), r.normal(), self.walk, 0.5, r.integers(3)])

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.walk, self.t = 0.0, 0
        return self.observe(), {}

    def step(self, action):
        self.walk += float(action) - 0.5
        self.t += 1
        return self.observe(), 1.0, self.t >= 10, False, {}


gymnasium.register("MixedBox-v0", entry_point=Mixed, max_episode_steps=10)


class Constant(Mixed):
    def observe(self):
        return np.full(5, 0.5)


gymnasium.register("ConstantBox-v0", entry_point=Constant, max_episode_steps=10)


def replayed(env_id: str, steps: int, limit: int) -> np.ndarray:
    """The random-policy sample as the module docstring states it, played here step by step."""
    env = gymnasium.make(env_id)
    env.action_space.seed(SAMPLE_SEED)
    rows = [env.reset(seed=SAMPLE_SEED)[0]]
    t = 0
    for _ in range(10 * steps):
        if len(rows) == steps:
            break
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        rows.append(obs)
        t += 1
        if (terminated or truncated or t == limit) and len(rows) < steps:
            rows.append(env.reset()[0])
            t = 0
    env.close()
    return np.array(rows, np.float64).reshape(steps, -1)


def expected(space, sample: np.ndarray, k: int) -> tuple[list, list]:
    """(thresholds, source) per entry: linspace over finite bounds the sample crosses, else the
    sample's quantiles j/(k+1) inside [min, max), each once."""
    lists, sources = [], []
    for i, column in enumerate(sample.T):
        low, high = float(space.low.reshape(-1)[i]), float(space.high.reshape(-1)[i])
        grid = np.linspace(low, high, k + 2)[1:-1] if np.isfinite([low, high]).all() else None
        if grid is not None and column.min() <= grid[0] and grid[-1] < column.max():
            lists.append(grid), sources.append("bounds")
            continue
        q = np.quantile(column, [j / (k + 1) for j in range(1, k + 1)])
        lists.append(np.array(sorted({t for t in q if column.min() <= t < column.max()})))
        sources.append("sample")
    return lists, sources


def every_bit_moves(space, thresholds, sample) -> None:
    encode, size = encoder_for(space, "thresholds", thresholds)
    bits = np.stack([encode(row) for row in sample])
    assert bits.shape[1] == size and (bits.min(0) == 0).all() and (bits.max(0) == 1).all()


@pytest.mark.parametrize("env_id,k,steps", [("CartPole-v1", 8, 1000), ("MixedBox-v0", 8, 600), (STATELESS, 5, 400)])
def test_derived_thresholds_are_numpys_and_every_bit_moves(env_id, k, steps):
    env = GymnasiumEnv(1, torch.Generator(), 0, env_id, thresholds="auto", bits_per_entry=k, sample_steps=steps)
    limit = env.max_steps
    space = gymnasium.make(env_id).observation_space
    sample = replayed(env_id, steps, limit)
    np.testing.assert_array_equal(sample, random_policy_sample(gymnasium.make(env_id), steps, limit))
    lists, sources = expected(space, sample, k)
    assert env.derived is not None and env.derived.sources == sources
    for got, want in zip(env.thresholds, lists):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    every_bit_moves(space, env.thresholds, sample)
    assert env.observation_size == sum(len(t) for t in lists)
    assert env.distinct_codes == int(np.prod([len(t) + 1 for t in lists]))
    described = env.describe()
    assert described["thresholds"] == env.thresholds and described["derived"]["sample_steps"] == steps
    env.close()


def test_each_entry_gets_the_source_it_was_built_for():
    """CartPole: velocities unbounded, x's and θ's bounds twice their termination bounds, so every
    entry from the sample; the mixed Box: one case per entry (``Mixed``), the constant one said."""
    cart = GymnasiumEnv(1, torch.Generator(), 0, "CartPole-v1", thresholds="auto")
    assert cart.derived is not None and cart.derived.sources == ["sample"] * 4
    assert [len(t) for t in cart.thresholds] == [8] * 4 and cart.observation_size == 32
    cart.close()
    mixed = GymnasiumEnv(1, torch.Generator(), 0, "MixedBox-v0", bits_per_entry=8, sample_steps=600)  # null: auto
    assert mixed.derived is not None and mixed.derived.sources == ["bounds", "sample", "sample", "sample", "sample"]
    np.testing.assert_allclose(mixed.thresholds[0], np.arange(1, 9) / 9)
    assert mixed.thresholds[3] == [] and 0 < len(mixed.thresholds[4]) < 8  # three values: quantiles repeat
    assert "entries [3]" in mixed.unused_bits and "did not vary" in mixed.unused_bits
    mixed.close()


def test_quantile_thresholds_split_the_sample_into_levels_of_equal_frequency():
    """On a continuous entry, a share j/(k+1) of the sample lies at or below θ_j (to one observation)."""
    env = GymnasiumEnv(1, torch.Generator(), 0, "MixedBox-v0", bits_per_entry=4, sample_steps=1000)
    sample = replayed("MixedBox-v0", 1000, env.max_steps)
    below = [(sample[:, 1] <= t).mean() for t in env.thresholds[1]]
    np.testing.assert_allclose(below, [0.2, 0.4, 0.6, 0.8], atol=1 / 1000)
    env.close()


@pytest.mark.parametrize(
    "env_id,kwargs,key,says",
    [
        ("CartPole-v1", {"encoding": "onehot", "thresholds": "auto"}, "env.thresholds", "auto derives a Box"),
        ("CartPole-v1", {"bits_per_entry": 200}, "env.max_observations", "bits_per_entry"),  # 201⁴ codes
        ("ConstantBox-v0", {}, "env.thresholds", "no entry varied"),
    ],
)
def test_derived_encodings_refused_at_set_up(env_id, kwargs, key, says):
    with pytest.raises(ConfigError) as refused:
        GymnasiumEnv(1, torch.Generator(), 0, env_id, **kwargs)
    assert str(refused.value).startswith(key) and says in str(refused.value), refused.value


def test_auto_thresholds_train_stateless_cartpole_end_to_end(tmp_path):
    """train.py on the stateless CartPole with no thresholds typed: the run plays to the end, its
    log states every entry's thresholds and records/run.json keeps them."""
    run_dir = tmp_path / "run"
    result = run_train(
        "experiment=popgym_repeat_previous_easy",
        f"env.id={STATELESS}",
        "env.thresholds=auto",
        "env.reward_scale=1",
        "env.optimal_return=null",
        "n_runs=2",
        "trainer.n_episodes=4",
        "trainer.log_every=2",
        "trainer.checkpoint_every=4",
        f"hydra.run.dir={run_dir}",
        env=ENV,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    described = json.loads((run_dir / "records" / "run.json").read_text())["env"]
    assert described["derived"]["sources"] == ["sample", "sample"] and described["observation_size"] == 16
    log = (run_dir / "train.log").read_text()
    assert log.count("env.thresholds=auto: 16 bits") == 1 and "entry 1 (sample, 8 bits)" in log
    summary = json.loads((run_dir / "summary.json").read_text())
    assert all(r >= 8 for r in summary["metrics"]["final_return"]), summary


def test_the_gaussian_rbm_on_a_gymnasium_env_is_refused_for_what_it_is(tmp_path):
    """Issue 61: "takes 26 inputs … but the environment's observations have 26 values" named sizes
    that agreed; the preprocessor fits on the data's images and processes a table known in advance,
    which an environment that discovers its observations has not: one line saying so."""
    run_dir = tmp_path / "out" / "run"
    result = run_train(
        "experiment=popgym_repeat_previous_easy",
        "env.id=CartPole-v1",
        "preprocessor=gaussian_rbm",
        "n_runs=1",
        f"hydra.run.dir={run_dir}",
        timeout=300,
    )
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith("ferl: error: preprocessor:") and "discover their observations" in lines[0]
    assert not (tmp_path / "out").exists()
