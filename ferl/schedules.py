"""Meta-parameter schedules over training progress p ∈ [0, 1] (§3.5, Table 4.1).

* learning rate α: exponential decay 0.1 → 0.01 over an epoch (§3.5)
* inverse temperature β: linear 0 → 2 (§3.5) or 0 → 10 (Table 4.1)
"""

from dataclasses import dataclass


@dataclass(frozen=True)
class Constant:
    """The same value at every p: α or β held fixed."""

    value: float

    def __call__(self, progress: float) -> float:
        return self.value


@dataclass(frozen=True)
class Linear:
    """start + (end − start)·p: β rising linearly 0 → 2 (§3.5) or 0 → 10 (Table 4.1)."""

    start: float
    end: float

    def __call__(self, progress: float) -> float:
        return self.start + (self.end - self.start) * progress


@dataclass(frozen=True)
class Exponential:
    """start·(end/start)^p: geometric interpolation, both ends must be positive."""

    start: float
    end: float

    def __post_init__(self):
        if self.start <= 0 or self.end <= 0:
            raise ValueError(f"exponential schedule needs positive ends, got {self.start} → {self.end}")

    def __call__(self, progress: float) -> float:
        return self.start * (self.end / self.start) ** progress
