"""Elman-type recurrent predictors batched over runs, trained by BPTT (§2.4, §4.2, §5.2).

The memory m_t summarises the history (y_0, a_0, …, y_{t−1}, a_{t−1}); the output heads
(``ferl.predictors.heads``) predict y_t and r_t from it:

* m_0 = σ_{β_m}(b_init)                                                         (Eq. 4.1)
* m_t = σ_{β_m}(W_my (c_y y_{t−1}) + W_ma (c_a a_{t−1}) + W_mm m_{t−1} + b_m)     (Eq. 4.3)

σ_β(x) = 1/(1 + exp(−βx)). §2.4.1 is ambiguous about the time reduction: it defines the objective
as the average J(T) = 1/(T+1) Σ_t E_t, yet its BPTT algorithm (steps 7–8) accumulates and applies
the plain sum Σ_t. ``time_average`` picks the average (J(T)) or the sum. Training is in pattern
mode: one SGD step per sequence (§4.3.1), on gradients from BPTT written out (Eqs. 2.57–2.63):
a few batched matrix products per step instead of autograd's graph, which costs more in
per-operation overhead than the arithmetic of these small networks.

All parameters carry the run dimension first, W_mm (R, M, M). Sequences are padded batches
y (R, B, T+1, Y), a (R, B, T, A) one-hot, r (R, B, T+1, ·) with r[:, :, 0] unused, and lengths (R, B),
the number of actions T of each sequence; steps beyond a sequence's length are masked.
"""

import torch

from ferl.predictors.heads import affine, baddbmm, linear, members_heads, scaled
from ferl.predictors.recurrent import RecurrentPredictor

MEMORY_PARAMETERS = ("W_my", "W_ma", "W_mm", "b_m", "b_init")


def memory_drive(params: list, gains: tuple, y_prev: torch.Tensor, a_prev: torch.Tensor) -> torch.Tensor:
    """W_my (c_y y_{t−1}) + W_ma (c_a a_{t−1}) + b_m (Eq. 4.3) for memory parameters
    (W_my, W_ma, W_mm, b_m, b_init) and gains (c_y, c_a, β_m)."""
    W_my, W_ma, _, b_m, _ = params
    return affine(scaled(y_prev, gains[0]), W_my, b_m) + linear(scaled(a_prev, gains[1]), W_ma)


def recur(W_mm: torch.Tensor, beta_m: float, drive: torch.Tensor, m_prev: torch.Tensor) -> torch.Tensor:
    """m_t = σ_{β_m}(drive + W_mm m_{t−1}), Eq. (4.3): drive, m_prev (R, B, M)."""
    return torch.sigmoid(scaled(baddbmm(drive, m_prev, W_mm.transpose(1, 2)), beta_m))


def unroll(params: list, gains: tuple, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Memories m_0 … m_T (R, B, T+1, M) of padded sequences y (R, B, T+1, Y), a (R, B, T, A),
    Eqs. (4.1, 4.3)."""
    drive = memory_drive(params, gains, y[:, :, :-1], a)  # (R, B, T, M): input to m_1 … m_T
    m = [torch.sigmoid(scaled(params[4], gains[2])).unsqueeze(1).expand(-1, y.shape[1], -1)]
    for drive_t in drive.unbind(2):
        m.append(recur(params[2], gains[2], drive_t, m[-1]))
    return torch.stack(m, 2)


def backprop_memory(W_mm: torch.Tensor, gains: tuple, m, dm, y, a) -> list:
    """The memory's part of BPTT (§2.4.1): from ∂J/∂m_t of the heads, dm (R, B, T+1, M), the
    memory errors from t = T down, δ^m_t = (dm_t + W_mmᵀ δ^m_{t+1}) ⊙ β_m m_t (1 − m_t)
    (Eqs. 2.60–2.62), and the gradients of W_my, W_ma, W_mm, b_m, b_init: Σ_t δ^m_t (c u_{t−1})ᵀ
    (Eq. 2.63), Σ_t δ^m_t m_{t−1}ᵀ (Eq. 2.59), Σ_t δ^m_t, and δ^m_0 (m_0 = σ(β_m b_init))."""
    R, B, T1, M = m.shape
    T = T1 - 1
    slope = scaled(m * (1 - m), gains[2]).unbind(2)
    dm = dm.unbind(2)
    back = [dm[T] * slope[T]]  # δ^m_T, Eq. (2.61)
    for t in range(T - 1, -1, -1):
        back.append(baddbmm(dm[t], back[-1], W_mm).mul_(slope[t]))
    d_init = back.pop().sum(1)  # δ^m_0: the gradient of b_init
    d_t = torch.stack(back[::-1], 2).view(R, B * T, M).transpose(1, 2)  # δ^m_1 … δ^m_T
    prev = lambda x: x[:, :, :T].reshape(R, B * T, x.shape[-1])  # noqa: E731  inputs at t − 1
    return [
        scaled(torch.bmm(d_t, prev(y)), gains[0]),
        scaled(torch.bmm(d_t, a.reshape(R, B * T, -1)), gains[1]),
        torch.bmm(d_t, prev(m)),
        d_t.sum(2),
        d_init,
    ]


def bptt(members: list, memory: list, y, a, rs: list, steps, reward_steps) -> list:
    """BPTT of §2.4.1 written out for predictors that share the form of the memory, stacked along
    the run axis (P·R, …): the gradients of Σ_b Σ_t steps_{b,t} E_t(b) with respect to ``memory``
    (their memory parameters, concatenated) and then every member's head parameters. y, a as for
    ``unroll``; rs[k] member k's targets (R, B, T+1, ·) or None; steps (P·R, B, T+1) the weight
    of every step (0 on padding), reward_steps the same without t = 0."""
    gains = members[0].gains
    m = unroll(memory, gains, y, a)
    heads, dm = members_heads(members, m, y, rs, steps, reward_steps)
    return backprop_memory(memory[2], gains, m, dm, y, a) + heads


class ElmanPredictor(RecurrentPredictor):
    """Eqs. 4.1–4.6 (joint observation + encoded-reward predictor, ch. 4) and Eqs. 5.1/5.2 (ch. 5):
    the memory ``memory: elman`` of ``ferl.predictors.recurrent.predictor``, with its BPTT written
    out. β_m is the gain of the memory's sigmoid (Eq. 4.3)."""

    kind, uses_beta_m = "elman", True
    traceable_bptt = True  # its BPTT is tensor operations only, so PredictorBatch.fuse can compile it

    def init_memory(self, gaussian, generators: list, n_obs: int, n_actions: int, n_memory: int) -> None:
        M = n_memory
        self.W_my, self.W_ma, self.W_mm = gaussian(M, n_obs), gaussian(M, n_actions), gaussian(M, M)
        self.b_m, self.b_init = gaussian(M), gaussian(M)

    # ---- network equations ------------------------------------------------------------------
    def memory_parameters(self) -> list:
        """W_my, W_ma, W_mm, b_m, b_init: everything Eqs. (4.1, 4.3) use, in ``parameters()`` order."""
        return [getattr(self, name) for name in MEMORY_PARAMETERS]

    @property
    def gains(self) -> tuple:
        """(c_y, c_a, β_m): what the memory equations take besides their parameters."""
        return self.c_y, self.c_a, self.beta_m

    @staticmethod
    def bptt(members: list, memory: list, y, a, rs: list, steps, reward_steps) -> list:
        """The gradients of a batch of Elman predictors (``bptt`` below)."""
        return bptt(members, memory, y, a, rs, steps, reward_steps)

    @torch.no_grad()
    def memory_gradients(self, y, a, dm) -> list:
        """The memory's part of the written-out BPTT (``backprop_memory``, Eqs. 2.59–2.63) from
        the error dm (R, B, T+1, M) on m_0 … m_T (``RecurrentPredictor.memory_gradients``)."""
        params = self.memory_parameters()
        return backprop_memory(self.W_mm, self.gains, unroll(params, self.gains, y, a), dm, y, a)

    # ---- online API (actor phase) ---------------------------------------------------------------
    @torch.no_grad()
    def initial_state(self) -> torch.Tensor:
        """m_0 = σ_{β_m}(b_init), (R, M), Eq. (4.1)."""
        return torch.sigmoid(scaled(self.b_init, self.beta_m))

    def memory(self, state: torch.Tensor) -> torch.Tensor:
        """The Elman state is the memory the actor sees, (R, M)."""
        return state

    @torch.no_grad()
    def step(self, m_prev: torch.Tensor, y_prev: torch.Tensor, a_prev: torch.Tensor) -> torch.Tensor:
        """m_t (R, M) of Eq. (4.3) from m_{t−1} (R, M), y_{t−1} (R, Y) and one-hot a_{t−1} (R, A)."""
        drive = memory_drive(self.memory_parameters(), self.gains, y_prev, a_prev)
        return recur(self.W_mm, self.beta_m, drive.unsqueeze(1), m_prev.unsqueeze(1)).squeeze(1)

    @torch.no_grad()
    def drive_table(self, observations: torch.Tensor) -> torch.Tensor:
        """The feed-forward part of Eq. (4.3), W_my (c_y y) + W_ma (c_a a) + b_m, for every
        observation vector y of ``observations`` (ids, Y) — or per run (R, ids, Y) — and every
        one-hot action a: (R, ids · A, M), row id · A + a."""
        R = self.W_my.shape[0]
        obs = observations.expand(R, -1, -1) if observations.dim() == 2 else observations
        from_obs = affine(scaled(obs, self.c_y), self.W_my, self.b_m)  # (R, ids, M)
        from_action = scaled(self.W_ma, self.c_a).transpose(1, 2)  # (R, A, M): W_ma times a one-hot
        return (from_obs.unsqueeze(2) + from_action.unsqueeze(1)).flatten(1, 2)

    def frozen_step(self, table: torch.Tensor, n_actions: int):
        """With the predictor frozen (the actor phase) the drive of every (observation id, action)
        is a table (``drive_table``), so a memory step is one lookup and the recurrence."""
        drives = self.drive_table(table).flatten(0, 1)  # (R · ids · A, M)
        ids = table.shape[-2]
        offsets = torch.arange(self.W_mm.shape[0], device=drives.device) * (ids * n_actions)

        @torch.no_grad()
        def step(m_prev: torch.Tensor, obs_id: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
            rows = torch.add(action, obs_id, alpha=n_actions) + offsets  # (y_{t−1}, a_{t−1}) of run r
            return recur(
                self.W_mm, self.beta_m, drives.index_select(0, rows).unsqueeze(1), m_prev.unsqueeze(1)
            ).squeeze(1)

        return step

    # ---- sequences ------------------------------------------------------------------------------
    def unroll(self, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """Memories m_0 … m_T (R, B, T+1, M) of padded sequences y (R, B, T+1, Y), a (R, B, T, A)."""
        return unroll(self.memory_parameters(), self.gains, y, a)

    time_chunks = True  # sequence_start and run_steps split the unroll (ferl.predictors.training.chunked_bptt)

    def sequence_start(self, params: list, y: torch.Tensor, a: torch.Tensor) -> tuple:
        """The drive of every step of Eq. (4.3) (R, B, T, M) and m_0 = σ_{β_m}(b_init) (Eq. 4.1),
        (R, B, M), as the state and as the memory."""
        m_0 = torch.sigmoid(scaled(params[4], self.beta_m)).unsqueeze(1).expand(-1, y.shape[1], -1)
        return memory_drive(params, self.gains, y[:, :, :-1], a), m_0, m_0

    def run_steps(self, params: list, x: torch.Tensor, state: torch.Tensor) -> tuple:
        """m_t of Eq. (4.3) for the steps of drives x (R, B, n, M) from m = ``state``: (R, B, n, M), and the last."""
        m = []
        for drive_t in x.unbind(2):
            state = recur(params[2], self.beta_m, drive_t, state)
            m.append(state)
        return torch.stack(m, 2), state
