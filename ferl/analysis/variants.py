"""Agents side by side (§5.4, beyond the dissertation): on every task of a sweep, the
dissertation's agent against each variant of its components, as findings of ours.

A *task* is what a run's environment recorded of itself (`records/run.json` `env`): runs whose
environments describe themselves alike faced the same task, whatever experiment or override
produced them. An *agent* is what differs from the dissertation's components: the actor's value
form (`actor.q`), a preprocessor other than the RBM, no predictor where the dissertation has one
(`predictor=none`), predictor memories other than Elman, a trainer other than the phased algorithms, curiosity. A task gets a
table (the headline metrics of its summary, mean ± s.e.m. over runs) and one learning-curve
figure with every agent's mean ± s.e.m. when it was run by at least two agents.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.figure import Figure

from ferl import stats
from ferl.analysis import generic
from ferl.analysis.figures import band
from ferl.analysis.io import fmt, table_lines, write_csv
from ferl.analysis.records import Run
from ferl.analysis.sweep import metric_values

DISSERTATION_AGENT = "dissertation agent"
# The metrics a task's row shows, in this order, where its summaries have them (CONTRACT §2).
HEADLINES = ("solved", "final_correct_goal_rate", "final_discounted_return", "reward_per_step_last10pct",
             "greedy_accuracy/0.125", "env_steps_total", "agent_steps_per_s")
CURVE = {"episode": "discounted_return", "step": "reward"}  # the curve each unit of run draws


def agent(manifest) -> str:
    """The components of a run that are not the dissertation's, or DISSERTATION_AGENT."""
    parts = []
    q = manifest.actor.get("q", "free_energy")
    if q != "free_energy":
        parts.append(f"actor.q={q}")
    if manifest.preprocessor is not None and manifest.preprocessor.get("kind") != "rbm":
        parts.append(f"preprocessor={manifest.preprocessor.get('kind')}")
    memories = sorted({str(p.get("kind")) for p in manifest.predictors.values()} - {"elman"})
    if manifest.episodic and not manifest.predictors:  # the dissertation's episodic agents all remember
        parts.append("predictor=none")
    if memories:
        parts.append(f"memory={'+'.join(memories)}")
    if manifest.episodic and manifest.trainer.get("kind") != "phased":
        parts.append(f"trainer={manifest.trainer.get('kind')}")
    if manifest.trainer.get("curiosity"):
        parts.append(f"curiosity={manifest.trainer['curiosity']:g}")
    return ", ".join(parts) or DISSERTATION_AGENT


def task_key(manifest) -> str:
    return json.dumps(manifest.env, sort_keys=True, default=str)


@dataclass
class Entry:
    agent: str
    job: object   # ferl.analysis.sweep.Job

    @property
    def run(self) -> Run:
        return Run.load(self.job.run_dir, self.job.manifest)


def tasks(jobs: Sequence) -> list[list[Entry]]:
    """Jobs grouped by task, each group in job order, the dissertation's agent first; only
    tasks that more than one agent ran."""
    groups: dict[str, list[Entry]] = {}
    for job in jobs:
        if job.manifest is not None:
            groups.setdefault(task_key(job.manifest), []).append(Entry(agent(job.manifest), job))
    ranked = [sorted(g, key=lambda e: e.agent != DISSERTATION_AGENT) for g in groups.values()]
    return [g for g in ranked if len({(e.agent, e.job.variant) for e in g}) > 1]


def title(group: Sequence[Entry]) -> str:
    experiments = sorted({e.job.experiment for e in group})
    return f"{group[0].job.manifest.env_kind}: " + ", ".join(experiments)


def headline(entry: Entry) -> dict[str, tuple[float, float, int]]:
    values = metric_values(entry.job.summary)
    return {name: stats.mean_sem(values[name]) for name in HEADLINES if name in values}


def cell_text(name: str, value) -> str:
    """``solved`` as runs of runs, other metrics as mean ± s.e.m. (large ones without decimals)."""
    if value is None:
        return ""
    mean, sem, n = value
    if np.isnan(mean):
        return "n/a"
    if name == "solved":
        return f"{round(mean * n)}/{n}"
    digits = 0 if abs(mean) >= 1000 else 3
    return f"{mean:,.{digits}f} ± {sem:,.{digits}f}" if n > 1 else f"{mean:,.{digits}f}"


def curve_figure(group: Sequence[Entry]) -> Figure | None:
    """Every agent's main learning curve (mean ± s.e.m. over runs) in one panel."""
    fig = Figure(figsize=(7.5, 4), layout="constrained")
    ax = fig.subplots()
    optimum, drawn = None, 0
    for k, entry in enumerate(group):
        c = generic.curves(entry.run)
        if c is None:
            continue
        key = CURVE[c.unit]
        mean, sem = c.mean_sem(key)
        color = f"C{k % 10}"
        band(ax, c.x, mean, sem, None, color)
        ax.lines[-1].set_label(" ".join([entry.agent, *(o for o in entry.job.overrides if o not in entry.agent)]))
        optimum = c.optima.get(key) if optimum is None else optimum
        ax.set_xlabel(c.unit + "s")
        ax.set_ylabel(f"{c.labels[key]} ({c.window}-{c.unit} moving average)")
        drawn += 1
    if not drawn:
        return None
    if optimum is not None:
        ax.axhline(optimum, color="k", ls=":", label=f"optimum {optimum:.5g}")
    ax.legend(fontsize="x-small", loc="best")
    ax.set_title(title(group), fontsize="medium")
    return fig


def report(jobs: Sequence, out: Path, figures: dict, data_files: list) -> list[str]:
    """The "Agents side by side" section of a sweep report (empty without such tasks); adds its
    figures and CSV."""
    groups = tasks(jobs)
    if not groups:
        return []
    lines = ["", "## Agents side by side (findings of ours, §5.4)", "",
             "Per task (runs whose environments recorded the same settings), the dissertation's agent "
             "and every variant of its components that the sweep ran: mean ± s.e.m. over runs."]
    rows = []
    for i, group in enumerate(groups):
        cells = [(e, headline(e)) for e in group]
        names = [n for n in HEADLINES if any(n in h for _, h in cells)]
        lines += ["", f"### {title(group)}", ""]
        lines += table_lines(["agent", "run as", "runs", *names],
                             [(e.agent, e.job.label, max((h[n][2] for n in h), default=0),
                               *(cell_text(n, h.get(n)) for n in names)) for e, h in cells])
        rows += [(title(group), e.agent, e.job.variant, n, *map(fmt, h[n][:2]), h[n][2])
                 for e, h in cells for n in names if n in h]
        fig = curve_figure(group)
        if fig is not None:
            name = f"agents_task{i + 1}"
            figures[name] = (fig, f"Learning curves of every agent, {title(group)}")
            lines += ["", f"![{name}]({name}.png)"]
    write_csv(out / "agents_side_by_side.csv", ["task", "agent", "overrides", "metric", "mean", "sem", "n"], rows)
    data_files.append("agents_side_by_side.csv")
    return lines

