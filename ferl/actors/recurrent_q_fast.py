"""The recurrent Q-learner's replay step on the fast path (``ferl.compiled``; docs/performance.md):
the gather of the replayed episodes, the BPTT gradient of the Huber TD loss and the Adam update
of ``RecurrentQActor.adam_step`` as one graph. The gradient is ``torch.func.grad`` of the same
``loss``, which dynamo traces into the graph (AOTAutograd writes its backward), so there is no
second formulation of the loss; the step sizes enter as tensors, so that one graph serves every
step. ``adam_step`` run eagerly is the reference (tests/test_recurrent_q_fast.py holds the two
within float32 rounding).
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


def replay_step(actor, index: torch.Tensor, step_size: torch.Tensor, root: torch.Tensor) -> None:
    """One Adam step of every run on its replayed episodes at slots ``index`` (R, B), in place:
    θ ← θ − step_size · m / (√v / root + ε) with the moments of ``actor.moments``."""
    assert actor.replay is not None
    batch = stored_episodes(actor.replay, index)
    p = actor.params()
    trained = {name: p[name] for name in actor.names}
    grads = torch.func.grad(lambda q: actor.loss({**p, **q}, batch))(trained)
    with torch.no_grad():
        for name in actor.names:
            m, v = actor.moments(name, grads[name])
            getattr(actor, name).sub_(step_size * m / (v.sqrt() / root + ADAM_EPS))
