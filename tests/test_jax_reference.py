"""The JAX reference of the recurrent Q-learner (benchmarks/jax_reference.py) against ferl: its
passive T-maze step by step against ferl.envs.tmaze.TMaze(passive=True), an episode it plays
replayed in ferl's maze, its returns and optimum, and its TD loss at zero weights. Skipped where
JAX is not installed (it is an optional dependency: ``pip install -e '.[jax]'``)."""

import importlib.util
import itertools
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402

from ferl.envs.tmaze import TMaze  # noqa: E402

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "jax_reference.py"
_spec = importlib.util.spec_from_file_location("ferl_benchmarks_jax_reference", _PATH)
ref = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = ref
_spec.loader.exec_module(ref)

GOAL = 5.0


def ferl_maze(L: int, cues: np.ndarray) -> TMaze:
    """ferl's passive maze, one run per cue, its cues set."""
    env = TMaze(
        len(cues), torch.Generator().manual_seed(0), corridor_length=L, max_steps=None, passive=True, goal_reward=GOAL
    )
    env.set_signals(torch.as_tensor(cues, dtype=torch.long))
    return env


def ferl_episodes(L: int, cues: np.ndarray, actions: np.ndarray):
    """ferl's observation bits (T+1, n, 7), rewards and terminations (T, n) of action sequences (n, T)."""
    env = ferl_maze(L, cues)
    observations, rewards, terminated = [env.observe().numpy()], [], []
    for a in torch.as_tensor(actions, dtype=torch.long).T:
        obs, r, term, _ = env.step(a)
        observations.append(obs.numpy())
        rewards.append(r.numpy())
        terminated.append(term.numpy())
    return np.stack(observations), np.stack(rewards), np.stack(terminated)


@pytest.mark.parametrize("L", [2, 3, 6])
def test_env_step_is_ferls_passive_maze(L):
    """Every action sequence (L = 2), or 200 random ones, with both cues: the same observation
    bits, rewards and terminations as ferl's maze at every step."""
    T = L + 1
    if L == 2:
        actions = np.array(list(itertools.product(range(4), repeat=T)))
    else:
        actions = np.random.default_rng(L).integers(0, 4, (200, T))
        actions[:4] = [[0] * L + [a] for a in range(4)]  # the shortest path, then every action
    actions = np.concatenate([actions, actions])
    cues = np.repeat([0, 1], len(actions) // 2)
    observations, rewards, terminated = ferl_episodes(L, cues, actions)
    step = jax.jit(jax.vmap(lambda p, t, c, a: ref.env_step(p, t, c, a, L, GOAL)))
    seen = jax.jit(jax.vmap(lambda p, t, c: ref.observation(p, t, c, L)))
    position = t = jnp.zeros(len(cues), jnp.int32)
    cue = jnp.asarray(cues)
    np.testing.assert_array_equal(ref.OBS_BITS[np.asarray(seen(position, t, cue))], observations[0])
    for k in range(T):
        position, t, r = step(position, t, cue, jnp.asarray(actions[:, k]))
        np.testing.assert_array_equal(ref.OBS_BITS[np.asarray(seen(position, t, cue))], observations[k + 1])
        np.testing.assert_allclose(np.asarray(r), rewards[k], rtol=1e-6)
        np.testing.assert_array_equal(np.asarray(t) >= T, terminated[k])
    # the shortest path pays the goal in the cued goal only
    assert rewards[-1, [0, 1, 3]].tolist() == [0.0, 0.0, GOAL] and rewards[-1, len(cues) // 2 + 1] == GOAL


def test_played_episode_replays_in_ferls_maze():
    """Episodes the reference plays (β = 0 and β = 5, random weights) give, replayed action by
    action in ferl's maze with their cue, the same observations, rewards and goal outcome."""
    L, n = 4, 16
    cfg = ref.Config(corridor=L)
    shapes = jax.eval_shape(lambda: ref.init_params(jax.random.PRNGKey(0), cfg.n_hidden))
    rng = np.random.default_rng(3)
    params = {name: rng.uniform(-0.5, 0.5, x.shape).astype(np.float32) for name, x in shapes.items()}

    @jax.jit
    def play(params, key, beta):  # one compile: the episodes' keys split inside
        return jax.vmap(lambda k: ref.play(params, k, beta, cfg))(jax.random.split(key, n))

    for beta in (0.0, 5.0):
        obs, actions, rewards, correct = play(params, jax.random.PRNGKey(int(beta)), beta)
        obs, actions = np.asarray(obs, np.int64), np.asarray(actions, np.int64)
        cues = obs[:, 0] - ref.START
        observations, ferl_rewards, _ = ferl_episodes(L, cues, actions)
        np.testing.assert_array_equal(ref.OBS_BITS[obs.T], observations)
        np.testing.assert_allclose(np.asarray(rewards).T, ferl_rewards, rtol=1e-6)
        np.testing.assert_array_equal(np.asarray(correct), ferl_rewards[-1] == GOAL)


def test_returns_and_optimum():
    """Σ_t γ^t r_{t+1} and Σ_t r_{t+1} of rewards written out; the optimum is ferl's."""
    rewards = np.random.default_rng(0).normal(size=(3, 7)).astype(np.float32)
    discounted, undiscounted = ref.returns(jnp.asarray(rewards), 0.9)
    expected = [sum(0.9**t * r for t, r in enumerate(row)) for row in rewards]
    np.testing.assert_allclose(np.asarray(discounted), expected, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(undiscounted), rewards.sum(1), rtol=1e-5)
    for L in (2, 5, 10, 50):
        ferl_optimum = ferl_maze(L, np.array([0])).optimal_discounted_return(0.95)
        assert ref.optimal_return(L, 0.95, GOAL) == pytest.approx(ferl_optimum, rel=1e-12)


def test_loss_at_zero_weights_is_the_rewards_huber():
    """With every weight 0, Q = 0 for online and target network: each TD error is −r_{t+1}, so
    the loss is the mean Huber of the rewards, and the gradient reaches every parameter."""
    L, B = 3, 5
    rng = np.random.default_rng(2)
    shapes = jax.eval_shape(lambda: ref.init_params(jax.random.PRNGKey(0), 8))
    p = {name: np.zeros(x.shape, np.float32) for name, x in shapes.items()}
    obs = rng.integers(0, 6, (B, L + 2)).astype(np.int8)
    actions = rng.integers(0, 4, (B, L + 1)).astype(np.int8)
    rewards = rng.choice([-2.0, -0.5, 0.0, 5.0], (B, L + 1)).astype(np.float32)
    value, g = jax.jit(jax.value_and_grad(ref.loss), static_argnums=5)(p, p, obs, actions, rewards, 0.95)
    expected = np.where(np.abs(rewards) < 1, 0.5 * rewards**2, np.abs(rewards) - 0.5).mean()
    assert float(value) == pytest.approx(expected, rel=1e-6)
    assert np.abs(np.asarray(g["b_q"])).sum() > 0
