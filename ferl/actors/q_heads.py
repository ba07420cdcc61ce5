"""The value heads of the recurrent Q-learner (``actor.head``; ``ferl.actors.recurrent_q``): Q(h, a)
of every action from the core's h_t (R, B, H) → (R, B, nA). Parameters carry the run dimension first.

* ``linear``: Q(h, ·) = W_qᵀ h + b_q, W_q (R, H, nA), b_q (R, nA): DRQN's (Hausknecht & Stone 2015).
* ``free_energy``: the dissertation's RBM with h as its state nodes and a one-hot action,
  Q(h, a) = −F(h, a) = hᵀb_s + b_a,a + Σ_k softplus(x_k),  x = W_shᵀ h + W_ah,a + b_k   (Eqs. 2.21–2.22, 3.1);
  W_sh (R, H, K), W_ah (R, nA, K), b_s (R, H), b_a (R, nA), b_k (R, K) (the hidden biases, b_h of Eq. 2.18) for K = ``head_hidden`` nodes.
* ``scaled_free_energy`` (Elfwing et al. 2013) and ``expected_energy`` (Elfwing et al. 2016): the
  same RBM read by the other value forms of ``ferl.actors.values`` (docs/beyond.md).

The heads are differentiable tensor functions, so the TD loss's gradient flows through head and
core by autograd.
"""

import torch

from ferl.actors.values import FreeEnergy, value_form


class Head:
    """A value head over H inputs and nA actions."""

    name = ""

    def __init__(self, n_hidden: int, n_actions: int):
        self.n_hidden, self.n_actions = n_hidden, n_actions

    def shapes(self) -> dict[str, tuple]:
        """The parameters' shapes without the run dimension, in drawing order."""
        raise NotImplementedError

    def q(self, p: dict, h: torch.Tensor) -> torch.Tensor:
        """Q (R, B, nA) from h (R, B, H)."""
        raise NotImplementedError

    def adjust(self, params: dict, exact: bool = False) -> None:
        """Changes to the drawn initial parameters (in place); ``exact``: Q(0, a) = 0 for every
        action exactly, where the head has an offset per action."""

    def describe(self) -> dict:
        return {"head": self.name}


class LinearHead(Head):
    """``head: linear``."""

    name = "linear"

    def shapes(self) -> dict[str, tuple]:
        return {"W_q": (self.n_hidden, self.n_actions), "b_q": (self.n_actions,)}

    def q(self, p: dict, h: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(p["b_q"].unsqueeze(1), h, p["W_q"])


class EnergyHead(Head):
    """``head: free_energy``, ``scaled_free_energy``, ``expected_energy``: an RBM of ``head_hidden``
    hidden nodes whose visible nodes are h and the one-hot action, read by a value form."""

    def __init__(self, n_hidden: int, n_actions: int, form: FreeEnergy, head_hidden: int):
        super().__init__(n_hidden, n_actions)
        self.form, self.head_hidden, self.name = form, head_hidden, form.name

    def shapes(self) -> dict[str, tuple]:
        H, A, K = self.n_hidden, self.n_actions, self.head_hidden
        return {"W_sh": (H, K), "W_ah": (A, K), "b_s": (H,), "b_a": (A,), "b_k": (K,)}

    def q(self, p: dict, h: torch.Tensor) -> torch.Tensor:
        """The hidden inputs of every action x (R, B, nA, K) = W_shᵀ h + W_ah + b_k, the visible
        term hᵀb_s + b_a (R, B, nA), and Q = −energy of the value form."""
        x = torch.bmm(h, p["W_sh"]).unsqueeze(2) + (p["W_ah"] + p["b_k"].unsqueeze(1)).unsqueeze(1)
        visible = torch.bmm(h, p["b_s"].unsqueeze(-1)) + p["b_a"].unsqueeze(1)
        return -self.form.energy(visible, x)

    def adjust(self, params: dict, exact: bool = False) -> None:
        """The action biases start lowered by Σ_k φ(0) (K ln 2 for the free energies, 0 for the
        expected energy), so that Q starts near 0 as the linear head's does: otherwise every
        action's Q starts near K ln 2 ≈ 14, far above the returns, and the bootstrapped targets
        of unfinished episodes keep that optimism long after a goal's true value is learnt.

        ``exact`` (the wide initialisation, ``head_init_std``): each action's own offset,
        b_a,a = −Σ_k φ(W_ah,a,k + b_k), so that Q(h = 0, a) = 0 for every action however wide
        W_ah is drawn: the contrast between actions then comes from h alone."""
        if exact:
            params["b_a"] = -self.form.hidden_term(params["W_ah"] + params["b_k"].unsqueeze(-2)).sum(-1)
        else:
            params["b_a"] -= self.form.hidden_term(torch.zeros(self.head_hidden)).sum()

    def describe(self) -> dict:
        return {"head": self.name, "head_hidden": self.head_hidden, "q_scale": 1.0 / self.form.scale}


def head(name: str, n_hidden: int, n_actions: int, head_hidden: int, q_scale: float | None) -> Head:
    """The head ``actor.head`` names; Z of the scaled free energy is ``q_scale`` or √H (√ of the
    state nodes, Elfwing et al. 2013's choice, as the FERL actor's ``q_scale``)."""
    if name == LinearHead.name:
        return LinearHead(n_hidden, n_actions)
    form = value_form(name, q_scale or n_hidden**0.5)
    return EnergyHead(n_hidden, n_actions, form, head_hidden)
