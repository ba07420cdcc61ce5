"""Directed exploration: what an episodic trainer adds to the actor's own (Boltzmann) choice.

With Eq. (3.11)'s softmax from β = 0 (the online trainer's start, §5.4) an agent's walk along a
corridor of aliased observations is diffusive: it reaches the end of a corridor of T_min steps in
~T_min² steps, so a long T-maze's junction is rarely met and no memory is ever tested there
(docs/beyond.md). Thrun (1992) calls such exploration *undirected*; a *directed* method either
changes the choice of actions (``choose``: temporally extended ε-greedy, Dabney, Ostrovski &
Barreto 2021, ``ferl.exploration.ez_greedy``) or adds a bonus to the reward the actor learns from
(``reward_bonus``: a count bonus on hashed states, Tang et al. 2017, ``ferl.exploration.counts``).

Each method is one option of the config group ``exploration`` (``conf/exploration/<method>.yaml``,
``none`` by default) built by the ``Job`` for R runs and called by the episode loop that every
episodic trainer shares (``ferl.trainers.actor_episodes.ActorEpisodes.episode``: Algorithm 1's
actor phase, the online trainer). ``Exploration`` declares every hook; ``ExplorationBase`` gives
the do-nothing defaults, and ``NoExploration`` is them alone. Returns and every metric stay on
the environment's raw rewards and the actions taken.
"""

from typing import Protocol, runtime_checkable

import torch
from torch import Tensor, nn

from ferl.config.params import ConfigError, PositiveInt


@runtime_checkable
class Exploration(Protocol):
    """The hooks of a directed-exploration method, batched over R runs (module docstring)."""

    n_runs: int
    # False: every hook leaves the actor's choice and rewards as they are (the episode loop then
    # skips them, and the fused episode of ``ferl.compiled`` stays available)
    active: bool
    # True when ``choose`` and ``reward_bonus`` are tensor operations on state kept in tensors (no
    # Python counter or number that changes within a training): an episode with them can then be
    # compiled in chunks of steps (``ferl.trainers.fused_episodes``); False: it runs eagerly
    traceable: bool

    def check_actor(self, actor) -> None:
        """ConfigError when the method cannot work with this actor (checked before any work)."""

    def begin_episode(self, generator: torch.Generator, max_steps: int, progress: float) -> None:
        """Before an episode of every run, at ``progress`` ∈ [0, 1) of the training (episode k of N:
        k / N, what the actor's schedules read): forget what the previous episode held and draw
        this episode's random numbers from the batch's ``generator``, all at once in a fixed order
        (so that no run's episode length shifts another run's stream)."""

    def choose(self, actor, s: Tensor, proposal: tuple) -> tuple:
        """The action taken at states s (R, 1, S) given the actor's ``proposal`` (its ``act``'s
        (a (R, 1), F(s, a) (R, 1), cache (R, 1, ·), F_boot (R, 1))): the same tuple, for the
        action taken. Called once per step of the episode, in order."""

    def reward_bonus(self, s_next: Tensor, active: Tensor) -> Tensor | None:
        """What is added to the reward of the step into states s_next (R, 1, S) of the runs whose
        episode was on (``active`` (R,) bool): (R,), or None for nothing."""

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...

    def describe(self) -> dict: ...


class ExplorationBase(nn.Module):
    """The hooks' defaults: no exploration beyond the actor's own. A subclass names what it changes."""

    active = True
    traceable = False

    def __init__(self, n_runs: int):
        super().__init__()
        self.n_runs = n_runs

    # why the method cannot work with an actor that learns only from replayed episodes and steps
    # its memory in ``act`` (``Actor.learns_from_episodes``, DRQN); None: it can
    episode_learners_refused: str | None = None

    def check_actor(self, actor) -> None:
        if actor.learns_from_episodes and self.episode_learners_refused is not None:
            kind = self.describe()["kind"]
            raise ConfigError(f"exploration={kind} with {type(actor).__name__}: {self.episode_learners_refused}")

    def begin_episode(self, generator: torch.Generator, max_steps: int, progress: float) -> None: ...

    def choose(self, actor, s: Tensor, proposal: tuple) -> tuple:
        return proposal

    def reward_bonus(self, s_next: Tensor, active: Tensor) -> Tensor | None:
        return None

    def describe(self) -> dict:
        return {"kind": "none"}


class NoExploration(ExplorationBase):
    """``exploration=none``: the actor's own choice (Eq. 3.11) and the raw reward."""

    active = False

    def __init__(self, n_runs: PositiveInt):
        super().__init__(n_runs)


@runtime_checkable
class RetakesAction(Protocol):
    """An actor whose ``act`` steps a memory in place with the action it drew (``RecurrentQActor``:
    h_t from (s_t, a_{t−1}), then a_{t−1} ← a_t). A method that replaces the drawn action tells it."""

    def retake(self, a: Tensor) -> tuple[Tensor, Tensor]:
        """The action taken at the last ``act`` was a (R, 1), not the one drawn: the memory's next
        step reads a; returns F(s_t, a) (R, 1) and its cache (R, 1, ·) at the state ``act`` reached."""
        ...


def added(bonus: Tensor | None, more: Tensor | None) -> Tensor | None:
    """The sum of two reward bonuses (R,), either of them None for nothing."""
    if bonus is None:
        return more
    return bonus if more is None else bonus + more


def taken(actor, s: Tensor, proposal: tuple, take: Tensor, action: Tensor) -> tuple:
    """``proposal`` (the actor's ``act`` at s (R, 1, S)) with ``action`` (R,) in the runs where
    ``take`` (R,) bool: the action, its F(s, a) and cache, and the F a TD error bootstraps from at
    s — the taken action's own under SARSA (the actor's ``td_rule``, SARSA when it states none);
    Q(0)'s min_a F and expected SARSA's policy mean do not depend on the action taken. An actor
    whose ``act`` stepped its memory is told the action (``RetakesAction.retake``); else the
    actor's ``evaluate_actions`` gives F and cache of the given actions where it has one (factored
    actions are never enumerated), else they are picked from ``evaluate``'s every action."""
    a, _, _, F_boot = proposal
    a_new = torch.where(take.unsqueeze(1), action.unsqueeze(1), a)
    if isinstance(actor, RetakesAction):  # act has stepped its memory: evaluating again would step it twice
        F_new, cache_new = actor.retake(a_new)
    elif hasattr(actor, "evaluate_actions"):
        F_new, cache_new = actor.evaluate_actions(s, a_new)
    else:
        F_all, cache_all = actor.evaluate(s)  # (R, 1, nA), (R, 1, nA, ·)
        F_new = F_all.gather(2, a_new.unsqueeze(2)).squeeze(2)
        index = a_new.view(*a_new.shape, 1, 1).expand(-1, -1, 1, cache_all.shape[-1])
        cache_new = cache_all.gather(2, index).squeeze(2)
    sarsa = getattr(actor, "td_rule", "sarsa") == "sarsa"
    return a_new, F_new, cache_new, F_new if sarsa else F_boot
