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
* ``transformer``: the predictors' causal GPT-style transformer (``ferl.predictors.transformer``;
  Radford et al. 2019; Ni et al. 2023's memory) over x_0 … x_t, d_model = H, ``layers`` pre-LN
  blocks of ``heads`` heads, sinusoidal positions; h_t = tanh(LN_f(·)) at token t. Its state is a
  key/value cache of ``context`` tokens (``cached_token``), so acting steps one input at a time,
  while ``unroll`` runs every step of a batch of episodes at once under one causal mask.

Every core starts from the zero state and draws its weights uniform in ±1/√H, per run from the
run's generator, in the order of ``shapes`` (PyTorch's recurrent-cell initialisation; DRQN's);
the transformer rescales its draws to the predictors' transformer's scales (``adjust``).
A new memory is a ``Core`` subclass registered in ``CORES``: ``shapes``, ``fixed``, ``step`` and
``hidden`` are all the actor asks of it, ``unroll`` loops ``step`` unless the core overrides it
with a parallel form (the transformer's).
"""

import math
from collections.abc import Callable

import torch

from ferl.predictors.echo_state import leaky_step
from ferl.predictors.elman import recur
from ferl.predictors.gated import gru_cell, lstm_cell
from ferl.predictors.transformer import (
    Attention,
    Weights,
    affine,
    cached_token,
    causal_stack,
    initial_std,
    positions,
    weight_shapes,
)

ESN_LEAK, ESN_RADIUS, ESN_DENSITY = 0.5, 0.95, 0.2


class Core:
    """A recurrent core of ``n_hidden`` units over inputs of ``n_in`` values."""

    name = ""
    gates = 1
    parallel = False  # whether ``unroll`` runs every step at once (no loop over time to chunk)

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

    def input_weights(self, p: dict) -> torch.Tensor:
        """The weights from the inputs x_t into the core (R, X, ·), for the records' images."""
        return p["W_x"]

    def describe(self) -> dict:
        """What the records keep of the core beyond its name and size."""
        return {}

    def unroll(self, p: dict, x: torch.Tensor, readout: Callable = lambda h: h) -> torch.Tensor:
        """readout(h_t) of t = 0 … T stacked on dim 2, of inputs x (R, B, T+1, X), from the zero
        state: h_t (R, B, T+1, H) by default."""
        return self.run(p, x, self.zero_state(x), readout)[0]

    def zero_state(self, x: torch.Tensor) -> torch.Tensor:
        """The state before an episode's first input, for inputs x (R, B, …): zeros (R, B, state size)."""
        return x.new_zeros(*x.shape[:2], self.state_size)

    def run(
        self, p: dict, x: torch.Tensor, state: torch.Tensor, readout: Callable
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """readout(h_t) of every step of x (R, B, n, X) stacked on dim 2, from ``state``, and the
        state after the last step: ``unroll`` from the zero state, or one chunk of a fixed-size
        graph (``ferl.compiled.in_chunks``). The readout (a head's Q) runs step by step on each
        h_t as it comes, as DRQN's unroll did, so a head sees the same contiguous tensors."""
        out = []
        for t in range(x.shape[2]):
            state = self.step(p, x[:, :, t].contiguous(), state)
            out.append(readout(self.hidden(state)))
        return torch.stack(out, 2), state


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

    def input_weights(self, p: dict) -> torch.Tensor:
        return p["W_in"]


class TransformerCore(Core):
    """``memory: transformer``: ``Weights`` of ``ferl.predictors.transformer`` over tokens
    x_0 … x_t (the embedding W_in x_s + b_in + p_s, p_s sinusoidal), ``context`` tokens at most
    (≥ T_max + 1: s_0 … s_T_max). The state [h_t, n, cache] (R, B, H + 1 + layers · 2 · context · H)
    holds h_t, the tokens n seen and every layer's keys and values; the zero state is the
    episode's start (n = 0, nothing cached), so the actor's zero state needs no special case."""

    name, parallel = "transformer", True

    def __init__(
        self, n_in: int, n_hidden: int, context: int, layers: int = 1, heads: int = 1, qk_norm: float | None = None
    ):
        super().__init__(n_in, n_hidden)
        self.context, self.layers, self.attention = context, layers, Attention(heads, qk_norm)

    def shapes(self) -> dict[str, tuple]:
        return weight_shapes(self.n_in, self.n_hidden, self.layers)

    def adjust(self, params: dict) -> None:
        """The drawn U(±1/√H) weights (std 1/√(3H)) rescaled to the predictors' transformer's
        standard deviations (``initial_std``: 1/√fan-in, GPT-2's 1/√(2 · layers) on the residual
        projections), still uniform; biases 0 and LN gains 1, as GPT-2 starts."""
        for name, shape in self.shapes().items():
            if name.startswith("W_"):
                params[name].mul_(math.sqrt(3 * self.n_hidden) * initial_std(name, shape, self.layers))
            else:
                params[name].fill_(1.0 if name.endswith("_g") else 0.0)

    @property
    def state_size(self) -> int:
        return self.n_hidden + 1 + self.layers * 2 * self.context * self.n_hidden

    def weights(self, p: dict) -> Weights:
        return Weights(*(p[name] for name in Weights._fields))

    def step(self, p: dict, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Token n of the episode: x (R, B, X) attends to the cached tokens 0 … n − 1 and itself."""
        W, d = self.weights(p), self.n_hidden
        cache = state[..., d + 1 :].unflatten(-1, (self.layers, 2, self.context, d))
        head, cache = cached_token(W, self.attention, (state[..., : d + 1], cache), affine(x, W.W_in, W.b_in))
        return torch.cat([head, cache.flatten(-4)], -1)

    def unroll(self, p: dict, x: torch.Tensor, readout: Callable = lambda h: h) -> torch.Tensor:
        """The parallel form of stepping: every token of x (R, B, T+1, X) at once, token t
        attending to tokens 0 … t only (one causal mask, no loop over time), so padding after an
        episode's end reaches none of its steps; the readout sees h (R, B·(T+1), H)."""
        R, B, N, _ = x.shape
        if N > self.context:
            raise ValueError(f"context={self.context} is shorter than the episodes' {N} steps")
        W = self.weights(p)
        embedded = affine(x, W.W_in, W.b_in) + positions(torch.arange(N, device=x.device), self.n_hidden).to(x.dtype)
        out = readout(causal_stack(W, embedded, self.attention).reshape(R, B * N, self.n_hidden))
        return out.view(R, B, N, *out.shape[2:])

    def input_weights(self, p: dict) -> torch.Tensor:
        return p["W_in"].transpose(1, 2)

    def describe(self) -> dict:
        return {"context": self.context, "layers": self.layers, **self.attention._asdict()}


CORES: dict[str, type[Core]] = {
    core.name: core for core in (GRUCore, LSTMCore, ElmanCore, EchoStateCore, TransformerCore)
}
