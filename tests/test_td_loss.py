"""The recurrent Q-learner's TD loss (``actor.td_loss``) and its head's wide initialisation
(``actor.head_init_std``; ferl/actors/recurrent_q.py, ferl/actors/q_heads.py) against independent
computations: the loss from the unrolled Q by NumPy, its gradient by finite differences, and
Q(h = 0, a) of the RBM heads by their formulas."""

import numpy as np
import pytest
import torch

from ferl.actors.recurrent_q import RecurrentQActor
from ferl.schedules import Constant
from test_recurrent_q import HEADS, NA, SIZES, R, padded_batch

GAMMA = 0.9


def actor(**kwargs) -> RecurrentQActor:
    return RecurrentQActor(**SIZES, gamma=GAMMA, lr=Constant(0.01), beta=Constant(2.0), head_hidden=4, **kwargs)


def numpy_loss(agent: RecurrentQActor, batch: dict, loss: str) -> float:
    """Σ_r mean over valid steps of ℓ(Q(h_t, a_t) − y_t), Q and Q⁻ unrolled by the actor, the rest by NumPy."""
    prev = torch.nn.functional.one_hot(batch["actions"], NA).double()
    prev = torch.cat([torch.zeros_like(prev[:, :, :1]), prev], 2)
    with torch.no_grad():
        q = agent.unroll(agent.params(), batch["states"].double(), prev).numpy()
        q_target = agent.unroll(agent.params("_target"), batch["states"].double(), prev).numpy()
    total = 0.0
    for r in range(R):
        errors = []
        for b in range(batch["lengths"].shape[1]):
            n = int(batch["lengths"][r, b])
            for t in range(n):
                bootstrap = 0.0 if (t == n - 1 and bool(batch["terminated"][r, b])) else 1.0
                y = float(batch["rewards"][r, b, t]) + GAMMA * bootstrap * q_target[r, b, t + 1].max()
                e = q[r, b, t, int(batch["actions"][r, b, t])] - y
                errors.append(0.5 * e * e if loss == "squared" or abs(e) <= 1 else abs(e) - 0.5)
        total += float(np.mean(errors))
    return total


@pytest.mark.parametrize("td_loss", ["huber", "squared"])
@pytest.mark.parametrize("scale", [1.0, 20.0])  # rewards that keep |e| < 1 mostly, and that do not
def test_the_td_loss_equals_numpy_on_the_unrolled_q(td_loss, scale):
    agent = actor(head="free_energy", td_loss=td_loss, seed=3).double()
    for name in agent.names:  # a target network that differs from the online one
        getattr(agent, f"{name}_target").add_(torch.randn_like(getattr(agent, name)) * 0.1)
    batch = padded_batch()
    batch["rewards"] = batch["rewards"] * scale
    batch = {k: v.double() if v.is_floating_point() else v for k, v in batch.items()}
    got = float(agent.loss(agent.params(), batch))
    assert got == pytest.approx(numpy_loss(agent, batch, td_loss), rel=1e-9)


def test_the_squared_loss_gradient_is_the_td_error_times_dq_by_finite_differences():
    """d/dθ of the squared loss against central differences in float64 on a few coordinates of
    every trained parameter: with large rewards Huber's gradient would be clipped, the squared's not."""
    agent = actor(head="free_energy", td_loss="squared", seed=5).double()
    batch = padded_batch(T=4, B=3)
    batch = {
        k: (v.double() * 20 if k == "rewards" else v.double()) if v.is_floating_point() else v for k, v in batch.items()
    }
    p = {k: v.clone().requires_grad_(k in agent.names) for k, v in agent.params().items()}
    grads = dict(zip(agent.names, torch.autograd.grad(agent.loss(p, batch), [p[k] for k in agent.names])))
    gen = torch.Generator().manual_seed(0)
    for name in agent.names:
        flat = p[name].detach().reshape(-1)
        for i in torch.randint(flat.numel(), (3,), generator=gen).tolist():
            shifted = []
            for sign in (1, -1):
                q = {k: v.detach().clone() for k, v in p.items()}
                q[name].view(-1)[i] += sign * 1e-6
                shifted.append(float(agent.loss(q, batch)))
            assert float(grads[name].reshape(-1)[i]) == pytest.approx(
                (shifted[0] - shifted[1]) / 2e-6, rel=1e-5, abs=1e-7
            )


def test_huber_and_squared_differ_only_where_an_error_passes_one():
    small, large = padded_batch(), padded_batch()
    small["rewards"] = small["rewards"] * 0.01
    large["rewards"] = large["rewards"] * 20
    huber, squared = (actor(td_loss=loss, seed=1, init_std=0.05) for loss in ("huber", "squared"))  # |Q| small
    torch.testing.assert_close(huber.loss(huber.params(), small), squared.loss(squared.params(), small))
    assert float(squared.loss(squared.params(), large)) > 1.5 * float(huber.loss(huber.params(), large))


@pytest.mark.parametrize("head", [h for h in HEADS if h != "linear"])
def test_the_wide_head_starts_at_q_zero_for_every_action_with_the_cores_draws_unchanged(head):
    """With ``head_init_std`` the RBM head's Q(h = 0, a) = scale · (b_a,a + Σ_k φ(W_ah,a,k + b_k)) = 0
    for every action (φ by NumPy), its weights have that spread, and the core's weights are the
    default's draws."""
    std = 0.5
    wide = RecurrentQActor(
        n_runs=R, n_state=8, n_actions=NA, n_hidden=64, head_hidden=64, gamma=GAMMA, lr=Constant(0.01),
        beta=Constant(2.0), head=head, head_init_std=std, seed=2,
    )  # fmt: skip
    default = RecurrentQActor(
        n_runs=R, n_state=8, n_actions=NA, n_hidden=64, head_hidden=64, gamma=GAMMA, lr=Constant(0.01),
        beta=Constant(2.0), head=head, seed=2,
    )  # fmt: skip
    q0 = wide.head.q(wide.params(), torch.zeros(R, 1, 64)).squeeze(1)
    x = (wide.W_ah + wide.b_k.unsqueeze(1)).double().numpy()
    phi = x / (1 + np.exp(-x)) if head == "expected_energy" else np.log1p(np.exp(x))
    assert np.abs(wide.b_a.double().numpy() + phi.sum(-1)).max() < 1e-4
    torch.testing.assert_close(q0, torch.zeros(R, NA), atol=1e-4, rtol=0)
    spread = torch.cat([wide.W_sh.reshape(-1), wide.W_ah.reshape(-1)]).std()
    assert float(spread) == pytest.approx(std, rel=0.05)
    for name in wide.core.shapes():
        torch.testing.assert_close(getattr(wide, name), getattr(default, name), rtol=0, atol=0)
