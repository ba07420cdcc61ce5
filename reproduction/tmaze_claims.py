"""The measures that the T-maze claims of chapters 4 and 5 share, judged on a ``TMazeRun``.

A claim pairs one of them with the maze variant it is about (``claims.only``); a measure returns
None where the run lacks its data (a predictor role or a junction layer it did not record).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ferl.analysis.claims import (
    HELD,
    NOT_HELD,
    PARTLY,
    Claim,
    Measured,
    at_least,
    at_most,
    held_only_if,
    mean_sd_text,
    only,
)
from reproduction.tmaze import TMazeRun

Applies = Callable[[TMazeRun], bool]
Measure = Callable[[TMazeRun], Measured | None]

SOLVED_RUNS = (1.0, 0.8)  # share of runs ``solved`` (summary.json): all / at least 8 in 10
STEPS_RATIO = (1.05, 1.25)  # final steps to the goal ÷ optimum, mean over runs
CORRECT_GOAL = (0.95, 0.8)  # final correct-goal rate of the worst run
TD_DECREASE = (0.1, 0.5)  # last ÷ first final-window mean |δ| of the worst run ("to zero", §4.3.2)
TD_RUNS = 0.5  # "decreases … in all runs": share of runs whose |δ| falls, for partly
ERROR_DROP = 0.5  # final ÷ initial prediction error, training data
EARLY_EPOCHS = 0.1  # "rapidly": within the first 10 % of the epochs …
EARLY_SHARE = 0.5  # … at least half of the drop has happened
# "well generalized": final test error − final training error, and longer-T − test error, at
# most this share of the initial error (the colour scale of Figs. 4.5/4.10/5.2/5.17)
GENERALISATION_GAP = 0.1
GENERALISATION = 1.5  # the stricter rule, kept as a note: test ÷ train and longer ÷ test
SEPARATED = (0.5, 0.25)  # silhouette of the labels on PC1–3, mean over runs
MOST = 0.5  # "most of the variability": more than half, mean over runs (partly: some run)
MOST_VARIANCE = (0.8, 0.6)  # the stricter rule, kept as a note: held ≥ 0.8, partly ≥ 0.6


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


def with_note(measure: Measure, stricter: Callable[[Any], str], what: str) -> Measure:
    """``measure`` whose text adds the verdict of the stricter rule that judged the claim before
    its criterion was read from the dissertation's sentence (docs/readings.md, "Criteria"):
    nothing is hidden."""

    def noted(run: TMazeRun) -> Measured | None:
        found = measure(run)
        if found is None:
            return None
        return Measured(found.value, f"{found.text}; stricter rule ({what}): {stricter(found.value)}")

    return noted


def td_decreases(run: TMazeRun) -> Measured:
    """(last ÷ first final-window mean |δ| of the worst run, share of runs whose |δ| fell)."""
    first, last = run.window_mean("td_abs_mean", True), run.window_mean("td_abs_mean", False)
    ratio = last / np.where(first > 0, first, np.nan)
    # A run whose |δ| is not finite (diverged) did not decrease its TD error.
    broken = ~np.isfinite(ratio)
    worst = np.inf if broken.any() else float(ratio.max())
    fell = np.where(broken, False, ratio < 1.0)
    ok = ~broken
    window = run.run.final_window
    text = (
        f"mean |δ| over the first {window} episodes {mean_sd_text(first[ok])}, "
        f"over the last {window} {mean_sd_text(last[ok])}; "
        if ok.any()
        else ""
    )
    text += f"{int(fell.sum())}/{len(ratio)} runs decrease; " + (
        f"{int(broken.sum())} of {len(ratio)} runs with non-finite |δ| (diverged)"
        if broken.any()
        else f"last ÷ first in the worst run {worst:.3f}"
    )
    return Measured((worst, float(fell.mean())), text)


def td_to_zero(value: tuple[float, float]) -> str:
    """§4.3.2's "decreases to zero in all runs": the worst run's last ÷ first mean |δ|."""
    return at_most(*TD_DECREASE)(value[0])


def td_falls_in_all_runs(value: tuple[float, float]) -> str:
    """ "The TD error decreases over the episodes in all runs" (Figs. 4.8(a), 5.6(a), 5.19(c)):
    every run's last-window mean |δ| below its first; partly in at least ``TD_RUNS`` of them."""
    share = value[1]
    return HELD if share == 1.0 else PARTLY if share >= TD_RUNS else NOT_HELD


TD_TO_ZERO_TEXT = f"§4.3.2's \"to zero\": worst run's last ÷ first ≤ {TD_DECREASE[0]:g}, partly ≤ {TD_DECREASE[1]:g}"
TD_TEXT = (
    f"held: every run's mean |δ| over the last window below that over the first; partly: in ≥ {TD_RUNS:.0%} of the runs"
)
td_falls = with_note(td_decreases, td_to_zero, TD_TO_ZERO_TEXT)


def predictor_learns(role: str, drop: float = ERROR_DROP) -> Measure:
    """The first predictor of ``role``: its error falls by ``drop``, rapidly, and generalises."""

    def measure(run: TMazeRun) -> Measured | None:
        p = run.predictor(role)
        if p is None:
            return None
        e = run.error_trend(p, EARLY_EPOCHS)
        gap = GENERALISATION_GAP * e["initial"]
        checks = {"drop": e["final"] <= drop * e["initial"], "test": e["test"] - e["final"] <= gap}
        stricter = {"drop": checks["drop"], "test": e["test"] <= GENERALISATION * e["final"]}
        # Judged only where logged: epochs early in training, lengths beyond the trained ones.
        if np.isfinite(e["early_share"]):
            checks["rapid"] = stricter["rapid"] = e["early_share"] >= EARLY_SHARE
        if np.isfinite(e["longer"]):
            checks["longer"] = e["longer"] - e["test"] <= gap
            stricter["longer"] = e["longer"] <= GENERALISATION * e["test"]
        early = f"{100 * e['early_share']:.0f} % of the drop" if "rapid" in checks else "no epoch logged"
        text = (
            f"`{p.name}` error, t ≥ 1, trained lengths T ≤ {p.trained_max}: "
            f"{e['initial']:.3f} → {e['final']:.3f} (train); {early} within the first "
            f"{100 * EARLY_EPOCHS:g} % of the epochs; final test {e['test']:.3f}, test on "
            f"longer T {e['longer']:.3f}; criteria met: "
            + ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in checks.items())
            + f"; stricter rule (test ≤ {GENERALISATION:g} × train, longer T ≤ {GENERALISATION:g} × test): "
            + learns_and_generalises(stricter)
        )
        return Measured(checks, text)

    return measure


def learning_text(drop: float) -> str:
    return (
        f"held: final ≤ {drop:g} × initial training error, ≥ {EARLY_SHARE:.0%} of the drop within the first "
        f"{EARLY_EPOCHS:.0%} of the epochs (where logged), final test − final train and longer T − test each ≤ "
        f"{GENERALISATION_GAP:g} × the initial error (longer T where recorded); partly: the drop alone"
    )


GENERALISATION_TEXT = learning_text(ERROR_DROP)


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


def separated_after_learning(value: tuple[float, float]) -> str:
    """ "The four conditions are separately represented" (Figs. 4.15, 5.9; the text, unlike
    §5.3.2's, does not say "even before the learning"): well separated in the last phase and at
    least weakly in the first, both panels of the figure; partly: weakly in the last."""
    last, first = value
    if last >= SEPARATED[0] and first >= SEPARATED[1]:
        return HELD
    return PARTLY if last >= SEPARATED[1] else NOT_HELD


SEPARATED_AFTER_TEXT = (
    f"held: silhouette of the conditions ≥ {SEPARATED[0]:g} in the last phase and ≥ {SEPARATED[1]:g} in the "
    f"first; partly: ≥ {SEPARATED[1]:g} in the last"
)
SEPARATED_IN_BOTH_TEXT = f"both phases ≥ {SEPARATED[0]:g}, partly ≥ {SEPARATED[1]:g}"


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
            (float(share.mean()), float(share.max())),
            f"variance of `{layer}` on PC1–{n_pcs}, last {run.phase_episodes} episodes: {mean_sd_text(share)}"
            f", best run {share.max():.3f}",
        )

    return measure


def most_variance(value: tuple[float, float]) -> str:
    """ "Most of the variability": more than half of it, mean over runs; partly in some run (the
    figures show one run)."""
    mean, best = value
    return HELD if mean > MOST else PARTLY if best > MOST else NOT_HELD


def most_variance_strict(value: tuple[float, float]) -> str:
    return at_least(*MOST_VARIANCE)(value[0])


VARIANCE_TEXT = f"held: variance share, last phase, > {MOST:g} on the mean over runs; partly: in some run"
MOST_VARIANCE_TEXT = f"mean ≥ {MOST_VARIANCE[0]:g}, partly ≥ {MOST_VARIANCE[1]:g}"


def separation_claim(
    applies: Applies,
    layer: str,
    rule: Callable[[tuple[float, float]], str],
    text: str,
    source: str,
    criterion: str = "",
    stricter: tuple[Callable[[tuple[float, float]], str], str] | None = None,
) -> Claim:
    """A claim that the conditions separate in an actor layer at the T-junction: the state
    nodes (``separated_after_learning``: Figs. 4.15, 5.9; ``separated_in_both``, "even before the
    learning started": Fig. 5.22), the hidden nodes as the training proceeds
    (``separates_more``: Figs. 4.17–4.19, 5.11–5.12, 5.24–5.25); ``stricter``: a rule and its
    words whose verdict the text notes."""
    measure = conditions_separate(layer)
    if stricter is not None:
        measure = with_note(measure, *stricter)
    return Claim(text, source, only(applies, measure), rule, criterion)


def variance_claim(
    applies: Applies, layer: str, n_pcs: int, source: str, count: str = "", criterion: str = ""
) -> Claim:
    """ "Most of the variability of the actor's <layer> nodes is captured by the first <count>
    principal components" (Figs. 4.16, 4.19(a), 5.10(a), 5.13(a), 5.23(a), 5.25(b))."""
    return Claim(
        f"Most of the variability of the actor's {layer} nodes is captured by the "
        f"first {count or n_pcs} principal components.",
        source,
        only(applies, with_note(leading_variance(layer, n_pcs), most_variance_strict, MOST_VARIANCE_TEXT)),
        most_variance,
        criterion or VARIANCE_TEXT,
    )
