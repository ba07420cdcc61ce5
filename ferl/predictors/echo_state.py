"""An echo-state memory (Jaeger & Haas 2004; §5.4: "randomly initialized and properly adjusted
sparsely connected recurrent weights"), batched over runs: only the readout learns.

A fixed reservoir of N^m leaky-integrator tanh units reads u_{t−1} = (c_y y_{t−1}, c_a a_{t−1}):

    x_t = (1 − λ) x_{t−1} + λ tanh(W_in u_{t−1} + W_res x_{t−1}),   x_0 = 0

W_in has entries uniform in [−1, 1]; W_res keeps a fraction ``density`` of such entries and is
scaled to the spectral radius ρ (``spectral_radius``), which with the leak rate λ sets how long an
input echoes (the echo-state property needs ρ < 1 for λ = 1). The output heads (the readout) are
the only trained part, by SGD on the loss of ``ferl.predictors.heads`` with their gradients
written out; the actor sees the reservoir state x_t.
"""

from typing import Annotated

import torch

from ferl.config.params import Allowed, Positive, checked
from ferl.predictors.heads import linear, scaled
from ferl.predictors.recurrent import RecurrentPredictor

Fraction = Annotated[float, Allowed(lambda x: 0 < x <= 1, "in (0, 1]")]


def leaky_step(W_res: torch.Tensor, leak: float, drive: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """x_t = (1 − λ) x_{t−1} + λ tanh(drive + W_res x_{t−1}); drive, x (R, B, M)."""
    return torch.lerp(x, torch.tanh(torch.baddbmm(drive, x, W_res.transpose(1, 2))), leak)


class EchoStatePredictor(RecurrentPredictor):
    """``memory: esn``: ``spectral_radius`` ρ of W_res, ``leak_rate`` λ and the ``density`` of
    W_res's nonzero entries; the other arguments are ``RecurrentPredictor``'s."""

    kind = "esn"
    W_in: torch.Tensor  # (R, M, Y + A), fixed
    W_res: torch.Tensor  # (R, M, M), fixed, spectral radius ρ

    @checked
    def __init__(self, spectral_radius: Positive = 0.95, leak_rate: Fraction = 0.5, density: Fraction = 0.2, **kwargs):
        self.spectral_radius, self.leak_rate, self.density = spectral_radius, leak_rate, density
        super().__init__(**kwargs)

    def init_memory(self, gaussian, generators: list, n_obs: int, n_actions: int, n_memory: int) -> None:
        def uniform(*shape):
            return torch.stack([torch.rand(*shape, generator=g) * 2 - 1 for g in generators])

        W_in = uniform(n_memory, n_obs + n_actions)
        W_res = uniform(n_memory, n_memory)
        W_res *= torch.stack([torch.rand(n_memory, n_memory, generator=g) < self.density for g in generators])
        radius = torch.linalg.eigvals(W_res.double()).abs().amax(-1).float().clamp(min=1e-12)
        self.register_buffer("W_in", W_in)
        self.register_buffer("W_res", W_res * (self.spectral_radius / radius).view(-1, 1, 1))

    def memory_parameters(self) -> list:
        return []  # the reservoir is fixed

    # nor does it take the actor's TD error: not a ferl.trainers.memory_td.MemoryFromTD, which
    # td_to_memory refuses
    descend_memory = None  # type: ignore[assignment]

    @property
    def gains(self) -> tuple:
        return self.c_y, self.c_a, self.leak_rate

    def describe(self) -> dict:
        return {
            **super().describe(),
            "spectral_radius": self.spectral_radius,
            "leak_rate": self.leak_rate,
            "density": self.density,
        }

    def drive(self, W_in: torch.Tensor, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return linear(torch.cat([scaled(y, self.c_y), scaled(a, self.c_a)], -1), W_in)

    # ---- online API ---------------------------------------------------------------------------
    @torch.no_grad()
    def initial_state(self) -> torch.Tensor:
        return self.W_res.new_zeros(self.W_res.shape[0], self.memory_size)

    def memory(self, state: torch.Tensor) -> torch.Tensor:
        return state

    @torch.no_grad()
    def step(self, x: torch.Tensor, y_prev: torch.Tensor, a_prev: torch.Tensor) -> torch.Tensor:
        drive = self.drive(self.W_in, y_prev, a_prev).unsqueeze(1)
        return leaky_step(self.W_res, self.leak_rate, drive, x.unsqueeze(1)).squeeze(1)

    # ---- sequences ----------------------------------------------------------------------------
    def unroll_with(self, W_in: torch.Tensor, W_res: torch.Tensor, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """x_0 … x_T (R, B, T+1, M) of padded sequences under reservoir weights (R, …)."""
        drive = self.drive(W_in, y[:, :, :-1], a)
        x = [torch.zeros(*y.shape[:2], self.memory_size, dtype=y.dtype, device=y.device)]
        for drive_t in drive.unbind(2):
            x.append(leaky_step(W_res, self.leak_rate, drive_t, x[-1]))
        return torch.stack(x, 2)

    def unroll(self, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return self.unroll_with(self.W_in, self.W_res, y, a)

    @staticmethod
    @torch.no_grad()
    def bptt(members: list, memory: list, y, a, rs: list, steps, reward_steps) -> list:
        """The readouts' gradients (``OutputHeads.head_gradients``) on every member's reservoir
        states, the members stacked along the run axis (P·R, …); ``memory`` is empty."""
        cat = lambda xs: torch.cat(xs) if len(xs) > 1 else xs[0]  # noqa: E731
        x = members[0].unroll_with(cat([p.W_in for p in members]), cat([p.W_res for p in members]), y, a)
        R, grads = y.shape[0] // len(members), []
        for k, member in enumerate(members):
            part = slice(k * R, (k + 1) * R)
            grads += member.head_gradients(x[part], y[part], rs[k], steps[part], reward_steps[part])[0]
        return grads
