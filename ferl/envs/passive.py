"""The passive T-maze of Ni et al. (2023), "When do transformers shine in RL? Decoupling memory
from credit assignment" (NeurIPS; github.com/twni2016/Memory-RL, ``envs/tmaze.py``:
``TMazeClassicPassive``, registered by ``configs/envs/tmaze_passive.py``), as a mode of ferl's
T-maze (``TMaze(passive=True)``, docs/beyond.md "The passive T-maze").

Their definition, for a corridor of length L (their ``corridor_length``, the memory length):

* the agent starts on the oracle cell x = 0 and sees the cue (which goal pays) there, at the
  first step only; the corridor runs to the junction at x = L, the goals sit beside it;
* the episode lasts exactly the shortest path, L + 1 actions (``episode_length = L + 1``), and
  then ends (a finite horizon: their ``finite_horizon_terminal`` treats it as terminal);
* after the t-th action (t = 1 … L) the reward is the penalty −1/L if the agent is behind the
  shortest path, x < t ("\\sum_{t=1}^T -1/T = -1"), else 0; a step that does not move toward the
  junction falls behind for good (no action moves two cells), so every later step pays it too;
* after the last action (t = L + 1) the reward is the goal reward 1 if the agent stands in the
  cued goal, else 0 (no penalty then). That is their success: the episode ends in the cued goal.

The optimal (undiscounted) return is 1: L moves toward the junction, then the cued goal.

ferl's maze in this mode: cells 0 … L up the corridor (ferl's T_min = L + 1 cells, the junction at
cell L), so ``env.corridor_length`` is their L and ``max_steps`` their L + 1. Their actions right /
left / up / down are ferl's N / S / E, W (E/W enter the goals from the junction, a move into a
wall stays, as theirs does); their cue ±1 is ferl's signal s0 (1: the right goal). Their
ambiguous observations [0, cue] at the first step, [0, 0] on the corridor (the oracle cell
revisited included), [1, 0] at the junction and [1, ±1] in the goals are ferl's start_{s0},
corridor, junction and goal_left / goal_right bits. The goal reward is ferl's ``goal_reward``
and the penalty −goal_reward / L: ``goal_reward=1`` (``conf/experiment/passive_tmaze.yaml``) is
their rewards exactly; ``wall_reward`` and ``step_reward`` take no part.
"""

import numpy as np
import torch


def passive_penalty(corridor_length: int, goal_reward: float) -> float:
    """The penalty of a step behind the shortest path: −goal_reward / L (Ni et al.: −1/L)."""
    return -goal_reward / corridor_length


def passive_reward(
    position: torch.Tensor,
    t: torch.Tensor,
    rewarded_goal: torch.Tensor,
    max_steps: int | torch.Tensor,
    values: torch.Tensor,
) -> torch.Tensor:
    """Reward after the t-th action (R,) from the cell reached ``position`` (R,), the actions taken
    ``t`` (R,) and the cued goal's cell ``rewarded_goal`` (R,); ``values`` = (penalty, goal) (2,).
    The last action pays the goal, every other one the penalty when behind (cell < t)."""
    last = t >= max_steps
    paid = torch.where(last, position == rewarded_goal, position < t)
    return torch.where(paid, values.index_select(0, last.long()), 0.0)


def passive_optimal_return(next_position: np.ndarray, corridor_length: int, gamma: float, goal_reward: float) -> float:
    """Optimal discounted return from the start, the cue known (both cues equally likely), by
    backward induction over the L + 1 actions: V_t(p, side) = max_a r_{t+1}(p', side) +
    γ V_{t+1}(p', side), p' = next_position[p, a] (P, 4) (ferl's cells, goals last)."""
    L = corridor_length
    penalty = passive_penalty(L, goal_reward)
    V = np.zeros((next_position.shape[0], 2))  # value with no action left, per cued side (0: left goal, cell L + 1)
    for t in range(L + 1, 0, -1):  # the t-th action
        if t == L + 1:
            reward = np.stack([(next_position == L + 1 + side) * goal_reward for side in (0, 1)], -1)
        else:
            reward = np.repeat(((next_position < t) * penalty)[..., None], 2, -1)
        V = (reward + gamma * V[next_position]).max(1)  # (P, 4, 2) → (P, 2)
    return float(V[0].mean())
