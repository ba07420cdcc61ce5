"""A count-based exploration bonus on hashed actor states (Tang et al. 2017, "#Exploration").

The actor learns from r_{t+1} + b_{t+1} with

    b_{t+1} = scale / sqrt(N(φ(s_{t+1}))),   φ(s) = Σ_j [ (A s)_j > 0 ] 2^j   (SimHash)

where s_{t+1} is the actor's state after the step — the (processed) observation followed by every
predictor's memory — A (bits × S) has N(0, 1) entries drawn once per run, and N counts the run's
visits of each code since training began, this one included (Tang et al.'s Eq. 2). In a T-maze the
corridor's observation is one id all along it (Bakker 2002), so counting observation ids alone
could not tell the corridor's far end from its start; the predictor's memory can (Thrun 1992's
counter-based directed exploration, on a learnt state). Without predictors the state is the
observation and φ counts observations. ``bits`` sets how coarse the hash is: 2^bits counters
per run, nearby states sharing a code. Returns and every metric stay on the raw reward.
"""

import torch
from torch import Tensor

from ferl import rng
from ferl.config.params import Positive, PositiveInt, checked
from ferl.exploration import ExplorationBase

MAX_BITS = 24  # 2^24 counters per run: 64 MiB a run at float32


class CountBonus(ExplorationBase):
    """The SimHash count bonus over R runs (module docstring): ``scale`` the bonus at a first visit,
    ``bits`` the hash's length."""

    episode_learners_refused = (
        "it learns from its replayed episodes' raw rewards, which the bonus does not reach; use exploration=none"
    )
    A: torch.Tensor  # (R, S, bits) the hash's projections
    counts: torch.Tensor  # (R, 2^bits) N per run and code
    powers: torch.Tensor  # (bits,) 2^j

    @checked
    def __init__(
        self, n_runs: PositiveInt, n_state: PositiveInt, seed: int, scale: Positive = 0.1, bits: PositiveInt = 12
    ):
        super().__init__(n_runs)
        if bits > MAX_BITS:
            raise ValueError(f"bits={bits}: at most {MAX_BITS} (2^bits counters per run)")
        self.scale, self.bits = scale, bits
        projections = [torch.randn(n_state, bits, generator=g) for g in rng.run_generators(seed, n_runs)]
        self.register_buffer("A", torch.stack(projections))  # (R, S, bits)
        self.register_buffer("counts", torch.zeros(n_runs, 2**bits))  # N per run and code
        self.register_buffer("powers", 2 ** torch.arange(bits), persistent=False)

    def describe(self) -> dict:
        return {"kind": "count_bonus", "scale": self.scale, "bits": self.bits}

    def codes(self, s: Tensor) -> Tensor:
        """φ(s) of states s (R, 1, S) → (R,) long in [0, 2^bits)."""
        signs = torch.bmm(s, self.A).squeeze(1) > 0  # (R, bits)
        return (signs.long() * self.powers).sum(1)

    def reward_bonus(self, s_next: Tensor, active: Tensor) -> Tensor:
        """Count the active runs' visits of φ(s_next), then scale / sqrt(N) for them, 0 for the others."""
        code = self.codes(s_next).unsqueeze(1)  # (R, 1)
        self.counts.scatter_add_(1, code, active.to(self.counts.dtype).unsqueeze(1))
        n = self.counts.gather(1, code).squeeze(1)
        return torch.where(active, self.scale / n.clamp(min=1).sqrt(), 0.0)
