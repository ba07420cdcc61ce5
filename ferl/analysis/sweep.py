"""A sweep directory (the jobs of one or more Hydra multiruns) → its aggregate analysis.

Every job keeps its own ``analysis/`` (docs/records.md, "Analysis"); the sweep's ``analysis/`` gets:

* ``metrics.csv`` and one table per experiment: mean ± s.e.m. over runs of every
  ``summary.json`` metric, one column per variant of the experiment (a variant is a job's
  overrides besides ``experiment=…``; none = the setting of the experiment's YAML);
* the claims report: one row per claim the jobs judged, judged on the job of the experiment
  the claim names (``Claim.experiment``, the one its section describes) that runs it as its YAML
  does (the fewest overrides), the verdicts of the other jobs beside it,
  and the claims only a comparison of jobs can judge (``Registry.sweep_claims``);
* the sections that plug-ins register (``ferl.analysis.dispatch.Registry.sweep_sections``).

Means and s.e.m. over runs are ``ferl.stats``', metric names its flattening (``<metric>/<level>``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from ferl import runs, stats
from ferl.analysis.claims import VERDICTS, Claim, ClaimResult
from ferl.analysis.io import fmt, table_lines, write_csv
from ferl.analysis.records import Manifest
from ferl.analysis.report import RunAnalysis, RunOutcome

SCALARS = ("wall_time_s", "agent_steps_per_s")  # summary.json figures besides ``metrics``
BASE_SETTING = "no overrides"  # the variant of a job without overrides, of no reference's model
PLAIN_TITLE = "Report"  # a sweep's title where no job reproduces a reference (ferl.analysis.runner)
TRAIN_WALL_TIME = "train_wall_time_s"  # written by ``make reproduce``


def _job_overrides(run_dir: Path) -> tuple[str, ...]:
    """The job's command-line overrides besides the experiment and Hydra's own (launcher, dirs)."""
    return tuple(
        o
        for o in runs.load_overrides(run_dir).split()
        if not o.lstrip("+~").startswith(("experiment=", "hydra.", "hydra/"))
    )


@dataclass
class Job:
    """One analysed run directory of the sweep."""

    outcome: RunOutcome
    summary: dict
    # the work whose model the run follows ("dissertation": a registered chapter applies to it), ""
    # for none; set by ferl.analysis.runner, which knows the registry
    reference: str = ""

    @property
    def run_dir(self) -> Path:
        return self.outcome.run_dir

    @property
    def experiment(self) -> str:
        return str(self.summary.get("experiment", "?"))

    @cached_property
    def overrides(self) -> tuple[str, ...]:
        return _job_overrides(self.run_dir)

    @property
    def variant(self) -> str:
        """The job's overrides; without any, its experiment's own setting: "as in the
        dissertation" only where the run follows the dissertation's model (``reference``)."""
        return " ".join(self.overrides) or (f"as in the {self.reference}" if self.reference else BASE_SETTING)

    @property
    def label(self) -> str:
        """``experiment`` and its overrides, e.g. ``ch3_floor env.noise=0.5``."""
        return f"`{' '.join((self.experiment, *self.overrides))}`"

    @cached_property
    def manifest(self) -> Manifest | None:
        """None also for a damaged one: the run's own analysis has reported it."""
        try:
            return Manifest.load(self.run_dir)
        except (OSError, ValueError):
            return None

    def setting(self, part: str, key: str):
        """A parameter of a part of the run as records/run.json states it (``env.noise``,
        ``actor.n_hidden``), None without one."""
        facts = None if self.manifest is None else getattr(self.manifest, part)
        return (facts or {}).get(key)

    def verdict(self, source: str) -> ClaimResult | None:
        return next((r for r in self.outcome.results if r.claim.source == source), None)


@dataclass
class Sweep:
    """The analysed jobs of a sweep directory, for the report and the cross-job claims."""

    root: Path
    jobs: list[Job]

    def of(self, experiment: str) -> list[Job]:
        return [j for j in self.jobs if j.experiment == experiment]

    def varying(self, experiment: str, part: str, key: str) -> list[dict]:
        """The jobs of ``experiment`` that differ only in ``part.key`` (the override of that
        name), as sets {value: job}; one set per combination of the other overrides, fewest
        overrides first. The first job of a value stands for it (the same config and seed give
        the same numbers)."""
        override = f"{part}.{key}="
        sets: dict[tuple[str, ...], dict] = {}
        for job in self.of(experiment):
            value = job.setting(part, key)
            if value is not None:
                rest = tuple(o for o in job.overrides if not o.startswith(override))
                sets.setdefault(rest, {}).setdefault(value, job)
        return [sets[rest] for rest in sorted(sets, key=len)]


def metric_values(summary: dict) -> dict[str, list]:
    """Every headline figure of a summary as per-run values, named as ``ferl.stats`` flattens
    them (``greedy_accuracy/0.5``), then the run-level ``SCALARS``."""
    out = stats.flat_metrics(summary.get("metrics", {}))
    out |= {name: [summary[name]] for name in SCALARS if name in summary}
    return out


@dataclass(frozen=True)
class Aggregate:
    """Mean ± s.e.m. over runs of one metric of one variant of an experiment."""

    experiment: str
    variant: str
    metric: str
    mean: float
    sem: float
    n: int


def aggregate(jobs: Sequence[Job]) -> list[Aggregate]:
    """Mean ± s.e.m. over runs of every metric of every job, in job order."""
    return [
        Aggregate(job.experiment, job.variant, metric, *stats.mean_sem(values))
        for job in jobs
        for metric, values in metric_values(job.summary).items()
    ]


def _cell_text(a: Aggregate) -> str:
    if a.n == 0:
        return "—"
    return f"{a.mean:.4g}" + ("" if math.isnan(a.sem) else f" ± {a.sem:.2g}")


def experiment_tables(rows: Sequence[Aggregate]) -> dict[str, list[str]]:
    """experiment → markdown table: one row per metric, one column per variant."""
    tables = {}
    for experiment in dict.fromkeys(r.experiment for r in rows):
        mine = [r for r in rows if r.experiment == experiment]
        variants = list(dict.fromkeys(r.variant for r in mine))
        metrics = list(dict.fromkeys(r.metric for r in mine))
        by_key = {(r.metric, r.variant): r for r in mine}
        lines = table_lines(
            ["metric", *(f"`{v}`" for v in variants)],
            [[m, *(_cell_text(by_key[m, v]) if (m, v) in by_key else "—" for v in variants)] for m in metrics],
        )
        tables[experiment] = lines
    return tables


# ---- the reproduction report ---------------------------------------------------


@dataclass(frozen=True)
class ReportRow:
    """A row of the claims report: the judged claim, the job that judged it, and the others."""

    result: ClaimResult
    job: Job | None  # None: a claim judged across jobs
    others: tuple[tuple[Job, ClaimResult], ...]  # other jobs that judged the same claim


def reproduction_rows(
    jobs: Sequence[Job], sweep_results: Sequence[ClaimResult], order: Sequence[Claim]
) -> list[ReportRow]:
    """One row per claim, in the given order (the publication's): a job of the experiment the
    claim names judges it where the sweep has one, of those the one with the fewest overrides
    (ties: sweep order)."""
    answered: dict[tuple[str, str], list[tuple[Job, ClaimResult]]] = {}
    for job in jobs:
        for r in job.outcome.results:
            answered.setdefault(r.claim.key, []).append((job, r))
    rows = []
    for found in answered.values():
        named = found[0][1].claim.experiment
        ranks = [(bool(named) and job.experiment != named, len(job.overrides)) for job, _ in found]
        primary = min(range(len(found)), key=ranks.__getitem__)
        job, result = found[primary]
        rows.append(ReportRow(result, job, tuple(f for k, f in enumerate(found) if k != primary)))
    rows += [ReportRow(r, None, ()) for r in sweep_results]
    rank = {c.key: k for k, c in enumerate(order)}
    return sorted(rows, key=lambda row: rank.get(row.result.claim.key, len(rank)))


def _link(target: Path, start: Path) -> str:
    return os.path.relpath(target, start)


def claims_rows_markdown(rows: Sequence[ReportRow], out: Path, links: bool = True) -> list[str]:
    cells = []
    for row in rows:
        r = row.result
        if row.job is None:
            job = "across jobs"
        else:
            name = row.job.label
            job = f"[{name}]({_link(row.job.run_dir / 'analysis' / 'report.md', out)})" if links else name
            if r.claim.experiment and row.job.experiment != r.claim.experiment:
                job += f" (not the section's `{r.claim.experiment}`: it did not judge the claim)"
        others = "; ".join(f"{j.label}: {o.verdict}" for j, o in row.others) or "—"
        cells.append([r.claim.text, r.claim.source, r.measured.text, f"**{r.verdict}**", job, others])
    return table_lines(["claim", "source", "measured", "verdict", "job", "other jobs"], cells)


def verdict_counts(rows: Sequence[ReportRow]) -> str:
    return ", ".join(f"{sum(r.result.verdict == v for r in rows)} {v}" for v in VERDICTS)


def analyze_sweep(sweep: Sweep, out: Path, title: str = "Sweep report") -> RunAnalysis:
    """Write metrics.csv; return the analysis that the sweep's sections add figures and data
    files to."""
    analysis = RunAnalysis(f"{title}: sweep `{sweep.root}`")
    rows_data = aggregate(sweep.jobs)
    write_csv(
        out / "metrics.csv",
        ["experiment", "variant", "metric", "mean", "sem", "n_runs"],
        [(a.experiment, a.variant, a.metric, fmt(a.mean), fmt(a.sem), a.n) for a in rows_data],
    )
    analysis.data_files.append("metrics.csv")
    return analysis


def report_lines(
    sweep: Sweep,
    analysis: RunAnalysis,
    rows: Sequence[ReportRow],
    out: Path,
    wall: dict[str, float],
    claims_heading: str | None = "Claims",
) -> list[str]:
    """``analysis/report.md`` of a sweep: timing, claims (none without ``claims_heading``: a sweep
    no reference speaks to), per-experiment tables, every figure."""
    lines = [f"# {analysis.title}", ""]
    lines += [f"- **{k}**: {v:.0f} s" for k, v in wall.items()]
    if claims_heading is None:
        lines.append(f"- **jobs**: {len(sweep.jobs)}")
    else:
        lines += [f"- **jobs**: {len(sweep.jobs)}; **claims**: {len(rows)} ({verdict_counts(rows)})", ""]
        lines += [f"## {claims_heading}", ""] + claims_rows_markdown(rows, out)
    tables = experiment_tables(aggregate(sweep.jobs))
    lines += [
        "",
        "## Experiments",
        "",
        "Mean ± s.e.m. over runs of every `summary.json` metric (`name/level`: greedy "
        "accuracy at that test noise), one column per variant; `metrics.csv` holds them "
        "with the number of runs.",
    ]
    for experiment, table in tables.items():
        lines += ["", f"### {experiment}", ""] + table + [""]
        for job in sweep.of(experiment):
            lines.append(
                f"- `{job.variant}` — [{_link(job.run_dir, sweep.root)}]"
                f"({_link(job.run_dir / 'analysis' / 'report.md', out)})"
                + ("" if job.outcome.figures else f": {job.outcome.status}")
            )
            lines += [
                f"  - [{name}]({_link(job.run_dir / 'analysis' / f'{name}.png', out)}) — {caption}"
                for name, caption in job.outcome.figures
            ]
    if analysis.figures:
        lines += ["", "## Figures across jobs", ""]
        lines += [f"![{caption}]({name}.png)\n\n{caption}\n" for name, (_, caption) in analysis.figures.items()]
    lines += ["", "## Data", ""] + [f"- [{name}]({name})" for name in analysis.data_files]
    return lines
