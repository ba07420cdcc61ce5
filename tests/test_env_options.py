"""Every environment option's bad value stops train.py before any work (docs/usage.md, "Training"):
one line naming the option, exit status 2, no run directory. The tables below list one bad value
for every key of every conf/env/ option file, and a test holds them to the files, so an option
added without a check here fails.

``env=gymnasium`` goes through train.py itself, on Gymnasium's CartPole (a ``Box`` of 4 entries,
thresholds-coded); the other environments through what train.py does before any work
(tests/test_configs.py's ``config_error``: compose, validate, build and set up). The encodings the
checks guard are tested against codes written out by hand.
"""

import numpy as np
import pytest
from gymnasium import spaces
from omegaconf import OmegaConf

from conftest import ROOT, run_train
from ferl.envs.encodings import BadThresholds, distinct_codes, encoder_for, fixed_bits
from test_configs import config_error

# CartPole, one threshold on every entry, at a size set-up takes no time over
GYM = ["experiment=popgym_repeat_previous_easy", "env.id=CartPole-v1", "env.thresholds=[0.0]", "n_runs=1"]

# key → (overrides, what the line must say besides the key)
GYMNASIUM_BAD = {
    "id": (["env.id=NoSuchEnv-v0"], "not a registered Gymnasium id"),
    "kwargs": (["+env.kwargs.no_such_arg=1"], "does not take them"),
    "encoding": (["env.encoding=minigrid"], "not MiniGrid"),
    # one list per entry: four are needed
    "thresholds": (["env.thresholds=[[0.0],[0.0]]"], "4 entries"),
    # derived thresholds (env.thresholds=auto): their count per entry, the sample they come from
    "bits_per_entry": (["env.thresholds=auto", "env.bits_per_entry=0"], "≥ 1"),
    "sample_steps": (["env.thresholds=auto", "env.sample_steps=1"], "a sample that can vary"),
    "max_steps": (["env.max_steps=0"], ""),
    "vectorization": (["env.vectorization=fork"], ""),
    # 6^4 = 1296 codes known at set-up: a table of 100 rows could overflow mid-run
    "max_observations": (["env.thresholds=[-2,-1,0,1,2]", "env.max_observations=100"], "1296"),
    "success_threshold": (["env.success_threshold=high"], ""),
    "optimal_return": (["env.optimal_return=best"], ""),
    "reward_scale": (["env.reward_scale=0"], ""),
}

# the other environments: file → key → (overrides, the key the line names)
OTHER_BAD = {
    "digit_floor": {
        "patches": ["env.patches=0"],
        "arrangement": ["env.arrangement=[[0,1],[2,3]]"],
        "noise": ["env.noise=1.5"],
        "reward_condition": ["env.reward_condition=up"],
        "goal_reward": ["env.goal_reward=high"],
        "boundary_reward": ["env.boundary_reward=high"],
        "other_reward": ["env.other_reward=high"],
        "noise_tile": ["env.noise_tile=4"],  # the goal's class: the centre of the arrangement
    },
    "digit_tmaze": {
        "corridor_length": ["experiment=table4_2_digit", "env.corridor_length=0"],
        "max_steps": ["experiment=table4_2_digit", "env.max_steps=0"],
        "matching": ["experiment=table4_2_digit", "env.matching=perhaps"],
        "goal_reward": ["experiment=table4_2_digit", "env.goal_reward=high"],
        "wall_reward": ["experiment=table4_2_digit", "env.wall_reward=high"],
        "step_reward": ["experiment=table4_2_digit", "env.step_reward=high"],
        "digit_classes": ["experiment=table4_2_digit", "env.digit_classes.start_0=11"],
        "image_index": ["experiment=table4_2_digit", "env.image_index=-1"],
        "reservoir_size": ["experiment=table4_2_digit", "env.reservoir_size=0"],
        "binarize_threshold": ["experiment=table4_2_digit", "env.binarize_threshold=2"],
        "pixel_noise_std": ["experiment=table4_2_digit", "env.pixel_noise_std=-1"],
        "noise_copies": ["experiment=table4_2_digit", "env.noise_copies=0"],
    },
    "tmaze": {
        "corridor_length": ["experiment=table4_1_regular", "env.corridor_length=0"],
        "max_steps": ["experiment=table4_1_regular", "env.max_steps=0"],
        "matching": ["experiment=table4_1_regular", "env.matching=perhaps"],
        "passive": ["experiment=table4_1_regular", "env.passive=perhaps"],
        "goal_reward": ["experiment=table4_1_regular", "env.goal_reward=high"],
        "wall_reward": ["experiment=table4_1_regular", "env.wall_reward=high"],
        "step_reward": ["experiment=table4_1_regular", "env.step_reward=high"],
    },
    "large_action": {
        "state_bits": ["experiment=large_action", "env.state_bits=0"],
        "action_bits": ["experiment=large_action", "env.action_bits=0"],
        "key_states": ["experiment=large_action", "env.key_states=0"],
        "states": ["experiment=large_action", "env.states=sometimes"],
    },
}


def option_keys(name: str) -> set:
    return set(OmegaConf.load(ROOT / "conf" / "env" / f"{name}.yaml")) - {"_target_"}


def test_every_env_option_has_a_bad_value_here():
    assert set(GYMNASIUM_BAD) == option_keys("gymnasium")
    assert set(OTHER_BAD) | {"gymnasium"} == {p.stem for p in (ROOT / "conf" / "env").glob("*.yaml")}
    for name, bad in OTHER_BAD.items():
        assert set(bad) == option_keys(name), name


@pytest.mark.parametrize("key", sorted(GYMNASIUM_BAD))
def test_a_bad_gymnasium_option_stops_train_py_before_the_run_directory(tmp_path, key):
    overrides, says = GYMNASIUM_BAD[key]
    run_dir = tmp_path / "out" / "run"
    result = run_train(*GYM, *overrides, f"hydra.run.dir={run_dir}", timeout=300)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and lines[0].startswith(f"ferl: error: env.{key}"), result.stderr
    assert says in lines[0], lines[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name,key", [(n, k) for n, bad in OTHER_BAD.items() for k in bad])
def test_a_bad_option_of_the_other_envs_is_refused_before_any_work(compose_cfg, name, key):
    stage, message = config_error(compose_cfg, OTHER_BAD[name][key])
    assert stage in ("compose", "validate", "setup"), f"env.{key}: accepted"
    assert f"env.{key}" in message and "\n" not in message, message


def test_per_entry_thresholds_are_a_thermometer_code_per_entry():
    """Each entry its own increasing list: the bits [x_i > θ_ij], entry by entry, as written out."""
    space = spaces.Box(-np.inf, np.inf, (2, 2))
    theta = [[-2.4, 0.0, 2.4], [-0.2, 0.2], [0.0], [-1.0, -0.5, 0.0, 0.5]]
    encode, size = encoder_for(space, "thresholds", theta)
    assert size == 10 and distinct_codes(space, "thresholds", theta) == 4 * 3 * 2 * 5
    rng = np.random.default_rng(0)
    seen = set()
    for _ in range(2000):
        x = rng.normal(0, 1.5, (2, 2)).astype(np.float32)
        want = [int(x.reshape(-1)[i] > t) for i, row in enumerate(theta) for t in row]
        bits = encode(x)
        assert bits.tolist() == want
        seen.add(bits.tobytes())
    assert len(seen) <= 4 * 3 * 2 * 5  # the stated count bounds the codes met
    # "auto" takes the thresholds for a Box; the shared list is the per-entry list repeated
    shared, _ = encoder_for(space, "auto", [0.0, 1.0])
    repeated, _ = encoder_for(space, "thresholds", [[0.0, 1.0]] * 4)
    x = rng.normal(0, 1.5, (2, 2))
    assert shared(x).tolist() == repeated(x).tolist()


def test_thresholds_outside_an_entrys_bounds_are_bits_that_never_change():
    """x ∈ ±2.4 and θ ∈ ±0.2 with one shared list: θ = ±1 lies outside θ's range; drawn
    observations confirm that exactly those bits never change."""
    space = spaces.Box(np.array([-2.4, -0.2]), np.array([2.4, 0.2]), dtype=np.float64)
    assert fixed_bits(space, [-1.0, 0.0, 1.0]) == [(1, -1.0), (1, 1.0)]
    assert fixed_bits(space, [[-1.0, 0.0, 1.0], [-0.1, 0.0, 0.1]]) == []
    encode, _ = encoder_for(space, "thresholds", [-1.0, 0.0, 1.0])
    space.seed(0)
    bits = np.stack([encode(space.sample()) for _ in range(500)])
    assert np.flatnonzero(bits.min(0) == bits.max(0)).tolist() == [3, 5]  # entry 1's bits for −1 and 1


@pytest.mark.parametrize(
    "theta,says",
    [([[0.0]] * 3, "4 entries"), ([1.0, 0.0], "increasing"), ([[0.0], 1.0, 2.0, 3.0], "mixes"), (["a"], "numbers")],
)
def test_bad_thresholds_say_why(theta, says):
    with pytest.raises(BadThresholds, match=says):
        encoder_for(spaces.Box(-1, 1, (4,)), "thresholds", theta)


def test_distinct_codes_of_discrete_spaces():
    space = spaces.Tuple((spaces.Discrete(3), spaces.MultiDiscrete([2, 5]), spaces.MultiBinary(3)))
    assert distinct_codes(space, "auto") == 3 * 2 * 5 * 2**3
    minigrid = spaces.Dict({"direction": spaces.Discrete(4), "image": spaces.Box(0, 255, (7, 7, 3), np.uint8)})
    assert distinct_codes(minigrid, "auto") is None  # not known in advance


def test_per_entry_thresholds_train_through_the_actor_phase(tmp_path):
    """A list per entry of CartPole's Box (its ranges differ): the runs play and learn to the end."""
    import json

    run_dir = tmp_path / "run"
    per_entry = "env.thresholds=[[-1,0,1],[-1,0,1],[-0.1,0,0.1],[-1,0,1]]"
    result = run_train(
        *GYM,
        per_entry,
        "n_runs=2",
        "trainer.n_episodes=4",
        "trainer.log_every=2",
        "trainer.checkpoint_every=4",
        f"hydra.run.dir={run_dir}",
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    # CartPole's shortest episode is 8 steps of reward 1
    assert summary["task"] == "gymnasium" and all(r >= 8 for r in summary["metrics"]["final_return"]), summary


def test_the_table_of_observations_is_sized_to_the_codes_where_they_are_known():
    """null: as many rows as the encoding has codes (4⁴ for CartPole with 3 thresholds an entry),
    4096 where that count is unknown; a count whose table would not fit is refused unless a bound
    is stated; a stated bound below a count that fits is refused."""
    import torch

    from ferl.config.params import ConfigError
    from ferl.envs.gymnasium_vector import GymnasiumEnv
    from ferl.envs.observation_rows import TABLE_BYTES, UNKNOWN_ROWS, table_rows

    env = GymnasiumEnv(
        1, torch.Generator(), 0, "CartPole-v1", thresholds=[[-1, 0, 1], [-1, 0, 1], [-0.1, 0, 0.1], [-1, 0, 1]]
    )
    assert env.observation_table.shape == (4**4, 12) and env.describe()["distinct_codes"] == 256
    env.close()
    assert table_rows("x", None, 980, None) == UNKNOWN_ROWS and table_rows("x", None, 980, 50) == 50
    assert table_rows("x", 300, 8, None) == 300 and table_rows("x", 300, 8, 500) == 500
    huge = TABLE_BYTES // 4 + 1  # codes of one bit each: one byte more than the table may take
    assert table_rows("x", huge, 1, 1000) == 1000  # a stated bound where a table of every code would not fit
    with pytest.raises(ConfigError, match=r"^env\.max_observations: .* more than a table"):
        table_rows("x", huge, 1, None)
    with pytest.raises(ConfigError, match=r"^env\.max_observations=299: .* 300 distinct"):
        table_rows("x", 300, 8, 299)
