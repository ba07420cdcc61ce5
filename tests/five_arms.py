"""An environment whose sizes are none of the T-maze's, written outside ferl/ as a user would: 3
reward values, 5 actions, 6-bit observations. tests/test_sizes.py trains it with the stock
``predictor=joint`` (reward bits) and Algorithm 1 with no size typed anywhere: the predictor's 3
reward bits, its 6 inputs and the actor's 5 actions are all read off this class by the Job.

``FiveArms``: one of five arms is cued at the start (bit k of the observation), ``delay`` blank
steps follow (all bits 0), then the choice (bit 5): pulling the cued arm earns +1 and ends the
episode, any other arm −1; every other step earns 0.
"""

import torch

from ferl.config.params import PositiveInt, checked
from ferl.interfaces import EpisodicEnvironmentBase

N_ARMS = 5
OBSERVATIONS = (*(f"cue_{k}" for k in range(N_ARMS)), "blank", "choose")
STATE_KEYS = ("cue", "t", "done", "obs_id", "correct")


class FiveArms(EpisodicEnvironmentBase):
    """``n_runs`` cue-delay-choice episodes among five arms (``ferl.interfaces.EpisodicEnvironment``;
    its hooks keep the defaults of ``EpisodicEnvironmentBase``: episodes run eagerly)."""

    task = "five_arms"
    action_names = tuple(f"arm_{k}" for k in range(N_ARMS))
    n_actions = N_ARMS
    reward_values = (-1.0, 0.0, 1.0)

    @checked
    def __init__(self, n_runs: PositiveInt, generator: torch.Generator, delay: PositiveInt = 1, device="cpu"):
        self.n_runs, self.generator, self.device, self.delay = n_runs, generator, torch.device(device), delay
        table = torch.zeros(len(OBSERVATIONS), N_ARMS + 1, device=self.device)  # (ids, 6): the blank row stays 0
        table[torch.arange(N_ARMS), torch.arange(N_ARMS)] = 1.0
        table[-1, -1] = 1.0
        self.observation_table, self.observation_size, self.observation_names = table, table.shape[1], OBSERVATIONS
        self.max_steps = self.optimal_steps = delay + 1
        self.reset()

    def reset(self) -> torch.Tensor:
        self.cue = torch.randint(N_ARMS, (self.n_runs,), generator=self.generator, device=self.device)
        self.t = torch.zeros(self.n_runs, dtype=torch.long, device=self.device)
        self.done = torch.zeros(self.n_runs, dtype=torch.bool, device=self.device)
        self.correct = torch.zeros(self.n_runs, dtype=torch.bool, device=self.device)
        self.obs_id = self.cue.clone()
        return self.observe()

    def observe(self) -> torch.Tensor:
        return self.observation_table.index_select(0, self.obs_id)

    def advance(self, action: torch.Tensor):
        live, choosing = ~self.done, self.t == self.delay
        terminated = live & choosing
        self.correct = torch.where(terminated, action == self.cue, self.correct)
        reward = torch.where(terminated, torch.where(action == self.cue, 1.0, -1.0), 0.0)
        self.t = self.t + live
        self.done = self.done | terminated
        self.obs_id = torch.where(self.t >= self.delay, N_ARMS + 1, torch.where(self.t > 0, N_ARMS, self.cue))
        return reward, terminated, torch.zeros_like(terminated)

    def step(self, action: torch.Tensor):
        reward, terminated, truncated = self.advance(action)
        return self.observe(), reward, terminated, truncated

    @property
    def probe(self) -> torch.Tensor:
        return self.t == self.delay

    def labels(self) -> dict:
        return {"cue": self.cue}

    def outcomes(self) -> dict:
        return {"correct": self.correct}

    def optimal(self, gamma: float) -> dict:
        return {"discounted_return": gamma**self.delay, "steps_to_goal": self.optimal_steps}

    def describe(self) -> dict:
        return {
            "kind": "five_arms",
            "task": self.task,
            "episodic": True,
            "observation": "bits",
            "observation_size": self.observation_size,
            "n_actions": self.n_actions,
            "action_names": list(self.action_names),
            "observation_names": list(OBSERVATIONS),
            "max_steps": self.max_steps,
            "reward_values": list(self.reward_values),
            "labels": ["cue"],
            "outcomes": ["correct"],
        }

    def state_dict(self) -> dict:
        return {k: getattr(self, k).clone() for k in STATE_KEYS}

    def load_state_dict(self, state: dict) -> None:
        for k in STATE_KEYS:
            setattr(self, k, state[k].to(self.device))


class Forgetful(FiveArms):
    """FiveArms without the attributes an episodic environment declares about its observations and
    episodes, as a first draft might be: the refusal at setup names every one of them."""

    def __init__(self, n_runs: PositiveInt, generator: torch.Generator, delay: PositiveInt = 1, device="cpu"):
        super().__init__(n_runs, generator, delay, device)
        del self.observation_names, self.max_steps, self.optimal_steps
