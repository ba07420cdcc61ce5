"""Which analysis a run gets, decided on what it recorded (``records/run.json``), and the registry
through which analyses beyond the generic ones plug in.

Every run gets the generic figures (``ferl.analysis.generic``). On top of them, from a ``Registry``:

* the environment's own analysis, by ``env.kind`` (``Registry.environments``); an environment of a
  kind nobody registered has none;
* the claims and figure numbers of the first chapter whose model the run's facts match
  (``Chapter.applies``); a run that matches none is reported without claims.

A sweep gets, besides its generic tables, the claims only a comparison of jobs can judge
(``sweep_claims``) and the sections of ``sweep_sections``; ``pages`` pastes its results into pages of
the repository (``analyze.py --readme``).

ferl registers nothing: a package that reads runs against a publication registers its chapters,
environments and sweep sections into ``REGISTRY`` when imported (the dissertation's:
``reproduction``, which ``analyze.py`` imports). The package never imports it back: data flows one
way (docs/architecture.md). Each worker process of a parallel analysis imports the registered
``modules`` again, so that it sees the same registry.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from ferl.analysis.claims import Chapter, Claim, Numbering
from ferl.analysis.records import Manifest, Run
from ferl.analysis.report import RunAnalysis

if TYPE_CHECKING:
    from ferl.analysis.sweep import ReportRow, Sweep

# (run, figure numbers, out) → (the run as its chapter's claims read it, the analysis' parts), or
# None where the run recorded nothing of the environment's own
EnvironmentAnalysis = Callable[[Run, Numbering, Path], "tuple[Any, RunAnalysis] | None"]
# (sweep, out, the sweep's analysis) → the report's lines; figures and data files go into the
# analysis, whose figures are listed in the report's "Figures across jobs"
SweepSection = Callable[["Sweep", Path, RunAnalysis], list[str]]


class Pages(Protocol):
    """Writes a sweep's results into generated blocks of the repository's pages (--readme)."""

    BLOCKS: Sequence[tuple[str, str]]  # (begin, end) marker lines of every kind of block

    def blocks_in(self, text: str) -> list[tuple[str, str]]: ...

    def update_pages(
        self, pages: Sequence[Path], rows: Sequence[ReportRow], wall: dict[str, float], report: Path
    ) -> None: ...


@dataclass
class Registry:
    """What plug-ins add to the generic analysis (see the module's docstring)."""

    reference: str = ""  # the work whose claims are judged, e.g. "dissertation"
    sweep_title: str = "Sweep report"
    environments: dict[str, EnvironmentAnalysis] = field(default_factory=dict)  # env.kind → analysis
    chapters: list[Chapter] = field(default_factory=list)
    sweep_claims: list[Claim] = field(default_factory=list)
    claim_order: list[Claim] = field(default_factory=list)  # the reports' order of claims
    sweep_sections: list[SweepSection] = field(default_factory=list)
    pages: Pages | None = None
    modules: list[str] = field(default_factory=list)  # what registered: imported by every worker

    @property
    def all_claims(self) -> list[Claim]:
        """Every registered chapter's claims (a kept analysis finds its judged claims among them)."""
        return [claim for chapter in self.chapters for claim in chapter.claims]

    def chapter_of(self, manifest: Manifest) -> Chapter | None:
        return next((c for c in self.chapters if c.applies(manifest)), None)

    @property
    def claims_heading(self) -> str:
        return f"Claims of the {self.reference}" if self.reference else "Claims"


REGISTRY = Registry()


def import_plugins(modules: Sequence[str]) -> None:
    """Import the plug-ins a parent process had registered (in a worker process, whose
    ``REGISTRY`` starts empty); each registers itself on import."""
    for name in modules:
        importlib.import_module(name)
