"""Regular and matching T-mazes (§4.3.1, §4.3.2; Bakker 2002), batched over runs.

A vertical corridor of T_min cells (start at the bottom, index 0; the T-junction at the top,
index T_min − 1) ends in a left and a right goal, so the shortest path takes T_min actions.
Actions N E S W; E/W enter the goals from the junction and bump a wall elsewhere. Rewards:
±5 at the rewarded / other goal (the episode terminates), −1 for a wall bump (no move), −0.1
otherwise; the episode is cut off after T_max actions. Regular maze: a signal s0 shown at the
start, s0 = 1 rewards the right goal. Matching maze: s0 at the start and s1 at the junction,
s0 = s1 rewards the right goal (§4.3.2). Passive maze (``passive=True``): Ni et al. (2023)'s
passive T-maze, the episode exactly the shortest path, rewards of their definition
(``ferl.envs.passive``).

Observations are ids into ``observation_table``: 7 bits (5 position + 2 signal, Fig. 4.3), one
fixed image per observation (the digit matching T-maze, §4.3.3), or a reservoir of K images per
observation from which every visit draws one afresh (§5.3.2): observation n, image k has id
n·K + k. The dynamics are (position, action) tables, so a step is a few gathers.
"""

from typing import Annotated

import numpy as np
import torch

from ferl.config.params import ArgumentError, PositiveInt, at_least, checked
from ferl.envs.compass import ACTIONS, E, N, S, W
from ferl.envs.passive import passive_optimal_return, passive_penalty, passive_reward
from ferl.interfaces import EpisodicEnvironmentBase

POSITION_BITS = ("start", "corridor", "junction", "goal_left", "goal_right")
STATE_KEYS = ("position", "t", "done", "initial_signal", "junction_signal", "obs_id")


def observation_names(matching: bool) -> tuple:
    """Every distinct observation of the maze (the corridor one is never seen when T_min = 2)."""
    junction = ("junction_0", "junction_1") if matching else ("junction",)
    return ("start_0", "start_1", "corridor", *junction, "goal_left", "goal_right")


def true_state_names(corridor_length: int) -> tuple:
    """Every true state (position, s0, s1) of the maze, in id order position·4 + 2·s0 + s1 (the
    regular maze uses s1 = 0 only)."""
    places = ("start", *(f"corridor{p}" for p in range(1, corridor_length - 1)), "junction", "goal_left", "goal_right")
    return tuple(f"{place}_s{s0}{s1}" for place in places for s0 in (0, 1) for s1 in (0, 1))


def observation_bits(name: str) -> np.ndarray:
    """The 7-bit code of an observation: its position bit, plus bit 5 + v for a shown signal v."""
    place, _, signal = name.rpartition("_") if name[-1].isdigit() else (name, "", "")
    bits = np.zeros(len(POSITION_BITS) + 2, dtype=np.float32)
    bits[POSITION_BITS.index(place)] = 1.0
    if signal:
        bits[len(POSITION_BITS) + int(signal)] = 1.0
    return bits


def maze_tables(corridor_length: int, goal: float, wall: float, step: float):
    """Next position and reward of every (position, action, rewarded side) from the definition.

    Positions 0 … T_min − 1 run up the corridor, T_min / T_min + 1 are the left / right goal;
    goal rows (never acted from) stay put. Returns next (P, 4) and reward (P, 4, 2), side 0 = left.
    """
    junction, left, right = corridor_length - 1, corridor_length, corridor_length + 1
    nxt = np.tile(np.arange(corridor_length + 2)[:, None], (1, 4))
    reward = np.full((corridor_length + 2, 4, 2), float(wall))
    for p in range(corridor_length):
        moves = {
            N: p + 1 if p < junction else None,
            S: p - 1 if p > 0 else None,
            E: right if p == junction else None,
            W: left if p == junction else None,
        }
        for a, q in moves.items():
            if q is None:
                continue
            nxt[p, a] = q
            reward[p, a] = step if q < left else [goal if q - left == side else -goal for side in (0, 1)]
    return nxt, reward


def optimal_return(corridor_length: int, max_steps: int, gamma: float, goal: float, wall: float, step: float) -> float:
    """Optimal discounted return from the start with the state fully observed (the upper bound
    R_0 of Figs. 4.6, 4.11), by finite-horizon value iteration over the T_max actions."""
    nxt, reward = maze_tables(corridor_length, goal, wall, step)
    terminal = nxt >= corridor_length  # a goal entry ends the episode
    V = np.zeros((corridor_length + 2, 2))  # value with k actions left, per rewarded side
    for _ in range(max_steps):
        V = (reward + gamma * np.where(terminal[..., None], 0.0, V[nxt])).max(1)
    return float(V[0].mean())


class TMaze(EpisodicEnvironmentBase):
    """``n_runs`` T-mazes stepped together; ``done`` runs stay frozen until ``reset``
    (``ferl.interfaces.EpisodicEnvironment``)."""

    task = "tmaze"
    traceable_steps = True  # ``advance`` is tensor operations only: an episode can be one compiled graph
    action_names = ACTIONS
    n_actions = len(ACTIONS)

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        generator: torch.Generator,
        corridor_length: Annotated[int, at_least(2, "start, corridor cells, junction")] = 3,
        max_steps: PositiveInt | None = 10,
        matching: bool = False,
        goal_reward: float = 5.0,
        wall_reward: float = -1.0,
        step_reward: float = -0.1,
        true_state: bool = False,
        images=None,
        device="cpu",
        passive: bool = False,
    ):
        self.n_runs, self.generator, self.device = n_runs, generator, torch.device(device)
        # passive: corridor_length is Ni et al.'s L, the junction L cells up, so the maze has
        # L + 1 cells and its episode L + 1 actions (ferl.envs.passive); self.corridor_length is
        # the number of cells (T_min) in both modes
        self.passive, self.configured_length = passive, corridor_length
        if passive:
            corridor_length += 1
            max_steps = corridor_length
        assert max_steps is not None  # null only with passive (check_config)
        self.corridor_length, self.max_steps, self.matching = corridor_length, max_steps, matching
        # T_min and T_max as the steps read them: tensors, not constants of a compiled graph, so
        # that one graph serves every corridor (``tables_generic``)
        self._cells = torch.tensor(corridor_length, device=self.device)
        self._horizon = torch.tensor(max_steps, device=self.device)
        self.optimal_steps = corridor_length
        self.rewards = (goal_reward, wall_reward, step_reward)
        self.reward_values = tuple(sorted({-goal_reward, goal_reward, wall_reward, step_reward}))
        if passive:  # a reward of 0 (on schedule, the other goal) is no bit at all, as a done run's
            self.reward_values = (passive_penalty(self.configured_length, goal_reward), goal_reward)
        self._reward_values = torch.tensor(self.reward_values, dtype=torch.float32, device=self.device)

        self.observation_names = observation_names(matching)
        self.observation_kind = "bits" if images is None else "image"
        if images is None:
            table = torch.as_tensor(np.stack([observation_bits(n) for n in self.observation_names]))
        else:
            missing = [n for n in self.observation_names if n not in images]
            if missing:
                raise ValueError(f"images: no image for observation(s) {missing}")
            # each entry (V,) or a reservoir (K, V); all observations share one K
            entries = [torch.as_tensor(images[n], dtype=torch.float32) for n in self.observation_names]
            entries = [x.reshape(-1, x.shape[-1]) for x in entries]
            if len({len(x) for x in entries}) > 1:
                raise ValueError("images: every observation needs a reservoir of the same size")
            table = torch.cat(entries)
        self.reservoir_size = table.shape[0] // len(self.observation_names)
        # true_state: the oracle's view (``actor=oracle``), the hidden state (position, s0, s1)
        # one-hot instead of what the agent would see. Ids become true states (K rows each, as a
        # reservoir's images), so every lookup and random draw stays as it is.
        self.true_state = true_state
        if true_state:
            self.observation_names, self.observation_kind = true_state_names(corridor_length), "state"
            table = torch.eye(len(self.observation_names)).repeat_interleave(self.reservoir_size, 0)
        self.observation_table = table.to(self.device)
        # the passive maze shows its cue at the first step only (the oracle's true state is as it is)
        self._start_revisited = self.observation_names.index("corridor") if passive and not true_state else None
        self.observation_size = self.observation_table.shape[1]

        nxt, reward = maze_tables(corridor_length, *self.rewards)
        # flattened tables: (position, action) → position·4 + action, times 2 + rewarded side
        self.next_position = torch.as_tensor(nxt.reshape(-1), dtype=torch.long, device=self.device)
        self.move_reward = torch.as_tensor(reward.reshape(-1), dtype=torch.float32, device=self.device)
        self.observation_id_table = torch.as_tensor(self._observation_ids().reshape(-1), device=self.device)
        self.reset()

    @classmethod
    def check_config(cls, args: dict) -> None:
        length, max_steps = args["corridor_length"], args["max_steps"]
        if args.get("passive"):
            if args["matching"]:
                raise ArgumentError("matching", "false with passive=true (Ni et al.'s passive T-maze has one cue)")
            if max_steps not in (None, length + 1):
                raise ArgumentError(
                    "max_steps",
                    f"null or corridor_length + 1 = {length + 1} with passive=true (the episode is the shortest path)",
                )
        elif max_steps is None:
            raise ArgumentError("max_steps", "a positive integer (null only with passive=true)")
        elif max_steps < length:
            raise ArgumentError("max_steps", f"T_max ≥ corridor_length={length} (T_min)")

    def describe(self) -> dict:
        return {
            "kind": "tmaze",
            "task": self.task,
            "episodic": True,
            "observation": self.observation_kind,
            "observation_size": self.observation_size,
            "n_actions": self.n_actions,
            "action_names": list(self.action_names),
            "true_state": self.true_state,
            "matching": self.matching,
            "corridor_length": self.configured_length,
            **({"passive": True} if self.passive else {}),  # the other mazes' records stay as they were
            "max_steps": self.max_steps,
            "goal_reward": self.rewards[0],
            "reward_values": list(self.reward_values),
            "observation_names": list(self.observation_names),
            "reservoir_size": self.reservoir_size,
            "labels": list(self.labels()),
            "outcomes": list(self.outcomes()),
        }

    def tables_generic(self, generic) -> None:
        """The (position, action) and (position, signals) tables, (L + 2)·4 rows and more, through
        ``generic``: a compiled episode's graph then serves every corridor length."""
        self.next_position, self.move_reward = generic(self.next_position), generic(self.move_reward)
        self.observation_id_table = generic(self.observation_id_table)

    def _observation_ids(self) -> np.ndarray:
        """Observation id of every (position, s0, s1), shape (P, 2, 2)."""
        if self.true_state:  # id = position·4 + 2·s0 + s1 (``true_state_names``)
            return np.arange((self.corridor_length + 2) * 4).reshape(-1, 2, 2)
        ids = {n: i for i, n in enumerate(self.observation_names)}
        junction = self.corridor_length - 1
        table = np.full((self.corridor_length + 2, 2, 2), ids["corridor"], dtype=np.int64)
        for s0 in (0, 1):
            for s1 in (0, 1):
                table[0, s0, s1] = ids[f"start_{s0}"]
                table[junction, s0, s1] = ids[f"junction_{s1}" if self.matching else "junction"]
        table[junction + 1], table[junction + 2] = ids["goal_left"], ids["goal_right"]
        return table

    def _signal(self) -> torch.Tensor:
        return torch.randint(2, (self.n_runs,), generator=self.generator, device=self.device)

    @property
    def observation_class(self) -> torch.Tensor:
        """Index into ``observation_names`` of what every run sees now; the passive maze shows
        the cue at the first step only (its start revisited looks like the corridor)."""
        seen = self.observation_id_table.index_select(0, torch.add(self._signals, self.position, alpha=4))
        if self._start_revisited is not None:
            seen = torch.where((self.position == 0) & (self.t > 0), self._start_revisited, seen)
        return seen

    def _draw_observation(self) -> None:
        """Fix the observation id of the current visit; a reservoir draws a fresh image (§5.3.2),
        the one ``reset`` drew for this run's time step."""
        self.obs_id = self.observation_class
        if self.reservoir_size > 1:
            k = self.reservoir_draws.gather(0, self.t.unsqueeze(0)).squeeze(0)
            self.obs_id = self.obs_id * self.reservoir_size + k

    @property
    def condition(self) -> torch.Tensor:
        """Task condition: s0 (regular) or 2·s0 + s1 (matching)."""
        return 2 * self.initial_signal + self.junction_signal if self.matching else self.initial_signal

    @property
    def rewarded_side(self) -> torch.Tensor:
        """0 = left, 1 = right goal rewarded."""
        return (self.initial_signal == self.junction_signal).long() if self.matching else self.initial_signal

    @property
    def rewarded_goal(self) -> torch.Tensor:
        return self._cells + self.rewarded_side

    @property
    def at_junction(self) -> torch.Tensor:
        return self.position == self._cells - 1

    @property
    def probe(self) -> torch.Tensor:
        """The records keep the activations at the T-junction (Figs. 4.14–4.19)."""
        return self.at_junction

    def labels(self) -> dict:
        """What a junction visit is labelled with: the condition and both signals (−1: none)."""
        return {
            "condition": self.condition,
            "initial_signal": self.initial_signal,
            "junction_signal": self.junction_signal,
        }

    def outcomes(self) -> dict:
        """Facts of an ended episode: whether it ended in the rewarded goal, and its condition."""
        return {"correct_goal": self.correct, "condition": self.condition}

    @property
    def correct(self) -> torch.Tensor:
        """The episode ended in the rewarded goal (valid once ``done``)."""
        return self.position == self.rewarded_goal

    def observe(self) -> torch.Tensor:
        return self.observation_table.index_select(0, self.obs_id)

    def reset(self) -> torch.Tensor:
        """Start a new episode in every run with fresh signals."""
        zeros = torch.zeros(self.n_runs, dtype=torch.long, device=self.device)
        self.position, self.t = zeros, zeros.clone()
        self.done = torch.zeros(self.n_runs, dtype=torch.bool, device=self.device)
        signals = (self._signal(), self._signal() if self.matching else torch.full_like(zeros, -1))
        if self.reservoir_size > 1:
            # the images of every step of the episode, drawn now: how many random numbers an
            # episode takes then does not depend on how long any run's episode lasts, so runs
            # of a batch never shift each other's random streams (a diverged run included)
            self.reservoir_draws = torch.randint(
                self.reservoir_size, (self.max_steps + 1, self.n_runs), generator=self.generator, device=self.device
            )
        self.set_signals(*signals)
        return self.observe()

    def set_signals(self, initial: torch.Tensor, junction: torch.Tensor | None = None) -> None:
        """Set the episode's signals s0 (and s1) (R,), and what they fix for the whole episode:
        the rewarded side and the signals' column of the (position, s0, s1) observation table,
        so that a step is table lookups only."""
        self.initial_signal = initial
        if junction is not None:
            self.junction_signal = junction
        self._fix_episode()
        self._draw_observation()

    def _fix_episode(self) -> None:
        """What the signals fix for the episode: the rewarded side and the signals' table column."""
        self._side = self.rewarded_side
        self._signals = 2 * self.initial_signal + self.junction_signal.clamp(min=0)

    def advance(self, action: torch.Tensor):
        """Move every live run by its action (R,), fix the new observation id; returns (reward,
        terminated, truncated). Runs that are done stay put and get reward 0."""
        live = ~self.done
        move = torch.add(action, self.position, alpha=4)
        reward = torch.where(live, self.move_reward.index_select(0, torch.add(self._side, move, alpha=2)), 0.0)
        self.position = torch.where(live, self.next_position.index_select(0, move), self.position)
        self.t = self.t + live
        if self.passive:  # a finite horizon: the (L + 1)-th action ends every episode (ferl.envs.passive)
            paid = passive_reward(self.position, self.t, self.rewarded_goal, self._horizon, self._reward_values)
            reward = torch.where(live, paid, 0.0)
            terminated = live & (self.t >= self._horizon)
        else:
            terminated = live & (self.position >= self._cells)
        truncated = live & ~terminated & (self.t >= self._horizon)
        self.done = self.done | terminated | truncated
        self._draw_observation()
        return reward, terminated, truncated

    def step(self, action: torch.Tensor):
        """``advance`` and the new observations: (obs, reward, terminated, truncated)."""
        reward, terminated, truncated = self.advance(action)
        return self.observe(), reward, terminated, truncated

    def reward_code(self, reward: torch.Tensor) -> torch.Tensor:
        """One bit per reward value (§4.2 fn. 1), (R, len(reward_values)); all zero for a reward of 0 (done runs)."""
        return (reward.unsqueeze(1) == self._reward_values).float()

    def optimal_discounted_return(self, gamma: float) -> float:
        if self.passive:
            next_position = self.next_position.view(-1, 4).cpu().numpy()
            return passive_optimal_return(next_position, self.configured_length, gamma, self.rewards[0])
        return optimal_return(self.corridor_length, self.max_steps, gamma, *self.rewards)

    def optimal(self, gamma: float) -> dict:
        return {"discounted_return": self.optimal_discounted_return(gamma), "steps_to_goal": self.optimal_steps}

    def state_dict(self) -> dict:
        return {k: getattr(self, k).clone() for k in STATE_KEYS}

    def load_state_dict(self, state: dict) -> None:
        for k in STATE_KEYS:
            setattr(self, k, state[k].to(self.device))
        self._fix_episode()
