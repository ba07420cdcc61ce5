"""Beyond the dissertation (§5.4): what a sweep of online, memory and curiosity runs shows,
reported as findings of ours, never as claims of the dissertation.

Read from what every T-maze job recorded (``records/run.json``, ``summary.json``,
``records/episodes.npz``):

* **memory-length curves** (``reproduction.curves``): the online jobs of the passive and the
  regular (active) maze, by memory kind, exploration method and corridor length: solved runs, the
  success rate and the share of the final window's episodes that got to the choice;
* **sample efficiency**: per experiment, every training procedure side by side (the trainer's
  kind, curiosity η, memory, exploration method): solved runs, environment steps to solve (random collection
  included) per run, median and mean ± s.e.m. over the runs that solved, and how many never did.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ferl import stats
from ferl.analysis.io import fmt, table_lines, write_csv
from ferl.analysis.sweep import Job
from reproduction import curves
from reproduction.curves import pm


@dataclass(frozen=True)
class Procedure:
    """How a T-maze job trained: the trainer's kind, its curiosity η, the predictors' memories and
    the directed exploration method (``none``: the actor's own Boltzmann choice)."""

    trainer: str
    curiosity: float
    memory: str
    exploration: str = "none"

    @property
    def label(self) -> str:
        name = "Algorithm 1/2 (phased)" if self.trainer == "phased" else self.trainer
        return (
            name
            + (f" + curiosity η={self.curiosity:g}" if self.curiosity else "")
            + (f", {self.memory}" if self.memory != "elman" else "")
            + (f" + {self.exploration}" if self.exploration != "none" else "")
        )


def procedure(job) -> Procedure:
    m = job.manifest
    return Procedure(
        str(m.trainer.get("kind")),
        float(m.trainer.get("curiosity") or 0.0),
        curves.memory_kind(job),
        str(m.exploration.get("kind", "none")),
    )


def tmaze_jobs(jobs: Sequence) -> list:
    return [
        j
        for j in jobs
        if j.manifest is not None
        and j.manifest.env_kind == "tmaze"
        and "env_steps_to_solve" in j.summary.get("metrics", {})
    ]


@dataclass(frozen=True)
class Efficiency:
    experiment: str
    procedure: Procedure
    solved: int
    n: int
    steps: list  # env_steps_to_solve per run, None where never
    job: Job

    @property
    def reached(self) -> list[int]:
        return [s for s in self.steps if s is not None]

    @property
    def median(self) -> float:
        return float(np.median(self.reached)) if self.reached else float("nan")


def efficiency(jobs: Sequence) -> list[Efficiency]:
    out = []
    for job in tmaze_jobs(jobs):
        m = job.summary["metrics"]
        out.append(
            Efficiency(
                job.experiment,
                procedure(job),
                int(np.sum(m["solved"])),
                len(m["solved"]),
                list(m["env_steps_to_solve"]),
                job,
            )
        )
    return sorted(out, key=lambda e: (e.experiment, e.procedure.trainer != "phased", e.procedure.curiosity))


def report(jobs: Sequence, out: Path, figures: dict, data_files: list) -> list[str]:
    """The "Beyond the dissertation" section of a sweep report (empty without such jobs); adds
    its figure and CSVs."""
    rows = efficiency(jobs)
    beyond = [e for e in rows if e.procedure != Procedure("phased", 0.0, "elman")]
    curve_lines = curves.report(jobs, out, figures, data_files)
    if not curve_lines and not beyond:
        return []
    lines = [
        "",
        "## Beyond the dissertation (findings of ours, §5.4)",
        "",
        "Not claims of the dissertation: what its proposals for improvement (§5.4) measured on "
        "this code. Environment steps include Algorithm 1/2's random collection.",
        *curve_lines,
    ]
    if rows:
        write_csv(
            out / "sample_efficiency.csv",
            ["experiment", "procedure", "run", "solved", "env_steps_to_solve"],
            [
                (e.experiment, e.procedure.label, r, int(s is not None), "" if s is None else s)
                for e in rows
                for r, s in enumerate(e.steps)
            ],
        )
        data_files.append("sample_efficiency.csv")
        lines += ["", "### Sample efficiency: environment steps until solved", ""]
        lines += table_lines(
            [
                "experiment",
                "procedure",
                "overrides",
                "solved",
                "median steps to solve",
                "mean ± s.e.m.",
                "never solved",
                "vs phased (median)",
                "per run",
            ],
            [
                (
                    e.experiment,
                    e.procedure.label,
                    e.job.variant,
                    f"{e.solved}/{e.n}",
                    fmt(e.median),
                    pm(stats.mean_sem(e.reached)[:2]),
                    len(e.steps) - len(e.reached),
                    versus(e, rows),
                    " ".join("–" if s is None else str(s) for s in e.steps),
                )
                for e in rows
            ],
        )
    return lines


def versus(e: Efficiency, rows: Sequence[Efficiency]) -> str:
    """This procedure's median steps to solve over the phased algorithm's, same experiment."""
    base = next(
        (
            b
            for b in rows
            if b.experiment == e.experiment
            and b.procedure.trainer == "phased"
            and b.procedure.memory == e.procedure.memory
        ),
        None,
    )
    if base is None or base is e or not base.reached or not e.reached:
        return ""
    return f"{e.median / base.median:.0%}"
