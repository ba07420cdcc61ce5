"""Restricted Boltzmann machine quantities at unit temperature, batched over runs.

Energy (Eq. 2.18): E(v, h) = −vᵀWh − vᵀb_v − hᵀb_h.  With the visible units clamped the
hidden units are independent (Eq. 2.19), so

* hidden expectation  ĥ = σ(Wᵀv + b_h)                                 (Eq. 3.1c, β = 1)
* equilibrium free energy F(v) = −log Σ_h exp(−E(v, h))
                               = −vᵀb_v − Σ_k softplus((Wᵀv + b_h)_k)  (Eqs. 2.20–2.22)
* gradients ∂F/∂W = −v ĥᵀ, ∂F/∂b_v = −v, ∂F/∂b_h = −ĥ                 (Eqs. 2.23–2.25, 3.5–3.9)

The closed form follows from Eq. (2.22): −ĥx + ĥ ln ĥ + (1−ĥ) ln(1−ĥ) = −softplus(x) for ĥ = σ(x).
All tensors carry the run dimension first: v (R, B, V), W (R, V, H), b_v (R, V), b_h (R, H).
"""

import torch
import torch.nn.functional as F


def hidden_input(v: torch.Tensor, W: torch.Tensor, b_h: torch.Tensor) -> torch.Tensor:
    """Total input Wᵀv + b_h of every hidden unit: (R, B, V) → (R, B, H).

    v may also be (B, V), the same states shown to every run (test images).
    """
    if v.dim() == 2:
        return torch.einsum("bv,rvh->rbh", v, W) + b_h.unsqueeze(1)
    if torch.compiler.is_compiling() and v.shape[1] == 1:
        # one state per run: inductor fuses this product and sum with the weight update before
        # it into one pass over W; baddbmm would be an external kernel making a pass of its own
        return (v.transpose(1, 2) * W).sum(1, keepdim=True) + b_h.unsqueeze(1)
    return torch.baddbmm(b_h.unsqueeze(1), v, W)


def visible_term(v: torch.Tensor, b_v: torch.Tensor) -> torch.Tensor:
    """vᵀb_v per run and state: v (R, B, V) or shared (B, V) → (R, B)."""
    if v.dim() == 2:
        return (v @ b_v.T).T
    return torch.bmm(v, b_v.unsqueeze(-1)).squeeze(-1)


def free_energy_from_input(visible_term: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """F = −vᵀb_v − Σ_k softplus(x_k), given vᵀb_v and the hidden inputs x (Eq. 2.21–2.22)."""
    return -visible_term - F.softplus(x).sum(-1)


def free_energy(v: torch.Tensor, W: torch.Tensor, b_v: torch.Tensor, b_h: torch.Tensor) -> torch.Tensor:
    """Equilibrium free energy of clamped visible states v (R, B, V) → (R, B)."""
    return free_energy_from_input(visible_term(v, b_v), hidden_input(v, W, b_h))


def hidden_expectation(v: torch.Tensor, W: torch.Tensor, b_h: torch.Tensor) -> torch.Tensor:
    """ĥ = p(h = 1 | v), Eq. (3.1c) at β = 1: (R, B, V) → (R, B, H)."""
    return torch.sigmoid(hidden_input(v, W, b_h))
