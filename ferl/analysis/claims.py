"""Claims of a publication as data, and the chapters that hold them.

A ``Claim`` pairs a statement of a publication (with its section/figure) with a function
measuring the corresponding quantity on an analysed run and a threshold rule turning that
measurement into "held", "partly" or "not held" (spelled out, where given, by its ``criterion``).
A ``Chapter`` is the set of claims and figure numbers that apply to a run whose recorded facts
(``records/run.json``) match the chapter's model. This module holds no claim: the dissertation's
chapters are ``reproduction.ch3``, ``ch4``, ``ch5`` and ``sweep_claims``, registered through
``ferl.analysis.dispatch``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ferl import stats
from ferl.analysis.records import Manifest

HELD, PARTLY, NOT_HELD = "held", "partly", "not held"
VERDICTS = (HELD, PARTLY, NOT_HELD)


@dataclass(frozen=True)
class Measured:
    """What a claim's measure found on a run: the value its rule judges and the report's text."""

    value: Any  # what the rule judges
    text: str  # what the report prints


@dataclass(frozen=True)
class Claim:
    """A statement of a publication, where it says so, how to measure it on a run and how to judge
    the measurement."""

    text: str
    source: str
    measure: Callable[[Any], Measured | None]  # None: the run has no data for this claim
    rule: Callable[[Any], str]
    criterion: str = ""  # the rule in words, for the report
    # The job that the publication's section describes, as runs record their experiment
    # (summary.json): a sweep judges the claim on it where it has one ("": no preference).
    experiment: str = ""

    @property
    def key(self) -> tuple[str, str]:
        """What names the claim: its text and source. Not its identity: a run analysed in a worker
        process returns copies of the registered claims, a kept analysis the claims themselves."""
        return (self.text, self.source)


@dataclass(frozen=True)
class ClaimResult:
    """A claim judged on one run (or across the jobs of a sweep)."""

    claim: Claim
    measured: Measured
    verdict: str


def only(applies: Callable[[Any], bool], measure: Callable[[Any], Measured | None]) -> Callable[[Any], Measured | None]:
    """``measure`` on the runs that ``applies`` accepts (the claim's model or maze variant); None,
    no claim, on any other."""
    return lambda run: measure(run) if applies(run) else None


def evaluate(claims: Sequence[Claim], run: Any) -> list[ClaimResult]:
    """Judge every claim the run's data speaks to."""
    results = []
    for claim in claims:
        measured = claim.measure(run)
        if measured is not None:
            results.append(ClaimResult(claim, measured, claim.rule(measured.value)))
    return results


# ---- rules ---------------------------------------------------------------------


def at_least(held: float, partly: float) -> Callable[[float], str]:
    return lambda v: HELD if v >= held else PARTLY if v >= partly else NOT_HELD


def at_most(held: float, partly: float) -> Callable[[float], str]:
    return lambda v: HELD if v <= held else PARTLY if v <= partly else NOT_HELD


def all_or_some(flags: Sequence[bool]) -> str:
    return HELD if all(flags) else PARTLY if any(flags) else NOT_HELD


def held_only_if(level: str, ok: bool) -> str:
    """A verdict lowered from held to partly where the claim's second part fails."""
    return PARTLY if level == HELD and not ok else level


def at_least_text(what: str, limits: tuple[float, float]) -> str:
    return f"{what}: held ≥ {limits[0]:g}, partly ≥ {limits[1]:g}"


def at_most_text(what: str, limits: tuple[float, float]) -> str:
    return f"{what}: held ≤ {limits[0]:g}, partly ≤ {limits[1]:g}"


def threshold_claim(
    text: str,
    source: str,
    measure: Callable[[Any], Measured | None],
    limits: tuple[float, float],
    what: str,
    upper: bool = False,
    note: str = "",
) -> Claim:
    """A claim judged by one number against (held, partly) limits: at least them, or at most
    with ``upper``; its criterion says so in words (``what``, then ``note``)."""
    if upper:
        return Claim(text, source, measure, at_most(*limits), at_most_text(what, limits) + note)
    return Claim(text, source, measure, at_least(*limits), at_least_text(what, limits) + note)


def mean_sd_text(values) -> str:
    """ "mean ± s.d. (mean ± s.d., n runs)" over the runs that have a value (``ferl.stats``)."""
    mean, sd, n = stats.mean_sd(values)
    if n < 2:
        return f"{mean:.3g} ({n} run{'' if n == 1 else 's'})"
    return f"{mean:.3g} ± {sd:.2g} (mean ± s.d., {n} runs)"


# ---- chapters --------------------------------------------------------------------


@dataclass(frozen=True)
class LayerFigures:
    """Where a publication shows a junction layer: its activations, their PCA per phase with
    the explained variance, and the projection on PC1–3 (None: not shown, not drawn)."""

    activations: str
    pca: str
    pca3d: str | None = None


@dataclass(frozen=True)
class Numbering:
    """A publication's figure numbers of one model on one task ("" where it has none).

    ``predictor_panels`` gives a predictor role its panel of the prediction-error figure; ``layers``
    maps a junction layer (``state``, ``hidden``, ``memory_<role>``, and ``memory`` for any other
    memory) to its figures."""

    learning_curves: str = ""
    td_errors: str = ""
    prediction_errors: str = ""
    predictor_panels: dict[str, str] = field(default_factory=dict)
    parameters: str = ""  # the table of parameters (L_training)
    layers: dict[str, LayerFigures] = field(default_factory=dict)

    def prediction_figure(self, role: str | None) -> str:
        if not self.prediction_errors:
            return ""
        return self.prediction_errors + (self.predictor_panels.get(role, "") if role is not None else "")

    def layer(self, key: str) -> LayerFigures | None:
        return self.layers.get(key) or self.layers.get("memory" if key.startswith("memory") else key)


@dataclass(frozen=True)
class Chapter:
    """The claims and figure numbers of one model of a publication, and which runs they
    apply to, decided on the run's recorded facts."""

    model: str  # the report's line on the model
    applies: Callable[[Manifest], bool]
    numbering: Callable[[Manifest], Numbering]
    claims: list[Claim]


def caption(number: str, text: str) -> str:
    """A caption or title led by the publication's figure number, where it has one."""
    return f"{number}: {text}" if number else text
