"""A feed-forward Q-network actor: the recurrent-model architecture's Q-net (Whitehead & Lin
1995, Lin & Mitchell 1993) that §4.2 replaces with the FERL actor's RBM, as a baseline.

One hidden layer of sigmoid units (as many as the FERL actor's) and one linear output per action:

    h = σ(W_1ᵀ s + b_1),   Q(s, a) = W_2[:, a]ᵀ h + b_2[a],   F = −Q

trained online by the same TD rule (δ = r − γ F(s', a') + F(s, a), ``ferl.actors.td``) and the same
softmax / β schedule (Eq. 3.11) as the FERL actor. Its update is the hand-written gradient of
Q(s, a), θ ← θ + α δ ∂Q(s, a)/∂θ (the FERL actor's Eq. 3.10 with another Q):

    ∂Q/∂W_2[:, a] = h,   ∂Q/∂b_2[a] = 1,   ∂Q/∂b_1 = W_2[:, a] ⊙ h ⊙ (1 − h),   ∂Q/∂W_1 = s (∂Q/∂b_1)ᵀ

Parameters carry the run dimension first: W_1 (R, S, H), b_1 (R, H), W_2 (R, H, nA), b_2 (R, nA).
The cache of ``evaluate`` is h, shared by all actions: (R, B, nA, H) as a broadcast view.
"""

import math
from typing import Literal

import torch

from ferl.actors.softmax import SoftmaxActor
from ferl.config.params import NonNegative, PositiveInt, checked

LRNorm = Literal["fan_in", "none"]  # α / √(state inputs of a hidden node), or α as given


class MLPQActor(SoftmaxActor):
    """The feed-forward Q-network baseline (Lin & Mitchell 1993): Q(s, a) = W_2[:, a]ᵀ σ(W_1ᵀ s + b_1)
    + b_2[a] in place of the RBM of §4.2, with the FERL actor's TD rule and softmax (Eq. 3.11),
    updated by θ ← θ + α δ ∂Q/∂θ (Eq. 3.10 with this Q; module docstring)."""

    W_1: torch.Tensor  # (R, S, H)
    W_2: torch.Tensor  # (R, H, nA)
    b_1: torch.Tensor  # (R, H)
    b_2: torch.Tensor  # (R, nA)

    @checked
    def __init__(
        self,
        *,
        n_hidden: PositiveInt,
        lr_norm: LRNorm = "fan_in",
        init_std: NonNegative = 0.1,
        td_fresh: bool = True,
        **softmax,
    ):
        """``softmax``: the sizes, TD rule, γ, schedules and seed every softmax actor takes
        (``SoftmaxActor``)."""
        super().__init__(**softmax)
        n_runs, n_state, n_actions = self.sizes
        self.td_fresh, self.n_hidden = td_fresh, n_hidden
        self.lr_divisor = math.sqrt(n_state) if lr_norm == "fan_in" else 1.0
        gens = self.run_generators()
        draw = lambda *shape: torch.stack([torch.randn(*shape, generator=g) for g in gens]) * init_std  # noqa: E731
        self.register_buffer("W_1", draw(n_state, n_hidden))
        self.register_buffer("W_2", draw(n_hidden, n_actions))
        self.register_buffer("b_1", torch.zeros(n_runs, n_hidden))
        self.register_buffer("b_2", torch.zeros(n_runs, n_actions))

    @property
    def n_runs(self) -> int:
        return self.W_1.shape[0]

    def describe(self) -> dict:
        return {
            "kind": "mlp_q",
            "n_hidden": self.n_hidden,
            "gamma": self.gamma,
            "td_rule": self.td_rule,
            "td_fresh": self.td_fresh,
        }

    def state_weights(self) -> torch.Tensor:
        return self.W_1

    def hidden(self, h: torch.Tensor) -> torch.Tensor:
        return h

    def features(self, s: torch.Tensor) -> torch.Tensor:
        """h = σ(W_1ᵀ s + b_1): s (R, B, S) or shared (B, S) → (R, B, H)."""
        x = torch.matmul(s, self.W_1) if s.dim() == 2 else torch.bmm(s, self.W_1)
        return torch.sigmoid(x + self.b_1.unsqueeze(1))

    def evaluate(self, s: torch.Tensor):
        """F = −Q (R, B, nA) of every action and h broadcast over the actions (R, B, nA, H)."""
        h = self.features(s)
        F = -(torch.bmm(h, self.W_2) + self.b_2.unsqueeze(1))
        return F, h.unsqueeze(2).expand(-1, -1, F.shape[-1], -1)

    def evaluate_actions(self, s: torch.Tensor, a: torch.Tensor):
        """F (R, B) and h (R, B, H) of the given actions a (R, B)."""
        F, h = self.evaluate(s)
        return F.gather(-1, a.unsqueeze(-1)).squeeze(-1), h[:, :, 0]

    def learn(self, s, a, h, delta, lr, s_next, a_next, F_next, h_next):
        """θ ← θ + α δ ∂Q(s, a)/∂θ (``update``); then F and h of (s', a') for the next TD error,
        at the updated parameters with ``td_fresh`` (as the T-maze FERL actor)."""
        self.update(s, a, h, delta, lr)
        return self.evaluate_actions(s_next, a_next) if self.td_fresh else (F_next, h_next)

    @torch.no_grad()
    def update(self, s, a, h, delta, lr) -> None:
        """The gradient step of the module docstring, summed over the B axis: s (R, B, S),
        a (R, B), h (R, B, H) at (s, a), delta (R, B)."""
        step = lr * delta  # α δ (R, B)
        w_a = self.W_2.transpose(1, 2).gather(1, a.unsqueeze(-1).expand(-1, -1, self.n_hidden))  # W_2[:, a] (R, B, H)
        g_hidden = step.unsqueeze(-1) * w_a * h * (1 - h)  # α δ ∂Q/∂b_1
        onehot = torch.nn.functional.one_hot(a, self.W_2.shape[2]).to(h.dtype)  # (R, B, nA)
        self.W_2.baddbmm_(h.transpose(1, 2), step.unsqueeze(-1) * onehot)
        self.b_2.add_((step.unsqueeze(-1) * onehot).sum(1))
        self.W_1.baddbmm_(s.transpose(1, 2), g_hidden)
        self.b_1.add_(g_hidden.sum(1))
