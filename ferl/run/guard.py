"""Per-run divergence guard: a run whose TD errors turn non-finite or explode is frozen and
reported, while the other runs of the batch go on untouched.

The check runs on the TD errors the trainers record anyway, once per logging interval, so the
step loop pays one `torch.where` per step (`mask`) and no host synchronisation. The step at which
a run diverged is exact: the first recorded error of the interval that is non-finite or beyond
the limit. From then on its TD errors are replaced by 0, so its parameters stop changing (and a
run that exploded keeps finite ones).
"""
import sys

import torch


class DivergenceGuard:
    def __init__(self, n_runs: int, limit: float, seeds: list[int], device):
        self.limit, self.seeds = float(limit), list(seeds)
        self.alive = torch.ones(n_runs, 1, dtype=torch.bool, device=device)
        self.diverged_at = [None] * n_runs   # step (or episode) per run, None while healthy
        self.reasons = [None] * n_runs

    def mask(self, delta: torch.Tensor) -> torch.Tensor:
        """TD errors (R, B) with those of frozen runs set to 0."""
        return torch.where(self.alive, delta, 0.0)

    def check(self, errors: torch.Tensor, first_step: int, unit: str = "step") -> None:
        """Inspect recorded TD errors (T, R) of steps (or episodes: per-episode mean |δ|)
        first_step … first_step + T − 1."""
        bad = ~torch.isfinite(errors) | (errors.abs() > self.limit)
        new = bad.any(0) & self.alive.squeeze(1)
        if not bool(new.any()):
            return
        first = bad.float().argmax(0)
        for r in new.nonzero().squeeze(1).tolist():
            value = float(errors[first[r], r])
            self.reasons[r] = ("non-finite TD error" if not torch.isfinite(errors[first[r], r])
                               else f"|TD error| {abs(value):.3g} > limit {self.limit:g}")
            self.diverged_at[r] = first_step + int(first[r])
            print(f"ferl: run {r} (seed {self.seeds[r]}) diverged at {unit} {self.diverged_at[r]}: "
                  f"{self.reasons[r]}; frozen, the other runs go on", file=sys.stderr)
        self.alive &= ~new.unsqueeze(1)

    def report(self, unit: str = "step") -> list[dict]:
        """summary.json's `diverged`: one entry per diverged run."""
        return [{"run": r, "seed": self.seeds[r], unit: self.diverged_at[r], "reason": self.reasons[r]}
                for r in range(len(self.seeds)) if self.diverged_at[r] is not None]

    def state_dict(self) -> dict:
        return {"alive": self.alive.cpu(), "diverged_at": self.diverged_at, "reasons": self.reasons}

    def load_state_dict(self, state: dict) -> None:
        self.alive = state["alive"].to(self.alive.device)
        self.diverged_at, self.reasons = list(state["diverged_at"]), list(state["reasons"])
