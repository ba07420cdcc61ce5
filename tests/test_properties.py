"""Property-based tests (hypothesis): environment invariants under arbitrary action sequences,
and config validation against the allowed ranges it names (issue 7/7)."""

import copy

import numpy as np
import pytest
import torch
from hydra.core.hydra_config import HydraConfig
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf
from omegaconf.errors import ValidationError

from ferl.config.params import ConfigError
from ferl.config.validate import validate
from ferl.envs.digit_floor import DigitFloor
from ferl.envs.tmaze import TMaze
from test_digit_floor import tiny_split

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FLOOR_REWARDS = {10.0, 4.0, -2.0}  # goal, CW/CCW boundary move, any other move (§3.4)


@SETTINGS
@given(
    seed=st.integers(0, 2**31 - 1),
    corridor=st.integers(2, 6),
    extra=st.integers(0, 6),
    matching=st.booleans(),
    actions=st.lists(st.integers(0, 3), min_size=1, max_size=40),
)
def test_tmaze_invariants(seed, corridor, extra, matching, actions):
    """Rewards in the maze's set, positions on the maze, t ≤ T_max, ended runs frozen, every
    episode over by T_max actions — for any corridor, T_max ≥ T_min and action sequence."""
    R, max_steps = 3, corridor + extra
    env = TMaze(
        R, torch.Generator().manual_seed(seed), corridor_length=corridor, max_steps=max_steps, matching=matching
    )
    allowed = set(np.float32(env.reward_values).tolist()) | {0.0}
    for k, a in enumerate(actions):
        was_done, position = env.done.clone(), env.position.clone()
        _, reward, terminated, truncated = env.step(torch.full((R,), a))
        assert set(reward.tolist()) <= allowed
        assert not (terminated & truncated).any()
        assert ((reward != 0) == ~was_done).all()  # ended runs get nothing, live ones something
        assert torch.equal(env.position[was_done], position[was_done])
        assert ((env.position >= 0) & (env.position <= corridor + 1)).all()
        assert (env.t <= max_steps).all() and (env.t <= k + 1).all()
        assert torch.equal(env.done, (env.position >= corridor) | (env.t >= max_steps))
        assert ((reward.abs() == 5) == terminated).all()  # a goal reward exactly when a goal ends it
    if len(actions) >= max_steps:
        assert env.done.all()


@SETTINGS
@given(
    seed=st.integers(0, 2**31 - 1),
    patches=st.integers(1, 4),
    condition=st.sampled_from(["cw", "ccw", "none"]),
    actions=st.lists(st.integers(0, 3), min_size=1, max_size=30),
)
def test_digit_floor_invariants(seed, patches, condition, actions):
    """Rewards in the floor's set (all 0 without reward), the agent on a non-goal tile of the
    board after every step (entering the goal transports it, §3.4), observations in [0, 1]."""
    R = 3
    env = DigitFloor(
        R, SPLIT, torch.Generator().manual_seed(seed), patches=patches, noise=0.25, reward_condition=condition
    )
    n_tiles = (3 * patches) ** 2
    for a in actions:
        obs, reward, terminated, truncated = env.step(torch.full((R,), a))
        assert not (terminated | truncated).any()  # a continuing task (§3.4 fn. 1)
        assert set(reward.tolist()) <= ({0.0} if condition == "none" else FLOOR_REWARDS)
        assert ((env.tile >= 0) & (env.tile < n_tiles)).all()
        assert torch.isin(env.tile, env.non_goal_tiles).all()
        assert obs.shape == (R, 784) and (obs >= 0).all() and (obs <= 1).all()


SPLIT = tiny_split()


# ---- config validation: accepted exactly inside the range the error message names ----------


@pytest.fixture
def base_cfgs(compose_cfg):
    floor = compose_cfg(["experiment=ch3_floor"])
    maze = compose_cfg(["experiment=table4_1_matching"])
    HydraConfig.instance().set_config(floor)
    return {"floor": floor, "maze": maze}


def _accepted(cfg, key: str, value) -> bool:
    """Does the config take `key=value`: on assignment, then by ferl/config/validate.py (the
    annotations of the constructors the config names)?"""
    cfg = copy.deepcopy(cfg)
    try:
        OmegaConf.update(cfg, key, value, force_add=False)
        validate(cfg)
        return True
    except (ValidationError, ConfigError):
        return False


NUMBERS = st.one_of(st.integers(-5, 20), st.floats(-2.0, 3.0, allow_nan=False))


@pytest.mark.parametrize(
    "which, key, allowed",
    [
        ("floor", "env.noise", lambda x: 0 <= x <= 1),
        ("floor", "actor.gamma", lambda x: 0 <= x < 1),
        ("floor", "n_runs", lambda x: isinstance(x, int) and x >= 1),
        ("floor", "env.patches", lambda x: isinstance(x, int) and x >= 1),
        ("floor", "actor.n_hidden", lambda x: isinstance(x, int) and x >= 1),
        ("maze", "env.corridor_length", lambda x: isinstance(x, int) and 2 <= x <= 10),  # T_max = 10
        ("maze", "trainer.train_fraction", lambda x: 0 < x < 1),
        ("maze", "predictor.joint.lr", lambda x: x > 0),
    ],
)
def test_validation_accepts_exactly_the_allowed_values(base_cfgs, which, key, allowed):
    @SETTINGS
    @given(value=NUMBERS)
    def check(value):
        accepted = _accepted(base_cfgs[which], key, value)
        assert accepted == bool(allowed(value)), f"{key}={value!r}: accepted={accepted}"

    check()
