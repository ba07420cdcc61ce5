"""What the FERL actor's RBM says Q(s, a) is (``actor.q``, docs/beyond.md).

Every form is a function of the visible term c = sᵀb_s + aᵀb_a and the hidden inputs
x_k = (W_shᵀs + W_ahᵀa + b_h)_k of the state-action pair (Eq. 3.1c):

    Q(s, a) = κ (c + Σ_k φ(x_k))

so the online update θ ← θ + α δ ∂Q/∂θ (Eq. 3.10 with −F replaced by Q) adds κ α δ v to the
visible biases and κ α δ φ'(x_k) (v, 1) to hidden node k's weights and bias. The actor keeps the
energy −Q ("F": lower is better) in every formula of §3.2.

* ``free_energy`` (the dissertation, Eqs. 2.21–2.22, 3.1): φ = softplus, φ' = σ, κ = 1.
* ``scaled_free_energy`` (Elfwing, Uchibe & Doya 2013, Front. Neurorobot. 7:3): the free energy
  divided by a constant Z so that Q stays in a range the TD targets can reach when the state has
  many nodes: κ = 1/Z, φ = softplus.
* ``expected_energy`` (Elfwing, Uchibe & Doya 2016, Neural Networks 84: "From free energy to
  expected energy"): Q = −⟨E(s, a, h)⟩ under p(h | s, a) = c + Σ_k x_k σ(x_k), so
  φ(x) = x σ(x) and φ'(x) = σ(x) (1 + x (1 − σ(x))), κ = 1.
"""

import torch
from torch.nn import functional as nnf

from ferl import rbm


class FreeEnergy:
    """Q = −F(s, a), the equilibrium free energy (Eqs. 2.21–2.22)."""

    name = "free_energy"
    scale = 1.0  # κ
    boltzmann = True  # exp(β Q) is the RBM's own marginal: alternating Gibbs samples it

    def energy(self, visible: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """−Q from the visible term (…) and the hidden inputs (…, H)."""
        return rbm.free_energy_from_input(visible, x)

    def hidden_term(self, x: torch.Tensor) -> torch.Tensor:
        """φ(x) of every hidden node (…, H)."""
        return nnf.softplus(x)

    def hidden_gradient(self, x: torch.Tensor) -> torch.Tensor:
        """φ'(x) = ∂Q/∂x_k / κ of every hidden node (…, H): σ(x) (Eqs. 3.5–3.9)."""
        return torch.sigmoid(x)

    def gibbs_beta(self, beta: float) -> float:
        """The inverse temperature of a Gibbs chain whose stationary law is ∝ exp(β Q)."""
        return beta


class ScaledFreeEnergy(FreeEnergy):
    """Q = −F(s, a) / Z (Elfwing et al. 2013)."""

    name = "scaled_free_energy"

    def __init__(self, z: float):
        self.z = z
        self.scale = 1.0 / z

    def energy(self, visible: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return rbm.free_energy_from_input(visible, x) * self.scale

    def gibbs_beta(self, beta: float) -> float:
        """exp(β Q) = exp(−(β / Z) F): the chain runs at β / Z."""
        return beta * self.scale


class ExpectedEnergy(FreeEnergy):
    """Q = −⟨E(s, a, h)⟩ = c + Σ_k x_k σ(x_k) (Elfwing et al. 2016)."""

    name = "expected_energy"
    boltzmann = False  # exp(β Q) is not a marginal of the RBM: no Gibbs chain samples it

    def energy(self, visible: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return -visible - self.hidden_term(x).sum(-1)

    def hidden_term(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(x)

    def hidden_gradient(self, x: torch.Tensor) -> torch.Tensor:
        """d(x σ(x))/dx = σ(x) + x σ(x)(1 − σ(x))."""
        p = torch.sigmoid(x)
        return p * (1 + x * (1 - p))


FORMS: dict[str, type[FreeEnergy]] = {form.name: form for form in (FreeEnergy, ScaledFreeEnergy, ExpectedEnergy)}


def value_form(name: str, z: float) -> FreeEnergy:
    """The form ``actor.q`` names; ``z`` is Z of the scaled free energy."""
    return ScaledFreeEnergy(z) if name == ScaledFreeEnergy.name else FORMS[name]()
