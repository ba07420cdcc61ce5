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
from tqdm import tqdm


class DivergenceGuard:
    """Freezes a run whose TD errors stop being finite or exceed `limit`, leaving the batch's other
    runs going; what it froze goes to summary.json's `diverged` (docs/records.md)."""

    def __init__(self, n_runs: int, limit: float, seeds: list[int], device):
        self.limit, self.seeds = float(limit), list(seeds)
        self.alive = torch.ones(n_runs, 1, dtype=torch.bool, device=device)
        self.diverged_at: list[int | None] = [None] * n_runs  # step (or episode) per run, None while healthy
        self.reasons: list[str | None] = [None] * n_runs
        self.details: list[dict | None] = [None] * n_runs  # what else the report says of a run frozen by ``freeze``

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
            self.reasons[r] = (
                "non-finite TD error"
                if not torch.isfinite(errors[first[r], r])
                else f"|TD error| {abs(value):.3g} > limit {self.limit:g}"
            )
            self.diverged_at[r] = first_step + int(first[r])
            print(
                f"ferl: run {r} (seed {self.seeds[r]}) diverged at {unit} {self.diverged_at[r]}: "
                f"{self.reasons[r]}; frozen, the other runs go on",
                file=sys.stderr,
            )
        self.alive &= ~new.unsqueeze(1)

    def freeze(self, run: int, at: int, reason: str, details: dict) -> None:
        """Freeze ``run`` at step (or episode) ``at`` for ``reason`` (one stderr line), with
        ``details`` for its report (an outside environment's ``env_id`` and ``step``). A run frozen
        already keeps its first reason."""
        if self.diverged_at[run] is not None:
            return
        self.diverged_at[run], self.reasons[run], self.details[run] = at, reason, dict(details)
        self.alive[run] = False
        # tqdm.write: a line of its own, not the tail of the progress bar's
        tqdm.write(f"ferl: run {run} (seed {self.seeds[run]}): {reason}; frozen, the other runs go on", file=sys.stderr)

    def void_failed_envs(self, metrics: dict) -> dict:
        """``metrics`` (name → one value per run, or a dict of such) with None for every run frozen
        by ``freeze``: its episodes after the fault are stand-ins (module docstring)."""
        failed = {r for r, d in enumerate(self.details) if d is not None}
        if not failed:
            return metrics

        def void(value):
            if isinstance(value, dict):
                return {key: void(v) for key, v in value.items()}
            if isinstance(value, list) and len(value) == len(self.seeds):
                return [None if r in failed else v for r, v in enumerate(value)]
            return value

        return void(metrics)

    def report(self, unit: str = "step") -> list[dict]:
        """summary.json's `diverged`: one entry per diverged run."""
        return [
            {
                "run": r,
                "seed": self.seeds[r],
                unit: self.diverged_at[r],
                "reason": self.reasons[r],
                **{k: v for k, v in (self.details[r] or {}).items() if k != unit},
            }
            for r in range(len(self.seeds))
            if self.diverged_at[r] is not None
        ]

    def state_dict(self) -> dict:
        return {
            "alive": self.alive.cpu(),
            "diverged_at": self.diverged_at,
            "reasons": self.reasons,
            "details": self.details,
        }

    def load_state_dict(self, state: dict) -> None:
        self.alive = state["alive"].to(self.alive.device)
        self.diverged_at, self.reasons = list(state["diverged_at"]), list(state["reasons"])
        self.details = list(state.get("details", [None] * len(self.seeds)))
