"""The measures that the T-maze claims of chapters 4 and 5 share, judged on a ``TMazeRun``.

A claim pairs one of them with the maze variant it is about (``claims.only``); a measure returns
None where the run lacks its data (a predictor role or a junction layer it did not record).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ferl.analysis.claims import HELD, NOT_HELD, PARTLY, Claim, Measured, at_least, held_only_if, mean_sd_text, only
from reproduction.tmaze import TMazeRun

Applies = Callable[[TMazeRun], bool]
Measure = Callable[[TMazeRun], Measured | None]

SOLVED_RUNS = (1.0, 0.8)  # share of runs ``solved`` (summary.json): all / at least 8 in 10
STEPS_RATIO = (1.05, 1.25)  # final steps to the goal ÷ optimum, mean over runs
CORRECT_GOAL = (0.95, 0.8)  # final correct-goal rate of the worst run
TD_DECREASE = (0.1, 0.5)  # last ÷ first final-window mean |δ| of the worst run ("to ~0")
ERROR_DROP = 0.5  # final ÷ initial prediction error, training data
EARLY_EPOCHS = 0.1  # "rapidly": within the first 10 % of the epochs …
EARLY_SHARE = 0.5  # … at least half of the drop has happened
GENERALISATION = 1.5  # final error: test ÷ train and longer ÷ trained lengths
SEPARATED = (0.5, 0.25)  # silhouette of the labels on PC1–3, mean over runs
MOST_VARIANCE = (0.8, 0.6)  # explained-variance share of the leading PCs, last phase


def solved(run: TMazeRun) -> Measured:
    runs_solved = run.metric("solved")
    return Measured(
        runs_solved.mean(),
        f"{int(runs_solved.sum())}/{len(runs_solved)} runs solved "
        f"(summary.json); final discounted return "
        f"{mean_sd_text(run.metric('final_discounted_return'))}, "
        f"optimum {run.optimal_return:.4f}",
    )


def optimal_steps(run: TMazeRun) -> Measured:
    steps = run.metric("final_steps_to_goal")
    ratio = steps.mean() / run.optimal_steps
    return Measured(
        ratio, f"final steps to the goal {mean_sd_text(steps)} = {ratio:.2f} × optimum {run.optimal_steps:g}"
    )


def correct_goal(run: TMazeRun) -> Measured:
    rate = run.metric("final_correct_goal_rate")
    return Measured(rate.min(), f"final correct-goal rate {mean_sd_text(rate)}, worst run {rate.min():.3f}")


def td_decreases(run: TMazeRun) -> Measured:
    first, last = run.window_mean("td_abs_mean", True), run.window_mean("td_abs_mean", False)
    ratio = last / np.where(first > 0, first, np.nan)
    # A run whose |δ| is not finite (diverged) did not decrease its TD error.
    broken = ~np.isfinite(ratio)
    worst = np.inf if broken.any() else float(ratio.max())
    ok = ~broken
    window = run.run.final_window
    text = (
        f"mean |δ| over the first {window} episodes {mean_sd_text(first[ok])}, "
        f"over the last {window} {mean_sd_text(last[ok])}; "
        if ok.any()
        else ""
    )
    text += (
        f"{int(broken.sum())} of {len(ratio)} runs with non-finite |δ| (diverged)"
        if broken.any()
        else f"last ÷ first in the worst run {worst:.3f}"
    )
    return Measured(worst, text)


def predictor_learns(role: str, drop: float = ERROR_DROP) -> Measure:
    """The first predictor of ``role``: its error falls by ``drop``, rapidly, and generalises."""

    def measure(run: TMazeRun) -> Measured | None:
        p = run.predictor(role)
        if p is None:
            return None
        e = run.error_trend(p, EARLY_EPOCHS)
        checks = {"drop": e["final"] <= drop * e["initial"], "test": e["test"] <= GENERALISATION * e["final"]}
        # Judged only where logged: epochs early in training, lengths beyond the trained ones.
        if np.isfinite(e["early_share"]):
            checks["rapid"] = e["early_share"] >= EARLY_SHARE
        if np.isfinite(e["longer"]):
            checks["longer"] = e["longer"] <= GENERALISATION * e["test"]
        early = f"{100 * e['early_share']:.0f} % of the drop" if "rapid" in checks else "no epoch logged"
        text = (
            f"`{p.name}` error, t ≥ 1, trained lengths T ≤ {p.trained_max}: "
            f"{e['initial']:.3f} → {e['final']:.3f} (train); {early} within the first "
            f"{100 * EARLY_EPOCHS:g} % of the epochs; final test {e['test']:.3f}, test on "
            f"longer T {e['longer']:.3f}; criteria met: "
            + ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in checks.items())
        )
        return Measured(checks, text)

    return measure


def learns_and_generalises(checks: dict[str, bool]) -> str:
    return HELD if all(checks.values()) else PARTLY if checks["drop"] else NOT_HELD


def phase_means(run: TMazeRun, layer: str, labels: str) -> tuple[np.ndarray, str] | None:
    """(first, last) silhouette, mean over runs, and a note on the runs where it is undefined
    (no finite visit in the phase, or one label only). Those count as 0, no separation: the
    claim is about every run. None when it is undefined everywhere (no data)."""
    s = run.separation[layer, labels]
    undefined = np.isnan(s).sum(axis=1)
    if undefined.min() == run.n_runs:
        return None
    note = (
        ""
        if not undefined.any()
        else (
            f" ({undefined[0]} / {undefined[1]} of {run.n_runs} runs undefined in the first / last phase, counted as 0)"
        )
    )
    return np.nan_to_num(s, nan=0.0).mean(axis=1), note


def conditions_separate(layer: str) -> Measure:
    def measure(run: TMazeRun) -> Measured | None:
        if layer not in run.layers:
            return None
        found = phase_means(run, layer, "condition")
        if found is None:
            return None
        (first, last), note = found
        return Measured(
            (last, first),
            f"silhouette of the 4 conditions on PC1–3 of `{layer}`, "
            f"mean over runs: first {run.phase_episodes} episodes "
            f"{first:.2f}, last {run.phase_episodes} {last:.2f}{note}",
        )

    return measure


def separated_in_both(value: tuple[float, float]) -> str:
    return at_least(*SEPARATED)(min(value))


def separates_more(value: tuple[float, float]) -> str:
    last, first = value
    return held_only_if(at_least(*SEPARATED)(last), last > first)


def leading_variance(layer: str, n_pcs: int) -> Measure:
    def measure(run: TMazeRun) -> Measured | None:
        if layer not in run.layers:
            return None
        share = run.explained(layer, "last")[:, :n_pcs].sum(axis=1)
        if not share.size:
            return None
        return Measured(
            share.mean(),
            f"variance of `{layer}` on PC1–{n_pcs}, last {run.phase_episodes} episodes: {mean_sd_text(share)}",
        )

    return measure


def separation_claim(
    applies: Applies,
    layer: str,
    rule: Callable[[tuple[float, float]], str],
    text: str,
    source: str,
    criterion: str = "",
) -> Claim:
    """A claim that the conditions separate in an actor layer at the T-junction: the state
    nodes in both phases (``separated_in_both``: Figs. 4.15, 5.9, 5.22), the hidden nodes as the
    training proceeds (``separates_more``: Figs. 4.17–4.19, 5.11–5.12, 5.24–5.25)."""
    return Claim(text, source, only(applies, conditions_separate(layer)), rule, criterion)


def variance_claim(
    applies: Applies, layer: str, n_pcs: int, source: str, count: str = "", criterion: str = ""
) -> Claim:
    """ "Most of the variability of the actor's <layer> nodes is captured by the first <count>
    principal components" (Figs. 4.16, 4.19(a), 5.10(a), 5.13(a), 5.23(a), 5.25(b))."""
    return Claim(
        f"Most of the variability of the actor's {layer} nodes is captured by the "
        f"first {count or n_pcs} principal components.",
        source,
        only(applies, leading_variance(layer, n_pcs)),
        at_least(*MOST_VARIANCE),
        criterion,
    )
