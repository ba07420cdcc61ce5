"""FERL actor: Eq. (3.1) free energies, Eq. (3.5–3.10) updates vs autograd, Eq. (3.11) policy,
TD rules of §3.2 and alternating-Gibbs action sampling."""

import copy
import itertools

import pytest
import torch

from ferl import rbm
from ferl.actors.free_energy import FERLActor, action_code_table, sample_categorical
from ferl.actors.td import td_step
from ferl.schedules import Constant


def make_actor(R=3, S=6, A=4, H=5, code="onehot", td_rule="sarsa", init_std=0.5, **kw):
    actor = FERLActor(
        n_runs=R,
        n_state=S,
        n_actions=A,
        n_hidden=H,
        td_rule=td_rule,
        gamma=0.9,
        lr=Constant(0.1),
        beta=Constant(1.0),
        init_std=init_std,
        action_code=code,
        seed=3,
        **kw,
    ).double()
    g = torch.Generator().manual_seed(1)
    for name in ("b_s", "b_a", "b_h"):  # non-zero biases so every term is exercised
        getattr(actor, name).copy_(torch.randn(getattr(actor, name).shape, generator=g, dtype=torch.float64) * 0.3)
    return actor


@pytest.mark.parametrize("code", ["onehot", "binary"])
def test_free_energy_of_every_action_matches_rbm_on_visible_vector(code):
    """F(s, a) equals the RBM free energy of the concatenated visible vector v = (s, a)."""
    actor = make_actor(code=code)
    s = torch.rand(3, 2, 6, dtype=torch.float64)
    F, x = actor.evaluate(s)
    for a, code_row in enumerate(actor.codes):
        v = torch.cat([s, code_row.expand(3, 2, -1)], -1)
        W = torch.cat([actor.W_sh, actor.W_ah], 1)
        b_v = torch.cat([actor.b_s, actor.b_a], 1)
        torch.testing.assert_close(F[:, :, a], rbm.free_energy(v, W, b_v, actor.b_h))
        torch.testing.assert_close(torch.sigmoid(x[:, :, a]), rbm.hidden_expectation(v, W, actor.b_h))


def test_binary_codes_enumerate_all_bit_patterns():
    codes = action_code_table(4, "binary")
    assert codes.shape == (4, 2)
    assert {tuple(r) for r in codes.tolist()} == set(itertools.product([0.0, 1.0], repeat=2))


@pytest.mark.parametrize("code", ["onehot", "binary"])
def test_update_is_minus_lr_delta_grad_free_energy(code):
    """Eq. (3.10): Δθ = α δ (−∂F(s,a)/∂θ), checked against torch.autograd for every parameter."""
    actor = make_actor(code=code)
    s = torch.rand(3, 1, 6, dtype=torch.float64)
    a = torch.tensor([[0], [3], [2]])
    delta = torch.tensor([[1.5], [-0.7], [0.2]], dtype=torch.float64)
    params = {n: getattr(actor, n).clone().requires_grad_(True) for n in ("W_sh", "W_ah", "b_s", "b_a", "b_h")}
    codes = actor.codes[a]
    v = torch.cat([s, codes], -1)
    F = rbm.free_energy(
        v, torch.cat([params["W_sh"], params["W_ah"]], 1), torch.cat([params["b_s"], params["b_a"]], 1), params["b_h"]
    )
    # Σ_r δ_r F_r: its gradient wrt run r's parameters is δ_r ∂F_r/∂θ_r
    (F * delta).sum().backward()
    _, x = actor.evaluate(s)
    x_sa = x[torch.arange(3), 0, a[:, 0]].unsqueeze(1)
    before = {n: p.detach().clone() for n, p in params.items()}
    actor.update(s, a, x_sa, delta, lr=0.05)
    for name, p in params.items():
        torch.testing.assert_close(getattr(actor, name) - before[name], -0.05 * p.grad, msg=name)


@pytest.mark.parametrize("code", ["onehot", "binary"])
@pytest.mark.parametrize("fresh", [True, False])
def test_learn_returns_the_free_energy_after_the_update(code, fresh):
    """td_fresh: F(s', a') and x(s', a') from learn() equal a full re-evaluation with the
    parameters its update produced (Eq. 3.2: one θ in δ); without it, the values from before."""
    actor = make_actor(code=code, td_fresh=fresh)
    s, s_next = torch.rand(3, 1, 6, dtype=torch.float64), torch.rand(3, 1, 6, dtype=torch.float64)
    a, a_next = torch.tensor([[0], [3], [2]]), torch.tensor([[0], [1], [2]])  # same, other, same action
    delta = torch.tensor([[1.5], [-0.7], [2.0]], dtype=torch.float64)
    rows = torch.arange(3)
    _, x = actor.evaluate(s)
    F_next, x_next = actor.evaluate(s_next)
    before = F_next[rows, 0, a_next[:, 0]].unsqueeze(1), x_next[rows, 0, a_next[:, 0]].unsqueeze(1)
    got = actor.learn(s, a, x[rows, 0, a[:, 0]].unsqueeze(1), delta, 0.05, s_next, a_next, *before)
    F_after, x_after = actor.evaluate(s_next)
    want = (
        (F_after[rows, 0, a_next[:, 0]].unsqueeze(1), x_after[rows, 0, a_next[:, 0]].unsqueeze(1)) if fresh else before
    )
    torch.testing.assert_close(got, want)
    assert not torch.allclose(F_after[rows, 0, a_next[:, 0]].unsqueeze(1), before[0])  # the update moved F(s', a')


def test_policy_is_softmax_of_negative_free_energy():
    actor = make_actor()
    F = torch.tensor([[[1.0, 2.0, -1.0, 0.5]]], dtype=torch.float64)
    beta = 1.7
    direct = torch.exp(-beta * F) / torch.exp(-beta * F).sum(-1, keepdim=True)
    torch.testing.assert_close(actor.policy(F, beta), direct)
    assert torch.allclose(actor.policy(F, 0.0), torch.full_like(F, 0.25))


def test_sample_categorical_frequencies():
    g = torch.Generator().manual_seed(0)
    probs = torch.tensor([0.1, 0.2, 0.3, 0.4]).expand(200_000, 4)
    u = torch.rand(200_000, 1, generator=g)
    freq = torch.bincount(sample_categorical(probs, u), minlength=4).double() / 200_000
    torch.testing.assert_close(freq, torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=torch.float64), atol=4e-3, rtol=0)


@pytest.mark.parametrize("rule", ["sarsa", "q", "expected_sarsa"])
def test_td_errors(rule):
    """δ = r − γ F_boot + F(s, a) of td_step, F_boot by the TD rule (§3.2) from F of every action
    at s' (enumerated here); no bootstrap at terminals."""
    actor = make_actor(td_rule=rule)
    g = torch.Generator().manual_seed(4)
    s, s_next = torch.rand(3, 1, 6, dtype=torch.float64), torch.rand(3, 1, 6, dtype=torch.float64)
    r = torch.tensor([1.0, -2.0, 0.0], dtype=torch.float64)
    F_sa = torch.tensor([[-3.0], [0.5], [2.0]], dtype=torch.float64)
    uniform = torch.rand(3, 1, 1, generator=g, dtype=torch.float64)
    beta = 0.8
    F_next = torch.stack(
        [
            torch.stack(
                [
                    rbm.free_energy(
                        torch.cat([s_next, actor.codes[b].expand(3, 1, -1)], -1),
                        torch.cat([actor.W_sh, actor.W_ah], 1),
                        torch.cat([actor.b_s, actor.b_a], 1),
                        actor.b_h,
                    )
                    for b in range(4)
                ],
                -1,
            )
        ]
    ).squeeze(0)  # (R, 1, nA)
    a_next, F_a, _, F_boot = actor.act(s_next, beta, g, uniform)
    assert torch.equal(a_next, sample_categorical(torch.softmax(-beta * F_next, -1), uniform))
    torch.testing.assert_close(F_a, F_next.gather(-1, a_next.unsqueeze(-1)).squeeze(-1))
    if rule == "sarsa":
        boot = F_a
    elif rule == "q":  # max_a Q = −min_a F
        boot = F_next.min(-1).values
    else:
        w = torch.exp(-beta * F_next)
        boot = ((w / w.sum(-1, keepdim=True)) * F_next).sum(-1)
    torch.testing.assert_close(F_boot, boot)
    for terminal in (None, torch.tensor([[True], [False], [True]])):
        alive = torch.ones(3, 1, dtype=torch.bool)
        frozen = copy.deepcopy(actor)
        *_, delta = td_step(
            frozen,
            s,
            torch.zeros(3, 1, dtype=torch.long),
            F_sa,
            torch.zeros(3, 1, 5, dtype=torch.float64),
            r,
            s_next,
            0.0,
            beta,
            g,
            uniform,
            alive,
            terminal,
        )
        kept = boot if terminal is None else boot * (~terminal)
        torch.testing.assert_close(delta, r.unsqueeze(1) - 0.9 * kept + F_sa)


@pytest.mark.parametrize("code", ["onehot", "binary"])
def test_gibbs_sampling_reaches_free_energy_softmax(code):
    """The Gibbs chain's action law is exp(−β F_β(s,a)) normalised; β F_β(s, a) equals the unit-
    temperature free energy of the same RBM with all parameters scaled by β (§2.1.5)."""
    R, beta = 4000, 1.5
    actor = FERLActor(
        n_runs=R,
        n_state=3,
        n_actions=4,
        n_hidden=3,
        td_rule="sarsa",
        gamma=0.9,
        lr=Constant(0.1),
        beta=Constant(beta),
        init_std=0.0,
        action_code=code,
        action_selection="gibbs",
        gibbs_sweeps=30,
        seed=0,
    ).double()
    g = torch.Generator().manual_seed(0)
    # every run gets the same parameters so the R chains are R samples of one distribution
    shared = {
        n: torch.randn(getattr(actor, n).shape[1:], generator=g, dtype=torch.float64)
        for n in ("W_sh", "W_ah", "b_s", "b_a", "b_h")
    }
    for n, p in shared.items():
        getattr(actor, n).copy_(p.expand_as(getattr(actor, n)))
    s = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64).expand(R, 1, 3).contiguous()
    a, *_ = actor.act(s, beta, g)
    freq = torch.bincount(a.flatten(), minlength=4).double() / R
    scaled = make_actor(R=1, S=3, A=4, H=3, code=code)
    for n, p in shared.items():
        getattr(scaled, n).copy_(beta * p.unsqueeze(0))
    F_scaled, _ = scaled.evaluate(s[:1])
    target = torch.softmax(-F_scaled[0, 0], -1)
    torch.testing.assert_close(freq, target, atol=0.03, rtol=0)


def test_bias_init_std_draws_biases_and_leaves_the_weights_alone():
    """§4.3.1: "weights and biases … initialized with a spherical Gaussian with variance 1"."""
    kw = dict(
        n_runs=3,
        n_state=400,
        n_actions=4,
        n_hidden=300,
        td_rule="sarsa",
        gamma=0.9,
        lr=Constant(0.1),
        beta=Constant(1.0),
        init_std=1.0,
        seed=5,
    )
    zero, unit = FERLActor(**kw), FERLActor(**kw, bias_init_std=1.0)
    assert torch.equal(zero.W_sh, unit.W_sh) and torch.equal(zero.W_ah, unit.W_ah)
    for name in ("b_s", "b_a", "b_h"):
        assert getattr(zero, name).eq(0).all()
    biases = torch.cat([unit.b_s.flatten(), unit.b_h.flatten()])
    assert abs(biases.std().item() - 1.0) < 0.05 and abs(biases.mean().item()) < 0.05
    assert not torch.equal(unit.b_h[0], unit.b_h[1])  # every run its own draw
