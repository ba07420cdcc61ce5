"""A ``Box`` observation's thermometer thresholds derived per entry (``env.thresholds: auto``,
docs/beyond.md, "Outside POMDPs").

One threshold list typed for every entry wastes bits: CartPole's x spans ±2.4 and its pole angle
θ ±0.21, so a list fitted to x never moves θ's bits. Here each entry i gets its own k =
``bits_per_entry`` thresholds, computed once at set-up from a random-policy sample of
``sample_steps`` observations (``random_policy_sample``: seeded with ``SAMPLE_SEED``, not with the
run's seed, so every job of a sweep sees one encoding):

* ``bounds``: θ_ij = low_i + j (high_i − low_i) / (k + 1), j = 1 … k (levels of equal width over
  the space's bounds) where both bounds are finite and the sample crosses every one of them
  (min_i ≤ θ_i1 and θ_ik < max_i): the bounds are then the range the entry really takes.
* ``sample``: otherwise — infinite bounds (CartPole's velocities), or bounds wider than what is
  visited (CartPole's x: ±4.8, twice the ±2.4 at which an episode ends) — the quantiles
  θ_ij = Q_i(j / (k + 1)) of the entry's sample (levels of equal frequency; ``numpy.quantile``'s
  default, linear interpolation), keeping those with min_i ≤ θ_ij < max_i, each once: an entry of
  few distinct values repeats quantiles, and a quantile at the sample's maximum is a bit that
  never turns on.

Either way every bit moves on the sample: some observation lies at or below θ_ij (bit 0) and some
above it (bit 1). An entry constant over the sample gets no bits, and the run says so. The sample's
per-entry mean and standard deviation are kept too (``Derived.mean``, ``Derived.std``): the
statistics a real-valued input would be standardised with.
"""

import json
from dataclasses import dataclass

import numpy as np
from gymnasium import spaces

from ferl.envs.encodings import BadThresholds

SAMPLE_SEED = 0  # the sample's seed: one encoding for every run and every seed of a sweep
_DERIVED: dict[str, "Derived"] = {}  # derived_once's derivations, by their key


@dataclass(frozen=True)
class Derived:
    """Per-entry thresholds (C order) and where each list came from (``bounds`` | ``sample``)."""

    thresholds: list[list[float]]
    sources: list[str]
    bits_per_entry: int
    sample_steps: int
    mean: list[float]
    std: list[float]

    def describe(self, thresholds: bool = True) -> dict:
        """What records/run.json keeps, so that a run's encoding can be read and rebuilt; without
        ``thresholds`` (``env.encoding=real``), the sample's statistics alone."""
        made = {"sources": self.sources, "bits_per_entry": self.bits_per_entry} if thresholds else {}
        return {  # the thresholds themselves: the environment's ``thresholds``
            **made,
            "sample_steps": self.sample_steps,
            "sample_seed": SAMPLE_SEED,
            "sample_mean": self.mean,
            "sample_std": self.std,
        }

    def sample_stated(self, env_id: str) -> str:
        """One line for the run's log of ``env.encoding=real``: every entry's mean and spread."""
        entries = "; ".join(f"entry {i}: μ {m:.4g}, σ {s:.4g}" for i, (m, s) in enumerate(zip(self.mean, self.std)))
        return (
            f"env.encoding=real: {len(self.mean)} real values for {env_id!r}, μ ± 3σ mapped onto [0, 1], from a "
            f"{self.sample_steps}-step random-policy sample (seed {SAMPLE_SEED}): {entries}"
        )

    def stated(self, env_id: str) -> str:
        """One line for the run's log: every entry's thresholds and their source."""
        entries = "; ".join(
            f"entry {i} ({source}, {len(theta)} bits): [{', '.join(f'{t:.4g}' for t in theta)}]"
            for i, (source, theta) in enumerate(zip(self.sources, self.thresholds))
        )
        bits = sum(len(theta) for theta in self.thresholds)
        return (
            f"env.thresholds=auto: {bits} bits for {env_id!r}, derived from a {self.sample_steps}-step "
            f"random-policy sample (seed {SAMPLE_SEED}): {entries}"
        )


def derives(space, encoding: str, thresholds) -> bool:
    """Whether the thresholds of ``space`` are to be derived: a ``Box`` encoded by thresholds
    (``env.encoding`` thresholds, or auto) with ``auto`` or none given. ``auto`` for anything
    else is refused, as typed thresholds are (``ferl.envs.encodings``)."""
    box = isinstance(space, spaces.Box)
    wanted = thresholds == "auto" or not thresholds
    if box and encoding in ("auto", "thresholds"):
        return wanted
    if thresholds == "auto":
        raise BadThresholds(
            f"auto derives a Box's thermometer code, but env.encoding={encoding} encodes {space} "
            f"without thresholds; use env.thresholds=null"
        )
    return False


def random_policy_sample(env, steps: int, max_steps: int) -> np.ndarray:
    """``steps`` observations (steps, entries), float64, of ``env`` played by uniformly random
    actions: the first reset seeded with ``SAMPLE_SEED``, later ones continuing its stream, an
    episode cut after ``max_steps`` actions as the runs cut theirs. Reset observations count."""
    env.action_space.seed(SAMPLE_SEED)
    observation, _ = env.reset(seed=SAMPLE_SEED)
    rows, t = [observation], 0
    while len(rows) < steps:
        observation, _, terminated, truncated, _ = env.step(env.action_space.sample())
        rows.append(observation)
        t += 1
        if terminated or truncated or t >= max_steps:
            if len(rows) < steps:
                observation, _ = env.reset()
                rows.append(observation)
            t = 0
    return np.stack([np.asarray(row, np.float64).reshape(-1) for row in rows[:steps]])


def evenly_spaced(low: float, high: float, k: int) -> np.ndarray:
    """k thresholds cutting [low, high] into k + 1 levels of equal width."""
    return low + (high - low) * np.arange(1, k + 1) / (k + 1)


def quantile_thresholds(values: np.ndarray, k: int) -> np.ndarray:
    """The quantiles j / (k + 1), j = 1 … k, of ``values`` that lie in [min, max), each once."""
    theta = np.quantile(values, np.arange(1, k + 1) / (k + 1))
    return np.unique(theta[(theta >= values.min()) & (theta < values.max())])


def derived_once(env, key: list, k: int, steps: int, max_steps: int) -> Derived:
    """``derive`` on ``env``'s sample, once per process for the same ``key`` (its id and kwargs),
    k, steps and T_max: set-up builds the environment more than once (the memory estimate's probes),
    and each build must see the same encoding without playing the sample again."""
    cache_key = json.dumps([key, k, steps, max_steps], sort_keys=True, default=repr)
    if cache_key not in _DERIVED:
        _DERIVED[cache_key] = derive(env.observation_space, random_policy_sample(env, steps, max_steps), k)
    return _DERIVED[cache_key]


def entry_thresholds(low: float, high: float, values: np.ndarray, k: int) -> tuple[np.ndarray, str]:
    """One entry's thresholds and their source (module docstring)."""
    if np.isfinite(low) and np.isfinite(high):
        theta = evenly_spaced(low, high, k)
        if values.min() <= theta[0] and theta[-1] < values.max():
            return theta, "bounds"
    return quantile_thresholds(values, k), "sample"


def derive(space: spaces.Box, sample: np.ndarray, k: int) -> Derived:
    """Every entry's thresholds from the space's bounds or the sample (module docstring)."""
    low = np.asarray(space.low, np.float64).reshape(-1)
    high = np.asarray(space.high, np.float64).reshape(-1)
    made = [entry_thresholds(low[i], high[i], sample[:, i], k) for i in range(sample.shape[1])]
    if not any(len(theta) for theta, _ in made):
        raise BadThresholds(
            f"auto: no entry varied over the {len(sample)}-step random-policy sample; "
            f"raise env.sample_steps, or give the thresholds"
        )
    return Derived(
        thresholds=[[float(t) for t in theta] for theta, _ in made],
        sources=[source for _, source in made],
        bits_per_entry=k,
        sample_steps=len(sample),
        mean=[float(m) for m in sample.mean(0)],
        std=[float(s) for s in sample.std(0)],
    )


def constant_entries(derived: Derived) -> list[int]:
    """Entries that got no bits: constant over the sample."""
    return [i for i, theta in enumerate(derived.thresholds) if not theta]


def unused_bits(env_id: str, fixed: list, size: int, derived: Derived | None) -> str:
    """The warning for bits that never change (typed thresholds outside an entry's bounds) or
    entries without bits (derived ones constant over the sample); "" when there are none."""
    if derived is not None and constant_entries(derived):
        return (
            f"env.thresholds=auto: entries {constant_entries(derived)} of {env_id!r}'s observations did not vary "
            f"over the {derived.sample_steps}-step random-policy sample and have no bits; raise env.sample_steps, "
            f"or give one threshold list per entry"
        )
    if not fixed:
        return ""
    return (
        f"env.thresholds: {len(fixed)} of the {size} bits never change, their thresholds outside "
        f"the bounds of entries {sorted({i for i, _ in fixed})} of {env_id!r}'s observations (one list per "
        f"entry: [[θ_11, …], [θ_21, …], …], or env.thresholds=auto)"
    )
