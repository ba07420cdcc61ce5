"""TD into the predictors' memory: the online trainer's ``td_to_memory`` = λ ≥ 0 (docs/beyond.md,
"A memory shaped by reward").

The dissertation's predictors learn their memory m_t to predict the next observation and reward
(Eqs. 4.1–4.6); the actor only reads it, as part of its state s_t = (y_t, m_t) (§4.2). With λ > 0
the memory also descends the actor's TD loss, as a recurrent Q-learner's core does (DRQN,
Hausknecht & Stone 2015): after every episode each predictor's memory parameters θ_m take one
plain SGD step, at the predictor's own α, on

    L_λ(θ_m) = −λ Σ_t δ_t Q(s_t(θ_m), a_t)        (δ_t held fixed)

whose error on the memory the actor read is ∂L_λ/∂m_t = −λ δ_t ∂Q(s_t, a_t)/∂m_t: the
semi-gradient of ½ δ_t² (Eq. 3.2, the target r_{t+1} + γ Q(s_{t+1}, a_{t+1}) held fixed as the
actor's own update, Eq. 3.10, holds it), λ times, through the memory part of s_t. Its terms:

* δ_t: the TD error of (s_t, a_t) that the actor learned from at step t of the episode just played
  (Eq. 3.2 with the actor's TD rule, the reward bonus included where curiosity or exploration adds
  one), detached; 0 once a run's episode has ended, in runs the divergence guard froze, and where it
  is not finite;
* ∂Q(s_t, a_t)/∂s_t: the actor's ``state_gradient`` at the recorded state s_t (the observation
  then every predictor's memory, as the actor read them) and action a_t, with the actor's
  parameters at the episode's end (after its online updates) — analytic for every value form,
  κ (b_s + W_sh φ'(x)) (``FERLActor.state_gradient``); only the columns of predictor p's memory
  are sent to p;
* m_t(θ_m): the memories m_0 … m_{T−1} of the states where actions were taken (none at the last
  state m_T), recomputed from the episode by the predictor's own BPTT (``descend_memory``:
  Eqs. 2.59–2.63 written out for the Elman memory, autograd through ``unroll_with`` for the others).

The step is taken before the replay's BPTT steps, at the parameters that produced the episode's
memories. It draws no random numbers; λ = 0 skips it, so the run is today's to the bit.
"""

from typing import Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from torch import Tensor

from ferl.config.params import ConfigError
from ferl.config.swaps import chosen
from ferl.predictors.heads import clean


@runtime_checkable
class StateGradient(Protocol):
    """An actor that gives ∂Q(s, a)/∂s (R, B, S) at states s (R, B, S) and actions a (R, B)
    (``FERLActor.state_gradient``); optional, as ``ferl.interfaces.ActorViews``."""

    def state_gradient(self, s: Tensor, a: Tensor) -> Tensor: ...


@runtime_checkable
class MemoryFromTD(Protocol):
    """A predictor whose memory takes an error from outside: one plain SGD step of the memory's
    parameters θ_m at the predictor's own α down Σ dm · m, the error dm (R, B, T+1, M) on its
    memories m_0 … m_T of cleaned sequences y (R, B, T+1, Y), a (R, B, T, A), backpropagated by
    its BPTT (``RecurrentPredictor.descend_memory``); optional."""

    def descend_memory(self, y: Tensor, a: Tensor, dm: Tensor) -> None: ...


def check_td_to_memory(job, lam: float) -> None:
    """λ > 0 needs an actor that gives ∂Q/∂s and predictors whose memory learns from an error from
    outside: one line naming the key before any work otherwise."""
    if not isinstance(job.actor, StateGradient):
        raise ConfigError(
            f"trainer.td_to_memory={lam:g} is not allowed with {chosen('actor', type(job.actor).__name__)}: "
            "the TD gradient into the memory needs the actor's ∂Q(s, a)/∂s (its state_gradient; actor=ferl "
            "and its variants have it); 0 turns it off"
        )
    fixed = [name for name, p in job.predictors.items() if not isinstance(p, MemoryFromTD)]
    if fixed:
        raise ConfigError(
            f"trainer.td_to_memory={lam:g} is not allowed: the memory of predictor {', '.join(fixed)} does not "
            "learn from the actor's TD error (descend_memory; an echo-state reservoir is fixed); 0 turns it off"
        )


def memory_errors(actor, states, actions, deltas, lam: float, sizes: list[int]) -> list[torch.Tensor]:
    """dm = ∂L_λ/∂m_t of every predictor, (R, n+1, M_p): −λ δ_t ∂Q(s_t, a_t)/∂m_t for t < n and
    0 at m_n. states (n, R, S) whose last Σ M_p columns are the predictors' memories in order,
    actions (n, R), deltas (n, R) with 0 where there is no TD error."""
    g = actor.state_gradient(states.transpose(0, 1), actions.T)  # (R, n, S)
    weight = (-lam * deltas.T).unsqueeze(-1)
    d = F.pad(torch.where(weight != 0, weight * g, 0.0), (0, 0, 0, 1))  # m_n carries no TD error
    return list(d[..., g.shape[-1] - sum(sizes) :].split(sizes, -1))


@torch.no_grad()
def td_to_memory(predictors: list, actor, y, a, lengths, states, actions, deltas, lam: float) -> None:
    """One SGD step θ_m ← θ_m − α_p ∂L_λ/∂θ_m of every predictor p (module docstring) on the
    episode of every run: y (R, 1, n+1, Y), a (R, 1, n, A) its predictor inputs, lengths (R, 1),
    states (n, R, S), actions (n, R) and deltas (n, R) as the actor met them."""
    y, a, _ = clean(y, a, None, lengths)
    errors = memory_errors(actor, states, actions, deltas, lam, [p.memory_size for p in predictors])
    for p, dm in zip(predictors, errors):
        p.descend_memory(y, a, dm.unsqueeze(1))
