"""Per-run reward normalisation of a scalar reward head (``reward_norm=popart``): PopArt, "Preserving
Outputs Precisely, while Adaptively Rescaling Targets" (van Hasselt, Guez, Hessel, Mnih & Silver,
NeurIPS 2016), so that an outside environment is learnt at its own reward scale (docs/beyond.md,
"Reward scale").

Why: the linear reward head's squared error (Eq. 5.2) is what teaches a joint predictor's memory to
keep what decides a later reward. Its gradient into the memory, ρ_r (r̂_t − r_t) W_rm, grows with the
square of the rewards' scale, while the observation's cross entropy (Eq. 4.6) does not change. At a
scale of ±1 or POPGym's ±1/T that gradient is too weak beside the observation's, and the memory never
learns the cue (our measurement, docs/beyond.md). The head therefore learns the standardised reward

    z_t = (r_t − μ) / σ                                                   (van Hasselt et al., Eq. 6)

with μ, σ the mean and standard deviation of every reward the run has seen (``update``, once per
new episode, never per replayed one). When μ, σ move to μ', σ', the head's weights and bias are
rescaled so that its prediction in the environment's units, σ ẑ + μ, is unchanged (their Eq. 8):

    W'_rm = (σ / σ') W_rm,    b'_r = (σ b_r + μ − μ') / σ'

Off (``reward_norm=none``, the default) the head learns the raw reward, as the dissertation's.

A reward that has not varied: while the rewards seen have a standard deviation below ``RELATIVE_SIGMA``
of their root mean square (every reward equal so far, as CartPole's +1 a step), (μ, σ) are (0, 1),
so the head learns the raw reward, as with ``reward_norm=none``. Dividing by the vanishing σ instead
(or by a fixed floor under it) would turn the zero filler of the targets' first step, or the first
reward that differs, into targets ~1/σ from the rest, whose squared error swamps the memory's and
the exploration that follows it (docs/beyond.md, "Reward scale"). The switch to the standardised
reward, once the rewards vary, is a change of (μ, σ) as any other: the head is rescaled (Eq. 8).
"""

import torch
from torch import nn

SIGMA_FLOOR = 1e-4  # σ of rewards that vary, but only in their fourth decimal, is not below this
RELATIVE_SIGMA = 1e-3  # rewards whose σ is below this fraction of their r.m.s. have not varied (module docstring)


class RewardStatistics(nn.Module):
    """Per-run count, mean and sum of squared deviations of the rewards seen (Chan et al.'s
    parallel update of Welford's running variance), as buffers so that checkpoints carry them."""

    count: torch.Tensor  # (R,) float64, as the other two
    mean: torch.Tensor
    m2: torch.Tensor

    def __init__(self, n_runs: int):
        super().__init__()
        self.register_buffer("count", torch.zeros(n_runs, dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(n_runs, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(n_runs, dtype=torch.float64))

    def moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(μ, σ) per run, float32 (R,): the rewards' mean and standard deviation (σ ≥
        ``SIGMA_FLOOR``) once they have varied; (0, 1), the identity, before any reward and while
        they have not (module docstring)."""
        variance = self.m2 / self.count.clamp(min=1)
        sigma = variance.sqrt()
        varied = (self.count > 0) & (sigma > RELATIVE_SIGMA * (self.mean.square() + variance).sqrt())
        mu = torch.where(varied, self.mean, 0.0)
        return mu.float(), torch.where(varied, sigma.clamp(min=SIGMA_FLOOR), 1.0).float()

    @torch.no_grad()
    def update(self, rewards: torch.Tensor, mask: torch.Tensor) -> None:
        """Merge the rewards (R, …) where ``mask`` (same shape) is True into every run's moments."""
        r, w = rewards.double().flatten(1), mask.double().flatten(1)
        n = w.sum(1)
        mean_b = (r * w).sum(1) / n.clamp(min=1)
        m2_b = ((r - mean_b.unsqueeze(1)).square() * w).sum(1)
        total = self.count + n
        delta = mean_b - self.mean
        share = torch.where(total > 0, n / total.clamp(min=1), 0.0)
        self.mean += delta * share
        self.m2 += m2_b + delta.square() * self.count * share
        self.count.copy_(total)


def normalised(stats: RewardStatistics, rewards: torch.Tensor) -> torch.Tensor:
    """z = (r − μ) / σ of rewards (R, …) with every run's own μ, σ."""
    mu, sigma = stats.moments()
    shape = (-1,) + (1,) * (rewards.dim() - 1)
    return (rewards - mu.view(shape)) / sigma.view(shape)


@torch.no_grad()
def rescale_head(W: torch.Tensor, b: torch.Tensor, before: tuple, after: tuple) -> None:
    """Preserve the head's outputs in the environment's units across a change of (μ, σ) → (μ', σ')
    (module docstring): W (R, 1, M), b (R, 1) in place."""
    (mu, sigma), (mu_new, sigma_new) = before, after
    W.mul_((sigma / sigma_new).view(-1, 1, 1))
    b.copy_((sigma.view(-1, 1) * b + (mu - mu_new).view(-1, 1)) / sigma_new.view(-1, 1))


def observe_rewards(predictors, rewards: torch.Tensor, lengths: torch.Tensor) -> None:
    """Every predictor takes in new episodes' rewards (R, B, T_max) with lengths (R, B)
    (``Predictor.observe_rewards``: one that normalises its reward updates its statistics)."""
    for p in predictors:
        p.observe_rewards(rewards, lengths)
