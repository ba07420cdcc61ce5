"""The analysis every run gets, whatever trained it: learning curves, TD errors, prediction
errors and the summary table.

Episodic runs (``env.episodic`` in run.json) are read from ``episodes.npz``: the moving average,
over the run's final window of episodes (``Run.final_window``), of the discounted return, the
steps, the terminal reward and each boolean outcome the environment declares (``env.outcomes``,
e.g. the T-maze's ``correct_goal``), and of the episode-mean |δ|, with the per-step δ of the sampled episodes. Continuing runs are read from ``steps.npz``: the moving
average of the reward and of |δ| per step. Every predictor named in run.json gets its error
heatmaps from ``predictor.npz``; an online run (``online.npz``) its predictors' held-out error, β and
curiosity per episode. The summary table is mean ± s.d. over runs of every
``summary.json`` metric (``ferl.stats``). Where a registered chapter applies
(``ferl.analysis.dispatch``), its ``Numbering`` puts its publication's figure numbers into the
captions.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ferl import stats
from ferl.analysis import figures as figs
from ferl.analysis.claims import Numbering, caption
from ferl.analysis.coding import moving_average, nanmean
from ferl.analysis.io import fmt, table_lines, write_csv, write_numbers
from ferl.analysis.records import JOINT, OBSERVATION, REWARD, PredictorErrors, Run
from ferl.analysis.report import RunAnalysis

STEP_WINDOW = 100  # moving-average window of Fig. 3.4 (steps)
MAX_CURVE_POINTS = 2000  # a continuing run's curves are drawn at most this often: more adds nothing
FIGURE_RUN = 0  # the dissertation's per-run panels show its 1st run
ERROR_UNITS: dict[str | None, str] = {  # predictor role → its recorded error measure (Eq. 4.8; Figs. 5.2/5.17 (a), (b))
    JOINT: "Eq. 4.8 weighted absolute error\nρ_y Σ|y − ŷ| + ρ_r Σ|r − r̂|",
    OBSERVATION: "absolute error Σ|y − ŷ|\n(processed observations)",
    REWARD: "squared error (r − r̂)²\n(scalar reward)",
}
EPISODE_LABELS = {
    "discounted_return": "discounted return",
    "steps": "steps per episode",
    "terminal_reward": "terminal reward",
    "td_abs_mean": "mean |δ| per episode",
    "return": "return (undiscounted)",
}


@dataclass(frozen=True)
class Curves:
    """Moving averages of a run's per-episode or per-step records."""

    unit: str  # "episode" or "step"
    window: int
    length: int  # episodes or steps per run
    x: np.ndarray  # (n,) 1-based last episode/step of each window
    series: dict[str, np.ndarray]  # key → (R, n) moving average of every run
    labels: dict[str, str]
    optima: dict[str, float | None]
    td_key: str  # the series of |δ|

    @property
    def n_runs(self) -> int:
        return next(iter(self.series.values())).shape[0]

    def mean_sem(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        """Mean and s.e.m. over runs (``ferl.stats.sem``) of one series."""
        return self.series[key].mean(axis=0), stats.sem(self.series[key])


def _moving(values: np.ndarray, window: int, max_points: int | None) -> tuple[np.ndarray, np.ndarray]:
    """(x, (R, n) moving averages), every point or, with ``max_points``, at most about that many."""
    ma = moving_average(values, window)
    stride = 1 if max_points is None else max(1, ma.shape[1] // max_points)
    keep = np.arange(0, ma.shape[1], stride)
    return keep + window, ma[:, keep]


def curves(run: Run) -> Curves | None:
    """The run's learning curves; None for a run with neither record."""
    episodes, steps = run.records("episodes"), run.records("steps")
    if run.manifest.episodic and episodes is not None:
        recorded = [k for k in run.manifest.env.get("outcomes", []) if k in episodes]
        rates = [k for k in recorded if episodes[k].dtype == bool]
        averages = [k for k in recorded if episodes[k].dtype.kind == "f"]  # e.g. the undiscounted return
        keys = [k for k in ("discounted_return", "steps", "terminal_reward") if k in episodes]
        keys += averages + rates + ["td_abs_mean"]
        window = min(run.final_window, episodes["td_abs_mean"].shape[1])  # 200: Figs. 4.6–4.8, 4.11–4.13
        series: dict[str, np.ndarray] = {}
        for key in keys:
            x, series[key] = _moving(episodes[key].astype(np.float64), window, None)
        optima = {
            "discounted_return": episodes.get("optimal_return"),
            "steps": episodes.get("optimal_steps"),
            "terminal_reward": run.manifest.env.get("goal_reward"),
            "return": run.summary.get("optimal", {}).get("return"),
        }
        return Curves(
            "episode",
            window,
            episodes["td_abs_mean"].shape[1],
            x,
            series,
            {k: EPISODE_LABELS.get(k, f"{k.replace('_', ' ')} rate") for k in keys},
            {k: None if optima.get(k) is None or np.isnan(float(optima[k])) else float(optima[k]) for k in keys},
            "td_abs_mean",
        )
    if steps is None:
        return None
    window = min(STEP_WINDOW, steps["rewards"].shape[1])
    x, reward = _moving(steps["rewards"], window, MAX_CURVE_POINTS)
    _, td = _moving(np.abs(steps["td_errors"].astype(np.float64)), window, MAX_CURVE_POINTS)
    optimum = run.summary.get("optimal", {}).get("reward_per_step")
    return Curves(
        "step",
        window,
        steps["rewards"].shape[1],
        x,
        {"reward": reward, "td_abs": td},
        {"reward": "reward per step", "td_abs": "|δ| per step"},
        {"reward": None if optimum is None else float(optimum), "td_abs": None},
        "td_abs",
    )


# ---- data files ------------------------------------------------------------------


def _curves_table(c: Curves, out: Path) -> str:
    first = next(iter(c.series))
    columns = [column for key in c.series for column in c.mean_sem(key)]
    columns += list(c.series[first])
    write_numbers(
        out / "learning_curves.csv",
        [
            c.unit,
            *(f"{k}_ma{c.window}_{s}" for k in c.series for s in ("mean", "sem")),
            *(f"{first}_ma{c.window}_run_{r}" for r in range(c.n_runs)),
        ],
        np.asarray(c.x).astype(np.int64),
        np.stack(columns, axis=1),
    )
    return "learning_curves.csv"


def _prediction_table(p: PredictorErrors, out: Path) -> str:
    rows = []
    for split in ("train", "test"):
        err = p.errors(split)
        first, last = nanmean(err[:, 0], axis=0), nanmean(err[:, -1], axis=0)
        sem = stats.sem(err[:, -1])
        for k, T in enumerate(p.lengths):
            rows += [
                (split, int(T), t, int(T <= p.trained_max), fmt(first[k, t]), fmt(last[k, t]), fmt(sem[k, t]))
                for t in range(T + 1)
                if np.isfinite(last[k, t])
            ]
    name = f"prediction_errors_{p.name}.csv"
    write_csv(
        out / name,
        ["split", "T", "t", "trained_length", "epoch0_mean", f"epoch{p.epochs[-1]}_mean", f"epoch{p.epochs[-1]}_sem"],
        rows,
    )
    return name


def _summary_rows(summary: dict) -> list[tuple[str, float, float, int]]:
    """(metric, mean, s.d., runs) of every summary.json metric, flattened (``ferl.stats``)."""
    return [(name, *stats.mean_sd(values)) for name, values in stats.flat_metrics(summary.get("metrics", {})).items()]


def _summary_section(run: Run, out: Path) -> list[str]:
    rows = _summary_rows(run.summary)
    write_csv(
        out / "summary.csv", ["metric", "mean", "sd", "n_runs"], [(name, fmt(m), fmt(s), n) for name, m, s, n in rows]
    )
    lines = table_lines(
        ["metric", "mean", "s.d.", "runs"],
        [(name, f"{m:.4g}", "—" if np.isnan(s) else f"{s:.2g}", n) for name, m, s, n in rows],
    )
    optimal = run.summary.get("optimal") or {}
    if optimal:
        lines += ["", "Optimum: " + ", ".join(f"{k} {v:g}" for k, v in optimal.items())]
    return ["Mean ± s.d. (ddof = 1) over the runs that have a value, from `summary.json` (`summary.csv`).", ""] + lines


# ---- figures ---------------------------------------------------------------------


def _curve_figures(run: Run, c: Curves, num: Numbering) -> dict[str, tuple]:
    what = f"{run.experiment} ({run.task})"
    first = next(iter(c.series))
    panels = [(c.labels[k], *c.mean_sem(k), c.optima[k]) for k in c.series if k != c.td_key]
    shown = ", ".join(label for label, *_ in panels)
    out = {
        "learning_curves": (
            figs.learning_curves(
                c.x,
                panels,
                (c.labels[first], c.series[first], c.optima[first]),
                c.window,
                c.n_runs,
                f"{c.unit}",
                caption(num.learning_curves, what),
            ),
            caption(
                num.learning_curves,
                f"{shown}; {c.window}-{c.unit} moving average, mean ± "
                f"s.e.m. over runs, optimum dotted; the {c.labels[first]} "
                "of each run",
            ),
        )
    }
    episodes = run.records("episodes") if c.unit == "episode" else None
    sampled = (
        None
        if episodes is None or "td_sampled" not in episodes
        else (episodes["td_sampled"][FIGURE_RUN], episodes["td_sampled_episodes"])
    )
    out["td_errors"] = (
        figs.td_errors(
            c.x,
            *c.mean_sem(c.td_key),
            c.window,
            c.n_runs,
            c.unit,
            caption(num.td_errors, f"TD errors, {what}"),
            sampled,
        ),
        caption(
            num.td_errors,
            f"(a) {c.window}-{c.unit} moving average of {c.labels[c.td_key]}, "
            "mean ± s.e.m. over runs"
            + ("" if sampled is None else f"; (b) per-step δ of the sampled episodes of run {FIGURE_RUN}"),
        ),
    )
    return out


def _prediction_figure(run: Run, p: PredictorErrors, num: Numbering) -> tuple:
    number = num.prediction_figure(p.role)
    units = ERROR_UNITS.get(p.role, "prediction error\n(docs/records.md)")
    title = caption(
        number, f"prediction errors of the `{p.name}` predictor, mean over {p.n_runs} runs ({run.experiment})"
    )
    return (
        figs.prediction_errors(
            nanmean(p.train, axis=0), nanmean(p.test, axis=0), p.lengths, p.epochs, p.trained_max, units, title
        ),
        caption(
            number,
            f"{units.splitlines()[0]} of the `{p.name}` predictor per epoch × "
            "step, train (top) / test (bottom) by step-length T",
        ),
    )


ONLINE_LABELS = {
    "prediction_error": "held-out prediction error\n(Eq. 4.8, summed over predictors)",
    "beta": "inverse temperature β",
    "curiosity": "curiosity weight η",
}


def _online_figure(run: Run, online: dict) -> tuple:
    """The online trainer's course (``online.npz``): the predictors' held-out error and the β and η
    that follow from it, per episode."""
    window = min(run.final_window, online["beta"].shape[1])
    series = {k: _moving(online[k].astype(np.float64), window, None) for k in ONLINE_LABELS if k in online}
    x = next(iter(series.values()))[0]
    panels = [(ONLINE_LABELS[k], ma.mean(0), stats.sem(ma), None) for k, (_, ma) in series.items()]
    error = series["prediction_error"][1]
    return (
        figs.learning_curves(
            x,
            panels,
            ("held-out prediction error", error, None),
            window,
            error.shape[0],
            "episode",
            f"online training, {run.experiment}",
        ),
        "Online trainer: the predictors' held-out error (measured on every episode before they "
        "train on it), β following it, and the curiosity weight η; moving averages, mean ± s.e.m.",
    )


def _facts(what: dict | None, *keys: str) -> str:
    if not what:
        return "none"
    shown = [f"{k} {what[k]}" for k in keys if what.get(k) is not None]
    return f"`{what.get('kind')}`" + (f" ({', '.join(shown)})" if shown else "")


def _header(run: Run, c: Curves | None) -> list[tuple[str, str]]:
    m = run.manifest
    trainer = _facts(m.trainer) + (f", phases {' → '.join(m.trainer['phases'])}" if m.trainer.get("phases") else "")
    env = _facts(m.env, "observation", "observation_size", "n_actions") + (
        ", episodic" if m.episodic else ", continuing"
    )
    predictors = "; ".join(
        f"`{name}`: {_facts(facts, 'memory_size', 'reward_output')}, role {m.roles[name] or 'none'}"
        for name, facts in m.predictors.items()
    )
    header = [
        ("run directory", f"`{run.run_dir}`"),
        ("experiment", run.experiment),
        ("task", run.task),
        ("seeds", str(run.summary.get("seeds", "?"))),
        ("trainer", trainer),
        ("environment", env),
        ("preprocessor", _facts(m.preprocessor, "n_visible", "n_hidden")),
        ("predictors", predictors or "none"),
        ("actor", _facts(m.actor, "n_hidden", "gamma")),
    ]
    if c is not None:
        header += [
            (f"runs × {c.unit}s", f"{c.n_runs} × {c.length}"),
            ("moving averages", f"{c.window} {c.unit}s, mean ± s.e.m. over runs"),
        ]
    return header


def analyze(run: Run, num: Numbering, out: Path) -> RunAnalysis:
    """The generic figures, data files, header and summary table of any run."""
    c = curves(run)
    analysis = RunAnalysis(
        f"Report: {run.experiment} (task `{run.task}`)",  # a plug-in's environment analysis may retitle it
        _header(run, c),
        [("Summary", _summary_section(run, out))],
        data_files=["summary.csv"],
    )
    if c is not None:
        analysis.figures |= _curve_figures(run, c, num)
        analysis.data_files.append(_curves_table(c, out))
    online = run.records("online")
    if online is not None:
        analysis.figures["online_learning"] = _online_figure(run, online)
    for p in run.predictors:
        analysis.figures[f"prediction_errors_{p.name}"] = _prediction_figure(run, p, num)
        analysis.data_files.append(_prediction_table(p, out))
    return analysis
