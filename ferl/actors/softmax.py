"""What every actor with an enumerable set of actions shares (§3.2): the clamped softmax of
Eq. (3.11) over every action's energy F = −Q, the TD rules' bootstrap terms, and α and β following
the actor's schedules over training. Actors say only how they evaluate and update Q
(``evaluate``, ``learn``); the FERL actor adds its factored actions and Gibbs sampling.

All parameters carry the run dimension first and are buffers, so ``slice_runs`` can hand out views of
a slice of the runs whose updates land in the whole batch.
"""

import copy
from collections.abc import Callable
from typing import Literal, NamedTuple, get_args

import torch
from hydra.utils import instantiate
from torch import nn

from ferl import rng
from ferl.config.params import ArgumentError, Discount, NonNegativeInt, PositiveInt
from ferl.interfaces import ActorBase

TDRule = Literal["sarsa", "q", "expected_sarsa"]
TD_RULES = get_args(TDRule)


class ActorSizes(NamedTuple):
    """The sizes an actor is built with: runs R, state nodes S, actions nA (the environment's)."""

    runs: int
    state: int
    actions: int


def pick(x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Entries of the chosen actions on the online path: x (R, 1, nA, ...) at a (R, 1) → (R, 1, ...)."""
    flat = x.reshape(-1, *x.shape[3:]) if x.dim() > 3 else x.reshape(-1)
    index = a.squeeze(1) + torch.arange(0, flat.shape[0], x.shape[2], device=a.device)
    return flat.index_select(0, index).unsqueeze(1)


def sample_categorical(probs: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """One draw per row of probs (..., n) by inverting the CDF at uniforms u (..., 1)."""
    index = (probs.cumsum(-1) < u).sum(-1)
    return index.clamp_(max=probs.shape[-1] - 1)


def schedule(node):
    """A schedule given as an object, or as its config node (``_target_``: ``ferl.schedules``)."""
    return instantiate(node) if isinstance(node, dict) else node


def check_schedules(args: dict) -> None:
    """α and β of the schedules at the start and the end of training (both monotone)."""
    lr, beta = schedule(args["lr"]), schedule(args["beta"])
    if not all(lr(p) > 0 for p in (0.0, 1.0)):
        raise ArgumentError("lr", "a schedule of learning rates > 0")
    if not all(beta(p) >= 0 for p in (0.0, 1.0)):
        raise ArgumentError("beta", "a schedule of inverse temperatures ≥ 0")


class SoftmaxActor(ActorBase, nn.Module):
    """An actor choosing among its n actions by Eq. (3.11) and learning by a TD rule (§3.2).

    Its constructor takes what every such actor is given; a subclass takes its own keys by keyword
    and passes these on (``**softmax``), sets ``lr_divisor`` if α is normalised, and gives
    ``evaluate(s) → (F (R, B, nA), cache (R, B, nA, ·))`` and ``learn`` (or ``end_episode``);
    ``ActorBase`` gives the other hooks' defaults."""

    shared_buffers: tuple = ()  # buffers without a run dimension (``slice_runs`` keeps them whole)
    td_rule: str  # a TDRule
    gamma: float
    lr_schedule: Callable[[float], float]  # α at a fraction of training done
    beta_schedule: Callable[[float], float]  # β likewise
    lr_divisor: float

    def __init__(
        self,
        n_runs: PositiveInt,
        n_state: PositiveInt,
        n_actions: PositiveInt,
        td_rule: TDRule,
        gamma: Discount,
        lr,
        beta,
        seed: NonNegativeInt = 0,
    ):
        """The sizes (the environment's, ``sizes``), the TD rule and discount γ of §3.2, the α and β
        schedules over training (Eq. 3.11) and the seed of the runs' initial weights."""
        super().__init__()
        self.sizes = ActorSizes(n_runs, n_state, n_actions)
        self.td_rule, self.gamma, self.seed = td_rule, gamma, seed
        self.lr_schedule, self.beta_schedule, self.lr_divisor = lr, beta, 1.0

    def run_generators(self) -> list[torch.Generator]:
        """One generator per run, from seed + r (``ferl.rng``): run r's weights do not depend on R."""
        return rng.run_generators(self.seed, self.sizes.runs)

    def evaluate(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """F (R, B, nA) and the cache (R, B, nA, ·) at states s: the subclass's."""
        raise NotImplementedError

    @classmethod
    def check_config(cls, args: dict) -> None:
        check_schedules(args)

    def slice_runs(self, index: slice) -> "SoftmaxActor":
        """This actor restricted to a slice of its runs. The parameters are views, so updates
        of the slice land in this actor's."""
        part = copy.copy(self)
        part._buffers = {
            name: b if name in self.shared_buffers or b is None else b[index] for name, b in self._buffers.items()
        }
        return part

    def learning_rate(self, progress: float) -> float:
        """α of the schedule divided by the actor's ``lr_divisor`` (§3.5's normalisation)."""
        return self.lr_schedule(progress) / self.lr_divisor

    def inverse_temperature(self, progress: float) -> float:
        return self.beta_schedule(progress)

    def policy(self, F: torch.Tensor, beta: float) -> torch.Tensor:
        """Softmax action-selection probabilities, Eq. (3.11)."""
        return torch.softmax(-beta * F, dim=-1)

    def select(
        self,
        s: torch.Tensor,
        F: torch.Tensor,
        beta: float,
        generator: torch.Generator,
        uniform: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """An action index per (run, state) by the clamped softmax (Eq. 3.11); ``uniform``
        (R, B, 1) may carry pre-drawn U(0, 1) numbers."""
        if uniform is None:
            uniform = torch.rand(F.shape[:-1] + (1,), generator=generator, device=F.device, dtype=F.dtype)
        return sample_categorical(self.policy(F, beta), uniform)

    def act(self, s: torch.Tensor, beta: float, generator: torch.Generator, uniform: torch.Tensor | None = None):
        """At states s (R, 1, S): an action a (R, 1), its F(s, a) (R, 1) and cache (R, 1, ·), and
        the F a TD error bootstraps from at s (§3.2): F(s, a) (SARSA), min_a F (Q(0)) or the
        policy's mean F (expected SARSA)."""
        F, cache = self.evaluate(s)
        a = self.select(s, F, beta, generator, uniform)
        F_a = pick(F, a)
        if self.td_rule == "sarsa":
            F_boot = F_a
        else:
            F_boot = F.min(-1).values if self.td_rule == "q" else (self.policy(F, beta) * F).sum(-1)
        return a, F_a, pick(cache, a), F_boot
