"""A toy environment and a toy predictor, written outside ferl/ as a user would write their own: the
test of issue 1/8 that a new component is one module and one YAML (tests/toy/conf), built and
trained through the interfaces of ferl.interfaces alone (tests/test_extension.py).

``CueEnv``: a cue bit at the start, ``delay`` blank steps, then a choice: action 0/1 earns +1 when
it equals the cue, −1 otherwise, and ends the episode. ``TracePredictor``: an exponential trace of
the observations, m_t = λ m_{t−1} + (1 − λ) y_{t−1}, m_0 = 0, whose output heads (ferl's) learn by
full-batch gradient descent; the trace keeps λ^delay of the cue, so an actor that sees it can choose.
"""

import torch
from torch import nn

from ferl.config.params import Positive, PositiveInt, UnitInterval, checked
from ferl.interfaces import EpisodicEnvironmentBase, TrainingBatchBase
from ferl.predictors.heads import OutputHeads, clean, valid_steps

OBSERVATIONS = ("start_0", "start_1", "blank", "choose")
STATE_KEYS = ("cue", "t", "done", "obs_id")


class CueEnv(EpisodicEnvironmentBase):
    """``n_runs`` cue-delay-choice episodes stepped together (``ferl.interfaces.EpisodicEnvironment``)."""

    task = "cue"
    action_names = ("left", "right")
    n_actions = 2
    reward_values = (-1.0, 0.0, 1.0)

    @checked
    def __init__(self, n_runs: PositiveInt, generator: torch.Generator, delay: PositiveInt = 2, device="cpu"):
        self.n_runs, self.generator, self.device, self.delay = n_runs, generator, torch.device(device), delay
        self.observation_names = OBSERVATIONS
        self.observation_table = torch.eye(len(OBSERVATIONS), device=self.device)
        self.observation_size = len(OBSERVATIONS)
        self.max_steps = self.optimal_steps = delay + 1
        self.reset()

    def reset(self) -> torch.Tensor:
        self.cue = torch.randint(2, (self.n_runs,), generator=self.generator, device=self.device)
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
        self.obs_id = torch.where(self.t >= self.delay, 3, torch.where(self.t > 0, 2, self.cue))
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
        return {"correct": self.correct, "cue": self.cue}

    def optimal(self, gamma: float) -> dict:
        return {"discounted_return": gamma**self.delay, "steps_to_goal": self.optimal_steps}

    def describe(self) -> dict:
        return {
            "kind": "cue",
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
            "outcomes": ["correct", "cue"],
        }

    def state_dict(self) -> dict:
        return {k: getattr(self, k).clone() for k in STATE_KEYS}

    def load_state_dict(self, state: dict) -> None:
        for k in STATE_KEYS:
            setattr(self, k, state[k].to(self.device))


class TracePredictor(OutputHeads):
    """An exponential trace of the observations with ferl's output heads (``ferl.interfaces.Predictor``)."""

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        n_obs: PositiveInt,
        n_actions: PositiveInt,
        decay: UnitInterval = 0.5,
        lr: Positive = 0.5,
        seed: int = 0,
    ):
        super().__init__()
        gens = [torch.Generator().manual_seed(seed + r) for r in range(n_runs)]

        def gaussian(*shape):
            return nn.Parameter(torch.stack([torch.randn(*shape, generator=g) for g in gens]) * 0.1)

        self.init_heads(gaussian, n_obs, n_obs, 1, "linear", True, (1.0, 1.0), (1.0, 1.0))
        self.decay, self.lr, self.memory_size, self.n_runs = decay, lr, n_obs, n_runs

    @property
    def batch_key(self):
        return id(self)  # nothing to share: it trains alone

    @classmethod
    def training_batch(cls, members, y, a, rs, lengths, batch_size=None, summed=False):
        (member,), (r,) = members, rs
        return TraceBatch(member, y, a, r, lengths)

    def initial_state(self) -> torch.Tensor:
        return torch.zeros(self.n_runs, self.memory_size, device=self.b_y.device)

    def memory(self, state: torch.Tensor) -> torch.Tensor:
        return state

    def step(self, m: torch.Tensor, y_prev: torch.Tensor, a_prev: torch.Tensor) -> torch.Tensor:
        return self.decay * m + (1 - self.decay) * y_prev

    def frozen_step(self, table: torch.Tensor, n_actions: int):
        runs = torch.arange(self.n_runs, device=table.device)
        return lambda m, obs_id, action: self.step(m, table[runs, obs_id] if table.dim() == 3 else table[obs_id], None)

    def unroll(self, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        m = [torch.zeros(*y.shape[:2], self.memory_size, device=y.device)]
        for t in range(y.shape[2] - 1):
            m.append(self.step(m[-1], y[:, :, t], None))
        return torch.stack(m, 2)

    def describe(self) -> dict:
        return {"kind": "trace", "memory_size": self.memory_size, **self.describe_heads()}


class TraceBatch(TrainingBatchBase):
    """One full-batch gradient step of the heads per epoch (the trace itself does not learn)."""

    def __init__(self, member: TracePredictor, y, a, r, lengths):
        self.member = member
        self.y, self.a, self.r = clean(y, a, r, lengths)
        self.steps = valid_steps(lengths, y.shape[2]).float() / lengths.shape[1]

    @torch.no_grad()
    def train_epoch(self, orders) -> None:
        m = self.member.unroll(self.y, self.a)
        reward_steps = self.steps * (torch.arange(self.y.shape[2]) > 0)
        grads, _ = self.member.head_gradients(m, self.y, self.r, self.steps, reward_steps)
        torch._foreach_add_(self.member.head_parameters(), grads, alpha=-self.member.lr)
