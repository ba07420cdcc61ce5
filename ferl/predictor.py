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
mode: one SGD step per sequence (§4.3.1).

All parameters carry the run dimension first, W_mm (R, M, M). Sequences are padded batches
y (R, B, T+1, Y), a (R, B, T, A) one-hot, r (R, B, T+1, ·) with r[:, :, 0] unused, and lengths (R, B),
the number of actions T of each sequence; steps beyond a sequence's length are masked.
"""
import torch
import torch.nn.functional as F
from torch import nn

REWARD_OUTPUTS = ("bits", "linear", "none")


def linear(x: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """W x per run: x (R, …, I), W (R, O, I) → (R, …, O)."""
    out = torch.bmm(x.reshape(x.shape[0], -1, x.shape[-1]), W.transpose(1, 2))
    return out.view(*x.shape[:-1], W.shape[1])


def affine(x: torch.Tensor, W: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """W x + b per run: x (R, …, I), W (R, O, I), b (R, O) → (R, …, O)."""
    return linear(x, W) + b.view(b.shape[0], *(1,) * (x.dim() - 2), b.shape[1])


def valid_steps(lengths: torch.Tensor, n_steps: int) -> torch.Tensor:
    """(R, B, n_steps) True at the steps t ≤ T of each sequence (t = 0 … n_steps − 1)."""
    return torch.arange(n_steps, device=lengths.device) <= lengths.unsqueeze(-1)


def reward_steps(valid: torch.Tensor) -> torch.Tensor:
    """The valid steps that carry a reward, t ≥ 1."""
    return valid & (torch.arange(valid.shape[-1], device=valid.device) > 0)


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
    def initial_memory(self) -> torch.Tensor:
        """m_0 = σ_{β_m}(b_init), (R, M), Eq. (4.1)."""
        return torch.sigmoid(self.beta_m * self.b_init)

    def memory_drive(self, y_prev: torch.Tensor, a_prev: torch.Tensor) -> torch.Tensor:
        """W_my (c_y y_{t−1}) + W_ma (c_a a_{t−1}) + b_m, the feed-forward part of Eq. (4.3)."""
        return affine(self.c_y * y_prev, self.W_my, self.b_m) + linear(self.c_a * a_prev, self.W_ma)

    def memory(self, drive: torch.Tensor, m_prev: torch.Tensor) -> torch.Tensor:
        """m_t = σ_{β_m}(drive + W_mm m_{t−1}), Eq. (4.3): drive, m_prev (R, B, M)."""
        return torch.sigmoid(self.beta_m * torch.baddbmm(drive, m_prev, self.W_mm.transpose(1, 2)))

    def head_inputs(self, m: torch.Tensor):
        """Output logits z_y = β_y (W_ym m + b_y), ŷ = σ(z_y) (Eqs. 4.2, 4.4), and z_r =
        β_r (W_rm m + b_r), r̂ = σ(z_r) (Eq. 4.5), or r̂ = z_r = W_rm m + b_r (linear, Eq. 5.2)."""
        z_y = self.beta_y * affine(m, self.W_ym, self.b_y) if self.predict_obs else None
        if self.reward_output == "none":
            return z_y, None
        z_r = affine(m, self.W_rm, self.b_r)
        return z_y, (self.beta_r * z_r if self.reward_output == "bits" else z_r)

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

    # ---- sequences ------------------------------------------------------------------------------
    def unroll(self, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """Memories m_0 … m_T (R, B, T+1, M) of padded sequences y (R, B, T+1, Y), a (R, B, T, A)."""
        drive = self.memory_drive(y[:, :, :-1], a)  # (R, B, T, M): input to m_1 … m_T
        m = [self.initial_memory().unsqueeze(1).expand(-1, y.shape[1], -1)]
        for t in range(a.shape[2]):
            m.append(self.memory(drive[:, :, t], m[-1]))
        return torch.stack(m, 2)

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

        BPTT: this is a differentiable function of the unrolled Eqs. (4.1–4.5), so autograd's
        reverse pass through the unrolled recursion computes exactly the BPTT gradients of
        §2.4.1 (Eqs. 2.57–2.63: output errors δ^x_t = ρ_y β_y (ŷ_t − y_t), ρ_r β_r (r̂_t − r_t) or
        ρ_r (r̂_t − r_t) for the linear reward, memory errors δ^m_t propagated back through W_mm
        from t = T to 0). Padded steps are masked and contribute nothing.
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

    def train_epoch(self, y, a, r, lengths, order: torch.Tensor) -> None:
        """One epoch of BPTT in pattern mode (§4.3.1): for i = 1 … N every run takes a plain SGD
        step θ ← θ − α ∇_θ Σ_t E_t on its own sequence order[:, i] (order (R, N), a permutation
        of each run's N sequences). Runs share nothing: the summed loss of all runs has, for
        run r's parameters, the gradient of run r's loss alone. With ``batch_size`` B > 1 a step
        follows every B sequences, on the mean of their losses (padded steps masked)."""
        runs = torch.arange(order.shape[0], device=order.device).unsqueeze(1)
        y, a, lengths = y[runs, order], a[runs, order], lengths[runs, order]
        r = r[runs, order] if r is not None else None
        params = list(self.parameters())
        B, n = self.batch_size, lengths.shape[1]
        # T of every step: the longest sequence of its B positions over all runs, read once (one
        # host sync per epoch); it trims the padding all runs and sequences of the step share
        longest = F.pad(lengths.max(0).values, (0, -n % B)).view(-1, B).max(1).values.tolist()
        for i, T in zip(range(0, n, B), longest):
            s = slice(i, i + B)
            loss = self.loss(y[:, s, : T + 1], a[:, s, :T], r[:, s, : T + 1] if r is not None else None,
                             lengths[:, s]).sum() / lengths[:, s].shape[1]
            grads = torch.autograd.grad(loss, params)
            with torch.no_grad():
                for q, g in zip(params, grads):
                    q.sub_(g, alpha=self.lr)

    @torch.no_grad()
    def prediction_errors(self, y, a, r, lengths) -> torch.Tensor:
        """Prediction error of every step, (R, B, T+1): the weighted absolute error of Eq. (4.8),
        ρ_y Σ_i |y_{i,t} − ŷ_{i,t}| + ρ_r Σ_i |r_{i,t} − r̂_{i,t}| (reward term from t = 1), with the
        squared error ρ_r (r_t − r̂_t)² for a linear scalar reward (Fig. 5.17b).
        NaN at padded steps, and at t = 0 for a predictor without an observation head."""
        y_hat, r_hat, _ = self.forward_sequences(y, a, lengths)
        valid = valid_steps(lengths, y.shape[2])
        err = torch.zeros(valid.shape, dtype=y.dtype, device=y.device)
        if self.predict_obs:
            err = err + self.rho_y * (y - y_hat).abs().sum(-1)
        if self.reward_output != "none":
            diff = (r - r_hat).square() if self.reward_output == "linear" else (r - r_hat).abs()
            err = err + self.rho_r * torch.where(reward_steps(valid), diff.sum(-1), 0.0)
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
