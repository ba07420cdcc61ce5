"""The reproduction of Otsuka's dissertation, read from ferl's runs: its claims, its chapters'
figures, the findings beyond it, and the pages of this repository that show the results.

ferl's generic analysis (``ferl.analysis``) gives every run its learning curves, TD errors,
prediction errors and summary table; this package plugs into it through
``ferl.analysis.dispatch.REGISTRY`` when imported (``analyze.py`` imports it), and ferl never
imports it back:

* ``floor`` (digit floor, ``floor_figures``) and ``tmaze`` (T-junction, ``tmaze_figures``, with
  ``preprocessor`` for the RBM of §5.3.2) add their environment's figures, by ``env.kind``;
* ``ch3``, ``ch4``, ``ch5`` hold the dissertation's claims and figure numbers by chapter
  (``tmaze_claims`` the measures chapters 4 and 5 share), ``sweep_claims`` those only a comparison
  of jobs can judge, ``scope`` the runs they speak to (the dissertation's components, algorithm);
* a sweep's sections: ``noise_grid`` (Fig. 3.6 across jobs), ``beyond`` (findings beyond the
  dissertation, §5.4, with ``curves``: the passive and active T-mazes' memory curves) and ``variants`` (agents side by side per task: the variants, the baselines
  and the third-party suites);
* ``published`` pastes a sweep's results into README.md and docs/reproduction.md (``--readme``).
"""

from __future__ import annotations

from ferl.analysis import dispatch
from reproduction import beyond, ch3, ch4, ch5, floor, noise_grid, published, tmaze, variants
from reproduction.sweep_claims import SWEEP_CLAIMS

CHAPTERS = (ch3.CHAPTER, ch4.CHAPTER, ch5.CHAPTER)
# The order of the dissertation, for reports that gather claims from many runs.
CLAIM_ORDER = ch3.CLAIMS + SWEEP_CLAIMS + ch4.CLAIMS + ch5.CLAIMS


def register(registry: dispatch.Registry) -> None:
    """Plug the dissertation's analyses into ``registry`` (what analysis a run gets is still
    decided on what it recorded: ``env.kind`` and each chapter's ``applies``)."""
    registry.reference = "dissertation"
    registry.sweep_title = "Reproduction report"
    registry.environments |= {
        floor.ENV_KIND: lambda run, num, out: floor.analyze(run, out),
        tmaze.ENV_KIND: tmaze.analyze,
    }
    registry.chapters += CHAPTERS
    registry.sweep_claims += SWEEP_CLAIMS
    registry.claim_order += CLAIM_ORDER
    registry.sweep_sections += [
        noise_grid.report,
        lambda sweep, out, analysis: beyond.report(sweep.jobs, out, analysis.figures, analysis.data_files),
        lambda sweep, out, analysis: variants.report(sweep.jobs, out, analysis.figures, analysis.data_files),
    ]
    registry.pages = published
    registry.modules.append(__name__)


register(dispatch.REGISTRY)
