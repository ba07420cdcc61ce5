"""The recurrent cores of the recurrent Q-learner (``actor.memory``; ``ferl.actors.recurrent_q``):
the predictors' memories (``ferl.predictors``) read x_t = (s_t, onehot(a_{t−1})) and trained end to
end by the actor's TD loss instead of by prediction. Parameters carry the run dimension first.

* ``gru`` (Cho et al. 2014): ``ferl.predictors.gated.gru_cell`` with torch.nn.GRUCell's weights
  W_x (R, X, 3H), W_h (R, H, 3H), b_x, b_h (R, 3H): DRQN's core (Hausknecht & Stone 2015).
* ``lstm`` (Hochreiter & Schmidhuber 1997; forget gate of Gers et al. 2000, its bias 1 at first):
  ``ferl.predictors.gated.lstm_cell``; the state is (h_t, c_t), the head reads h_t.
* ``elman`` (Eq. 4.3 with β_m = 1): h_t = σ(W_xᵀ x_t + W_hᵀ h_{t−1} + b_x) (``ferl.predictors.elman.recur``).
* ``esn`` (Jaeger & Haas 2004): the echo-state reservoir of ``ferl.predictors.echo_state``
  (leak λ = 0.5, spectral radius 0.95, density 0.2), fixed; only the head learns through it.

Every core starts from the zero state and draws its weights uniform in ±1/√H, per run from the
run's generator, in the order of ``shapes`` (PyTorch's recurrent-cell initialisation; DRQN's).
A new memory (e.g. an attention window, whose state would hold the last inputs) is a ``Core``
subclass registered in ``CORES``: ``shapes``, ``fixed``, ``step`` and ``hidden`` are all the actor
asks of it, ``unroll`` loops ``step`` unless the core overrides it with a parallel form.
"""

from collections.abc import Callable

import torch

from ferl.predictors.echo_state import leaky_step
from ferl.predictors.elman import recur
from ferl.predictors.gated import gru_cell, lstm_cell

ESN_LEAK, ESN_RADIUS, ESN_DENSITY = 0.5, 0.95, 0.2


class Core:
    """A recurrent core of ``n_hidden`` units over inputs of ``n_in`` values."""

    name = ""
    gates = 1

    def __init__(self, n_in: int, n_hidden: int):
        self.n_in, self.n_hidden = n_in, n_hidden

    def shapes(self) -> dict[str, tuple]:
        """The trained parameters' shapes without the run dimension, in drawing order."""
        G, H = self.gates, self.n_hidden
        return {"W_x": (self.n_in, G * H), "W_h": (H, G * H), "b_x": (G * H,), "b_h": (G * H,)}

    def fixed(self, generators: list) -> dict[str, torch.Tensor]:
        """Untrained weights (R, ...) drawn after the trained ones: none but the reservoir's."""
        return {}

    def adjust(self, params: dict) -> None:
        """Changes to the drawn initial parameters (in place)."""

    @property
    def state_size(self) -> int:
        return self.n_hidden

    def step(self, p: dict, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """The state after input x (R, B, X) from ``state`` (R, B, state_size)."""
        raise NotImplementedError

    def hidden(self, state: torch.Tensor) -> torch.Tensor:
        """h_t (…, H), what the head reads, from the state (…, state_size)."""
        return state[..., : self.n_hidden]

    def unroll(self, p: dict, x: torch.Tensor, readout: Callable = lambda h: h) -> torch.Tensor:
        """readout(h_t) of t = 0 … T stacked on dim 2, of inputs x (R, B, T+1, X), from the zero
        state: h_t (R, B, T+1, H) by default. The readout (a head's Q) runs step by step on each
        h_t as it comes, as DRQN's unroll did, so a head sees the same contiguous tensors."""
        state = x.new_zeros(*x.shape[:2], self.state_size)
        out = []
        for t in range(x.shape[2]):
            state = self.step(p, x[:, :, t].contiguous(), state)
            out.append(readout(self.hidden(state)))
        return torch.stack(out, 2)


def drive(p: dict, x: torch.Tensor) -> torch.Tensor:
    """W_xᵀ x + b_x: (R, B, X) → (R, B, G·H)."""
    return torch.baddbmm(p["b_x"].unsqueeze(1), x, p["W_x"])


class GRUCore(Core):
    """``memory: gru`` (DRQN's)."""

    name, gates = "gru", 3

    def step(self, p: dict, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return gru_cell(drive(p, x), torch.baddbmm(p["b_h"].unsqueeze(1), state, p["W_h"]), state)


class LSTMCore(Core):
    """``memory: lstm``: the state (h_t, c_t), (R, B, 2H)."""

    name, gates = "lstm", 4

    def shapes(self) -> dict[str, tuple]:
        shapes = super().shapes()
        del shapes["b_h"]  # one bias per gate: b_x
        return shapes

    def adjust(self, params: dict) -> None:
        params["b_x"][:, self.n_hidden : 2 * self.n_hidden] = 1.0  # remember from the start

    @property
    def state_size(self) -> int:
        return 2 * self.n_hidden

    def step(self, p: dict, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return lstm_cell(drive(p, x), p["W_h"].transpose(1, 2), state)


class ElmanCore(Core):
    """``memory: elman``."""

    name = "elman"

    def shapes(self) -> dict[str, tuple]:
        shapes = super().shapes()
        del shapes["b_h"]
        return shapes

    def step(self, p: dict, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return recur(p["W_h"].transpose(1, 2), 1.0, drive(p, x), state)


class EchoStateCore(Core):
    """``memory: esn``: a fixed reservoir W_in (R, X, H), W_res (R, H, H), nothing trained."""

    name = "esn"

    def shapes(self) -> dict[str, tuple]:
        return {}

    def fixed(self, generators: list) -> dict[str, torch.Tensor]:
        X, H = self.n_in, self.n_hidden

        def uniform(*shape):
            return torch.stack([torch.rand(*shape, generator=g) * 2 - 1 for g in generators])

        W_in, W_res = uniform(X, H), uniform(H, H)
        W_res *= torch.stack([torch.rand(H, H, generator=g) < ESN_DENSITY for g in generators])
        radius = torch.linalg.eigvals(W_res.double()).abs().amax(-1).float().clamp(min=1e-12)
        return {"W_in": W_in, "W_res": W_res * (ESN_RADIUS / radius).view(-1, 1, 1)}

    def step(self, p: dict, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return leaky_step(p["W_res"], ESN_LEAK, torch.bmm(x, p["W_in"]), state)


CORES: dict[str, type[Core]] = {core.name: core for core in (GRUCore, LSTMCore, ElmanCore, EchoStateCore)}
