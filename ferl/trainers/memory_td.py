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

import torch
import torch.nn.functional as F

from ferl.predictors.heads import clean


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
