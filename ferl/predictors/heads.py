"""Output heads of a predictor, whatever its memory: what it predicts from m_t, how wrong it is, and
the heads' part of BPTT (§2.4.1, §4.2, §5.2). Batched over runs: parameters carry R first.

* ŷ_t = σ_{β_y}(W_ym m_t + b_y),  t = 0 … T                                      (Eqs. 4.2, 4.4)
* r̂_t = σ_{β_r}(W_rm m_t + b_r) for reward bits (Eq. 4.5) or W_rm m_t + b_r for a scalar
  reward with a linear output (Eq. 5.2),  t = 1 … T
* loss of a sequence Σ_t E_t: cross entropy ρ_y CE(y_t, ŷ_t) for t = 0 … T plus ρ_r CE(r_t, r̂_t)
  (Eq. 4.6, Eq. 5.1) or ½ ρ_r (r_t − r̂_t)² (Eq. 5.2) for t = 1 … T

σ_β(x) = 1/(1 + exp(−βx)). Sequences are padded batches y (R, B, T+1, Y), a (R, B, T, A) one-hot,
r (R, B, T+1, ·) with r[:, :, 0] unused, and lengths (R, B), the number of actions T of each.
"""

from itertools import repeat
from typing import Literal, cast, get_args

import torch
import torch.nn.functional as F
from torch import nn

from ferl.interfaces import PredictorBase
from ferl.predictors.popart import RewardStatistics, normalised, rescale_head

RewardOutput = Literal["bits", "linear", "none"]
REWARD_OUTPUTS = get_args(RewardOutput)
ERROR_CHUNK = 1 << 20  # output values per chunk of sequences in prediction_errors


def bmm(x: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """x W per run: x (R, N, I), W (R, I, O) → (R, N, O). Under torch.compile a product and a sum:
    inductor generates it as a loop fused with the element-wise work around it, where bmm would be
    an external kernel call that costs more than these small products' arithmetic (the fast path,
    ``ferl.compiled``; as ``ferl.rbm.hidden_input``). Eager keeps bmm, the reference."""
    if torch.compiler.is_compiling():
        return (x.unsqueeze(-1) * W.unsqueeze(1)).sum(-2)
    return torch.bmm(x, W)


def baddbmm(b: torch.Tensor, x: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """b + x W per run (``bmm``)."""
    return b + bmm(x, W) if torch.compiler.is_compiling() else torch.baddbmm(b, x, W)


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


def clean(y, a, r, lengths):
    """Zero the padded steps of y, a and r (r may be None), so padding can neither enter the
    memory nor carry NaNs into the gradients."""
    valid = valid_steps(lengths, y.shape[2]).unsqueeze(-1)
    y, a = torch.where(valid, y, 0.0), torch.where(valid[:, :, 1:], a, 0.0)
    return y, a, (torch.where(valid, r, 0.0) if r is not None else None)


class OutputHeads(PredictorBase, nn.Module):
    """The observation head (``predict_obs``) and the reward head (``reward_output``: "bits",
    sigmoid + cross entropy, Eqs. 4.5–4.6, ``n_reward`` bits; "linear", one scalar + squared
    error, Eq. 5.2; "none": the observation predictor of ch. 5) of a predictor whose memory
    ``unroll``s to m (R, B, T+1, M). A subclass draws its memory's parameters, then calls
    ``init_heads`` with the same per-run generators. A linear reward head with ``reward_stats``
    (``ferl.predictors.popart``) learns every run's standardised reward; None: the raw reward."""

    # A head that is off (predict_obs false, reward_output "none") has None for its weights; the code
    # reads them under those flags, never after a None check, so they are typed as the heads that exist.
    W_ym: nn.Parameter  # (R, Y, M)
    b_y: nn.Parameter  # (R, Y)
    W_rm: nn.Parameter  # (R, N^r, M), N^r = 1 for a linear reward head
    b_r: nn.Parameter  # (R, N^r)
    reward_stats: RewardStatistics | None
    predict_obs: bool
    reward_output: str

    def unroll(self, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The memory m (R, B, T+1, M) of cleaned sequences: the subclass's."""
        raise NotImplementedError

    def memory(self, state) -> torch.Tensor:
        """m_t of a memory state: the memory's own (``ferl.predictors.recurrent``)."""
        raise NotImplementedError

    def init_heads(
        self,
        gaussian,
        n_obs: int,
        n_memory: int,
        n_reward: int | None,
        reward_output: str,
        predict_obs: bool,
        gains: tuple,
        weights: tuple,
    ) -> None:
        """Head parameters from ``gaussian(*shape)`` (R, *shape); gains (β_y, β_r), error weights (ρ_y, ρ_r).
        ``n_reward``: the reward bits, one per reward value of the environment (None: it declares
        none, e.g. a third-party one, and the reward can only be predicted as a scalar)."""
        if reward_output == "bits" and n_reward is None:
            raise ValueError(
                "n_reward is required with reward_output=bits: one bit per reward value of the environment "
                "(its reward_values, which this one does not declare); use reward_output=linear "
                "(predictor=joint_scalar)"
            )
        self.reward_output, self.predict_obs = reward_output, predict_obs
        self.reward_stats = None  # a RewardStatistics module where the reward is normalised (ferl.predictors.popart)
        (self.beta_y, self.beta_r), (self.rho_y, self.rho_r) = gains, weights
        n_r = 1 if reward_output == "linear" else n_reward
        self.W_ym, self.b_y = (gaussian(n_obs, n_memory), gaussian(n_obs)) if predict_obs else (None, None)  # type: ignore[assignment]  # off: None (class note)
        self.W_rm, self.b_r = (gaussian(n_r, n_memory), gaussian(n_r)) if reward_output != "none" else (None, None)  # type: ignore[assignment]  # off: None (class note)

    def head_parameters(self) -> list:
        """The output heads' weights and biases that exist, in ``parameters()`` order."""
        return [q for q in (self.W_ym, self.b_y, self.W_rm, self.b_r) if q is not None]

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

    def observation_error(self, state, y: torch.Tensor) -> torch.Tensor | None:
        """ρ_y Σ_i |y_i − ŷ_i| (R,) of the observation ŷ that ``state`` predicts against y (R, Y)
        (Eq. 4.8's observation term); None without an observation head."""
        if not self.predict_obs:
            return None
        return self.rho_y * (self.outputs(self.memory(state))[0] - y).abs().sum(-1)

    def head_losses(self, m, y, r) -> tuple:
        """The loss of each head at every step, unweighted: (E_y, E_r), each (R, B, T+1) or None
        without that head, from the memories m and the targets y, r. E_y = CE(y_t, ŷ_t) summed over
        the observation's bits (Eqs. 4.6, 5.1); E_r = CE(r_t, r̂_t) over the reward bits (Eq. 4.6)
        or ½ (r_t − r̂_t)² for a linear scalar reward (Eq. 5.2). The one formula of the loss."""
        z_y, z_r = self.head_inputs(m)
        E_y = F.binary_cross_entropy_with_logits(z_y, y, reduction="none").sum(-1) if self.predict_obs else None
        if self.reward_output == "none":
            return E_y, None
        E_r = (
            F.binary_cross_entropy_with_logits(z_r, r, reduction="none")
            if self.reward_output == "bits"
            else 0.5 * (r - z_r).square()
        ).sum(-1)
        return E_y, E_r

    def step_errors(self, m, y, r, lengths) -> torch.Tensor:
        """E_t = ρ_y E_y + ρ_r E_r of every step (R, B, T+1) from the memories m of cleaned
        sequences (``head_losses``): the loss that BPTT differentiates; padded steps are 0."""
        E_y, E_r = self.head_losses(m, y, r)
        valid = valid_steps(lengths, y.shape[2])
        E = 0.0
        if E_y is not None:
            E = self.rho_y * torch.where(valid, E_y, 0.0)
        if E_r is not None:
            E = E + self.rho_r * torch.where(reward_steps(valid), E_r, 0.0)
        return cast(torch.Tensor, E)  # a tensor: the config lets no predictor go without a head

    def weighted_errors(self, m, y, r, steps: torch.Tensor, reward_steps: torch.Tensor) -> torch.Tensor:
        """Σ_b Σ_t steps_{b,t} E_t(b) (``head_losses``), the loss whose gradients ``head_gradients``
        writes out: a scalar to differentiate by autograd. Arguments as there."""
        E_y, E_r = self.head_losses(m, y, r)
        loss = 0.0
        if E_y is not None:
            loss = self.rho_y * (E_y * steps).sum()
        if E_r is not None:
            loss = loss + self.rho_r * (E_r * reward_steps).sum()
        return cast(torch.Tensor, loss)  # as step_errors

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
            out = torch.sigmoid(
                scaled(torch.baddbmm(self.b_y.unsqueeze(1), m_flat, self.W_ym.transpose(1, 2)), self.beta_y)
            )
            heads.append((out, flat(y), steps * (self.rho_y * self.beta_y), self.W_ym))
        if self.reward_output != "none":
            z = torch.baddbmm(self.b_r.unsqueeze(1), m_flat, self.W_rm.transpose(1, 2))
            out, gain = (
                (torch.sigmoid(scaled(z, self.beta_r)), self.beta_r) if self.reward_output == "bits" else (z, 1.0)
            )
            heads.append((out, flat(r), reward_steps * (self.rho_r * gain), self.W_rm))
        grads, dm = [], None
        for out, target, w, W in heads:
            delta = (out - target).mul_(w.view(R, -1, 1))  # δ^x_t (R, B(T+1), ·)
            grads += [torch.bmm(delta.transpose(1, 2), m_flat), delta.sum(1)]
            dm = torch.bmm(delta, W) if dm is None else torch.baddbmm(dm, delta, W)
        return grads, cast(torch.Tensor, dm).view(R, B, T1, -1)  # a head exists (checked by the config)

    @torch.no_grad()
    def prediction_errors(self, y, a, r, lengths) -> torch.Tensor:
        """Prediction error of every step, (R, B, T+1): the weighted absolute error of Eq. (4.8),
        ρ_y Σ_i |y_{i,t} − ŷ_{i,t}| + ρ_r Σ_i |r_{i,t} − r̂_{i,t}| (reward term from t = 1), with the
        squared error ρ_r (r_t − r̂_t)² for a linear scalar reward (Fig. 5.17b).
        NaN at padded steps, and at t = 0 for a predictor without an observation head.
        Computed in chunks of sequences, so that the temporaries of 784-pixel outputs stay in cache."""
        n = max(1, ERROR_CHUNK // (y.shape[0] * y.shape[2] * y.shape[3]))
        chunks = zip(
            y.split(n, 1), a.split(n, 1), r.split(n, 1) if r is not None else repeat(None), lengths.split(n, 1)
        )
        return torch.cat([self.chunk_errors(*chunk) for chunk in chunks], 1)

    def chunk_errors(self, y, a, r, lengths) -> torch.Tensor:
        """``prediction_errors`` of one chunk of sequences."""
        y_hat, r_hat, _ = self.forward_sequences(y, a, lengths)
        valid = valid_steps(lengths, y.shape[2])
        err = torch.zeros(valid.shape, dtype=y.dtype, device=y.device)
        if self.predict_obs:
            err += self.rho_y * y_hat.sub_(y).abs_().sum(-1)
        if self.reward_output != "none":
            diff = r_hat.sub_(r).square_() if self.reward_output == "linear" else r_hat.sub_(r).abs_()
            err += self.rho_r * torch.where(reward_steps(valid), diff.sum(-1), 0.0)
        return torch.where(valid if self.predict_obs else reward_steps(valid), err, torch.nan)

    def forward_sequences(self, y: torch.Tensor, a: torch.Tensor, lengths: torch.Tensor):
        """ŷ (R, B, T+1, Y), r̂ (R, B, T+1, ·) and m (R, B, T+1, M) of padded sequences.

        Index 0 predicts y_0 from m_0 (r̂[:, :, 0] is unused); index t ≥ 1 predicts (y_t, r_t) from
        m_t, which has seen (y_{t−1}, a_{t−1}). Padded inputs are zeroed, so the values at steps
        beyond a sequence's length are finite but meaningless.
        """
        y, a, _ = clean(y, a, None, lengths)
        m = self.unroll(y, a)
        return (*self.outputs(m), m)

    def reward_targets(self, reward_values, rewards: torch.Tensor):
        """Targets r (R, B, T+1, ·) of scalar rewards r_1 … r_T (R, B, T) (index 0 a zero filler):
        one bit per possible reward value ``reward_values`` (§4.2 fn. 1), the scalar itself
        (linear), or None ("none")."""
        if self.reward_output == "none":
            return None
        if self.reward_output == "linear":
            z = normalised(self.reward_stats, rewards) if self.reward_stats is not None else rewards
            return torch.cat([torch.zeros_like(z[..., :1]), z], -1).unsqueeze(-1)
        r = torch.cat([torch.zeros_like(rewards[..., :1]), rewards], -1).unsqueeze(-1)
        values = torch.as_tensor(reward_values, dtype=rewards.dtype, device=rewards.device)
        return (r == values).to(rewards.dtype)

    @torch.no_grad()
    def observe_rewards(self, rewards: torch.Tensor, lengths: torch.Tensor) -> None:
        """Merge the rewards r_1 … r_T of new episodes (R, B, T_max), lengths (R, B), into the
        reward statistics, and rescale the reward head so that its outputs in the environment's
        units are preserved (PopArt, ``ferl.predictors.popart``); nothing without statistics."""
        if self.reward_stats is None:
            return
        before = self.reward_stats.moments()
        self.reward_stats.update(
            rewards, torch.arange(rewards.shape[-1], device=rewards.device) < lengths.unsqueeze(-1)
        )
        rescale_head(self.W_rm, self.b_r, before, self.reward_stats.moments())

    def describe_heads(self) -> dict:
        norm: dict[str, str] = {} if self.reward_stats is None else {"reward_norm": "popart"}
        bits = {"reward_bits": self.W_rm.shape[-2]} if self.reward_output == "bits" else {}  # N^r, the environment's
        return {"predicts_observation": self.predict_obs, "reward_output": self.reward_output, **norm, **bits}


def members_heads(members: list, m, y, rs: list, steps, reward_steps) -> tuple[list, torch.Tensor]:
    """Every member's output heads' gradients (``OutputHeads.head_gradients``, members stacked
    along the run axis of m (P·R, B, T+1, M), y, steps and reward_steps; rs[k] member k's targets)
    and ∂J/∂m over all of them (P·R, B, T+1, M): the heads' part of a batch's BPTT."""
    R = y.shape[0] // len(members)
    heads, dm = [], []
    for k, member in enumerate(members):
        part = slice(k * R, (k + 1) * R)
        g, d = member.head_gradients(m[part], y[part], rs[k], steps[part], reward_steps[part])
        heads += g
        dm.append(d)
    return heads, torch.cat(dm) if len(dm) > 1 else dm[0]
