"""The typed hand-off of an ended episode to the actor (``ferl.interfaces.Actor.end_episode``)."""

from typing import NamedTuple

import torch
from torch import Tensor
from torch.nn import functional as nnf


class EndedEpisode(NamedTuple):
    """Every run's ended episode, as ``Actor.end_episode`` takes it (valid during the call): as the
    lockstep episode recorded it, ``steps`` ≤ T_max long, the states at every action (steps, R, S)
    and after the last (R, 1, S), actions and raw rewards (steps, R), ``lengths`` (R,) the actions
    of each run and ``terminated`` (R,) whether it ended in a terminal state (not at T_max)."""

    states: Tensor
    last_state: Tensor
    actions: Tensor
    rewards: Tensor
    lengths: Tensor
    terminated: Tensor
    max_steps: int  # T_max

    def padded(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Per run, padded to T_max actions: states (R, T_max+1, S), actions and rewards
        (R, T_max), lengths and terminated (R,) (computed here, for the actor that needs it)."""
        pad, states = self.max_steps - len(self.actions), torch.cat([self.states.transpose(0, 1), self.last_state], 1)
        return (
            nnf.pad(states, (0, 0, 0, pad)),
            nnf.pad(self.actions.T, (0, pad)),
            nnf.pad(self.rewards.T, (0, pad)),
            self.lengths.clone(),
            self.terminated,
        )
