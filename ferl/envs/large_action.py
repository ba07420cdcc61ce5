"""Sallans & Hinton (2004)'s large-action task (JMLR 5:1063–1088, §5), batched over runs.

States are K_s = 12 binary bits, actions K_a = 40 binary bits (2⁴⁰ actions). Thirteen key states,
each with a key action, are drawn at random. At every step the state is drawn uniformly at
random, independently of the action; the reward of action a in state s is the number of bits of a
that agree with the key action of the key state nearest to s in Hamming distance (ties: the
lower-numbered key state), so the optimum is K_a = 40 a step and a uniformly random action earns
K_a / 2. The next state does not depend on the action: the task rewards choosing well in a
state, which a discount γ = 0 expresses.

Actions are indices whose bits are the action (``ferl.bits``), so the task takes actions like
every environment; a run's key states and key actions come from its own stream seeded from
``seed + r``, so run r's task does not depend on n_runs.
"""

import copy
from typing import Literal

import torch

from ferl import rng
from ferl.bits import to_bits
from ferl.config.params import ArgumentError, NonNegativeInt, PositiveInt, checked
from ferl.interfaces import EnvironmentBase
from ferl.random_blocks import Blocks, steps_per_block


class LargeActionTask(EnvironmentBase):
    """Sallans & Hinton (2004)'s large-action task, batched over runs: 12-bit states drawn at
    random, 40-bit actions rewarded by their agreement with the key action of the nearest key
    state (module docstring); continuing, optimum 40 a step."""

    task = "large_action"

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        generator: torch.Generator,
        state_bits: PositiveInt = 12,
        action_bits: PositiveInt = 40,
        key_states: PositiveInt = 13,
        states: Literal["uniform", "key_states"] = "uniform",
        seed: NonNegativeInt = 0,
        device="cpu",
    ):
        self.n_runs, self.generator, self.device = n_runs, generator, torch.device(device)
        self.observation_size, self.action_bits = state_bits, action_bits
        self.n_actions, self.states = 2**action_bits, states
        self.action_names = [f"bit{k}" for k in range(action_bits)]  # what each action node means
        gens = rng.run_generators(seed, n_runs)
        self.keys = (
            torch.stack([torch.randint(2, (key_states, state_bits), generator=g) for g in gens]).float().to(self.device)
        )
        self.key_actions = (
            torch.stack([torch.randint(2, (key_states, action_bits), generator=g) for g in gens])
            .float()
            .to(self.device)
        )
        self.blocks = Blocks(self._draw_states, steps_per_block(n_runs * state_bits))
        self.state = self.blocks.next()[0].clone()

    @classmethod
    def check_config(cls, args: dict) -> None:
        """Distinct key states need 2^state_bits ≥ key_states; actions are int64 indices."""
        if 2 ** args["state_bits"] < args["key_states"]:
            raise ArgumentError("key_states", f"at most 2^state_bits = {2 ** args['state_bits']}")
        if args["action_bits"] > 62:
            raise ArgumentError("action_bits", "at most 62 (actions are 64-bit integer indices)")

    def describe(self) -> dict:
        return {
            "kind": "large_action",
            "task": self.task,
            "episodic": False,
            "observation": "bits",
            "observation_size": self.observation_size,
            "n_actions": self.n_actions,
            "action_bits": self.action_bits,
            "key_states": self.keys.shape[1],
            "states": self.states,
        }

    def optimal(self, gamma: float) -> dict:
        """Every key action matched bit for bit: ``action_bits`` a step; a random action half of it."""
        return {"reward_per_step": float(self.action_bits), "random_reward_per_step": self.action_bits / 2}

    def _draw_states(self, steps: int) -> tuple[torch.Tensor]:
        """Random states (steps, R, state_bits), as ``Blocks`` takes them: uniform over all states,
        or (``key_states``) uniform over the key states only."""
        if self.states == "uniform":
            return (
                torch.randint(
                    2, (steps, self.n_runs, self.observation_size), generator=self.generator, device=self.device
                ).float(),
            )
        pick = torch.randint(self.keys.shape[1], (steps, self.n_runs), generator=self.generator, device=self.device)
        return (self.keys[torch.arange(self.n_runs, device=self.device), pick],)

    def nearest_key(self, s: torch.Tensor) -> torch.Tensor:
        """Index (R,) of the key state nearest to s (R, state_bits) in Hamming distance."""
        return (s.unsqueeze(1) - self.keys).abs().sum(-1).argmin(1)

    def reward(self, s: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Bits of the actions (R,) that agree with the key action of s's nearest key state (R,)."""
        key_action = self.key_actions[torch.arange(self.n_runs, device=self.device), self.nearest_key(s)]
        return (to_bits(action, self.action_bits).to(key_action) == key_action).sum(-1).to(key_action)

    def reset(self) -> torch.Tensor:
        """The first state (R, state_bits): a copy, never the task's own state tensor."""
        self.state = self.blocks.next()[0].clone()
        return self.state.clone()

    def step_inputs(self, steps: int) -> tuple:
        """The next ``steps`` states (steps, R, state_bits), for ``step_with``."""
        return self.blocks.take(steps)

    def step_with(self, action: torch.Tensor, next_state: torch.Tensor):
        """The reward of ``action`` (R,) in the present state, then the next state: (next_state, reward)."""
        reward = self.reward(self.state, action)
        self.state.copy_(next_state)  # in place: a view of some runs (``slice_runs``) moves this batch's
        # observations are copies, never the task's state or a view of the drawn block: a compiled
        # chunk traced with its inputs aliased (the observation and the task's state) failed on
        # the next call, where they were not (AOT autograd compiles the aliasing it saw)
        return next_state.clone(), reward

    def step(self, action: torch.Tensor):
        """(next state (R, state_bits), reward (R,), terminated, truncated); a continuing task."""
        obs, reward = self.step_with(action, *self.blocks.next())
        never = torch.zeros(self.n_runs, dtype=torch.bool, device=self.device)
        return obs, reward, never, never

    def slice_runs(self, index: slice) -> "LargeActionTask":
        """The task restricted to a slice of the runs; its state is a view of this batch's."""
        part = copy.copy(self)
        part.state, part.keys, part.key_actions = self.state[index], self.keys[index], self.key_actions[index]
        part.n_runs = len(part.state)
        return part

    def state_dict(self) -> dict:
        return {
            "state": self.state,
            "keys": self.keys,
            "key_actions": self.key_actions,
            "blocks": self.blocks.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.state, self.keys, self.key_actions = (state[k].to(self.device) for k in ("state", "keys", "key_actions"))
        self.blocks.load_state_dict(state["blocks"], self.device)
