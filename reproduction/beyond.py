"""Beyond the dissertation (§5.4): what a sweep of online, memory and curiosity runs shows,
reported as findings of ours, never as claims of the dissertation.

Read from what every T-maze job recorded (``records/run.json``, ``summary.json``,
``records/episodes.npz``):

* **memory-length curve**: the online jobs of the regular maze, by memory kind (the predictors'
  ``kind``) and corridor length T_min: solved runs, the correct-goal rate and — to tell a memory
  that forgets from an agent that never finds the junction — the share of the episodes of the
  final window (each run's ``final_window``, 200 by default) that ended in a goal at all, and
  the correct share of those;
* **sample efficiency**: per experiment, every training procedure side by side (the trainer's
  kind, curiosity η, memory): solved runs, environment steps to solve (random collection
  included) per run, median and mean ± s.e.m. over the runs that solved, and how many never did.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ferl import stats
from ferl.analysis.io import fmt, load_npz, table_lines, write_csv
from ferl.analysis.records import recorded_window
from ferl.analysis.sweep import Job


@dataclass(frozen=True)
class Procedure:
    """How a T-maze job trained: the trainer's kind, its curiosity η, the predictors' memories."""

    trainer: str
    curiosity: float
    memory: str

    @property
    def label(self) -> str:
        name = "Algorithm 1/2 (phased)" if self.trainer == "phased" else self.trainer
        return (
            name
            + (f" + curiosity η={self.curiosity:g}" if self.curiosity else "")
            + (f", {self.memory}" if self.memory != "elman" else "")
        )


def procedure(job) -> Procedure:
    m = job.manifest
    memories = sorted({str(p.get("kind")) for p in m.predictors.values()}) or ["none"]
    return Procedure(str(m.trainer.get("kind")), float(m.trainer.get("curiosity") or 0.0), "+".join(memories))


def tmaze_jobs(jobs: Sequence) -> list:
    return [
        j
        for j in jobs
        if j.manifest is not None
        and j.manifest.env_kind == "tmaze"
        and "env_steps_to_solve" in j.summary.get("metrics", {})
    ]


def goal_shares(job) -> tuple[np.ndarray, np.ndarray]:
    """Per run, over the final window (the last ``final_window`` episodes, as the run recorded it):
    the share that ended in a goal, and the correct share of those (NaN where none did)."""
    episodes = load_npz(job.run_dir / "records" / "episodes.npz")
    goal = abs(float(job.manifest.env.get("goal_reward", 5.0)))
    last = slice(-recorded_window(episodes, job.manifest), None)
    reached = np.isclose(np.abs(episodes["terminal_reward"][:, last]), goal)
    correct = episodes["correct_goal"][:, last].astype(bool)
    n = reached.sum(1)
    return n / reached.shape[1], np.where(n > 0, (correct & reached).sum(1) / np.maximum(n, 1), np.nan)


@dataclass(frozen=True)
class CurvePoint:
    memory: str
    corridor: int
    solved: int
    n: int
    correct: tuple[float, float]  # mean, s.e.m. of final_correct_goal_rate
    reached: tuple[float, float]  # of the share of episodes ending in a goal
    correct_if_reached: tuple[float, float]
    job: Job


def memory_curve(jobs: Sequence) -> list[CurvePoint]:
    points = []
    for job in tmaze_jobs(jobs):
        p = procedure(job)
        if p.trainer != "online" or job.manifest.env.get("matching"):
            continue
        metrics = job.summary["metrics"]
        reached, given = goal_shares(job)
        points.append(
            CurvePoint(
                p.memory,
                int(job.manifest.env["corridor_length"]),
                int(np.sum(metrics["solved"])),
                len(metrics["solved"]),
                stats.mean_sem(metrics["final_correct_goal_rate"])[:2],
                stats.mean_sem(reached)[:2],
                stats.mean_sem(given[~np.isnan(given)])[:2],
                job,
            )
        )
    return sorted(points, key=lambda c: (c.memory, c.corridor))


def curve_figure(points: Sequence[CurvePoint]):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
    for memory in sorted({c.memory for c in points}):
        mine = [c for c in points if c.memory == memory]
        x = [c.corridor for c in mine]
        axes[0].plot(x, [c.solved / c.n for c in mine], "o-", label=memory)
        for ax, field in ((axes[1], "correct"), (axes[2], "reached"), (axes[3], "correct_if_reached")):
            mean, sem = np.array([getattr(c, field) for c in mine]).T
            ax.errorbar(x, mean, yerr=np.nan_to_num(sem), marker="o", capsize=3, label=memory)
    titles = (
        "solved runs (share)",
        "correct-goal rate, final window",
        "share of the final window's episodes that reached a goal",
        "correct share of those",
    )
    corridors = sorted({c.corridor for c in points})
    for ax, title in zip(axes, titles):
        ax.set_xscale("log")
        ax.set_xticks(corridors, [str(c) for c in corridors])
        ax.minorticks_off()
        ax.set_xlabel("corridor length T_min")
        ax.set_title(title, fontsize=9)
        ax.set_ylim(-0.05, 1.05)
    axes[0].legend(title="memory", fontsize=8)
    fig.tight_layout()
    return fig


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
    points, rows = memory_curve(jobs), efficiency(jobs)
    beyond = [e for e in rows if e.procedure != Procedure("phased", 0.0, "elman")]
    if not points and not beyond:
        return []
    lines = [
        "",
        "## Beyond the dissertation (findings of ours, §5.4)",
        "",
        "Not claims of the dissertation: what its proposals for improvement (§5.4) measured on "
        "this code. Environment steps include Algorithm 1/2's random collection.",
    ]
    if points:
        figures["memory_length_curve"] = (
            curve_figure(points),
            "Memory-length curve: regular T-maze, online trainer, one line per memory model (mean ± s.e.m. over runs)",
        )
        write_csv(
            out / "memory_length_curve.csv",
            [
                "memory",
                "corridor_length",
                "solved",
                "n_runs",
                "correct_goal_rate",
                "sem",
                "goal_reached_share",
                "sem",
                "correct_if_reached",
                "sem",
            ],
            [
                (c.memory, c.corridor, c.solved, c.n, *map(fmt, (*c.correct, *c.reached, *c.correct_if_reached)))
                for c in points
            ],
        )
        data_files.append("memory_length_curve.csv")
        lines += ["", "### Memory-length curve (regular T-maze, online trainer)", ""]
        lines += table_lines(
            ["memory", "T_min", "solved", "correct-goal rate", "episodes ending in a goal", "correct among those"],
            [
                (c.memory, c.corridor, f"{c.solved}/{c.n}", pm(c.correct), pm(c.reached), pm(c.correct_if_reached))
                for c in points
            ],
        )
        lines += ["", *limits(points)]
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


def pm(pair) -> str:
    mean, sem = pair
    return "n/a" if np.isnan(mean) else f"{mean:.3f} ± {sem:.3f}" if not np.isnan(sem) else f"{mean:.3f}"


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


def limits(points: Sequence[CurvePoint]) -> list[str]:
    """Each memory's longest corridor with ≥ 8/10 of its runs solved, and its first failure."""
    lines = []
    for memory in sorted({c.memory for c in points}):
        mine = [c for c in points if c.memory == memory]
        ok = [c.corridor for c in mine if c.solved >= 0.8 * c.n]
        bad = next((c for c in mine if c.solved < 0.8 * c.n), None)
        text = (
            f"- **{memory}**: solved (≥ 80 % of runs) up to T_min = {max(ok)}"
            if ok
            else f"- **{memory}**: solved (≥ 80 % of runs) at no corridor length"
        )
        if bad is not None:
            text += (
                f"; at T_min = {bad.corridor}: {bad.solved}/{bad.n} solved, "
                f"{pm(bad.reached)} of the last episodes reached a goal, {pm(bad.correct_if_reached)} "
                f"of those the rewarded one"
            )
        lines.append(text)
    return lines
