"""Gymnasium views of the batched environments (CONTRACT §5): API checks, seeding, episode ends,
vector autoreset, and agreement with the batched classes that training steps."""

import warnings

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode
from omegaconf import OmegaConf

import ferl.envs  # noqa: F401  (importing the package registers the ids)
from conftest import ROOT
from ferl.envs.digit_floor import DigitFloor
from ferl.envs.digit_tmaze import DigitTMaze
from ferl.envs.gym import (
    ENV_SPECS,
    FLOOR_EPISODE_STEPS,
    DigitFloorEnv,
    DigitFloorVectorEnv,
    TMazeVectorEnv,
    register_envs,
)
from ferl.envs.gym_batches import DIGIT_CLASSES, embedded_mnist
from ferl.envs.tmaze import TMaze

IDS = list(ENV_SPECS)
MAZE_REWARDS = (5.0, -5.0, -1.0, -0.1)
FLOOR_REWARDS = (10.0, 4.0, -2.0)
T_MAX = 10  # the registered mazes' max_steps (conf/env/tmaze.yaml)
PASSIVE = "ferl/PassiveTMaze-v0"  # Ni et al.'s passive maze, L = 3: 4 actions, rewards 1, 0, −1/3
PASSIVE_REWARDS = (1.0, 0.0, -1.0 / 3)


def allowed(reward: float, values) -> bool:
    return bool(np.isclose(reward, np.float32(values)).any())


def batched_twin(env_id: str, n_runs: int, seed: int):
    """The batched class behind ``env_id`` with its registered defaults, as ``reset(seed)`` builds it."""
    generator = torch.Generator().manual_seed(seed)
    if env_id == "ferl/DigitFloor-v0":
        return DigitFloor(n_runs, embedded_mnist(), generator)
    if env_id == "ferl/DigitMatchingTMaze-v0":
        return DigitTMaze(n_runs, generator, embedded_mnist(), DIGIT_CLASSES, matching=True)
    if env_id == PASSIVE:
        return TMaze(n_runs, generator, passive=True, max_steps=None, goal_reward=1.0)
    return TMaze(n_runs, generator, matching=env_id == "ferl/MatchingTMaze-v0")


def test_importing_the_package_registers_every_id_once():
    assert all(env_id in gymnasium.registry for env_id in IDS)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warns when an id is registered over
        register_envs()


@pytest.mark.parametrize("env_id", IDS)
def test_passes_gymnasium_env_checker(env_id):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker reports most problems as warnings
        check_env(gymnasium.make(env_id).unwrapped)


@pytest.mark.parametrize("env_id", IDS)
def test_random_agent_through_gymnasium_make(env_id):
    env = gymnasium.make(env_id)
    floor = env_id == "ferl/DigitFloor-v0"
    env.action_space.seed(0)
    obs, _ = env.reset(seed=0)
    length, lengths = 0, []
    for _ in range(1000):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        length += 1
        assert obs in env.observation_space
        assert allowed(reward, FLOOR_REWARDS if floor else PASSIVE_REWARDS if env_id == PASSIVE else MAZE_REWARDS)
        if floor:
            assert not terminated and truncated == (length == FLOOR_EPISODE_STEPS)
        elif env_id == PASSIVE:  # a finite horizon: L + 1 actions, then the end, wherever the agent is
            assert terminated == (length == 4) and not truncated
            assert info["correct"] == (terminated and reward > 0)
        else:
            assert terminated == (info["position"] >= 3)  # entering a goal ends the episode
            assert truncated == (not terminated and length == T_MAX)
            assert info["correct"] == (terminated and reward > 0)
        if terminated or truncated:
            lengths.append(length)
            obs, _ = env.reset()
            length = 0
    assert lengths and max(lengths) <= (FLOOR_EPISODE_STEPS if floor else T_MAX)


def rollout(env, seed: int, actions) -> list:
    """Observations, rewards and episode ends of ``actions``, resetting (unseeded) after each end."""
    obs, _ = env.reset(seed=seed)
    trace = [obs]
    for a in actions:
        obs, reward, terminated, truncated, _ = env.step(a)
        trace += [obs, reward, terminated, truncated]
        if terminated or truncated:
            trace.append(env.reset()[0])
    return trace


@pytest.mark.parametrize("env_id", IDS)
def test_same_seed_same_trajectory(env_id):
    actions = np.random.default_rng(0).integers(4, size=60)
    first = rollout(gymnasium.make(env_id), 3, actions)
    again = rollout(gymnasium.make(env_id), 3, actions)
    other = rollout(gymnasium.make(env_id), 4, actions)
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    assert len(first) != len(other) or not all(np.array_equal(a, b) for a, b in zip(first, other))


@pytest.mark.parametrize("env_id", IDS)
def test_single_view_steps_the_batched_environment(env_id):
    env = gymnasium.make(env_id).unwrapped
    twin = batched_twin(env_id, 1, seed=5)
    obs, _ = env.reset(seed=5)
    np.testing.assert_array_equal(obs, twin.reset()[0].numpy())
    for a in np.random.default_rng(1).integers(4, size=40):
        obs, reward, terminated, truncated, _ = env.step(a)
        twin_step = twin.step(torch.tensor([a]))
        np.testing.assert_array_equal(obs, twin_step[0][0].numpy())
        assert reward == twin_step[1].item()
        if terminated or truncated:
            assert (terminated, truncated) == (twin_step[2].item(), twin_step[3].item())
            break


def test_vector_env_matches_the_batched_environment_until_an_episode_ends():
    vec = gymnasium.make_vec("ferl/MatchingTMaze-v0", num_envs=6)
    twin = batched_twin("ferl/MatchingTMaze-v0", 6, seed=2)
    obs, _ = vec.reset(seed=2)
    np.testing.assert_array_equal(obs, twin.reset().numpy())
    for actions in np.random.default_rng(2).integers(4, size=(3, 6)):  # no episode ends in < T_min steps
        obs, reward, _, _, _ = vec.step(actions)
        twin_obs, twin_reward, _, _ = twin.step(torch.as_tensor(actions))
        np.testing.assert_array_equal(obs, twin_obs.numpy())
        np.testing.assert_array_equal(reward, twin_reward.numpy())


def test_vector_env_shapes_and_next_step_autoreset():
    vec = gymnasium.make_vec("ferl/TMaze-v0", num_envs=8)
    assert isinstance(vec, TMazeVectorEnv) and vec.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs, info = vec.reset(seed=0)
    assert obs.shape == (8, 7) and obs.dtype == np.int8 and obs in vec.observation_space
    assert info["steps"].shape == (8,)
    north = np.zeros(8, dtype=np.int64)
    for _ in range(2):
        obs, reward, terminated, truncated, info = vec.step(north)
    assert reward.shape == terminated.shape == truncated.shape == (8,) and not terminated.any()
    east = np.ones(8, dtype=np.int64)
    _, reward, terminated, _, info = vec.step(east)  # from the junction into the right goal
    assert terminated.all() and np.array_equal(reward > 0, info["rewarded_side"] == 1)
    obs, reward, terminated, truncated, info = vec.step(north)  # the action is ignored: a new episode starts
    assert (reward == 0).all() and not terminated.any() and not truncated.any()
    assert (info["position"] == 0).all() and (info["steps"] == 0).all() and (obs[:, 0] == 1).all()
    _, reward, _, _, info = vec.step(north)
    assert (info["position"] == 1).all() and np.allclose(reward, -0.1)


def test_vector_env_truncates_at_max_steps_and_at_max_episode_steps():
    vec = gymnasium.make_vec("ferl/TMaze-v0", num_envs=3)
    vec.reset(seed=0)
    south = np.full(3, 2)  # bumps the start's wall until T_max
    ends = [vec.step(south)[3].tolist() for _ in range(T_MAX + 1)]
    assert ends[T_MAX - 1] == [True] * 3 and not any(any(e) for e in ends[: T_MAX - 1] + ends[T_MAX:])

    floor = gymnasium.make_vec("ferl/DigitFloor-v0", num_envs=2, max_episode_steps=3)
    assert isinstance(floor, DigitFloorVectorEnv)
    obs, _ = floor.reset(seed=0)
    assert obs.shape == (2, 784) and obs.dtype == np.float32
    steps = [floor.step(np.array([0, 1])) for _ in range(5)]
    assert [s[3].tolist() for s in steps] == [[False] * 2, [False] * 2, [True] * 2, [False] * 2, [False] * 2]
    assert (steps[3][1] == 0).all() and not any(s[2].any() for s in steps)
    assert DigitFloorVectorEnv(2).max_episode_steps is None  # constructed directly: the continuing task


def test_registered_floor_truncates_but_the_env_itself_does_not():
    assert gymnasium.spec("ferl/DigitFloor-v0").max_episode_steps == FLOOR_EPISODE_STEPS
    env = DigitFloorEnv(noise=0.0, reward_condition="none")
    env.reset(seed=0)
    outcomes = {env.step(a)[1:4] for a in np.random.default_rng(0).integers(4, size=FLOOR_EPISODE_STEPS + 5)}
    assert outcomes == {(0.0, False, False)}


def test_info_describes_the_state():
    env = gymnasium.make("ferl/DigitFloor-v0", reward_condition="ccw", noise_tile=5)
    _, info = env.reset(seed=1)
    assert set(info) == {"tile", "position", "label", "optimal_action"}
    assert info["position"] != 4 and info["label"] == ("N" if info["position"] == 5 else str(info["position"]))
    maze = gymnasium.make("ferl/MatchingTMaze-v0", corridor_length=5, max_steps=12)
    _, info = maze.reset(seed=1)
    assert set(info) == {"position", "steps", "condition", "rewarded_side", "correct"}
    assert info["condition"] in range(4) and info["rewarded_side"] == int(info["condition"] in (0, 3))


@pytest.mark.parametrize("env_id", IDS)
def test_render_returns_an_rgb_image(env_id):
    env = gymnasium.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    env.step(0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    cells = {"ferl/DigitFloor-v0": 12, PASSIVE: 4}.get(env_id, 3)  # the passive maze: L + 1 = 4 cells up
    assert frame.shape[:2] == ((336, 336) if env_id == "ferl/DigitFloor-v0" else (cells * 28, 3 * 28))
    assert (frame == (0, 0, 255)).all(axis=2).any() or (frame == (255, 0, 0)).all(axis=2).any()  # the agent
    assert gymnasium.make(env_id).unwrapped.render() is None  # no render_mode: nothing to draw


def test_vector_render_gives_one_frame_per_env():
    vec = gymnasium.make_vec("ferl/DigitMatchingTMaze-v0", num_envs=2, render_mode="rgb_array", reservoir_size=5)
    vec.reset(seed=0)
    frames = vec.render()
    assert len(frames) == 2 and all(f.shape == (84, 84, 3) and f.dtype == np.uint8 for f in frames)


def test_digit_maze_reservoir_and_grey_levels():
    env = gymnasium.make("ferl/DigitMatchingTMaze-v0", reservoir_size=20, binarize_threshold=None)
    obs, _ = env.reset(seed=0)
    starts = {obs.tobytes()} | {env.reset()[0].tobytes() for _ in range(30)}
    assert len(starts) > 2  # two start signals, each drawn from 20 images (§5.3.2)
    assert ((obs > 0) & (obs < 1)).any() and obs in env.observation_space


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="reward_condition"):
        gymnasium.make("ferl/DigitFloor-v0", reward_condition="up")
    with pytest.raises(ValueError, match="max_steps"):
        gymnasium.make("ferl/TMaze-v0", corridor_length=5, max_steps=4)
    env = gymnasium.make("ferl/TMaze-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(4)
    vec = gymnasium.make_vec("ferl/TMaze-v0", num_envs=2)
    with pytest.raises(TypeError, match="one integer"):
        vec.reset(seed=[1, 2])


def test_default_digit_classes_are_those_of_the_config():
    cfg = OmegaConf.load(ROOT / "conf" / "env" / "digit_tmaze.yaml")
    assert OmegaConf.to_container(cfg.digit_classes) == DIGIT_CLASSES
