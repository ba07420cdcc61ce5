"""The memory curves of the T-mazes (beyond the dissertation, §5.4; docs/beyond.md, "Memory
curves"): how long a corridor each memory bridges, one line per memory model (and directed
exploration), read from what every T-maze job whose memory learns as it acts recorded (the online
trainer's predictors, or an actor with a memory of its own: the recurrent Q-learner) —
``records/run.json`` (the environment's ``passive``, ``corridor_length``, ``matching`` and
``goal_reward``, the predictors' ``kind`` or the actor's ``kind``, ``memory`` and ``head``, the
``exploration``'s kind, none where the run recorded none), ``summary.json`` (per run
``solved`` and ``final_correct_goal_rate``) and ``records/episodes.npz`` — never from experiment
or directory names:

* **passive T-maze** (``env.passive``; Ni et al. 2023, "When do transformers shine in RL?
  Decoupling memory from credit assignment", NeurIPS; ``ferl/envs/passive.py``): x is their memory
  length L = ``env.corridor_length``;
* **active T-maze** (the dissertation's regular maze, §4.3.1): x is T_min = ``env.corridor_length``,
  a line per memory and exploration method.

Each point: solved runs (share; ferl's ``solved`` on the final window), the success rate (the
final window's correct-goal rate: Ni et al.'s success, the episode ends in the cued goal) and, to
tell a memory that forgets from an agent that never gets to the choice, the share of the final
window's episodes (each run's recorded ``final_window``) that got to it, and the correct share of
those. *Got to the choice* is, in the active maze, ended in a goal at all (either goal ends the
episode with ±``goal_reward``); in the passive maze, reached the junction on schedule: its wrong
goal and a last step that stays at the junction both pay 0, so its records cannot tell a goal
entry, but every step behind the shortest path pays −goal_reward/L and leaves the goals out of
reach in the L + 1 actions, so an episode's discounted return is ≥ 0 exactly when its walk was on
schedule.

A line's **limit** is its longest corridor solved in ≥ 80 % of its runs (8/10; ``SOLVED_SHARE``).
At the shortest longer corridor that failed, the limit is called *exploration* when fewer than
half of the final window's episodes got to the choice (``REACHED_SHARE``), else *memory* (the
agent gets there and still chooses wrong). A corridor whose optimal discounted return is negative
(summary.json's ``optimal``: the active maze's step costs outweigh its discounted goal at long
corridors, e.g. T_min = 50 for γ 0.95–0.99) cannot be solved at all (``solved`` asks for ≥ 0.95 ×
the optimum, which lies above it), so it sets no limit and the report says so.
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

SOLVED_SHARE = 0.8  # a corridor is within a line's limit when ≥ 80 % of its runs were solved (8/10)
REACHED_SHARE = 0.5  # below it, a failure is the walk's (exploration), not the memory's

# Ni et al. (2023) give their passive T-maze success per memory length only in figures (their
# Figs. 3 and 6, as their repository's readme names them; the logs behind them sit on a Google
# Drive, not in the repository): the numbers their readme and budget.py state are the lengths they
# ran and their budgets, not success rates, so no published point is drawn.
NI_ET_AL = (
    "Ni et al. (2023, NeurIPS; github.com/twni2016/Memory-RL) ran the passive T-maze at memory lengths "
    "L = 50 … 1 500 (GPT-2 and LSTM, DQN; budgets in their budget.py) and publish its success rates only "
    "in figures (their Figs. 3 and 6): no per-length success numbers are stated that could be drawn here"
)


@dataclass(frozen=True)
class Curve:
    """One of the two curves: its figure / CSV name, caption and what "got to the choice" means."""

    name: str
    passive: bool
    title: str
    x_label: str
    reached_column: str
    reached_words: str


PASSIVE = Curve(
    "passive_tmaze_curve",
    True,
    "Memory-length curve: passive T-maze (Ni et al. 2023), one line per memory model "
    f"(mean ± s.e.m. over runs). {NI_ET_AL}",
    "memory length L (env.corridor_length)",
    "junction_on_schedule_share",
    "reached the junction on schedule",
)
ACTIVE = Curve(
    "memory_length_curve",
    False,
    "Memory-length curve: regular (active) T-maze, one line per memory model and "
    "exploration method (dashed: directed exploration; mean ± s.e.m. over runs)",
    "corridor length T_min (env.corridor_length)",
    "goal_reached_share",
    "reached a goal",
)


@dataclass(frozen=True)
class CurvePoint:
    memory: str
    exploration: str
    corridor: int
    solved: int
    n: int
    correct: tuple[float, float]  # mean, s.e.m. over runs of final_correct_goal_rate
    reached: tuple[float, float]  # of the share of the final window that got to the choice
    correct_if_reached: tuple[float, float]
    job: Job
    optimum: float | None = None  # the optimal discounted return the runs' ``solved`` compares with

    @property
    def line(self) -> tuple[str, str]:
        return self.memory, self.exploration

    @property
    def solvable(self) -> bool:
        """Whether ``solved`` can be met: return ≥ 0.95 × optimum needs an optimum ≥ 0."""
        return self.optimum is None or self.optimum >= 0

    @property
    def ok(self) -> bool:
        return self.solved >= SOLVED_SHARE * self.n


def own_memory(job: Job) -> str | None:
    """The memory of an actor that learns its own (``actor=recurrent_q``, ``drqn``: run.json's actor
    ``memory``) where no predictor gives one: ``drqn``, ``recurrent_q lstm``, ``recurrent_q gru
    free_energy`` (its head unless linear); None otherwise."""
    actor = job.manifest.actor
    if job.manifest.predictors or "memory" not in actor:
        return None
    if actor.get("kind") == "drqn":
        return "drqn"
    head = actor.get("head", "linear")
    return " ".join([str(actor.get("kind")), str(actor["memory"]), *([str(head)] if head != "linear" else [])])


def memory_kind(job: Job) -> str:
    """The line a job is on: the predictors' memory kinds, joined (``lstm``; ``elman+lstm`` for
    mixed predictors), or the actor's own memory (``own_memory``)."""
    kinds = "+".join(sorted({str(p.get("kind")) for p in job.manifest.predictors.values()}))
    return kinds or own_memory(job) or "none"


def curve_jobs(jobs: Sequence[Job], curve: Curve) -> list[Job]:
    """The non-matching T-maze jobs of ``curve``'s maze that recorded the final metrics and whose
    memory learns while the agent acts: the online trainer's predictors, or an actor's own."""
    return [
        j
        for j in jobs
        if j.manifest is not None
        and j.manifest.env_kind == "tmaze"
        and (j.manifest.trainer.get("kind") == "online" or own_memory(j) is not None)
        and not j.manifest.env.get("matching")
        and bool(j.manifest.env.get("passive")) == curve.passive
        and "final_correct_goal_rate" in j.summary.get("metrics", {})
    ]


def got_to_choice(episodes: dict, env: dict) -> np.ndarray:
    """Per episode (R, E): it got to the choice (module doc). ``episodes``: the records'
    ``discounted_return`` and ``terminal_reward`` (R, E); ``env``: run.json's environment facts."""
    if env.get("passive"):
        return episodes["discounted_return"] >= 0.0  # no penalty paid: on schedule at the junction
    goal = abs(float(env.get("goal_reward", 5.0)))
    return np.isclose(np.abs(episodes["terminal_reward"]), goal)  # ended in either goal


def reached_shares(job: Job) -> tuple[np.ndarray, np.ndarray]:
    """Per run (R,), over its final window: the share of the episodes that got to the choice,
    and the correct share of those (NaN where none did)."""
    episodes = load_npz(job.run_dir / "records" / "episodes.npz")
    last = slice(-recorded_window(episodes, job.manifest), None)
    reached = got_to_choice(
        {k: episodes[k][:, last] for k in ("discounted_return", "terminal_reward")}, job.manifest.env
    )
    correct = episodes["correct_goal"][:, last].astype(bool)
    n = reached.sum(1)
    return n / reached.shape[1], np.where(n > 0, (correct & reached).sum(1) / np.maximum(n, 1), np.nan)


def curve_points(jobs: Sequence[Job], curve: Curve) -> list[CurvePoint]:
    points = []
    for job in curve_jobs(jobs, curve):
        metrics = job.summary["metrics"]
        reached, given = reached_shares(job)
        points.append(
            CurvePoint(
                memory_kind(job),
                str(job.manifest.exploration.get("kind", "none")),
                int(job.manifest.env["corridor_length"]),
                int(np.sum(metrics["solved"])),
                len(metrics["solved"]),
                stats.mean_sem(metrics["final_correct_goal_rate"])[:2],
                stats.mean_sem(reached)[:2],
                stats.mean_sem(given[~np.isnan(given)])[:2],
                job,
                job.summary.get("optimal", {}).get("discounted_return"),
            )
        )
    return sorted(points, key=lambda c: (c.memory, c.exploration != "none", c.exploration, c.corridor))


def lines_of(points: Sequence[CurvePoint]) -> dict[tuple[str, str], list[CurvePoint]]:
    """(memory, exploration) → its points, in corridor order."""
    out: dict[tuple[str, str], list[CurvePoint]] = {}
    for c in points:
        out.setdefault(c.line, []).append(c)
    return out


def label(line: tuple[str, str]) -> str:
    memory, exploration = line
    return memory if exploration == "none" else f"{memory} + {exploration}"


def curve_figure(points: Sequence[CurvePoint], curve: Curve):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
    for line, mine in lines_of(points).items():
        x, style = [c.corridor for c in mine], "--" if line[1] != "none" else "-"
        axes[0].plot(x, [c.solved / c.n for c in mine], "o" + style, label=label(line))
        for ax, field in ((axes[1], "correct"), (axes[2], "reached"), (axes[3], "correct_if_reached")):
            mean, sem = np.array([getattr(c, field) for c in mine]).T
            ax.errorbar(x, mean, yerr=np.nan_to_num(sem), marker="o", ls=style, capsize=3, label=label(line))
    titles = (
        "solved runs (share)",
        "success rate (correct-goal rate), final window",
        f"share of the final window's episodes\nthat {curve.reached_words}",
        "correct share of those",
    )
    corridors = sorted({c.corridor for c in points})
    for ax, title in zip(axes, titles):
        ax.set_xscale("log")
        ax.set_xticks(corridors, [str(c) for c in corridors])
        ax.minorticks_off()
        ax.set_xlabel(curve.x_label, fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.set_ylim(-0.05, 1.05)
    axes[0].legend(title="memory", fontsize=8)
    fig.tight_layout()
    return fig


@dataclass(frozen=True)
class Limit:
    """A line's limit: its longest corridor solved in ≥ 80 % of runs (None: none), the shortest
    longer corridor that failed (None: none measured) and what failed there."""

    longest: int | None
    failed: CurvePoint | None

    @property
    def cause(self) -> str | None:
        if self.failed is None:
            return None
        return "exploration" if self.failed.reached[0] < REACHED_SHARE else "memory"


def limit(mine: Sequence[CurvePoint]) -> Limit:
    ok = [c.corridor for c in mine if c.ok]
    longest = max(ok) if ok else None
    failed = next((c for c in mine if not c.ok and c.solvable and (longest is None or c.corridor > longest)), None)
    return Limit(longest, failed)


def limit_lines(points: Sequence[CurvePoint], curve: Curve) -> list[str]:
    """Each line's limit in words and numbers, and whether memory or exploration sets it."""
    lines = []
    for line, mine in lines_of(points).items():
        lim, runs = limit(mine), " / ".join(f"{c.solved}/{c.n}" for c in mine)
        text = f"- **{label(line)}**: limit " + (
            f"{lim.longest} (the longest corridor solved in ≥ {SOLVED_SHARE:.0%} of runs)"
            if lim.longest is not None
            else f"none (no corridor solved in ≥ {SOLVED_SHARE:.0%} of runs)"
        )
        text += f"; solved runs at {' / '.join(str(c.corridor) for c in mine)}: {runs}"
        bad = lim.failed
        if bad is None:
            text += "; no longer corridor measured failed"
        else:
            text += (
                f". At {bad.corridor}: {pm(bad.reached)} of the final window's episodes {curve.reached_words}, "
                f"{pm(bad.correct_if_reached)} of those chose the cued goal: limited by **{lim.cause}**"
            )
        out_of_reach = [c for c in mine if not c.solvable]
        if out_of_reach:
            text += (
                f". `solved` cannot be met at {' / '.join(str(c.corridor) for c in out_of_reach)}: the optimal "
                f"discounted return is negative there ({' / '.join(fmt(c.optimum) for c in out_of_reach)}), and "
                "0.95 × it lies above it"
            )
        lines.append(text)
    return lines


def section(points: Sequence[CurvePoint], curve: Curve, out: Path, figures: dict, data_files: list) -> list[str]:
    """The curve's figure, CSV, table and limits (nothing without points)."""
    if not points:
        return []
    figures[curve.name] = (curve_figure(points, curve), curve.title)
    header = ["memory", "exploration", "corridor_length", "solved", "n_runs", "correct_goal_rate", "sem"]
    write_csv(
        out / f"{curve.name}.csv",
        [*header, curve.reached_column, "sem", "correct_if_reached", "sem"],
        [
            (
                c.memory,
                c.exploration,
                c.corridor,
                c.solved,
                c.n,
                *map(fmt, (*c.correct, *c.reached, *c.correct_if_reached)),
            )
            for c in points
        ],
    )
    data_files.append(f"{curve.name}.csv")
    maze = "passive T-maze (Ni et al. 2023)" if curve.passive else "regular T-maze"
    lines = ["", f"### Memory-length curve, {maze}", ""]
    lines += table_lines(
        [
            "memory",
            "exploration",
            "corridor",
            "solved",
            "success rate",
            f"episodes that {curve.reached_words}",
            "correct among those",
        ],
        [
            (
                c.memory,
                c.exploration,
                c.corridor,
                f"{c.solved}/{c.n}" + ("" if c.solvable else " (cannot be met)"),
                pm(c.correct),
                pm(c.reached),
                pm(c.correct_if_reached),
            )
            for c in points
        ],
    )
    lines += ["", *limit_lines(points, curve)]
    return lines + (["", NI_ET_AL + "."] if curve.passive else [])


def report(jobs: Sequence[Job], out: Path, figures: dict, data_files: list) -> list[str]:
    """Both curves' sections: the passive maze's, then the active maze's."""
    return [
        line
        for curve in (PASSIVE, ACTIVE)
        for line in section(curve_points(jobs, curve), curve, out, figures, data_files)
    ]


def pm(pair) -> str:
    mean, sem = pair
    return "n/a" if np.isnan(mean) else f"{mean:.3f} ± {sem:.3f}" if not np.isnan(sem) else f"{mean:.3f}"
