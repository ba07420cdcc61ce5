"""Which analysis a run gets, decided on what it recorded (`records/run.json`).

Every run gets the generic figures (`ferl.analysis.generic`). On top of them:

* the environment's own figures, by `env.kind`: the digit floor's (`floor`) or the T-maze's
  junction and preprocessor figures (`tmaze`); an environment of another kind has none;
* the claims and figure numbers of the first chapter whose model the run's facts match
  (`Chapter.applies`): chapter 3 for the digit floor, chapter 4 for a T-maze with one joint
  predictor, chapter 5 for a T-maze with an observation and a reward predictor; a run that
  matches none is reported without claims.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ferl.analysis import ch3, ch4, ch5, floor, tmaze
from ferl.analysis.claims import Chapter, Claim, Numbering
from ferl.analysis.records import Manifest, Run
from ferl.analysis.report import RunAnalysis
from ferl.analysis.sweep_claims import SWEEP_CLAIMS

CHAPTERS: tuple[Chapter, ...] = (ch3.CHAPTER, ch4.CHAPTER, ch5.CHAPTER)

# env.kind → its analysis: (run, figure numbers, out) → (the run as its chapter's claims read
# it, the analysis' parts), or None where the run recorded nothing of the environment's own
ENVIRONMENTS: dict[str, Callable[[Run, Numbering, Path], tuple[Any, RunAnalysis] | None]] = {
    floor.ENV_KIND: lambda run, num, out: floor.analyze(run, out),
    tmaze.ENV_KIND: tmaze.analyze,
}

# The order of the dissertation, for reports that gather claims from many runs.
CLAIM_ORDER: list[Claim] = ch3.CLAIMS + SWEEP_CLAIMS + ch4.CLAIMS + ch5.CLAIMS


def chapter_of(manifest: Manifest) -> Chapter | None:
    return next((c for c in CHAPTERS if c.applies(manifest)), None)
