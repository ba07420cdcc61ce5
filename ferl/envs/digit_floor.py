"""The digit-floor task (§3.4), batched over runs.

A floor is an L×L torus of 3×3 patches (Fig. 3.1); every tile shows its own training image
of its class, and the observation is that image with a fraction ``noise`` of its 784 pixels
replaced by uniform white noise, drawn afresh at every step (Fig. 3.2). Actions N E S W move
one tile. Rewards (§3.4, R_0): +10 for a move into the goal (the patch centre, "4"), +4 for a
move along the patch boundary in the rewarded direction (CW 0→1→2→5→8→7→6→3→0, or CCW),
−2 otherwise; the ``none`` condition delivers no reward (§3.5.3, Fig. 3.10d). After entering
the goal the agent is moved to a uniformly random non-goal tile (P⁰ of §3.4).

The dynamics are position tables over tiles (next tile, reward), so a step is a few gathers.
"""

import copy
from typing import Annotated, Literal, get_args

import numpy as np
import torch

from ferl.config.params import Allowed, ArgumentError, PositiveInt, UnitInterval, checked
from ferl.data import MnistSplit, noise_draw_sizes, pixel_noise_draws, with_pixel_noise
from ferl.envs.compass import ACTIONS
from ferl.interfaces import EnvironmentBase
from ferl.random_blocks import Blocks, steps_per_block

MOVES = ((-1, 0), (0, 1), (1, 0), (0, -1))
GOAL = 4  # the patch centre (Fig. 3.3)
CW_CYCLE = (0, 1, 2, 5, 8, 7, 6, 3)
RewardCondition = Literal["cw", "ccw", "none"]
REWARD_CONDITIONS = get_args(RewardCondition)
NOISE_CLASS = "N"


def patch_move(p: int, action: int):
    """In-patch position after a move, or None when the move leaves the patch."""
    r, c = divmod(p, 3)
    r, c = r + MOVES[action][0], c + MOVES[action][1]
    return 3 * r + c if 0 <= r < 3 and 0 <= c < 3 else None


def patch_rewards(condition: str, goal: float = 10.0, boundary: float = 4.0, other: float = -2.0) -> np.ndarray:
    """Reward of every (in-patch position, action), shape (9, 4), from the definition of §3.4."""
    if condition == "none":
        return np.zeros((9, 4))
    cycle = CW_CYCLE if condition == "cw" else CW_CYCLE[::-1]
    successor = {cycle[i]: cycle[(i + 1) % len(cycle)] for i in range(len(cycle))}
    table = np.full((9, 4), other)
    for p in range(9):
        for a in range(4):
            q = patch_move(p, a)
            if q == GOAL:
                table[p, a] = goal
            elif q is not None and successor.get(p) == q:
                table[p, a] = boundary
    return table


def patch_transitions() -> np.ndarray:
    """P[p, a, q]: in-patch dynamics on the periodic floor, goal → uniform non-goal restart."""
    P = np.zeros((9, 4, 9))
    non_goal = [q for q in range(9) if q != GOAL]
    for p in range(9):
        for a in range(4):
            r, c = divmod(p, 3)
            q = 3 * ((r + MOVES[a][0]) % 3) + (c + MOVES[a][1]) % 3
            if q == GOAL:
                P[p, a, non_goal] = 1.0 / len(non_goal)
            else:
                P[p, a, q] = 1.0
    return P


def optimal_policy(rewards: np.ndarray, gamma: float = 0.9, tol: float = 1e-9):
    """Optimal actions by value iteration on the 9 patch positions (Figs. 3.3, 3.9) and the
    long-run reward per step of that policy (the stationary distribution of its chain).

    Returns (mask (9, 4) of optimal actions, action (9,) with −1 where not unique or goal, rate).
    """
    P = patch_transitions()
    V = np.zeros(9)
    for _ in range(10_000):
        Q = rewards + gamma * P @ V
        V_new = Q.max(1)
        if np.abs(V_new - V).max() < tol:
            break
        V = V_new
    mask = Q >= Q.max(1, keepdims=True) - 1e-6
    action = np.where(mask.sum(1) == 1, mask.argmax(1), -1)
    action[GOAL] = -1
    greedy = mask.argmax(1)
    chain = P[np.arange(9), greedy]
    evals, evecs = np.linalg.eig(chain.T)
    stationary = np.real(evecs[:, np.argmin(np.abs(evals - 1))])
    stationary /= stationary.sum()
    rate = float(stationary @ rewards[np.arange(9), greedy])
    return mask, action, rate


DIGITS = tuple(str(d) for d in range(10))


def is_arrangement(rows) -> bool:
    """3 rows of 3 distinct digit classes."""
    labels = [str(c) for row in rows for c in row]
    return (
        len(rows) == 3 and all(len(r) == 3 for r in rows) and len(set(labels)) == 9 and all(c in DIGITS for c in labels)
    )


class DigitFloor(EnvironmentBase):
    """``n_runs`` digit floors (one per run) stepped together; positions are tile indices. A
    continuing task (§3.4 fn. 1): no step terminates or truncates."""

    task = "digit_floor"
    action_names = ACTIONS
    n_actions = len(ACTIONS)
    pixels = 784
    observation_size = pixels  # the tile's image (``true_state``: its in-patch position)

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        data: MnistSplit,
        generator: torch.Generator,
        arrangement: Annotated[list[list[str | int]], Allowed(is_arrangement, "(3 × 3 distinct classes 0–9)")] = (
            ("0", "1", "2"),
            ("3", "4", "5"),
            ("6", "7", "8"),
        ),  # type: ignore[assignment]  # immutable default
        patches: PositiveInt = 4,
        noise: UnitInterval = 0.125,
        reward_condition: RewardCondition = "cw",
        goal_reward: float = 10.0,
        boundary_reward: float = 4.0,
        other_reward: float = -2.0,
        noise_tile: Annotated[str | int, Allowed(lambda c: str(c) in DIGITS, "(a class 0–9)")] | None = None,
        true_state: bool = False,
        device="cpu",
    ):
        self.n_runs, self.noise, self.generator, self.device = n_runs, noise, generator, torch.device(device)
        self.reward_condition, self.patches = reward_condition, patches
        # true_state: the oracle's view (``actor=oracle``), the tile's in-patch position one-hot
        # (its digit class) instead of its noisy image; the same random numbers are drawn
        self.true_state = true_state
        layout = [str(c) for row in arrangement for c in row]
        if noise_tile is not None:
            layout = [NOISE_CLASS if c == str(noise_tile) else c for c in layout]
        self.layout = layout  # class label of every in-patch position
        self.arrangement = np.array(layout).reshape(3, 3)
        self.classes = sorted(set(layout), key=lambda c: (c == NOISE_CLASS, c))

        rewards = patch_rewards(reward_condition, goal_reward, boundary_reward, other_reward)
        _, self.optimal_action, self.optimal_reward_rate = optimal_policy(rewards)
        self.class_optimal_action = self.optimal_action[[layout.index(c) for c in self.classes]]

        side = 3 * patches
        rows, cols = np.divmod(np.arange(side * side), side)
        position = 3 * (rows % 3) + cols % 3  # in-patch position of every tile
        next_tile = np.stack([((rows + dr) % side) * side + (cols + dc) % side for dr, dc in MOVES], 1)
        as_tensor = lambda x, dtype: torch.as_tensor(x, dtype=dtype, device=self.device)  # noqa: E731
        self.tile_position = as_tensor(position, torch.long)
        # (tile, action) tables flattened to tile·4 + action: one index_select per lookup
        self.next_tile = as_tensor(next_tile.reshape(-1), torch.long)
        self.tile_reward = as_tensor(rewards[position].reshape(-1), torch.float32)
        self.lands_in_goal = as_tensor((position == GOAL)[next_tile].reshape(-1), torch.bool)
        self.non_goal_tiles = as_tensor(np.flatnonzero(position != GOAL), torch.long)
        self._build_floor(data, position)
        if true_state:
            self.observation_size = len(layout)
        # a block's size from the numbers drawn a step (positions and values, per run), not from what
        # is handed on: it sets the order of the draws, so it keeps the random stream of every level
        drawn = sum(noise_draw_sizes(self.pixels, noise))
        self.noise_blocks = Blocks(self._draw_noise, steps_per_block(n_runs * (drawn + 1)))
        self.tile = self._random_non_goal()

    @classmethod
    def check_config(cls, args: dict) -> None:
        """The noise tile replaces a class of the arrangement, but not the goal (§3.5.3)."""
        tile, labels = args["noise_tile"], [str(c) for row in args["arrangement"] for c in row]
        if tile is not None and str(tile) not in labels:
            raise ArgumentError("noise_tile", f"null or a class of the arrangement {sorted(labels)}")
        if tile is not None and str(tile) == labels[4]:
            raise ArgumentError("noise_tile", "null or a class of the arrangement other than the goal (its centre)")

    def describe(self) -> dict:
        return {
            "kind": "digit_floor",
            "task": self.task,
            "episodic": False,
            "observation": "state" if self.true_state else "image",
            "true_state": self.true_state,
            "observation_size": self.observation_size,
            "n_actions": self.n_actions,
            "action_names": list(self.action_names),
            "noise": self.noise,
            "reward_condition": self.reward_condition,
            "patches": self.patches,
            "classes": list(self.classes),
            "noise_class": NOISE_CLASS,
        }

    def optimal(self, gamma: float) -> dict:
        """The long-run reward per step of the optimal policy (8 for the default floor)."""
        return {"reward_per_step": self.optimal_reward_rate}

    def step_inputs(self, steps: int) -> tuple:
        """The random numbers of the next ``steps`` steps (noisy pixels and values, transports),
        stacked, for ``step_with``: what a compiled chunk of steps takes as inputs."""
        return self.noise_blocks.take(steps)

    def _draw_noise(self, steps: int):
        """Noisy-pixel positions and values plus transport targets for ``steps`` future steps."""
        idx, values = pixel_noise_draws(steps * self.n_runs, self.pixels, self.noise, self.generator)
        transport = self.non_goal_tiles[
            torch.randint(len(self.non_goal_tiles), (steps, self.n_runs), generator=self.generator, device=self.device)
        ]
        return idx.view(steps, self.n_runs, -1), values.view(steps, self.n_runs, -1), transport

    def _build_floor(self, data: MnistSplit, position: np.ndarray) -> None:
        """Give every tile of every run its own image of its class (without replacement while the
        class has enough training images); noise tiles get independent pure-noise images."""
        bank = [data.train_images.to(self.device)]
        tile_image = torch.empty(self.n_runs, len(position), dtype=torch.long, device=self.device)
        for label in self.classes:
            tiles = torch.as_tensor(np.flatnonzero(np.array(self.layout)[position] == label), device=self.device)
            if label == NOISE_CLASS:
                offset = sum(len(b) for b in bank)
                bank.append(
                    torch.rand(self.n_runs * len(tiles), self.pixels, generator=self.generator, device=self.device)
                )
                ids = offset + torch.arange(self.n_runs * len(tiles), device=self.device).view(self.n_runs, -1)
            else:
                pool = torch.nonzero(data.train_labels.to(self.device) == int(label)).squeeze(1)
                if len(pool) == 0:
                    raise ValueError(f"env.arrangement: no training image of class {label}")
                if len(pool) >= len(tiles):
                    keys = torch.rand(self.n_runs, len(pool), generator=self.generator, device=self.device)
                    pick = keys.argsort(1)[:, : len(tiles)]
                else:
                    pick = torch.randint(
                        len(pool), (self.n_runs, len(tiles)), generator=self.generator, device=self.device
                    )
                ids = pool[pick]
            tile_image[:, tiles] = ids
        self.bank = torch.cat(bank)
        self.tile_image = tile_image

    def slice_runs(self, index: slice) -> "DigitFloor":
        """These floors restricted to a slice of the runs. Their positions are a view, so moves
        (``step_with``) land in this batch's."""
        part = copy.copy(self)
        part.tile, part.tile_image = self.tile[index], self.tile_image[index]
        part.n_runs = len(part.tile)
        return part

    def _random_non_goal(self) -> torch.Tensor:
        k = torch.randint(len(self.non_goal_tiles), (self.n_runs,), generator=self.generator, device=self.device)
        return self.non_goal_tiles[k]

    def _observe(self, idx, values) -> torch.Tensor:
        """The current tile's image with its noisy pixels replaced: (R, 784); its position one-hot
        with ``true_state``."""
        if self.true_state:
            return torch.nn.functional.one_hot(
                self.tile_position.index_select(0, self.tile), self.observation_size
            ).float()
        image = self.bank.index_select(0, self.tile_image.gather(1, self.tile.unsqueeze(1)).squeeze(1))
        # the sizes from the inputs, not from the noise level: a compiled chunk guards on each attribute
        # it reads, and every noise level would then compile a graph of its own (ferl.trainers.chunks)
        return with_pixel_noise(image, idx, values)

    def observe(self) -> torch.Tensor:
        """The current tile's image with fresh pixel noise (§3.4, Fig. 3.2)."""
        idx, values, _ = self.noise_blocks.next()
        return self._observe(idx, values)

    def reset(self) -> torch.Tensor:
        self.tile = self._random_non_goal()
        return self.observe()

    def step(self, action: torch.Tensor):
        """Move every run by its action (R,); returns (observation (R, 784), reward (R,), terminated,
        truncated), the last two always False."""
        obs, reward = self.step_with(action, *self.noise_blocks.next())
        never = torch.zeros(self.n_runs, dtype=torch.bool, device=self.device)
        return obs, reward, never, never

    def step_with(self, action: torch.Tensor, idx, values, transport):
        """``step`` with its random numbers given (one step of ``noise_blocks``), so that a
        compiled loop of several steps can take them as inputs."""
        move = self.tile * self.n_actions + action
        reward = self.tile_reward.index_select(0, move)
        moved = self.next_tile.index_select(0, move)
        self.tile.copy_(torch.where(self.lands_in_goal.index_select(0, move), transport, moved))  # in place: see runs
        return self._observe(idx, values), reward

    def state_dict(self) -> dict:
        return {
            "tile": self.tile,
            "tile_image": self.tile_image,
            "bank": self.bank,
            "noise_blocks": self.noise_blocks.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.tile, self.tile_image, self.bank = (state[k].to(self.device) for k in ("tile", "tile_image", "bank"))
        self.noise_blocks.load_state_dict(state["noise_blocks"], self.device)
