"""The markdown reports: a run's ``analysis/report.md`` and the jobs table of a sweep's."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from ferl.analysis.claims import VERDICTS, ClaimResult
from ferl.analysis.io import table_lines

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclass
class RunAnalysis:
    """What an analysis hands to the writer: header, tables, figures, data files, judged claims."""

    title: str
    header: list[tuple[str, str]] = field(default_factory=list)
    sections: list[tuple[str, list[str]]] = field(default_factory=list)  # (title, markdown lines)
    figures: dict[str, tuple[Figure, str]] = field(default_factory=dict)  # name → (fig, caption)
    data_files: list[str] = field(default_factory=list)
    results: list[ClaimResult] = field(default_factory=list)
    # whether a registered publication's claims speak to the run (its chapter applies): only then
    # has the report a claims section, so that a run of one's own task meets no one's claims
    claims_apply: bool = False

    def add(self, other: RunAnalysis) -> None:
        """Append another analysis' parts of the same run (its title is dropped)."""
        self.header += other.header
        self.sections += other.sections
        self.figures |= other.figures
        self.data_files += other.data_files
        self.results += other.results


def claims_table(results: Sequence[ClaimResult], reference: str = "") -> list[str]:
    """One row per claim; a criterion column where any claim states its rule. ``reference`` names
    the work the claims come from (``ferl.analysis.dispatch.Registry.reference``)."""
    if not results:
        return [f"No {reference} claim applies to this run." if reference else "No claim applies to this run."]
    criteria = any(r.claim.criterion for r in results)
    header = ["claim", "source", "measured", *(["criterion"] if criteria else []), "verdict"]
    return table_lines(
        header,
        [
            [
                r.claim.text,
                r.claim.source,
                r.measured.text,
                *([r.claim.criterion or "—"] if criteria else []),
                f"**{r.verdict}**",
            ]
            for r in results
        ],
    )


def write_run_report(path: Path, analysis: RunAnalysis, reference: str = "") -> None:
    """``analysis/report.md`` of one run: header, tables, claims (of ``reference``, where they
    apply), figure and data links."""
    lines = [f"# {analysis.title}", ""]
    lines += [f"- **{key}**: {value}" for key, value in analysis.header]
    for title, body in analysis.sections:
        lines += ["", f"## {title}", ""] + body
    if analysis.claims_apply or analysis.results:
        lines += ["", "## Claims", ""] + claims_table(analysis.results, reference)
    lines += ["", "## Figures", ""]
    lines += [f"- [{name}.png]({name}.png) — {caption}" for name, (_, caption) in analysis.figures.items()]
    lines += ["", "## Data", ""] + [f"- [{name}]({name})" for name in analysis.data_files]
    path.write_text("\n".join(lines) + "\n")


@dataclass
class RunOutcome:
    """One line of a sweep report."""

    run_dir: Path
    experiment: str
    task: str
    status: str  # "analyzed", "skipped: …" or "failed: …"
    verdicts: dict[str, int] = field(default_factory=dict)
    results: list[ClaimResult] = field(default_factory=list)
    figures: list[tuple[str, str]] = field(default_factory=list)  # (name, caption)


def jobs_table(sweep_dir: Path, out: Path, outcomes: Sequence[RunOutcome]) -> list[str]:
    """One row per job of a sweep, linking its report (from ``out``) and counting its verdicts."""
    rows = []
    for o in outcomes:
        name = os.path.relpath(o.run_dir, sweep_dir)
        if o.status == "analyzed":
            name = f"[{name}]({os.path.relpath(o.run_dir / 'analysis' / 'report.md', out)})"
        rows.append([name, o.experiment, o.task, o.status, *(str(o.verdicts.get(v, "")) for v in VERDICTS)])
    return table_lines(["run", "experiment", "task", "status", *VERDICTS], rows)
