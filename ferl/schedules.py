"""Meta-parameter schedules over training progress p ∈ [0, 1] (§3.5, Table 4.1).

* learning rate α: exponential decay 0.1 → 0.01 over an epoch (§3.5)
* inverse temperature β: linear 0 → 2 (§3.5) or 0 → 10 (Table 4.1)
"""

from dataclasses import dataclass

from ferl.config.params import Share


@dataclass(frozen=True)
class Constant:
    """The same value at every p: α or β held fixed."""

    value: float

    def __call__(self, progress: float) -> float:
        return self.value


@dataclass(frozen=True)
class Linear:
    """start + (end − start)·min(1, p / over): β rising linearly 0 → 2 (§3.5) or 0 → 10
    (Table 4.1) over the whole training (``over`` = 1, the default), or over its first share
    ``over`` ∈ (0, 1] and held at ``end`` after it."""

    start: float
    end: float
    over: Share = 1.0  # checked with the config (one line naming the key), and here for direct use

    def __post_init__(self):
        check_share(self.over)

    def __call__(self, progress: float) -> float:
        return self.start + (self.end - self.start) * min(1.0, progress / self.over)


@dataclass(frozen=True)
class Exponential:
    """start·(end/start)^min(1, p / over): geometric interpolation over the training's first share
    ``over`` (1: all of it), held at ``end`` after it; both ends must be positive."""

    start: float
    end: float
    over: Share = 1.0

    def __post_init__(self):
        if self.start <= 0 or self.end <= 0:
            raise ValueError(f"exponential schedule needs positive ends, got {self.start} → {self.end}")
        check_share(self.over)

    def __call__(self, progress: float) -> float:
        return self.start * (self.end / self.start) ** min(1.0, progress / self.over)


def check_share(over: float) -> None:
    """``over`` of a schedule built in code (the config checks it before a run)."""
    if not 0 < over <= 1:
        raise ValueError(f"a schedule's over is a share of the training in (0, 1], got {over}")
