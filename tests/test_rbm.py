"""Free energy and hidden expectations against brute-force enumeration of all 2^H hidden states."""

import itertools

import pytest
import torch

from ferl import rbm


def brute_force(v, W, b_v, b_h):
    """F(v) = −log Σ_h exp(−E(v, h)) and ⟨h⟩ by enumerating every h ∈ {0,1}^H (Eq. 2.18, 2.20)."""
    H = W.shape[-1]
    hs = torch.tensor(list(itertools.product([0.0, 1.0], repeat=H)), dtype=torch.float64)  # (2^H, H)
    # E(v, h) = −vᵀWh − vᵀb_v − hᵀb_h for every run r, state b, hidden config k
    energy = -(
        torch.einsum("rbv,rvh,kh->rbk", v, W, hs)
        + (v * b_v[:, None]).sum(-1, keepdim=True)
        + torch.einsum("rh,kh->rk", b_h, hs)[:, None]
    )
    F = -torch.logsumexp(-energy, dim=-1)
    p = torch.softmax(-energy, dim=-1)
    return F, torch.einsum("rbk,kh->rbh", p, hs)


@pytest.mark.parametrize("H", [1, 3, 6])
def test_free_energy_matches_enumeration(H):
    g = torch.Generator().manual_seed(H)
    R, B, V = 3, 5, 4
    v = torch.rand(R, B, V, generator=g, dtype=torch.float64)
    W = torch.randn(R, V, H, generator=g, dtype=torch.float64)
    b_v, b_h = torch.randn(R, V, generator=g, dtype=torch.float64), torch.randn(R, H, generator=g, dtype=torch.float64)
    F_ref, h_ref = brute_force(v, W, b_v, b_h)
    torch.testing.assert_close(rbm.free_energy(v, W, b_v, b_h), F_ref)
    torch.testing.assert_close(rbm.hidden_expectation(v, W, b_h), h_ref)


def test_shared_states_equal_per_run_states():
    """(B, V) states shown to every run give the same numbers as the same states repeated per run."""
    g = torch.Generator().manual_seed(0)
    v = torch.rand(7, 4, generator=g)
    W, b_v, b_h = torch.randn(3, 4, 5, generator=g), torch.randn(3, 4, generator=g), torch.randn(3, 5, generator=g)
    torch.testing.assert_close(rbm.free_energy(v, W, b_v, b_h), rbm.free_energy(v.expand(3, 7, 4), W, b_v, b_h))
