"""Elman-type recurrent predictors batched over runs, trained by BPTT (§2.4, §4.2, §5.2).

The memory m_t summarises the history (y_0, a_0, …, y_{t−1}, a_{t−1}); heads predict y_t and r_t:

* m_0 = σ_{β_m}(b_init)                                                         (Eq. 4.1)
* m_t = σ_{β_m}(W_my (c_y y_{t−1}) + W_ma (c_a a_{t−1}) + W_mm m_{t−1} + b_m)     (Eq. 4.3)
* ŷ_t = σ_{β_y}(W_ym m_t + b_y),  t = 0 … T                                      (Eqs. 4.2, 4.4)
* r̂_t = σ_{β_r}(W_rm m_t + b_r) for reward bits (Eq. 4.5) or W_rm m_t + b_r for a scalar
  reward with a linear output (Eq. 5.2),  t = 1 … T
* loss of a sequence Σ_t E_t: cross entropy ρ_y CE(y_t, ŷ_t) for t = 0 … T plus ρ_r CE(r_t, r̂_t)
  (Eq. 4.6, Eq. 5.1) or ½ ρ_r (r_t − r̂_t)² (Eq. 5.2) for t = 1 … T

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
from itertools import repeat

import torch
import torch.nn.functional as F
from torch import nn

REWARD_OUTPUTS = ("bits", "linear", "none")
MEMORY_PARAMETERS = ("W_my", "W_ma", "W_mm", "b_m", "b_init")
ERROR_CHUNK = 1 << 20  # output values per chunk of sequences in prediction_errors


def linear(x: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """W x per run: x (R, …, I), W (R, O, I) → (R, …, O)."""
    out = torch.bmm(x.reshape(x.shape[0], -1, x.shape[-1]), W.transpose(1, 2))
    return out.view(*x.shape[:-1], W.shape[1])


def affine(x: torch.Tensor, W: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """W x + b per run: x (R, …, I), W (R, O, I), b (R, O) → (R, …, O)."""
    return linear(x, W) + b.view(b.shape[0], *(1,) * (x.dim() - 2), b.shape[1])


def scaled(x: torch.Tensor, gain: float) -> torch.Tensor:
    """gain · x; a gain of 1 (most of Tables 4.1–5.1) costs no operation."""
    return x if gain == 1 else gain * x


def valid_steps(lengths: torch.Tensor, n_steps: int) -> torch.Tensor:
    """(R, B, n_steps) True at the steps t ≤ T of each sequence (t = 0 … n_steps − 1)."""
    return torch.arange(n_steps, device=lengths.device) <= lengths.unsqueeze(-1)


def reward_steps(valid: torch.Tensor) -> torch.Tensor:
    """The valid steps that carry a reward, t ≥ 1."""
    return valid & (torch.arange(valid.shape[-1], device=valid.device) > 0)


def memory_drive(params: list, gains: tuple, y_prev: torch.Tensor, a_prev: torch.Tensor) -> torch.Tensor:
    """W_my (c_y y_{t−1}) + W_ma (c_a a_{t−1}) + b_m (Eq. 4.3) for memory parameters
    (W_my, W_ma, W_mm, b_m, b_init) and gains (c_y, c_a, β_m)."""
    W_my, W_ma, _, b_m, _ = params
    return affine(scaled(y_prev, gains[0]), W_my, b_m) + linear(scaled(a_prev, gains[1]), W_ma)


def recur(W_mm: torch.Tensor, beta_m: float, drive: torch.Tensor, m_prev: torch.Tensor) -> torch.Tensor:
    """m_t = σ_{β_m}(drive + W_mm m_{t−1}), Eq. (4.3): drive, m_prev (R, B, M)."""
    return torch.sigmoid(scaled(torch.baddbmm(drive, m_prev, W_mm.transpose(1, 2)), beta_m))


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
        back.append(torch.baddbmm(dm[t], back[-1], W_mm).mul_(slope[t]))
    d_init = back.pop().sum(1)  # δ^m_0: the gradient of b_init
    d_t = torch.stack(back[::-1], 2).view(R, B * T, M).transpose(1, 2)  # δ^m_1 … δ^m_T
    prev = lambda x: x[:, :, :T].reshape(R, B * T, x.shape[-1])  # noqa: E731  inputs at t − 1
    return [scaled(torch.bmm(d_t, prev(y)), gains[0]), scaled(torch.bmm(d_t, a.reshape(R, B * T, -1)), gains[1]),
            torch.bmm(d_t, prev(m)), d_t.sum(2), d_init]


def bptt(members: list, memory: list, y, a, rs: list, steps, reward_steps) -> list:
    """BPTT of §2.4.1 written out for predictors that share the form of the memory, stacked along
    the run axis (P·R, …): the gradients of Σ_b Σ_t steps_{b,t} E_t(b) with respect to ``memory``
    (their memory parameters, concatenated) and then every member's head parameters. y, a as for
    ``unroll``; rs[k] member k's targets (R, B, T+1, ·) or None; steps (P·R, B, T+1) the weight
    of every step (0 on padding), reward_steps the same without t = 0."""
    gains, R = members[0].gains, y.shape[0] // len(members)
    m = unroll(memory, gains, y, a)
    heads, dm = [], []
    for k, member in enumerate(members):
        part = slice(k * R, (k + 1) * R)
        g, d = member.head_gradients(m[part], y[part], rs[k], steps[part], reward_steps[part])
        heads += g
        dm.append(d)
    return backprop_memory(memory[2], gains, m, torch.cat(dm) if len(dm) > 1 else dm[0], y, a) + heads


class ElmanPredictor(nn.Module):
    """Eqs. 4.1–4.6 (joint observation + encoded-reward predictor, ch. 4) and Eqs. 5.1/5.2 (ch. 5).

    ``reward_output``: "bits" (sigmoid + cross entropy, Eqs. 4.5–4.6, n_reward bits), "linear"
    (one linear scalar output + squared error, Eq. 5.2; n_reward is then ignored) or "none" (no
    reward head: the observation predictor of ch. 5). ``predict_obs=False`` drops the observation
    head (the reward predictor of ch. 5); its output is then None, as is r̂ for "none".
    """

    def __init__(self, n_runs: int, n_obs: int, n_actions: int, n_memory: int = 20, n_reward: int = 4,
                 reward_output: str = "bits", c_y: float = 1.0, c_a: float = 1.0, beta_m: float = 1.0,
                 beta_y: float = 1.0, beta_r: float = 1.0, rho_y: float = 1.0, rho_r: float = 1.0,
                 lr: float = 0.05, init_std: float = 1.0, predict_obs: bool = True,
                 time_average: bool = False, batch_size: int = 1, seed: int = 0):
        super().__init__()
        if reward_output not in REWARD_OUTPUTS:
            raise ValueError(f"reward_output must be one of {REWARD_OUTPUTS}, got {reward_output!r}")
        if not predict_obs and reward_output == "none":
            raise ValueError("a predictor needs an observation or a reward head")
        self.reward_output, self.predict_obs = reward_output, predict_obs
        self.c_y, self.c_a, self.beta_m, self.beta_y, self.beta_r = c_y, c_a, beta_m, beta_y, beta_r
        self.rho_y, self.rho_r, self.lr, self.time_average = rho_y, rho_r, lr, time_average
        self.batch_size = batch_size
        # Each run is initialised from its own seed, so run r does not depend on n_runs (§4.3.1:
        # all weights and biases from a spherical Gaussian of variance init_std²).
        gens = [torch.Generator().manual_seed(seed + r) for r in range(n_runs)]

        def gaussian(*shape):
            return nn.Parameter(torch.stack([torch.randn(*shape, generator=g) for g in gens]) * init_std)

        M, n_r = n_memory, (1 if reward_output == "linear" else n_reward)
        self.W_my, self.W_ma, self.W_mm = gaussian(M, n_obs), gaussian(M, n_actions), gaussian(M, M)
        self.b_m, self.b_init = gaussian(M), gaussian(M)
        self.W_ym, self.b_y = (gaussian(n_obs, M), gaussian(n_obs)) if predict_obs else (None, None)
        self.W_rm, self.b_r = (gaussian(n_r, M), gaussian(n_r)) if reward_output != "none" else (None, None)

    # ---- network equations ------------------------------------------------------------------
    def memory_parameters(self) -> list:
        """W_my, W_ma, W_mm, b_m, b_init: everything Eqs. (4.1, 4.3) use, in ``parameters()`` order."""
        return [getattr(self, name) for name in MEMORY_PARAMETERS]

    def head_parameters(self) -> list:
        """The output heads' weights and biases that exist, in ``parameters()`` order."""
        return [q for q in (self.W_ym, self.b_y, self.W_rm, self.b_r) if q is not None]

    def initial_memory(self) -> torch.Tensor:
        """m_0 = σ_{β_m}(b_init), (R, M), Eq. (4.1)."""
        return torch.sigmoid(scaled(self.b_init, self.beta_m))

    def memory_drive(self, y_prev: torch.Tensor, a_prev: torch.Tensor) -> torch.Tensor:
        """W_my (c_y y_{t−1}) + W_ma (c_a a_{t−1}) + b_m, the feed-forward part of Eq. (4.3)."""
        return memory_drive(self.memory_parameters(), self.gains, y_prev, a_prev)

    def memory(self, drive: torch.Tensor, m_prev: torch.Tensor) -> torch.Tensor:
        """m_t = σ_{β_m}(drive + W_mm m_{t−1}), Eq. (4.3): drive, m_prev (R, B, M)."""
        return recur(self.W_mm, self.beta_m, drive, m_prev)

    @property
    def gains(self) -> tuple:
        """(c_y, c_a, β_m): what the memory equations take besides their parameters."""
        return self.c_y, self.c_a, self.beta_m

    @property
    def batch_key(self) -> tuple:
        """Predictors with equal keys can train as one ``PredictorBatch``: the same form of
        memory (sizes, gains) and the same α, objective and batch size."""
        return self.W_my.shape, self.W_ma.shape, self.gains, self.lr, self.time_average, self.batch_size

    def head_inputs(self, m: torch.Tensor):
        """Output logits z_y = β_y (W_ym m + b_y), ŷ = σ(z_y) (Eqs. 4.2, 4.4), and z_r =
        β_r (W_rm m + b_r), r̂ = σ(z_r) (Eq. 4.5), or r̂ = z_r = W_rm m + b_r (linear, Eq. 5.2)."""
        z_y = scaled(affine(m, self.W_ym, self.b_y), self.beta_y) if self.predict_obs else None
        if self.reward_output == "none":
            return z_y, None
        z_r = affine(m, self.W_rm, self.b_r)
        return z_y, (scaled(z_r, self.beta_r) if self.reward_output == "bits" else z_r)

    def outputs(self, m: torch.Tensor):
        """(ŷ, r̂) from the memory m (R, …, M)."""
        z_y, z_r = self.head_inputs(m)
        y_hat = torch.sigmoid(z_y) if z_y is not None else None
        return y_hat, (torch.sigmoid(z_r) if self.reward_output == "bits" else z_r)

    # ---- online API (actor phase) ---------------------------------------------------------------
    @torch.no_grad()
    def initial(self):
        """m_0 (R, M) and the prediction ŷ_0 (R, Y) of the initial observation, Eqs. (4.1–4.2)."""
        m0 = self.initial_memory()
        return m0, self.outputs(m0)[0]

    @torch.no_grad()
    def step(self, m_prev: torch.Tensor, y_prev: torch.Tensor, a_prev: torch.Tensor):
        """One step of Eqs. (4.3–4.5): m_{t−1} (R, M), y_{t−1} (R, Y), one-hot a_{t−1} (R, A)
        → m_t (R, M), ŷ_t (R, Y), r̂_t (R, n_reward)."""
        m = self.memory(self.memory_drive(y_prev, a_prev).unsqueeze(1), m_prev.unsqueeze(1)).squeeze(1)
        return (m, *self.outputs(m))

    @torch.no_grad()
    def drive_table(self, observations: torch.Tensor) -> torch.Tensor:
        """The feed-forward part of Eq. (4.3), W_my (c_y y) + W_ma (c_a a) + b_m, for every
        observation vector y of ``observations`` (ids, Y) — or per run (R, ids, Y) — and every
        one-hot action a: (R, ids · A, M), row id · A + a. With the predictor frozen (the actor
        phase) a memory step is then one lookup and the recurrence (``online_memory``)."""
        R = self.W_my.shape[0]
        obs = observations.expand(R, -1, -1) if observations.dim() == 2 else observations
        from_obs = affine(scaled(obs, self.c_y), self.W_my, self.b_m)  # (R, ids, M)
        from_action = scaled(self.W_ma, self.c_a).transpose(1, 2)  # (R, A, M): W_ma times a one-hot
        return (from_obs.unsqueeze(2) + from_action.unsqueeze(1)).flatten(1, 2)

    @torch.no_grad()
    def online_memory(self, table: torch.Tensor, rows: torch.Tensor, m_prev: torch.Tensor) -> torch.Tensor:
        """m_t (R, M) from m_{t−1} (R, M) and the rows (R,) of ``drive_table`` flattened to
        (R · ids · A, M) that (y_{t−1}, a_{t−1}) select, Eq. (4.3)."""
        return self.memory(table.index_select(0, rows).unsqueeze(1), m_prev.unsqueeze(1)).squeeze(1)

    # ---- sequences ------------------------------------------------------------------------------
    def unroll(self, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """Memories m_0 … m_T (R, B, T+1, M) of padded sequences y (R, B, T+1, Y), a (R, B, T, A)."""
        return unroll(self.memory_parameters(), self.gains, y, a)

    def forward_sequences(self, y: torch.Tensor, a: torch.Tensor, lengths: torch.Tensor):
        """ŷ (R, B, T+1, Y), r̂ (R, B, T+1, ·) and m (R, B, T+1, M) of padded sequences.

        Index 0 predicts y_0 from m_0 (r̂[:, :, 0] is unused); index t ≥ 1 predicts (y_t, r_t) from
        m_t, which has seen (y_{t−1}, a_{t−1}). Padded inputs are zeroed, so the values at steps
        beyond a sequence's length are finite but meaningless.
        """
        y, a, _ = self.clean(y, a, None, lengths)
        m = self.unroll(y, a)
        return (*self.outputs(m), m)

    @staticmethod
    def clean(y, a, r, lengths):
        """Zero the padded steps of y, a and r (r may be None), so padding can neither enter the
        memory nor carry NaNs into the gradients."""
        valid = valid_steps(lengths, y.shape[2]).unsqueeze(-1)
        y, a = torch.where(valid, y, 0.0), torch.where(valid[:, :, 1:], a, 0.0)
        return y, a, (torch.where(valid, r, 0.0) if r is not None else None)

    def loss(self, y, a, r, lengths) -> torch.Tensor:
        """Σ_t E_t, or J(T) = Σ_t E_t / (T + 1) with ``time_average``, per (run, sequence), (R, B): Eq. (4.6) cross entropy ρ_y CE(y_t, ŷ_t) for
        t = 0 … T plus ρ_r CE(r_t, r̂_t) (bits) or ½ ρ_r (r_t − r̂_t)² (linear, Eq. 5.2) for t = 1 … T.

        Training uses ``gradients``, BPTT written out; this loss is what it differentiates, and
        autograd's reverse pass through it is the independent check (tests/test_predictor.py).
        Padded steps are masked and contribute nothing.
        """
        y, a, r = self.clean(y, a, r, lengths)
        z_y, z_r = self.head_inputs(self.unroll(y, a))
        valid = valid_steps(lengths, y.shape[2])
        E = 0.0
        if self.predict_obs:
            E_y = F.binary_cross_entropy_with_logits(z_y, y, reduction="none").sum(-1)
            E = self.rho_y * torch.where(valid, E_y, 0.0)
        if self.reward_output != "none":
            E_r = (F.binary_cross_entropy_with_logits(z_r, r, reduction="none") if self.reward_output == "bits"
                   else 0.5 * (r - z_r).square()).sum(-1)
            E = E + self.rho_r * torch.where(reward_steps(valid), E_r, 0.0)
        return E.sum(-1) / (lengths + 1) if self.time_average else E.sum(-1)

    @torch.no_grad()
    def gradients(self, y, a, r, lengths, weight: torch.Tensor) -> list:
        """∂/∂θ of Σ_b weight_b · Σ_t E_t(b) for every parameter (in ``parameters()`` order): BPTT
        of §2.4.1 written out, no autograd (``bptt``, as training runs it).
        Inputs as for ``loss``, already ``clean``ed; weight (R, B)."""
        steps = valid_steps(lengths, y.shape[2]) * weight.unsqueeze(-1)
        return bptt([self], self.memory_parameters(), y, a, [r], steps, steps * (torch.arange(y.shape[2], device=y.device) > 0))

    def head_gradients(self, m, y, r, steps: torch.Tensor, reward_steps: torch.Tensor):
        """The output heads' part of BPTT: their gradients (``head_parameters()`` order) and
        ∂J/∂m_t from them, (R, B, T+1, M). m from ``unroll``, y and r the targets, steps (R, B, T+1)
        the weight of every step (0 on padding), reward_steps the same with t = 0 left out.

        Output errors (Eq. 2.58): a sigmoid output under cross entropy, and the linear reward under
        ½(r − r̂)², both give δ^x_t = ρ · gain · (x̂_t − x_t); the weights' gradients are
        Σ_t δ^x_t m_tᵀ (Eq. 2.57) and ∂J/∂m_t = Σ_j δ^x_{j,t} w^{xm}_j (Eqs. 2.61–2.62, first term).
        """
        R, B, T1 = m.shape[:3]
        flat = lambda x: x.reshape(R, B * T1, x.shape[-1])  # noqa: E731
        m_flat, heads = flat(m), []
        if self.predict_obs:
            out = torch.sigmoid(scaled(torch.baddbmm(self.b_y.unsqueeze(1), m_flat, self.W_ym.transpose(1, 2)), self.beta_y))
            heads.append((out, flat(y), steps * (self.rho_y * self.beta_y), self.W_ym))
        if self.reward_output != "none":
            z = torch.baddbmm(self.b_r.unsqueeze(1), m_flat, self.W_rm.transpose(1, 2))
            out, gain = (torch.sigmoid(scaled(z, self.beta_r)), self.beta_r) if self.reward_output == "bits" else (z, 1.0)
            heads.append((out, flat(r), reward_steps * (self.rho_r * gain), self.W_rm))
        grads, dm = [], None
        for out, target, w, W in heads:
            delta = (out - target).mul_(w.view(R, -1, 1))  # δ^x_t (R, B(T+1), ·)
            grads += [torch.bmm(delta.transpose(1, 2), m_flat), delta.sum(1)]
            dm = torch.bmm(delta, W) if dm is None else torch.baddbmm(dm, delta, W)
        return grads, dm.view(R, B, T1, -1)

    def train_epoch(self, y, a, r, lengths, order: torch.Tensor) -> None:
        """One epoch of BPTT in pattern mode (§4.3.1): for i = 1 … N every run takes a plain SGD
        step θ ← θ − α ∇_θ Σ_t E_t on its own sequence order[:, i] (order (R, N), a permutation
        of each run's N sequences). Runs share nothing: each run's parameters move by the
        gradient of its own loss alone. With ``batch_size`` B > 1 a step follows every B
        sequences, on the mean of their losses (padded steps masked)."""
        PredictorBatch([self], y, a, [r], lengths).train_epoch([order])

    @torch.no_grad()
    def prediction_errors(self, y, a, r, lengths) -> torch.Tensor:
        """Prediction error of every step, (R, B, T+1): the weighted absolute error of Eq. (4.8),
        ρ_y Σ_i |y_{i,t} − ŷ_{i,t}| + ρ_r Σ_i |r_{i,t} − r̂_{i,t}| (reward term from t = 1), with the
        squared error ρ_r (r_t − r̂_t)² for a linear scalar reward (Fig. 5.17b).
        NaN at padded steps, and at t = 0 for a predictor without an observation head.
        Computed in chunks of sequences, so that the temporaries of 784-pixel outputs stay in cache."""
        n = max(1, ERROR_CHUNK // (y.shape[0] * y.shape[2] * y.shape[3]))
        chunks = zip(y.split(n, 1), a.split(n, 1), r.split(n, 1) if r is not None else repeat(None), lengths.split(n, 1))
        return torch.cat([self._prediction_errors(*chunk) for chunk in chunks], 1)

    def _prediction_errors(self, y, a, r, lengths) -> torch.Tensor:
        y_hat, r_hat, _ = self.forward_sequences(y, a, lengths)
        valid = valid_steps(lengths, y.shape[2])
        err = torch.zeros(valid.shape, dtype=y.dtype, device=y.device)
        if self.predict_obs:
            err += self.rho_y * y_hat.sub_(y).abs_().sum(-1)
        if self.reward_output != "none":
            diff = r_hat.sub_(r).square_() if self.reward_output == "linear" else r_hat.sub_(r).abs_()
            err += self.rho_r * torch.where(reward_steps(valid), diff.sum(-1), 0.0)
        return torch.where(valid if self.predict_obs else reward_steps(valid), err, torch.nan)

    def reward_targets(self, env, rewards: torch.Tensor):
        """Targets r (R, B, T+1, ·) of scalar rewards r_1 … r_T (R, B, T) (index 0 a zero filler):
        one bit per possible reward value ``env.reward_values`` (§4.2 fn. 1), the scalar itself
        (linear), or None ("none")."""
        if self.reward_output == "none":
            return None
        r = torch.cat([torch.zeros_like(rewards[..., :1]), rewards], -1).unsqueeze(-1)
        if self.reward_output == "linear":
            return r
        values = torch.as_tensor(env.reward_values, dtype=rewards.dtype, device=rewards.device)
        return (r == values).to(rewards.dtype)


class PredictorBatch:
    """Elman predictors that share the form of the memory (its size and inputs, c_y, c_a, β_m),
    α, the objective and the batch size, trained on the same sequences as one batch along the
    run axis — chapter 5's observation and reward predictors (§5.2). Their memories unroll and
    backpropagate in the same batched products (``bptt``); only the output heads
    (``head_gradients``) are separate. Every predictor still takes its own sequence
    order and plain SGD steps, so each one's training equals training it alone."""

    def __init__(self, predictors: list, y, a, rs: list, lengths):
        """Members and their training sequences: y (R, N, T+1, Y), a (R, N, T, A), lengths (R, N)
        shared, targets rs[k] (R, N, T+1, ·) or None per member; the padding is zeroed once here."""
        if len({p.batch_key for p in predictors}) != 1:
            raise ValueError("a PredictorBatch needs predictors with the same memory, gains, lr, objective and batch size")
        self.members = list(predictors)
        self.lead = predictors[0]
        y, a, _ = self.lead.clean(y, a, None, lengths)
        valid = valid_steps(lengths, y.shape[2]).unsqueeze(-1)
        self.y, self.a, self.lengths = y, a, lengths
        self.rs = [torch.where(valid, r, 0.0) if r is not None else None for r in rs]

    @torch.no_grad()
    def train_epoch(self, orders: list) -> None:
        """One pattern-mode epoch (``ElmanPredictor.train_epoch``) of every member, member k
        taking the sequences in its order orders[k] (R, N)."""
        p, P = self.lead, len(self.members)
        runs = torch.arange(self.lengths.shape[0], device=self.lengths.device).unsqueeze(1)
        R = runs.shape[0]
        cat = lambda xs: torch.cat(xs) if P > 1 else xs[0]  # noqa: E731
        L = cat([self.lengths[runs, o] for o in orders])
        y, a = cat([self.y[runs, o] for o in orders]), cat([self.a[runs, o] for o in orders])
        rs = [r[runs, o] if r is not None else None for r, o in zip(self.rs, orders)]
        # the memories' parameters of all members in one (P·R, …) tensor each while training
        memory = p.memory_parameters() if P == 1 else [torch.cat(qs) for qs in zip(*(q.memory_parameters() for q in self.members))]
        params = memory + [q for member in self.members for q in member.head_parameters()]
        B, n = p.batch_size, L.shape[1]
        # the weight of every step in its update's loss: 1/(T+1) under J(T), over the sequences
        # of the update (B, fewer in a last short one), 0 on padding; rewards count from t = 1
        chunk = torch.arange(n, device=L.device) // B
        scale = (1.0 / (L + 1).to(y.dtype) if p.time_average else torch.ones_like(L, dtype=y.dtype)) / chunk.bincount()[chunk]
        steps = valid_steps(L, y.shape[2]) * scale.unsqueeze(-1)
        reward_steps = steps * (torch.arange(y.shape[2], device=L.device) > 0)
        # T of every step: the longest sequence of its B positions over all runs, read once (one
        # host sync per epoch); it trims the padding all runs and sequences of the step share
        longest = F.pad(L.max(0).values, (0, -n % B)).view(-1, B).max(1).values.tolist()
        for i, T in zip(range(0, n, B), longest):
            s = slice(i, i + B)
            grads = bptt(self.members, memory, y[:, s, : T + 1], a[:, s, :T],
                         [r[:, s, : T + 1] if r is not None else None for r in rs],
                         steps[:, s, : T + 1], reward_steps[:, s, : T + 1])
            torch._foreach_add_(params, grads, alpha=-p.lr)
        if P > 1:
            for k, member in enumerate(self.members):
                for q, merged in zip(member.memory_parameters(), memory):
                    q.copy_(merged[k * R:(k + 1) * R])
