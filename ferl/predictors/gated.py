"""Gated memories that last (§5.4): LSTM (Hochreiter & Schmidhuber 1997, with the forget gate of
Gers et al. 2000) and GRU (Cho et al. 2014), batched over runs, trained by BPTT through autograd.

The memory reads u_{t−1} = (c_y y_{t−1}, c_a a_{t−1}), as the Elman memory does (Eq. 4.3):

LSTM  (i, f, g, o) = (σ, σ, tanh, σ)(W u_{t−1} + U h_{t−1} + b)
      c_t = f ⊙ c_{t−1} + i ⊙ g,   h_t = o ⊙ tanh(c_t)
GRU   (r, z) = σ(W_{r,z} u_{t−1} + U_{r,z} h_{t−1} + b_{r,z})
      n = tanh(W_n u_{t−1} + b_n + r ⊙ (U_n h_{t−1} + b_hn)),   h_t = (1 − z) ⊙ n + z ⊙ h_{t−1}

h_0 = c_0 = 0. The output heads and the actor see h_t (``memory``); the LSTM's cell state c_t stays
inside the memory (the actor's state keeps the dissertation's size N^m). The memory's weights start
uniform in ±1/√N^m (the usual initialisation of gated cells: the unit-variance Gaussian of §4.3.1
saturates the gates), the LSTM's forget-gate bias at 1 (Gers et al. 2000) so that it remembers
from the start; the heads start as the Elman predictor's do. Parameters (R, G·M, ·) for G gates.
"""

import torch
from torch import nn

from ferl.predictors.heads import linear, scaled
from ferl.predictors.recurrent import RecurrentPredictor, autograd_bptt


def lstm_cell(x: torch.Tensor, U: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
    """(h_t, c_t) concatenated (…, 2M) from the input drive x = W u + b (R, B, 4M) and (h, c)."""
    h, c = state.chunk(2, -1)
    i, f, g, o = torch.baddbmm(x, h, U.transpose(1, 2)).chunk(4, -1)
    c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    return torch.cat([torch.sigmoid(o) * torch.tanh(c), c], -1)


def gru_cell(x: torch.Tensor, h_drive: torch.Tensor, h: torch.Tensor, b_hn: torch.Tensor | None = None) -> torch.Tensor:
    """h_t (R, B, M) from the input drive x = W u + b (R, B, 3M), the recurrent drive U h_{t−1}
    (R, B, 3M) and h_{t−1}, the gates in PyTorch's order (r, z, n) and with its arithmetic
    (torch.nn.GRUCell): n = tanh(x_n + r ⊙ (U_n h_{t−1} + b_hn)), h_t = n + z ⊙ (h_{t−1} − n).
    b_hn (R, M): the recurrent bias of n where ``h_drive`` leaves it out. The one GRU cell of
    ferl: the gated memory's and DRQN's (``ferl.actors.drqn``)."""
    x_r, x_z, x_n = x.chunk(3, -1)
    h_r, h_z, h_n = h_drive.chunk(3, -1)
    r, z = torch.sigmoid(x_r + h_r), torch.sigmoid(x_z + h_z)
    n = torch.tanh(x_n + r * (h_n if b_hn is None else h_n + b_hn.unsqueeze(1)))
    return n + z * (h - n)


class GatedPredictor(RecurrentPredictor):
    """A gated memory of ``n_memory`` units (see the module docstring); the other arguments are
    ``RecurrentPredictor``'s."""

    gates = 0

    def init_memory(self, gaussian, generators: list, n_obs: int, n_actions: int, n_memory: int) -> None:
        M, k = n_memory, n_memory**-0.5

        def uniform(*shape):
            return nn.Parameter(torch.stack([torch.rand(*shape, generator=g) * 2 - 1 for g in generators]) * k)

        self.W, self.U, self.b = (
            uniform(self.gates * M, n_obs + n_actions),
            uniform(self.gates * M, M),
            uniform(self.gates * M),
        )

    def memory_parameters(self) -> list:
        return [self.W, self.U, self.b]

    def drive(self, params: list, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """W u + b for inputs y (R, …, Y), a (R, …, A): (R, …, G·M)."""
        u = torch.cat([scaled(y, self.c_y), scaled(a, self.c_a)], -1)
        return linear(u, params[0]) + params[2].view(params[2].shape[0], *(1,) * (u.dim() - 2), -1)

    def cell(self, params: list, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def state_size(self) -> int:
        return self.memory_size

    # ---- online API ---------------------------------------------------------------------------
    @torch.no_grad()
    def initial_state(self) -> torch.Tensor:
        """h_0 (and c_0) = 0, (R, state size)."""
        return self.W.new_zeros(self.W.shape[0], self.state_size())

    def memory(self, state: torch.Tensor) -> torch.Tensor:
        """h_t, (R, M): what the heads and the actor see."""
        return state[:, : self.memory_size]

    @torch.no_grad()
    def step(self, state: torch.Tensor, y_prev: torch.Tensor, a_prev: torch.Tensor) -> torch.Tensor:
        """The state after y_{t−1} (R, Y) and one-hot a_{t−1} (R, A)."""
        params = self.memory_parameters()
        x = self.drive(params, y_prev, a_prev).unsqueeze(1)
        return self.cell(params, x, state.unsqueeze(1)).squeeze(1)

    # ---- sequences ----------------------------------------------------------------------------
    def unroll_with(self, params: list, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """h_0 … h_T (R, B, T+1, M) of padded sequences y (R, B, T+1, Y), a (R, B, T, A) under
        memory parameters ``params`` (leaves of autograd while training)."""
        x, state, h_0 = self.sequence_start(params, y, a)
        h, _ = self.run_steps(params, x, state)
        return torch.cat([h_0.unsqueeze(2), h], 2)

    def sequence_start(self, params: list, y: torch.Tensor, a: torch.Tensor) -> tuple:
        """The drive W u_{t−1} + b of every step (R, B, T, G·M), the state h_0 (and c_0) = 0 and h_0."""
        R, B = y.shape[:2]
        state = torch.zeros(R, B, self.state_size(), dtype=y.dtype, device=y.device)
        return self.drive(params, y[:, :, :-1], a), state, state[..., : self.memory_size]

    def run_steps(self, params: list, x: torch.Tensor, state: torch.Tensor) -> tuple:
        """h_t of the steps of drives x (R, B, n, G·M) from ``state``, (R, B, n, M), and the state after them."""
        h = []
        for x_t in x.unbind(2):
            state = self.cell(params, x_t, state)
            h.append(state[..., : self.memory_size])
        return torch.stack(h, 2), state

    def unroll(self, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return self.unroll_with(self.memory_parameters(), y, a)

    traceable_bptt = True  # autograd_bptt is tensor operations and torch.func: PredictorBatch.fuse compiles it
    time_chunks = True  # sequence_start and run_steps split the unroll (ferl.predictors.training.chunked_bptt)
    bptt = staticmethod(autograd_bptt)


class LSTMPredictor(GatedPredictor):
    """``memory: lstm``: the state is (h_t, c_t), (R, 2M); the actor sees h_t."""

    kind, gates = "lstm", 4

    def init_memory(self, gaussian, generators: list, n_obs: int, n_actions: int, n_memory: int) -> None:
        super().init_memory(gaussian, generators, n_obs, n_actions, n_memory)
        with torch.no_grad():
            self.b[:, n_memory : 2 * n_memory] = 1.0  # forget gate open at first (Gers et al. 2000)

    def state_size(self) -> int:
        return 2 * self.memory_size

    def cell(self, params: list, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return lstm_cell(x, params[1], state)


class GRUPredictor(GatedPredictor):
    """``memory: gru``: the state is h_t, (R, M)."""

    kind, gates = "gru", 3

    def init_memory(self, gaussian, generators: list, n_obs: int, n_actions: int, n_memory: int) -> None:
        super().init_memory(gaussian, generators, n_obs, n_actions, n_memory)
        self.b_hn = nn.Parameter(torch.zeros(len(generators), n_memory))

    def memory_parameters(self) -> list:
        return [self.W, self.U, self.b, self.b_hn]

    def cell(self, params: list, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return gru_cell(x, torch.bmm(state, params[1].transpose(1, 2)), state, params[3])
