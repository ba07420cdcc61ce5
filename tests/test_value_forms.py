"""Value forms of the FERL actor (actor.q): Q(s, a) against brute-force enumeration of the hidden
states, the update against autograd, td_fresh, the normalised step, and factored Gibbs actions
against the exact Boltzmann law over every action."""

import itertools

import pytest
import torch

from ferl.actors import free_energy
from ferl.actors.free_energy import FERLActor
from ferl.bits import from_bits, to_bits
from ferl.schedules import Constant

FORMS = ["free_energy", "scaled_free_energy", "expected_energy"]
PARAMS = ("W_sh", "W_ah", "b_s", "b_a", "b_h")


def make_actor(q, R=2, S=3, A=4, H=4, code="onehot", **kw):
    actor = FERLActor(
        n_runs=R,
        n_state=S,
        n_actions=A,
        n_hidden=H,
        td_rule="sarsa",
        gamma=0.9,
        lr=Constant(0.1),
        beta=Constant(1.0),
        init_std=0.8,
        action_code=code,
        q=q,
        seed=2,
        **kw,
    ).double()
    g = torch.Generator().manual_seed(7)
    for name in ("b_s", "b_a", "b_h"):
        getattr(actor, name).copy_(torch.randn(getattr(actor, name).shape, generator=g, dtype=torch.float64) * 0.5)
    return actor


def brute_force_q(q, params, s, code, n_state):
    """Q of one run's (s, code) by summing over all 2^H hidden states: the free energy
    F = −log Σ_h exp(−E(v, h)) (divided by Z = √S when scaled) or the expected energy
    −Σ_h p(h | v) E(v, h), with E(v, h) = −vᵀWh − vᵀb_v − hᵀb_h (Eq. 2.18)."""
    W = torch.cat([params["W_sh"], params["W_ah"]], 0)
    b_v = torch.cat([params["b_s"], params["b_a"]], 0)
    v = torch.cat([s, code])
    hs = torch.tensor(list(itertools.product([0.0, 1.0], repeat=W.shape[1])), dtype=torch.float64)
    neg_energy = hs @ (W.T @ v) + v @ b_v + hs @ params["b_h"]  # −E(v, h) for every h
    if q == "expected_energy":
        return (torch.softmax(neg_energy, 0) * neg_energy).sum()
    log_z = torch.logsumexp(neg_energy, 0)
    return log_z / n_state**0.5 if q == "scaled_free_energy" else log_z


@pytest.mark.parametrize("code", ["onehot", "binary"])
@pytest.mark.parametrize("q", FORMS)
def test_every_form_is_its_sum_over_hidden_states(q, code):
    actor = make_actor(q, code=code)
    s = torch.rand(2, 3, 3, dtype=torch.float64)
    F, _ = actor.evaluate(s)
    for r, b, a in itertools.product(range(2), range(3), range(4)):
        params = {n: getattr(actor, n)[r] for n in PARAMS}
        assert -F[r, b, a].item() == pytest.approx(
            brute_force_q(q, params, s[r, b], actor.codes[a], 3).item(), rel=1e-10
        )
    if code == "binary":  # only the chosen actions' F
        a = torch.tensor([[0, 3, 1], [2, 2, 0]])
        F_a, _ = actor.evaluate_actions(s, a)
        torch.testing.assert_close(F_a, F.gather(-1, a.unsqueeze(-1)).squeeze(-1))


@pytest.mark.parametrize("code", ["onehot", "binary"])
@pytest.mark.parametrize("q", FORMS)
def test_update_is_lr_delta_grad_q(q, code):
    """θ ← θ + α δ ∂Q/∂θ (Eq. 3.10 with Q for −F), ∂Q/∂θ by autograd of the brute-force Q."""
    actor = make_actor(q, code=code)
    s = torch.rand(2, 1, 3, dtype=torch.float64)
    a = torch.tensor([[1], [3]])
    delta = torch.tensor([[0.8], [-1.3]], dtype=torch.float64)
    before = {n: getattr(actor, n).clone() for n in PARAMS}
    _, x = actor.evaluate(s)
    x_sa = x[torch.arange(2), 0, a[:, 0]].unsqueeze(1)
    actor.update(s, a, x_sa, delta, lr=0.05)
    for r in range(2):
        params = {n: before[n][r].clone().requires_grad_(True) for n in PARAMS}
        brute_force_q(q, params, s[r, 0], actor.codes[a[r, 0]], 3).backward()
        for n in PARAMS:
            torch.testing.assert_close(getattr(actor, n)[r] - before[n][r], 0.05 * delta[r, 0] * params[n].grad, msg=n)


@pytest.mark.parametrize("code", ["onehot", "binary"])
@pytest.mark.parametrize("q", FORMS)
def test_td_fresh_gives_the_next_value_at_the_updated_parameters(q, code):
    actor = make_actor(q, code=code, td_fresh=True)
    s, s_next = torch.rand(2, 1, 3, dtype=torch.float64), torch.rand(2, 1, 3, dtype=torch.float64)
    a, a_next = torch.tensor([[1], [3]]), torch.tensor([[1], [0]])
    delta = torch.tensor([[0.8], [-1.3]], dtype=torch.float64)
    rows = torch.arange(2)
    _, x = actor.evaluate(s)
    F_next, x_next = actor.evaluate(s_next)
    got = actor.learn(
        s,
        a,
        x[rows, 0, a[:, 0]].unsqueeze(1),
        delta,
        0.05,
        s_next,
        a_next,
        F_next[rows, 0, a_next[:, 0]].unsqueeze(1),
        x_next[rows, 0, a_next[:, 0]].unsqueeze(1),
    )
    F_after, x_after = actor.evaluate(s_next)
    torch.testing.assert_close(
        got, (F_after[rows, 0, a_next[:, 0]].unsqueeze(1), x_after[rows, 0, a_next[:, 0]].unsqueeze(1))
    )


@pytest.mark.parametrize("q", FORMS)
def test_gradient_norm_and_the_normalised_step(q):
    """‖∂Q/∂θ‖² against autograd; with lr_norm=gradient one update changes Q(s, a) by ≈ α δ."""
    actor = make_actor(q, code="binary", lr_norm="gradient")
    s = torch.rand(2, 1, 3, dtype=torch.float64)
    a = torch.tensor([[2], [1]])
    F, x = actor.evaluate(s)
    rows = torch.arange(2)
    x_sa = x[rows, 0, a[:, 0]].unsqueeze(1)
    for r in range(2):
        params = {n: getattr(actor, n)[r].clone().requires_grad_(True) for n in PARAMS}
        brute_force_q(q, params, s[r, 0], actor.codes[a[r, 0]], 3).backward()
        want = sum(p.grad.pow(2).sum() for p in params.values())
        assert actor.gradient_norm(s, a, x_sa)[r, 0].item() == pytest.approx(want.item(), rel=1e-10)
    delta = torch.full((2, 1), 1.0, dtype=torch.float64)
    actor.learn(s, a, x_sa, delta, 1e-4, s, a, F[rows, 0, a[:, 0]].unsqueeze(1), x_sa)
    F_after, _ = actor.evaluate(s)
    change = -(F_after - F)[rows, 0, a[:, 0]]
    torch.testing.assert_close(change, torch.full((2,), 1e-4, dtype=torch.float64), rtol=1e-3, atol=0)


def factored_actor(R, beta, q="free_energy", sweeps=30):
    actor = FERLActor(
        n_runs=R,
        n_state=3,
        n_actions=8,
        n_hidden=3,
        td_rule="sarsa",
        gamma=0.0,
        lr=Constant(0.1),
        beta=Constant(beta),
        init_std=0.0,
        action_code="binary",
        action_selection="gibbs",
        gibbs_sweeps=sweeps,
        q=q,
        seed=0,
    ).double()
    g = torch.Generator().manual_seed(3)
    shared = {n: torch.randn(getattr(actor, n).shape[1:], generator=g, dtype=torch.float64) for n in PARAMS}
    for n, p in shared.items():  # every run the same network: R chains are R samples of one law
        getattr(actor, n).copy_(p.expand_as(getattr(actor, n)))
    return actor


def exact_law(actor, s, beta):
    """P(a | s) ∝ exp(−β F_β(s, a)) of the chain at inverse temperature β over all 8 actions:
    β F_β is the free energy of the same RBM with every parameter multiplied by β (§2.1.5)."""
    W = torch.cat([actor.W_sh[0], actor.W_ah[0]], 0) * beta
    b_v, b_h = torch.cat([actor.b_s[0], actor.b_a[0]]) * beta, actor.b_h[0] * beta
    codes = to_bits(torch.arange(8), 3).double()
    v = torch.cat([s.expand(8, 3), codes], 1)
    neg_F = v @ b_v + torch.nn.functional.softplus(v @ W + b_h).sum(1)
    return torch.softmax(neg_F, 0)


@pytest.mark.parametrize("q", ["free_energy", "scaled_free_energy"])
def test_factored_gibbs_samples_the_boltzmann_law_over_all_actions(monkeypatch, q):
    """Total variation between the sampler's empirical law over all 2^3 actions and the exact law
    ≤ 0.02 (the sampling error of 20 000 draws is ≈ 0.01); a chain at a wrong temperature misses it."""
    monkeypatch.setattr(free_energy, "MAX_ENUMERATED_ACTIONS", 4)  # 8 actions: factored, never enumerated
    R, beta = 20_000, 1.5
    actor = factored_actor(R, beta, q)
    assert not actor.enumerated
    s = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    a, F_a, _, F_boot = actor.act(s.expand(R, 1, 3).contiguous(), beta, torch.Generator().manual_seed(5))
    freq = torch.bincount(a.flatten(), minlength=8).double() / R
    chain_beta = beta / 3**0.5 if q == "scaled_free_energy" else beta
    exact = exact_law(actor, s, chain_beta)
    assert 0.5 * (freq - exact).abs().sum() < 0.02
    assert 0.5 * (exact_law(actor, s, 2 * chain_beta) - exact).abs().sum() > 0.05  # the bound tells them apart
    torch.testing.assert_close(F_boot, F_a)  # SARSA bootstraps from the sampled action's F


def test_bits_round_trip():
    i = torch.tensor([0, 1, 5, 2**40 - 1, 2**39 + 3])
    bits = to_bits(i, 40)
    assert bits.shape == (5, 40) and bits[2, -3:].tolist() == [1.0, 0.0, 1.0]
    assert torch.equal(from_bits(bits), i)


def test_annealed_chain_rises_geometrically_to_beta():
    """gibbs_anneal_from: the sweeps' inverse temperatures go from that value to β by a constant
    ratio (at β / Z for the scaled free energy); without it every sweep runs at β."""
    plain = FERLActor(
        n_runs=1,
        n_state=3,
        n_actions=8,
        n_hidden=2,
        td_rule="sarsa",
        gamma=0.0,
        lr=Constant(0.1),
        beta=Constant(1.0),
        action_code="binary",
        action_selection="gibbs",
        gibbs_sweeps=5,
    )
    assert plain.chain_betas(4.0) == [4.0] * 5
    annealed = FERLActor(
        n_runs=1,
        n_state=4,
        n_actions=8,
        n_hidden=2,
        td_rule="sarsa",
        gamma=0.0,
        lr=Constant(0.1),
        beta=Constant(1.0),
        action_code="binary",
        action_selection="gibbs",
        gibbs_sweeps=5,
        gibbs_anneal_from=1.0,
        q="scaled_free_energy",
    )
    betas = torch.tensor(annealed.chain_betas(16.0), dtype=torch.float64)
    torch.testing.assert_close(betas, torch.tensor([1.0, 2.0, 4.0, 8.0, 16.0], dtype=torch.float64) / 2)


def test_the_configs_value_forms_are_the_implemented_ones():
    """``actor.q``'s allowed values (a Literal the type checker reads) name exactly the forms of
    ``ferl.actors.values``: a form added to one and not the other fails here."""
    from typing import get_args

    from ferl.actors.values import FORMS

    assert sorted(get_args(free_energy.ValueForm)) == sorted(FORMS)
