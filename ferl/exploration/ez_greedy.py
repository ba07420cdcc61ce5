"""Temporally extended ε-greedy, εz-greedy (Dabney, Ostrovski & Barreto 2021, Algorithm 1).

At a step where no random option is running, with probability ε a run starts one: an action ω
drawn uniformly from the n actions, repeated for n steps with n drawn from the zeta distribution

    P(n) = n^(−μ) / ζ(μ),   n = 1, 2, …   (μ > 1; ζ the Riemann zeta function)

and otherwise it takes the actor's own choice (Eq. 3.11; their "greedy"). ε may fall linearly
from ``epsilon`` to ``epsilon_end`` over the first share ``epsilon_over`` of the training (episode
k of N: ε_k = ε + (ε_end − ε) min(1, k / (``epsilon_over`` N)); 1 by default: all of it), as the
actor's β rises: a method that still starts options in the final window keeps its episodes off
the greedy return that ``solved`` asks for (docs/records.md). The heavy tail gives
the Lévy-flight walks that cross a corridor of aliased observations in ~T_min steps where a
one-step random walk needs ~T_min² (Dabney et al.'s §3). A duration longer than the episode's
remaining choices is cut by the episode's end, so n is drawn from the zeta law censored at
T_max + 1 (every longer n acts alike): the exact distribution of what is acted.

The random numbers of an episode — per run and choice, U(0, 1) for "start an option", for ω and
for n — are drawn when it starts (``begin_episode``), (T_max + 1, R, 3) from the batch's
generator. An option never outlives its episode.
"""

from typing import Annotated

import torch
from torch import Tensor

from ferl.compiled import size_generic
from ferl.config.params import Allowed, PositiveInt, Share, UnitInterval, checked
from ferl.exploration import ExplorationBase, taken
from ferl.schedules import Linear

AboveOne = Annotated[float, Allowed(lambda x: x > 1, "> 1 (the zeta distribution needs μ > 1)")]


def zeta_cdf(mu: float, longest: int) -> Tensor:
    """P(n ≤ k) for k = 1 … longest − 1 of the zeta law P(n) = n^(−μ)/ζ(μ) (float64, (longest − 1,)):
    the thresholds that ``zeta_durations`` inverts (n ≥ longest is one last class)."""
    k = torch.arange(1, longest, dtype=torch.float64)
    return (k ** (-mu)).cumsum(0) / torch.special.zeta(torch.tensor(mu, dtype=torch.float64), 1.0)


def zeta_durations(cdf: Tensor, u: Tensor) -> Tensor:
    """Durations n ≥ 1 by inverting the zeta CDF at uniforms u (any shape): n = 1 + #{k : cdf_k ≤ u}
    … capped at len(cdf) + 1 (the censored class)."""
    return 1 + torch.searchsorted(cdf, u.to(cdf.dtype).contiguous(), right=True)


class EzGreedy(ExplorationBase):
    """εz-greedy over R runs (module docstring): ``epsilon`` the chance of starting an option at a
    step without one (falling linearly to ``epsilon_end`` over the first share ``epsilon_over`` of
    the training; None: constant), ``mu`` the zeta exponent (2: Dabney et al.'s choice across Atari)."""

    held: torch.Tensor  # (R,) ω, the action of each run's option
    left: torch.Tensor  # (R,) steps of ω still to take (0: no option running)
    cdf: torch.Tensor  # (T_max,) float64, ``zeta_cdf`` for the episode's T_max + 1 choices
    uniforms: torch.Tensor  # (T_max + 1, R, 3) the episode's draws: start, ω, n
    # choices made in the episode (1,) and the episode's ε (): tensors, so that a compiled episode
    # reads them as inputs, not as constants of its graph (``traceable``)
    step: torch.Tensor
    epsilon_t: torch.Tensor
    traceable = True

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        n_actions: PositiveInt,
        epsilon: UnitInterval = 0.1,
        mu: AboveOne = 2.0,
        epsilon_end: UnitInterval | None = None,
        epsilon_over: Share = 1.0,
    ):
        super().__init__(n_runs)
        self.n_actions, self.epsilon, self.mu, self.epsilon_end = n_actions, epsilon, mu, epsilon_end
        end = epsilon if epsilon_end is None else epsilon_end
        self.schedule = Linear(epsilon, end, epsilon_over)  # ε of an episode at its progress
        self.epsilon_now = epsilon  # ε of the episode under way
        self.longest = 0  # T_max + 1, known at the first episode
        self.register_buffer("held", torch.zeros(n_runs, dtype=torch.long), persistent=False)  # ω per run
        self.register_buffer("left", torch.zeros(n_runs, dtype=torch.long), persistent=False)  # steps of ω to go
        self.register_buffer("step", torch.zeros(1, dtype=torch.long), persistent=False)
        self.register_buffer("epsilon_t", torch.tensor(float(epsilon)), persistent=False)

    def describe(self) -> dict:
        return {
            "kind": "ez_greedy",
            "epsilon": self.epsilon,
            "epsilon_end": self.epsilon_end,
            "epsilon_over": self.schedule.over,
            "mu": self.mu,
        }

    def begin_episode(self, generator: torch.Generator, max_steps: int, progress: float) -> None:
        """No option held; ε of the episode at ``progress``; its uniforms (T_max + 1, R, 3), drawn in one call."""
        self.epsilon_now = self.schedule(progress)
        # both sized by T_max: generic in a compiled episode (``size_generic``), whose graph then
        # serves every corridor, as the maze's own tables do
        if self.longest != max_steps + 1:
            self.longest = max_steps + 1
            self.cdf = size_generic(zeta_cdf(self.mu, self.longest).to(self.held.device), 0)
        draws = torch.rand(max_steps + 1, self.n_runs, 3, generator=generator, device=self.held.device)
        self.uniforms = size_generic(draws, 0, 1)
        self.epsilon_t.fill_(self.epsilon_now)
        self.step.zero_()
        self.left.zero_()

    def choose(self, actor, s: Tensor, proposal: tuple) -> tuple:
        """Algorithm 1 of Dabney et al.: continue a running option, else start one with chance ε,
        else the actor's proposal."""
        # (R, 3): start, ω, n; a compiled episode's padded steps past T_max (every run has ended,
        # nothing they choose is kept) read the last row
        u = self.uniforms.index_select(0, self.step.clamp(max=self.uniforms.shape[0] - 1)).squeeze(0)
        self.step = self.step + 1
        start = (self.left == 0) & (u[:, 0] < self.epsilon_t)
        omega = (u[:, 1] * self.n_actions).long().clamp(max=self.n_actions - 1)
        self.held = torch.where(start, omega, self.held)
        self.left = torch.where(start, zeta_durations(self.cdf, u[:, 2]), self.left)
        take = self.left > 0
        self.left = (self.left - 1).clamp(min=0)
        return taken(actor, s, proposal, take, self.held)
