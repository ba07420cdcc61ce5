"""The recurrent Q-learner's replay step on the fast path (``ferl.compiled``; docs/performance.md,
"Graphs of fixed size"): BPTT of the Huber TD loss through graphs whose size does not depend on
the episodes' length.

* A recurrent core (GRU, LSTM, Elman, echo state) unrolls its replayed episodes in compiled chunks
  of ``ferl.compiled.CHUNK_STEPS`` steps of core and head (``RecurrentQActor.unroll_chunk``), the
  state carried from chunk to chunk (``ferl.compiled.in_chunks``). Autograd chains the chunks'
  compiled backward graphs, so the gradient is that of the same ``loss``: there is no second
  formulation of it. The target network's unroll runs the same chunks without gradient.
* The transformer's unroll has no loop over time (one causal mask over every token): its whole
  loss is one graph, whose size does not depend on T either.
* The Adam update (``adam_update``) is one small graph, the step sizes entering as tensors so that
  one graph serves every step.

``RecurrentQActor.adam_step`` run eagerly is the reference (tests/test_recurrent_q_fast.py holds
the two within float32 rounding at T_max of 11, 51 and 201).
"""

import math

import torch

from ferl.replay import stored_episodes

ADAM_BETAS, ADAM_EPS = (0.9, 0.999), 1e-8  # Kingma & Ba (2015)'s defaults, DRQN's


def adam_scalars(lr: float, k: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Adam's step k's bias-corrected step size α / (1 − β1^k) and √(1 − β2^k), as 0-d tensors
    computed in double precision as ``adam_step`` computes them."""
    (b1, b2) = ADAM_BETAS
    return (
        torch.tensor(lr / (1 - b1**k), device=device),
        torch.tensor(math.sqrt(1 - b2**k), device=device),
    )


def adam_update(actor, grads: tuple, step_size: torch.Tensor, root: torch.Tensor) -> None:
    """θ ← θ − step_size · m / (√v / root + ε) for every trained parameter of ``actor`` and its
    gradient in ``grads`` (in the order of ``actor.names``), with the moments of ``actor.moments``;
    in place."""
    for name, g in zip(actor.names, grads):
        m, v = actor.moments(name, g)
        getattr(actor, name).sub_(step_size * m / (v.sqrt() / root + ADAM_EPS))


def replay_step(actor, index: torch.Tensor, step_size: torch.Tensor, root: torch.Tensor, update=adam_update) -> None:
    """One Adam step of every run on its replayed episodes at slots ``index`` (R, B), in place: the
    gradient of ``actor.replay_loss`` (``loss``, through the compiled chunks where the actor has
    them) by autograd, then ``update`` (``adam_update``, compiled or not)."""
    assert actor.replay is not None
    batch = stored_episodes(actor.replay, index)
    p = actor.params()
    trained = {name: p[name].detach().requires_grad_() for name in actor.names}
    with torch.enable_grad():
        grads = torch.autograd.grad(actor.replay_loss({**p, **trained}, batch), tuple(trained.values()))
    with torch.no_grad():
        update(actor, grads, step_size, root)
