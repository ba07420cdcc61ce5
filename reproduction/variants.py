"""Agents side by side (§5.4, beyond the dissertation): on every task of a sweep, the
dissertation's agent against each variant of its components, as findings of ours.

A *task* is what a run's environment recorded of itself (``records/run.json`` ``env``): runs whose
environments describe themselves alike faced the same task, whatever experiment or override
produced them, and whatever view of it the agent had (the oracle's true state). An *agent* is
what differs from the dissertation's components: the oracle's view, the actor's kind (the
baselines: ``mlp_q``, ``drqn``, ``tabular_q``, an external ``recurrent_ppo``) and value form
(``actor.q``), a preprocessor other than the RBM, no predictor where the dissertation has one
(``predictor=none``), predictor memories other than Elman, a trainer other than the phased
algorithms, curiosity, an inverse temperature β that stays 0 (a random policy). A task gets a
table (the headline metrics of its summary, mean ± s.e.m. over runs), the finding of which agent
leads it, and one learning-curve figure with every agent's mean ± s.e.m. when it was run by at
least two agents.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ferl import stats
from ferl.analysis import generic
from ferl.analysis.figures import band
from ferl.analysis.io import fmt, table_lines, write_csv
from ferl.analysis.records import Run
from ferl.analysis.sweep import Job, metric_values
from ferl.run.jsonio import strict_dumps

DISSERTATION_AGENT = "dissertation agent"
RANDOM_POLICY = "β=0 (random policy)"  # an agent whose inverse temperature stays 0 (``random_policy``)
# The metrics a task's row shows, in this order, where its summaries have them (docs/records.md).
HEADLINES = (
    "solved",
    "final_correct_goal_rate",
    "final_success_rate",
    "final_return",
    "best_return",
    "final_discounted_return",
    "reward_per_step_last10pct",
    "greedy_accuracy/0.125",
    "env_steps_to_solve",
    "env_steps_total",
    "wall_time_s",
    "agent_steps_per_s",
)
# How agents are ranked on a task: by the first of these their summaries have (higher is better),
# then the next on ties; the finding compares the leader with the runner-up on the first of them
# on which the two differ.
# (An outside task's undiscounted return before the discounted one: its agents may discount differently.)
RANKING = (
    "solved",
    "final_correct_goal_rate",
    "final_success_rate",
    "final_return",
    "final_discounted_return",
    "reward_per_step_last10pct",
)
# What a view of the environment changes of its facts (the oracle's ``true_state``): the task stays.
# what an agent's view of a task is (the oracle's true state; an outside task's encoding and the
# scale of the rewards it learns from), not the task
VIEW_KEYS = (
    "true_state",
    "observation",
    "observation_size",
    "observation_names",
    "encoding",
    "vectorization",
    "reward_scale",
)
ORACLE = "oracle"
# the curve each unit of run draws: the first of these it has (an outside task's undiscounted return)
CURVE = {"episode": ("return", "discounted_return"), "step": ("reward",)}


def agent(manifest) -> str:
    """The components of a run that are not the dissertation's, or DISSERTATION_AGENT."""
    parts = [ORACLE] if manifest.env.get("true_state") else []
    kind = manifest.actor.get("kind", "free_energy")
    if kind != "free_energy":
        parts.append(f"actor={kind}")
    if kind == "recurrent_q":  # ``drqn`` is the GRU core with the linear head
        parts.append(f"actor.head={manifest.actor.get('head')}")
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
    if manifest.trainer.get("td_to_memory"):
        parts.append(f"trainer.td_to_memory={manifest.trainer['td_to_memory']:g}")
    if manifest.trainer.get("curiosity"):
        parts.append(f"curiosity={manifest.trainer['curiosity']:g}")
    if random_policy(manifest):
        parts.append(RANDOM_POLICY)
    return ", ".join(parts) or DISSERTATION_AGENT


def random_policy(manifest) -> bool:
    """β = 0 from the first episode to the last (run.json's ``actor.beta``): the softmax picks
    actions uniformly at random, whatever the agent learnt; a run recorded before ``beta`` was
    is taken as not."""
    beta = manifest.actor.get("beta") or {}
    return beta.get("start") == 0 and beta.get("end") == 0


def task_key(manifest) -> str:
    """The environment's facts but those of the view its agent had of it."""
    return strict_dumps({k: v for k, v in manifest.env.items() if k not in VIEW_KEYS}, sort_keys=True, default=str)


@dataclass
class Entry:
    agent: str
    job: Job

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


def ranking_key(cells: dict) -> tuple:
    return tuple(cells[n][0] if n in cells and not np.isnan(cells[n][0]) else -np.inf for n in RANKING)


def finding(cells: Sequence[tuple[Entry, dict]]) -> str | None:
    """Which agent leads the task (the oracle aside: it sees the true state), by how much on the
    first ranking metric that tells it from the runner-up, with the s.e.m. of the difference; where
    FERL (``ferl_agent``) does not lead, how far behind it is and its rank; and the oracle's
    ceiling."""
    agents = [(e, h) for e, h in cells if not e.agent.startswith(ORACLE)]
    if len(agents) < 2:
        return None
    (best, b), (second, c) = sorted(agents, key=lambda eh: ranking_key(eh[1]), reverse=True)[:2]
    compared = difference(b, c)
    if compared is None:
        return None
    metric, diff, sem = compared
    clear = "" if diff > 2 * sem else " — within two s.e.m.: no clear leader"
    text = (
        f"**Best: {named(best)}**, {metric} {cell_text(metric, b[metric])}, ahead of {named(second)} "
        f"({cell_text(metric, c[metric])}) by {gap_text(diff, sem)} (s.e.m. of the difference){clear}."
    )
    ours = ferl_agent([(e, h) for e, h in agents if metric in h])
    if ours is not None and ours[0] is not best:
        gap, gap_sem = b[metric][0] - ours[1][metric][0], float(np.hypot(b[metric][1], ours[1][metric][1]))
        rank = 1 + sum(ranking_key(h) > ranking_key(ours[1]) for _, h in agents)
        text += (
            f" FERL ({named(ours[0])}): {cell_text(metric, ours[1][metric])}, "
            f"{gap_text(gap, gap_sem)} behind, rank {rank} of {len(agents)}."
        )
    oracle = [(e, h) for e, h in cells if e.agent.startswith(ORACLE) and metric in h]
    if oracle:
        text += f" Ceiling (oracle on the true state): {cell_text(metric, oracle[0][1][metric])}."
    return text


def named(entry: Entry) -> str:
    return f"{entry.agent} ({entry.job.label})"


def difference(b: dict, c: dict) -> tuple[str, float, float] | None:
    """``b`` − ``c`` on the first ranking metric both measured on which they differ (solved 0/10
    against 0/10 says nothing), else the first they share, with the s.e.m. of the difference."""
    shared = [n for n in RANKING if n in b and n in c and not np.isnan(b[n][0]) and not np.isnan(c[n][0])]
    if not shared:
        return None
    # means equal but for float32 rounding (a return of 1 in every episode of every run) are equal
    same = {n: bool(np.isclose(b[n][0], c[n][0], rtol=1e-5, atol=1e-8)) for n in shared}
    metric = next((n for n in shared if not same[n]), shared[0])
    diff = 0.0 if same[metric] else b[metric][0] - c[metric][0]
    return metric, diff, float(np.hypot(b[metric][1], c[metric][1]))


def gap_text(diff: float, sem: float, sign: str = "") -> str:
    """A difference ± its s.e.m., to 3 decimals, or in 2 significant digits where 3 decimals would
    show a difference of 0 that is not (−0.00019 ± 0.00006: 3 s.e.m.); ``sign="+"`` signs it."""
    digits = ".1e" if 0 < max(abs(diff), sem) < 0.0005 else ".3f"
    return f"{diff:{sign}{digits}} ± {sem:{digits}}"


def verdict(diff: float, sem: float, ahead: str, behind: str) -> str:
    """Who leads by a difference, unless it is within two of its s.e.m."""
    if abs(diff) <= 2 * sem:
        return "within two s.e.m.: neither leads"
    return f"{ahead} leads" if diff > 0 else f"{behind} leads"


def head_finding(cells: Sequence[tuple[Entry, dict]]) -> list[str]:
    """Per recurrent core that both ran: does the free-energy head (Q = −F, Eqs. 2.21–2.22, on the core's
    state) beat the linear head (DRQN) of the same recurrent Q-learner, by how much?"""
    cores: dict[str, dict[str, tuple[Entry, dict]]] = {}
    for e, h in cells:
        actor = e.job.manifest.actor
        if "head" in actor:
            cores.setdefault(str(actor.get("memory")), {}).setdefault(actor["head"], (e, h))
    lines = []
    for memory, heads in cores.items():
        if "free_energy" in heads and "linear" in heads:
            (_, f), (_, c) = heads["free_energy"], heads["linear"]
            compared = difference(f, c)
            if compared is not None:
                metric, diff, sem = compared
                lines.append(
                    f"**Free-energy head against linear head** ({memory} core): {metric} "
                    f"{cell_text(metric, f[metric])} against {cell_text(metric, c[metric])}, a difference "
                    f"of {gap_text(diff, sem, sign='+')} (s.e.m. of the difference): "
                    f"{verdict(diff, sem, 'the free-energy head', 'the linear head')}."
                )
    return lines


def free_energy_family(entry: Entry) -> bool:
    """The dissertation's actor, whatever its memory, or a recurrent Q-learner with a free-energy
    value form as its head."""
    actor = entry.job.manifest.actor
    return actor.get("kind", "free_energy") == "free_energy" or actor.get("head", "linear") != "linear"


def family_finding(cells: Sequence[tuple[Entry, dict]]) -> str | None:
    """The best agent of the free-energy family against the best of the others (the oracle aside)."""
    agents = [(e, h) for e, h in cells if not e.agent.startswith(ORACLE)]
    ours = [eh for eh in agents if free_energy_family(eh[0])]
    others = [eh for eh in agents if not free_energy_family(eh[0])]
    if not ours or not others:
        return None
    (best, b), (other, c) = (max(side, key=lambda eh: ranking_key(eh[1])) for side in (ours, others))
    compared = difference(b, c)
    if compared is None:
        return None
    metric, diff, sem = compared
    return (
        f"**Free-energy family:** its best, {named(best)}, {metric} {cell_text(metric, b[metric])}, against "
        f"the best other agent, {named(other)}, {cell_text(metric, c[metric])}: {gap_text(diff, sem, sign='+')} "
        f"(s.e.m. of the difference), {verdict(diff, sem, 'the family', 'the other agent')}."
    )


def ferl_agent(cells: Sequence[tuple[Entry, dict]]):
    """The dissertation's agent, or where no run has its components (an outside task), the best
    ranked run of its architecture: the free-energy actor on predictors' memories."""
    exact = [(e, h) for e, h in cells if e.agent == DISSERTATION_AGENT]
    same_kind = [
        (e, h)
        for e, h in cells
        if e.job.manifest.actor.get("kind", "free_energy") == "free_energy"
        and e.job.manifest.predictors
        and not e.agent.startswith(ORACLE)
    ]
    candidates = exact or same_kind
    return max(candidates, key=lambda eh: ranking_key(eh[1])) if candidates else None


def curve_figure(group: Sequence[Entry]) -> Figure | None:
    """Every agent's main learning curve (mean ± s.e.m. over runs) in one panel."""
    fig = Figure(figsize=(7.5, 4), layout="constrained")
    ax = fig.subplots()
    optimum, drawn = None, 0
    for k, (entry, label) in enumerate(zip(group, legend_labels(group))):
        c = generic.curves(entry.run)
        if c is None:
            continue
        key = next(name for name in CURVE[c.unit] if name in c.series)
        mean, sem = c.mean_sem(key)
        color = f"C{k % 10}"
        band(ax, c.x, mean, sem, None, color)
        ax.lines[-1].set_label(label)
        if len(c.x) == 1:  # a run as long as the window (MiniGrid's 200 episodes): one point, with its s.e.m.
            ax.errorbar(c.x, mean, sem, fmt="o", color=color, capsize=3)
        optimum = c.optima.get(key) if optimum is None else optimum
        ax.set_xlabel(c.unit + "s")
        ax.set_ylabel(f"{c.labels[key]} ({c.window}-{c.unit} moving average)")
        drawn += 1
    if not drawn:
        return None
    if optimum is not None:
        ax.axhline(optimum, color="k", ls=":", label=f"optimum {optimum:.5g}")
    fig.legend(fontsize="x-small", loc="outside lower center", ncols=2)
    ax.set_title(title(group), fontsize="medium")
    return fig


def legend_labels(group: Sequence[Entry]) -> list[str]:
    """Each run's agent, with the overrides that tell it from the other runs of the same agent
    (the matching maze's FERL under Algorithms 1 and 2)."""
    labels = []
    for entry in group:
        twins = [e for e in group if e.agent == entry.agent]
        shared = set.intersection(*(set(e.job.overrides) for e in twins))
        labels.append(" ".join([entry.agent, *(o for o in entry.job.overrides if o not in shared)]))
    return labels


def report(jobs: Sequence, out: Path, figures: dict, data_files: list) -> list[str]:
    """The "Agents side by side" section of a sweep report (empty without such tasks); adds its
    figures and CSV."""
    groups = tasks(jobs)
    if not groups:
        return []
    lines = [
        "",
        "## Agents side by side (findings of ours, §5.4)",
        "",
        "Per task (runs whose environments recorded the same settings), the dissertation's agent "
        "and every variant of its components or baseline agent that the sweep ran: mean ± s.e.m. over "
        "runs (`env_steps_to_solve`: over the runs that solved).",
    ]
    rows = []
    for i, group in enumerate(groups):
        cells = [(e, headline(e)) for e in group]
        names = [n for n in HEADLINES if any(n in h for _, h in cells)]
        lines += ["", f"### {title(group)}", ""]
        lines += table_lines(
            ["agent", "run as", "runs", *names],
            [
                (e.agent, e.job.label, max((h[n][2] for n in h), default=0), *(cell_text(n, h.get(n)) for n in names))
                for e, h in cells
            ],
        )
        for line in [finding(cells), *head_finding(cells), family_finding(cells)]:
            if line:
                lines += ["", line]
        rows += [
            (title(group), e.agent, e.job.variant, n, *map(fmt, h[n][:2]), h[n][2])
            for e, h in cells
            for n in names
            if n in h
        ]
        fig = curve_figure(group)
        if fig is not None:
            name = f"agents_task{i + 1}"
            figures[name] = (fig, f"Learning curves of every agent, {title(group)}")
            lines += ["", f"![{name}]({name}.png)"]
    write_csv(out / "agents_side_by_side.csv", ["task", "agent", "overrides", "metric", "mean", "sem", "n"], rows)
    data_files.append("agents_side_by_side.csv")
    return lines
