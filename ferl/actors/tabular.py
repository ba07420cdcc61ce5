"""Tabular Q-learning: the oracle baseline's actor (``actor=oracle``, with the environment's
``true_state`` view, docs/records.md).

Q(s, a) = sᵀ Θ[:, a] with Θ (R, S, nA). On one-hot states — the environment's true hidden state,
e.g. (maze position, s0, s1) — Θ is the table of Q-values and the TD update (§3.2)

    Q(s, a) ← Q(s, a) + α δ,   δ = r + γ max_a' Q(s', a') − Q(s, a)  (td_rule q)

is Watkins' Q-learning; on other states it is the linear Q of the same gradient rule
(θ ← θ + α δ ∂Q/∂θ, ∂Q/∂Θ[:, a] = s). The TD step and the softmax / β schedule (Eq. 3.11) are
those of every actor (``ferl.actors.td``). With values initialised to 0 the table learns from
what it visits only, as value iteration's fixed point (``tests/test_baselines.py``) requires.
"""

import torch

from ferl.actors.softmax import SoftmaxActor
from ferl.config.params import checked


class TabularQActor(SoftmaxActor):
    """The oracle baseline's actor: Q(s, a) = sᵀ Θ[:, a] (a Q-table on one-hot true states),
    Watkins' Q-learning by the TD update of §3.2 and the softmax of Eq. 3.11 (module docstring)."""

    Q: torch.Tensor  # (R, S, nA)

    @checked
    def __init__(self, *, init_value: float = 0.0, **softmax):
        """``softmax``: the sizes, TD rule, γ, schedules and seed every softmax actor takes
        (``SoftmaxActor``); every Q starts at ``init_value``."""
        super().__init__(**softmax)
        self.register_buffer("Q", torch.full(self.sizes, float(init_value)))

    @property
    def n_runs(self) -> int:
        return self.Q.shape[0]

    def describe(self) -> dict:
        return {"kind": "tabular_q", "gamma": self.gamma, "td_rule": self.td_rule, "n_hidden": 0}

    def state_weights(self) -> torch.Tensor:
        return self.Q

    def hidden(self, q: torch.Tensor) -> torch.Tensor:
        """No hidden layer: the records keep the chosen action's value."""
        return q

    def evaluate(self, s: torch.Tensor):
        """F = −Q (R, B, nA) and, as the cache, Q itself (R, B, nA, 1)."""
        q = torch.matmul(s, self.Q) if s.dim() == 2 else torch.bmm(s, self.Q)
        return -q, q.unsqueeze(-1)

    def learn(self, s, a, q_sa, delta, lr, s_next, a_next, F_next, q_next):
        """Θ[:, a] += α δ s (Q(s, a) += α δ for one-hot s); F(s', a') afresh, so a state that
        follows itself bootstraps from its updated value."""
        onehot = torch.nn.functional.one_hot(a, self.Q.shape[2]).to(s.dtype)  # (R, B, nA)
        self.Q.baddbmm_(s.transpose(1, 2), (lr * delta).unsqueeze(-1) * onehot)
        q = torch.bmm(s_next, self.Q).gather(-1, a_next.unsqueeze(-1))
        return -q.squeeze(-1), q
