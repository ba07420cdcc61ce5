"""The batched environments as the Gymnasium views step them (``ferl.envs.gym``): each rebuilt on a
seed and reset run by run, with its observations, info and rendering as the views return them."""

import math
from functools import cache

import numpy as np
import torch
from gymnasium import spaces

from ferl.data import IMAGE_PIXELS, MnistEmbedded, MnistSplit
from ferl.envs.digit_floor import DigitFloor
from ferl.envs.digit_tmaze import DigitTMaze
from ferl.envs.tmaze import TMaze
from ferl.images import IMAGE_SIDE

# the observation → digit class map of conf/env/digit_tmaze.yaml (Fig. 4.20)
DIGIT_CLASSES = {
    "start_0": 0,
    "start_1": 1,
    "corridor": 2,
    "junction_0": 3,
    "junction_1": 4,
    "goal_left": 5,
    "goal_right": 6,
}
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

    def build(self, generator: torch.Generator):
        """The batched environment, its randomness drawn from ``generator``."""
        raise NotImplementedError

    def reset(self, mask: torch.Tensor) -> torch.Tensor:
        """Observations (R, …) after resetting the runs where ``mask`` (R,) is set."""
        raise NotImplementedError

    def step(self, actions: torch.Tensor):
        """(obs, reward, terminated, truncated) of every run after ``actions`` (R,)."""
        raise NotImplementedError

    def info(self) -> dict:
        raise NotImplementedError

    def render(self, run: int) -> np.ndarray:
        raise NotImplementedError


class FloorBatch(Batch):
    """Digit floors (§3.4): L×L patches of 3×3 tiles, each tile its own MNIST image, observed with a
    fraction ``noise`` of its pixels replaced by uniform noise; rewards +10 / +4 / −2 (cw, ccw) or
    none (§3.5.3); ``noise_tile`` turns a class's tiles into pure-noise images (§3.5.3 uses 5)."""

    observation_space = spaces.Box(0.0, 1.0, (IMAGE_PIXELS,), np.float32)

    def __init__(
        self,
        n_runs: int,
        noise: float = 0.125,
        reward_condition: str = "cw",
        noise_tile: int | str | None = None,
        patches: int = 4,
        data: MnistSplit | None = None,
    ):
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
        return {
            "tile": tile,
            "position": position,
            "label": np.array(self.env.layout)[position],
            "optimal_action": self.env.optimal_action[position],
        }

    def render(self, run: int) -> np.ndarray:
        """The run's floor, every tile its noise-free image, the agent's tile framed in red."""
        side = math.isqrt(self.env.tile_image.shape[1])
        tiles = self.env.bank[self.env.tile_image[run]].view(side, side, IMAGE_SIDE, IMAGE_SIDE)
        gray = to_numpy(tiles.permute(0, 2, 1, 3).reshape(side * IMAGE_SIDE, side * IMAGE_SIDE) * 255, np.uint8)
        frame = np.repeat(gray[..., None], 3, axis=2)
        row, col = divmod(int(self.env.tile[run]), side)
        cell = frame[row * IMAGE_SIDE : (row + 1) * IMAGE_SIDE, col * IMAGE_SIDE : (col + 1) * IMAGE_SIDE]
        for edge in (cell[:2], cell[-2:], cell[:, :2], cell[:, -2:]):
            edge[:] = FRAME
        return frame


class MazeBatch(Batch):
    """T-mazes with 7-bit observations (Fig. 4.3): regular (§4.3.1) or matching (§4.3.2); rewards
    ±5 at the goals, −1 for a wall bump, −0.1 otherwise; cut off after ``max_steps`` actions. Or
    (``passive=True``) Ni et al.'s passive T-maze of corridor ``corridor_length`` (``ferl.envs.passive``)."""

    observation_space: spaces.Space = spaces.MultiBinary(7)

    def __init__(
        self,
        n_runs: int,
        corridor_length: int = 3,
        max_steps: int | None = 10,
        matching: bool = False,
        passive: bool = False,
        goal_reward: float = 5.0,
    ):
        self.maze = dict(
            corridor_length=corridor_length,
            max_steps=max_steps,
            matching=matching,
            passive=passive,
            goal_reward=goal_reward,
        )
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
        return {
            "position": to_numpy(env.position),
            "steps": to_numpy(env.t),
            "condition": to_numpy(env.condition),
            "rewarded_side": to_numpy(env.rewarded_side),
            "correct": to_numpy(env.correct),
        }

    def render(self, run: int) -> np.ndarray:
        """The maze, corridor up the middle, goals green (rewarded) / red, the agent blue; with
        image observations the agent's cell shows what it sees."""
        env, T = self.env, self.env.corridor_length
        frame = np.full((T * IMAGE_SIDE, 3 * IMAGE_SIDE, 3), WALL, np.uint8)

        def cell(position: int) -> np.ndarray:
            row, col = (T - 1 - position, 1) if position < T else (0, 0 if position == T else 2)
            return frame[row * IMAGE_SIDE : (row + 1) * IMAGE_SIDE, col * IMAGE_SIDE : (col + 1) * IMAGE_SIDE]

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

    def __init__(
        self,
        n_runs: int,
        corridor_length: int = 3,
        max_steps: int = 10,
        reservoir_size: int = 1,
        binarize_threshold: float | None = 0.5,
        image_index: int = 0,
        digit_classes: dict | None = None,
        data: MnistSplit | None = None,
    ):
        self.digits = dict(
            data=embedded_mnist() if data is None else data,
            digit_classes=DIGIT_CLASSES if digit_classes is None else digit_classes,
            image_index=image_index,
            reservoir_size=reservoir_size,
            binarize_threshold=binarize_threshold,
        )
        super().__init__(n_runs, corridor_length, max_steps, matching=True)

    def build(self, generator: torch.Generator) -> TMaze:
        return DigitTMaze(self.n_runs, generator, **self.digits, **self.maze)
