"""Dissertation claims as data, judged against a run, and the markdown reports.

A `Claim` pairs a statement of the dissertation (with its section/figure) with
a function measuring the corresponding quantity on a loaded run and a threshold
rule turning that measurement into "held", "partly" or "not held" (spelled out,
where given, by its `criterion`). `FLOOR_CLAIMS` covers chapter 3 (§3.5.1–§3.5.3),
`TMAZE_CLAIMS` chapter 4 (§4.3.1–§4.3.3) and chapter 5 (§5.3.1–§5.3.2); a run only
gets the claims its data speaks to (a measure returns None otherwise).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ferl.analysis.floor import FloorRun
    from ferl.analysis.sweep import Sweep
    from ferl.analysis.tmaze import TMazeRun

HELD, PARTLY, NOT_HELD = "held", "partly", "not held"
VERDICTS = (HELD, PARTLY, NOT_HELD)

# Thresholds of the verdict rules (fractions unless stated).
NEAR_OPTIMAL = (0.8, 0.5)        # reward/step ÷ optimum
MOST_IMAGES = (0.8, 0.5)         # greedy accuracy
CHANCE_TOLERANCE = (0.1, 0.2)    # |accuracy − 1/|A||
SATISFACTORY = 0.9               # accuracy ÷ accuracy at the training noise
OUTLIER_GAIN = (0.2, 0.05)       # rise of the median P(optimal | "1")
SELECTIVITY_GAIN = (2.0, 1.0)    # class selectivity after ÷ before
PAIR_RUNS = 0.6                  # share of runs in which a pair must cluster
LOW_ACTIVATION = 0.1             # median activation counted as "very low"


@dataclass(frozen=True)
class Measured:
    value: Any   # what the rule judges
    text: str    # what the report prints


@dataclass(frozen=True)
class Claim:
    text: str
    source: str
    measure: Callable[[Any], Measured | None]  # None: the run has no data for this claim
    rule: Callable[[Any], str]
    criterion: str = ""                        # the rule in words, for the report


@dataclass(frozen=True)
class ClaimResult:
    claim: Claim
    measured: Measured
    verdict: str


@dataclass
class RunAnalysis:
    """What a task's analysis hands to the writer: figures, data files, judged claims."""
    title: str
    header: list[tuple[str, str]]
    figures: dict[str, tuple[Figure, str]] = field(default_factory=dict)  # name → (fig, caption)
    data_files: list[str] = field(default_factory=list)
    results: list[ClaimResult] = field(default_factory=list)


def evaluate(claims: Sequence[Claim], run: Any) -> list[ClaimResult]:
    """Judge every claim the run's data speaks to."""
    results = []
    for claim in claims:
        measured = claim.measure(run)
        if measured is not None:
            results.append(ClaimResult(claim, measured, claim.rule(measured.value)))
    return results


def at_least(held: float, partly: float) -> Callable[[float], str]:
    return lambda v: HELD if v >= held else PARTLY if v >= partly else NOT_HELD


def at_most(held: float, partly: float) -> Callable[[float], str]:
    return lambda v: HELD if v <= held else PARTLY if v <= partly else NOT_HELD


def all_or_some(flags: Sequence[bool]) -> str:
    return HELD if all(flags) else PARTLY if any(flags) else NOT_HELD


def _mean_sd(values: np.ndarray) -> str:
    return f"{np.mean(values):.3g} ± {np.std(values):.2g} (mean ± s.d., {len(values)} runs)"


# ---- chapter 3: digit floor -------------------------------------------------

def _near_optimal(run: FloorRun) -> Measured | None:
    if run.reward_free:
        return None
    per_seed = np.asarray(run.summary["metrics"]["reward_per_step_last10pct"], dtype=float)
    ratio = per_seed.mean() / run.optimal_reward
    return Measured(ratio, f"{_mean_sd(per_seed)} reward/step = {ratio:.2f} × optimum "
                           f"{run.optimal_reward:g}")


def _accuracy_at_training_noise(phase: str) -> Callable[[FloorRun], Measured | None]:
    def measure(run: FloorRun) -> Measured | None:
        if run.reward_free or not run.has_optimal_actions:
            return None
        acc = run.accuracy[phase][:, run.probe_level]
        text = f"greedy accuracy {_mean_sd(acc)} at {100 * run.probe_noise:g} % test noise"
        if phase == "before":
            return Measured(abs(acc.mean() - run.chance),
                            f"{text}; chance {run.chance:.2f}")
        return Measured(acc.mean(), text)
    return measure


def _noise_tolerance(train_noise: float, last_ok: float,
                     first_bad: float) -> Callable[[FloorRun], Measured | None]:
    def measure(run: FloorRun) -> Measured | None:
        levels = run.noise_levels
        if (run.reward_free or not run.has_optimal_actions
                or not np.isclose(run.probe_noise, train_noise)
                or not np.isclose(levels, first_bad).any()):
            return None
        acc = np.nanmean(run.accuracy["after"], axis=0)
        reference = acc[run.probe_level]
        ok = acc[(levels <= last_ok + 1e-9)].min() >= SATISFACTORY * reference
        bad = acc[np.isclose(levels, first_bad)][0] < SATISFACTORY * reference
        shown = "; ".join(f"{100 * x:g} %: {a:.2f}" for x, a in zip(levels, acc))
        return Measured((ok, bad), f"mean greedy accuracy after training by test noise — {shown} "
                                   f"(satisfactory: ≥ {SATISFACTORY:g} × {reference:.2f})")
    return measure


def _robust_then_deteriorates(value: tuple[bool, bool]) -> str:
    return {2: HELD, 1: PARTLY, 0: NOT_HELD}[sum(value)]


def _outlier_detection(run: FloorRun) -> Measured | None:
    if run.reward_free or "1" not in run.classes:
        return None
    c = run.classes.index("1")
    a = run.optimal_action[c]
    if a < 0:
        return None
    med = {phase: np.median(run.test[f"probs_{phase}"][:, c, :, a], axis=1)
           for phase in ("before", "after")}
    gain = float(np.mean(med["after"] - med["before"]))
    return Measured(gain, f'median P(\'{run.action_names[a]}\' | "1") over test images: '
                          f"before {_mean_sd(med['before'])}, after {_mean_sd(med['after'])}")


def _class_selectivity(run: FloorRun) -> Measured | None:
    if run.reward_free:
        return None
    sel = {phase: run.selectivity(phase).mean() for phase in ("before", "after")}
    ratio = sel["after"] / sel["before"] if sel["before"] > 0 else np.inf
    return Measured(ratio, f"s.d. over classes of the median activation, mean over units and "
                           f"runs: before {sel['before']:.3f}, after {sel['after']:.3f} "
                           f"(ratio {ratio:.2f})")


SOURCES = {"hidden": "MFR dendrogram (Eq. 3.12)",
           "hidden_marginal": "dendrogram of the policy-weighted activation of fn. 6"}


def _pairs_cluster(pairs_of: Callable[[FloorRun], list[tuple[int, int]]], with_reward: bool,
                   source: str = "hidden") -> Callable[[FloorRun], Measured | None]:
    def measure(run: FloorRun) -> Measured | None:
        pairs = pairs_of(run)
        if run.reward_free == with_reward or not pairs:
            return None
        hits = [run.cluster_hits(i, j, source) for i, j in pairs]
        text = "; ".join(f'("{run.classes[i]}", "{run.classes[j]}"): {sum(h)}/{len(h)} runs'
                         for (i, j), h in zip(pairs, hits))
        return Measured([np.mean(h) >= PAIR_RUNS for h in hits],
                        f"runs in which the pair is merged directly in the {SOURCES[source]}: {text}")
    return measure


def _named_pairs(names: Sequence[tuple[str, str]]) -> Callable[[FloorRun], list[tuple[int, int]]]:
    def pairs_of(run: FloorRun) -> list[tuple[int, int]]:
        return [(run.classes.index(a), run.classes.index(b)) for a, b in names
                if a in run.classes and b in run.classes]
    return pairs_of


PERCEPTUAL_PAIRS = (("1", "7"), ("3", "8"))


def _low_activation(run: FloorRun) -> Measured | None:
    if not run.reward_free:
        return None
    level = {phase: float(np.median(run.test[f"hidden_marginal_{phase}"], axis=2).mean())
             for phase in ("before", "after")}
    verdict_value = (level["after"] <= LOW_ACTIVATION, level["after"] < level["before"])
    return Measured(verdict_value, f"median activation, mean over classes, units and runs: "
                                   f"before {level['before']:.3f}, after {level['after']:.3f}")


def _low_rule(value: tuple[bool, bool]) -> str:
    very_low, lower = value
    return HELD if very_low else PARTLY if lower else NOT_HELD


def _mi_pairs(run: FloorRun) -> Measured | None:
    pairs = _named_pairs(PERCEPTUAL_PAIRS)(run)
    if not pairs or run.mi_linkage is None:
        return None
    labels = run.digit_classes
    flags = [run.mi_pair_clusters(run.classes[i], run.classes[j]) for i, j in pairs]
    text = "; ".join(f'("{run.classes[i]}", "{run.classes[j]}"): {"merged" if f else "not merged"}'
                     for (i, j), f in zip(pairs, flags))
    return Measured(flags, f"MI dendrogram of {len(labels)} digit classes — {text}")


def _noise_class_mi(run: FloorRun) -> Measured | None:
    if "N" not in run.classes or len(run.digit_classes) < 2:
        return None
    mi, n = run.mutual_information, run.classes.index("N")
    digits = [run.classes.index(c) for c in run.digit_classes]
    with_noise = mi[n, digits]
    among_digits = mi[np.ix_(digits, digits)][np.triu_indices(len(digits), 1)]
    value = (with_noise.min() > among_digits.max(), with_noise.mean() > among_digits.mean())
    return Measured(value, f'MI (nats) of "N" with digits: {with_noise.min():.3f}–'
                           f"{with_noise.max():.3f}; among digits: {among_digits.min():.3f}–"
                           f"{among_digits.max():.3f}")


def _every_or_on_average(value: tuple[bool, bool]) -> str:
    every, on_average = value
    return HELD if every else PARTLY if on_average else NOT_HELD


SAME_ACTION_PAIRS_SOURCE = "§3.5.3, Figs. 3.11(a)/(b), 3.13"


FLOOR_CLAIMS: list[Claim] = [
    Claim("Despite the observation noise the agent performs at a nearly optimal level "
          "at the end of training (upper bound 8 reward/step).",
          "§3.5.1, Fig. 3.4, fn. 4", _near_optimal, at_least(*NEAR_OPTIMAL)),
    Claim("After training, most held-out test images at the training noise level make "
          "the optimal action greedy, for every digit.",
          "§3.5.1, Fig. 3.6(b)", _accuracy_at_training_noise("after"), at_least(*MOST_IMAGES)),
    Claim("Before training the agent has no behavioural tendency for a certain digit "
          "(greedy accuracy at chance).",
          "§3.5.1, Fig. 3.6(a)", _accuracy_at_training_noise("before"),
          at_most(*CHANCE_TOLERANCE)),
    Claim("Trained at 12.5 % noise, the agent performs satisfactorily up to 37.5 % test "
          "noise and deteriorates from 50 %.",
          "§3.5.1, fn. 5, Fig. 3.6(c)", _noise_tolerance(0.125, 0.375, 0.5),
          _robust_then_deteriorates),
    Claim("Trained at 50 % noise, the agent performs satisfactorily up to 62.5 % test "
          "noise and deteriorates at 75 %.",
          "§3.5.1, Fig. 3.6(d)", _noise_tolerance(0.5, 0.625, 0.75), _robust_then_deteriorates),
    Claim('Outlier detection: after training, typical "1"s make the optimal action '
          "(south) clearly more probable than before training.",
          "§3.5.2, Fig. 3.7", _outlier_detection, at_least(*OUTLIER_GAIN)),
    Claim("Before training hidden nodes show no preference for particular digits "
          "(vertical bands); after training their activation patterns differ between digits.",
          "§3.5.3, Fig. 3.10(a)–(c)", _class_selectivity, at_least(*SELECTIVITY_GAIN)),
    Claim("Pairs of tiles with the same optimal action form their own clusters of the "
          "median firing rates.",
          SAME_ACTION_PAIRS_SOURCE,
          _pairs_cluster(lambda run: run.same_action_pairs, with_reward=True), all_or_some),
    Claim("Pairs of tiles with the same optimal action form their own clusters of the hidden "
          "activation defined in fn. 6 (actions weighted by the policy instead of uniformly).",
          "§3.5.3 fn. 6, Figs. 3.10–3.11",
          _pairs_cluster(lambda run: run.same_action_pairs, with_reward=True, source="hidden_marginal"),
          all_or_some),
    Claim("Without reward, the activation of all hidden nodes becomes very low.",
          "§3.5.3, Fig. 3.10(d)", _low_activation, _low_rule),
    Claim('Without reward, perceptually similar "1" and "7", and "3" and "8", are grouped '
          "together.",
          "§3.5.3, Fig. 3.11(c)",
          _pairs_cluster(_named_pairs(PERCEPTUAL_PAIRS), with_reward=False), all_or_some),
    Claim('Clustering the digits by pixel–label mutual information groups "1" with "7" '
          'and "3" with "8", as in Fig. 3.11(c).',
          "§3.5.3, Fig. 3.12", _mi_pairs, all_or_some),
    Claim('The noise tile "N" has a much higher mutual information with every digit than '
          "the digits have with each other.",
          "§3.5.3, Fig. 3.12", _noise_class_mi, _every_or_on_average),
]


# ---- chapter 4: T-mazes -----------------------------------------------------

SOLVED_RUNS = (1.0, 0.8)     # share of runs `solved` (summary.json): all / at least 8 in 10
STEPS_RATIO = (1.05, 1.25)   # final steps to the goal ÷ optimum, mean over runs
CORRECT_GOAL = (0.95, 0.8)   # final correct-goal rate of the worst run
TD_DECREASE = (0.1, 0.5)     # last ÷ first 200-episode mean |δ| of the worst run ("to ~0")
ERROR_DROP = 0.5             # final ÷ initial prediction error, training data
EARLY_EPOCHS = 0.1           # "rapidly": within the first 10 % of the epochs …
EARLY_SHARE = 0.5            # … at least half of the drop has happened
GENERALISATION = 1.5         # final error: test ÷ train and longer ÷ trained lengths
SEPARATED = (0.5, 0.25)      # silhouette of the labels on PC1–3, mean over runs
MOST_VARIANCE = (0.8, 0.6)   # explained-variance share of the leading PCs, last phase
ABOVE_CHANCE = (0.6, 0.55)   # final correct-goal rate, mean over runs (chance 0.5)


def _variant_is(variant: str) -> Callable[[TMazeRun], bool]:
    """Chapter-4 claims are about the one-predictor model on one T-maze variant."""
    return lambda run: run.chapter4 and run.variant == variant


def _solved(applies: Callable[[TMazeRun], bool]) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not applies(run):
            return None
        solved = run.metric("solved")
        return Measured(solved.mean(), f"{int(solved.sum())}/{len(solved)} runs solved "
                                       f"(summary.json); final discounted return "
                                       f"{_mean_sd(run.metric('final_discounted_return'))}, "
                                       f"optimum {run.optimal_return:.4f}")
    return measure


def _optimal_steps(applies: Callable[[TMazeRun], bool]) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not applies(run):
            return None
        steps = run.metric("final_steps_to_goal")
        ratio = steps.mean() / run.optimal_steps
        return Measured(ratio, f"final steps to the goal {_mean_sd(steps)} = {ratio:.2f} × "
                               f"optimum {run.optimal_steps:g}")
    return measure


def _correct_goal(applies: Callable[[TMazeRun], bool]) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not applies(run):
            return None
        rate = run.metric("final_correct_goal_rate")
        return Measured(rate.min(), f"final correct-goal rate {_mean_sd(rate)}, worst run "
                                    f"{rate.min():.3f}")
    return measure


def _td_decreases(applies: Callable[[TMazeRun], bool]) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not applies(run):
            return None
        first, last = run.window_mean("td_abs_mean", True), run.window_mean("td_abs_mean", False)
        ratio = last / np.where(first > 0, first, np.nan)
        # A run whose |δ| is not finite (diverged) did not decrease its TD error.
        broken = ~np.isfinite(ratio)
        worst = np.inf if broken.any() else float(ratio.max())
        ok = ~broken
        text = (f"mean |δ| over the first 200 episodes {_mean_sd(first[ok])}, over the last 200 "
                f"{_mean_sd(last[ok])}; " if ok.any() else "")
        text += (f"{int(broken.sum())} of {len(ratio)} runs with non-finite |δ| (diverged)"
                 if broken.any() else f"last ÷ first in the worst run {worst:.3f}")
        return Measured(worst, text)
    return measure


def _predictor_learns(applies: Callable[[TMazeRun], bool], name: str = "joint",
                      drop: float = ERROR_DROP) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not (applies(run) and name in run.predictors):
            return None
        e = run.error_trend(name, EARLY_EPOCHS)
        checks = {"drop": e["final"] <= drop * e["initial"],
                  "test": e["test"] <= GENERALISATION * e["final"]}
        # Judged only where logged: epochs early in training, lengths beyond the trained ones.
        if np.isfinite(e["early_share"]):
            checks["rapid"] = e["early_share"] >= EARLY_SHARE
        if np.isfinite(e["longer"]):
            checks["longer"] = e["longer"] <= GENERALISATION * e["test"]
        early = (f"{100 * e['early_share']:.0f} % of the drop" if "rapid" in checks
                 else "no epoch logged")
        text = (f"`{name}` error, t ≥ 1, trained lengths T ≤ {run.trained_max(name)}: "
                f"{e['initial']:.3f} → {e['final']:.3f} (train); {early} within the first "
                f"{100 * EARLY_EPOCHS:g} % of the epochs; final test {e['test']:.3f}, test on "
                f"longer T {e['longer']:.3f}; criteria met: "
                + ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in checks.items()))
        return Measured(checks, text)
    return measure


def _learns_and_generalises(checks: dict[str, bool]) -> str:
    return HELD if all(checks.values()) else PARTLY if checks["drop"] else NOT_HELD


def _phase_means(run: TMazeRun, layer: str, labels: str) -> tuple[np.ndarray, str] | None:
    """(first, last) silhouette, mean over runs, and a note on the runs where it is undefined
    (no finite visit in the phase, or one label only). Those count as 0, no separation: the
    claim is about every run. None when it is undefined everywhere (no data)."""
    s = run.separation[layer, labels]
    undefined = np.isnan(s).sum(axis=1)
    if undefined.min() == run.n_runs:
        return None
    note = "" if not undefined.any() else (
        f" ({undefined[0]} / {undefined[1]} of {run.n_runs} runs undefined in the first / last "
        "phase, counted as 0)")
    return np.nan_to_num(s, nan=0.0).mean(axis=1), note


def _memory_keeps_signal(run: TMazeRun) -> Measured | None:
    if not (run.chapter4 and run.matching and run.memory_layers):
        return None
    kept = {layer: _phase_means(run, layer, "initial_signal") for layer in run.memory_layers}
    kept = {layer: v for layer, v in kept.items() if v is not None}
    if not kept:
        return None
    # Kept = separated in both phases, in any recorded memory layer.
    best = max(means.min() for means, _ in kept.values())
    text = "; ".join(f"`{layer}`: first {means[0]:.2f}, last {means[1]:.2f}{note}"
                     for layer, (means, note) in kept.items())
    return Measured(best, f"silhouette of the initial signal on PC1–3 of the memory at the "
                          f"junction, mean over runs — {text}")


def _conditions_separate(applies: Callable[[TMazeRun], bool],
                         layer: str) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not (applies(run) and layer in run.layers):
            return None
        found = _phase_means(run, layer, "condition")
        if found is None:
            return None
        (first, last), note = found
        return Measured((last, first), f"silhouette of the 4 conditions on PC1–3 of `{layer}`, "
                                       f"mean over runs: first {run.phase_episodes} episodes "
                                       f"{first:.2f}, last {run.phase_episodes} {last:.2f}{note}")
    return measure


def _separated_in_both(value: tuple[float, float]) -> str:
    return at_least(*SEPARATED)(min(value))


def _held_only_if(level: str, ok: bool) -> str:
    """A verdict lowered from held to partly where the claim's second part fails."""
    return PARTLY if level == HELD and not ok else level


def _separates_more(value: tuple[float, float]) -> str:
    last, first = value
    return _held_only_if(at_least(*SEPARATED)(last), last > first)


def _leading_variance(applies: Callable[[TMazeRun], bool], layer: str,
                      n_pcs: int) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not (applies(run) and layer in run.layers):
            return None
        share = run.explained(layer, "last")[:, :n_pcs].sum(axis=1)
        if not share.size:
            return None
        return Measured(share.mean(), f"variance of `{layer}` on PC1–{n_pcs}, last "
                                      f"{run.phase_episodes} episodes: {_mean_sd(share)}")
    return measure


def _digit_correct_goal(run: TMazeRun) -> Measured | None:
    if not _variant_is("digit matching")(run):
        return None
    rate, solved = run.metric("final_correct_goal_rate"), run.metric("solved")
    ret = run.metric("final_discounted_return")
    return Measured(rate.mean(), f"final correct-goal rate {_mean_sd(rate)} (chance 0.5); "
                                 f"{int(solved.sum())}/{len(solved)} runs solved; final "
                                 f"discounted return {_mean_sd(ret)}, optimum "
                                 f"{run.optimal_return:.4f}")


_REGULAR, _MATCHING = _variant_is("regular"), _variant_is("matching")

CH4_TMAZE_CLAIMS: list[Claim] = [
    Claim("The regular T-maze is solved optimally in all 10 runs.",
          "§4.3.1, Fig. 4.6", _solved(_REGULAR), at_least(*SOLVED_RUNS)),
    Claim("The agent learns to reach the goal in the optimal number of steps (3).",
          "§4.3.1, Fig. 4.7(a)", _optimal_steps(_REGULAR), at_most(*STEPS_RATIO)),
    Claim("The agent learns to reach the correct goal (terminal reward +5) in all 10 runs.",
          "§4.3.1, Fig. 4.7(b)", _correct_goal(_REGULAR), at_least(*CORRECT_GOAL)),
    Claim("The TD error decreases over the episodes in all runs.",
          "§4.3.1, Fig. 4.8(a)", _td_decreases(_REGULAR), at_most(*TD_DECREASE)),
    Claim("The predictor's error decreases rapidly in the first epochs and generalises to "
          "the test set and to longer, untrained sequences.",
          "§4.3.1, Fig. 4.5", _predictor_learns(_REGULAR), _learns_and_generalises),
    Claim("The matching T-maze is solved optimally in all 10 runs.",
          "§4.3.2, Fig. 4.11", _solved(_MATCHING), at_least(*SOLVED_RUNS)),
    Claim("The agent reaches the goal in the optimal number of steps (3).",
          "§4.3.2, Fig. 4.12(a)", _optimal_steps(_MATCHING), at_most(*STEPS_RATIO)),
    Claim("The agent reaches the correct goal (terminal reward +5) in all runs.",
          "§4.3.2, Fig. 4.12(b)", _correct_goal(_MATCHING), at_least(*CORRECT_GOAL)),
    Claim("The TD error decreases to zero in all runs.",
          "§4.3.2, Fig. 4.13(a)", _td_decreases(_MATCHING), at_most(*TD_DECREASE)),
    Claim("Predictable observations and rewards are well estimated after training; the "
          "learning generalises to the test set and to longer sequences.",
          "§4.3.2, Fig. 4.10", _predictor_learns(_MATCHING), _learns_and_generalises),
    Claim("The initial signal is kept in the predictor's memory at the T-junction, in the "
          "first and in the last 1000 episodes.",
          "§4.3.2, Fig. 4.14; §4.3.3", _memory_keeps_signal, at_least(*SEPARATED)),
    Claim("The four conditions are separately represented in the actor's state nodes.",
          "§4.3.2, Fig. 4.15", _conditions_separate(_MATCHING, "state"), _separated_in_both),
    Claim("Most of the variability of the actor's state nodes is captured by the first two "
          "principal components.",
          "§4.3.2, Fig. 4.16", _leading_variance(_MATCHING, "state", 2), at_least(*MOST_VARIANCE)),
    Claim("The four conditions separate in the actor's hidden nodes in the last 1000 "
          "episodes, more than in the first 1000.",
          "§4.3.2, Figs. 4.17–4.19", _conditions_separate(_MATCHING, "hidden"), _separates_more),
    Claim("Most of the variability of the actor's hidden nodes is captured by the first three "
          "principal components.",
          "§4.3.2, Fig. 4.19(a)", _leading_variance(_MATCHING, "hidden", 3), at_least(*MOST_VARIANCE)),
    Claim("Digit matching T-maze: performance stays suboptimal, but the agent chooses the "
          "correct goal more often than chance.",
          "§4.3.3, Fig. 4.21", _digit_correct_goal, at_least(*ABOVE_CHANCE)),
]



# ---- chapter 5: T-mazes with Algorithm 2 -------------------------------------

MOST_RUNS_SOLVED = (0.8, 0.5)     # share of runs `solved`: "8 of 10" near-optimal (§5.3.1)
HIGH_CORRECT_GOAL = (0.8, 0.6)    # final correct-goal rate, mean over runs: "high" (§5.3.2)
NOISY_ERROR_DROP = 0.9            # final ÷ initial error of the pixel observation predictor,
                                  # whose noisy targets keep a high baseline (Fig. 5.17a)
NOT_SEPARATED = SEPARATED[1]      # initial-signal silhouette under which a memory "does not"
CLASS_STRUCTURE = (0.9, 0.5)      # class silhouette on PC1–3, processed ÷ raw images
RECONSTRUCTION_DROP = (0.5, 0.9)  # held-out reconstruction error, after ÷ before training
CH5_MEMORIES = ("memory_reward", "memory_observation")  # m^r, m^y (§5.2)


def _chapter5(digit: bool) -> Callable[[TMazeRun], bool]:
    """Chapter-5 claims are about the two-predictor model of Algorithm 2 on the matching
    T-maze with bit (§5.3.1) or noisy digit-image (§5.3.2) observations."""
    return lambda run: not run.chapter4 and run.matching and run.digit == digit


def _only_reward_memory_keeps_signal(
        applies: Callable[[TMazeRun], bool]) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not (applies(run) and set(CH5_MEMORIES) <= set(run.layers)):
            return None
        found = {layer: _phase_means(run, layer, "initial_signal") for layer in CH5_MEMORIES}
        if None in found.values():
            return None
        text = "; ".join(f"`{layer}`: first {means[0]:.2f}, last {means[1]:.2f}{note}"
                         for layer, (means, note) in found.items())
        # judged on the first phase: §5.3.2 finds the signal in m^r "even before the actor's
        # learning starts", while the paths still vary; once every episode takes the same
        # shortest path, any faint trace of s0 in m^y clusters perfectly under a silhouette
        return Measured(tuple(found[layer][0][0] for layer in CH5_MEMORIES),
                        f"silhouette of the initial signal on PC1–3 at the junction, mean over "
                        f"runs, first / last {run.phase_episodes} episodes — {text}")
    return measure


def _only_reward_memory_separates(value: tuple[float, float]) -> str:
    reward, observation = value
    return _held_only_if(at_least(*SEPARATED)(reward), observation < NOT_SEPARATED)


def _positive_return(
        applies: Callable[[TMazeRun], bool]) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not applies(run):
            return None
        ret = run.metric("final_discounted_return")
        return Measured((ret > 0).mean(), f"{int((ret > 0).sum())}/{len(ret)} runs with a "
                                          f"positive final discounted return, {_mean_sd(ret)}; "
                                          f"optimum {run.optimal_return:.4f}")
    return measure


def _good_but_never_optimal(
        applies: Callable[[TMazeRun], bool]) -> Callable[[TMazeRun], Measured | None]:
    def measure(run: TMazeRun) -> Measured | None:
        if not applies(run):
            return None
        rate, solved = run.metric("final_correct_goal_rate"), run.metric("solved")
        return Measured((rate.mean(), int(solved.sum())),
                        f"final correct-goal rate {_mean_sd(rate)}; final steps to the goal "
                        f"{_mean_sd(run.metric('final_steps_to_goal'))}, optimum "
                        f"{run.optimal_steps:g}; {int(solved.sum())}/{len(solved)} runs solved")
    return measure


def _high_but_never_optimal(value: tuple[float, int]) -> str:
    rate, n_solved = value
    return _held_only_if(at_least(*HIGH_CORRECT_GOAL)(rate), n_solved == 0)


def _class_structure_kept(run: TMazeRun) -> Measured | None:
    pre = run.preprocessing
    if pre is None:
        return None
    raw, processed = pre.silhouettes
    # Without class structure in the raw images (silhouette ≤ 0) there is none to keep.
    ratio = processed.mean() / raw if raw > 0 else float("nan")
    return Measured(ratio, f"silhouette of the {len(pre.class_names)} digit classes on PC1–3: "
                           f"raw images {raw:.2f}, processed {_mean_sd(processed)}; processed ÷ "
                           f"raw {ratio:.2f}")


def _reconstruction_falls(run: TMazeRun) -> Measured | None:
    pre = run.preprocessing
    if pre is None:
        return None
    before, after = pre.held_out("before").mean(), pre.held_out("after").mean()
    errors = pre.reconstruction.mean(axis=0)
    return Measured(after / before,
                    f"held-out reconstruction error {before:.4f} before → {after:.4f} after "
                    f"training = {after / before:.2f} ×, mean over {pre.n_runs} runs; training "
                    f"curve {errors[0]:.4f} (sweep 1) → {errors[-1]:.4f} (sweep {len(errors)})")


def _at_least_text(what: str, limits: tuple[float, float]) -> str:
    return f"{what}: held ≥ {limits[0]:g}, partly ≥ {limits[1]:g}"


def _at_most_text(what: str, limits: tuple[float, float]) -> str:
    return f"{what}: held ≤ {limits[0]:g}, partly ≤ {limits[1]:g}"


def _learning_text(drop: float) -> str:
    return (f"held: final ≤ {drop:g} × initial training error, ≥ {EARLY_SHARE:.0%} of the drop "
            f"within the first {EARLY_EPOCHS:.0%} of the epochs (where logged), final test ≤ "
            f"{GENERALISATION:g} × train and longer T ≤ {GENERALISATION:g} × trained T (where "
            "recorded); partly: the drop alone")


_BIT, _PIXEL = _chapter5(False), _chapter5(True)
_TD_TEXT = _at_most_text("last ÷ first 200-episode mean |δ|, worst run", TD_DECREASE)
_MEMORY_TEXT = (_at_least_text("reward-memory silhouette, first phase", SEPARATED)
                + f"; held needs the observation memory's < {NOT_SEPARATED:g} in the same phase, else partly")
_STATE_TEXT = _at_least_text("silhouette of the conditions in both phases", SEPARATED)
_HIDDEN_TEXT = (_at_least_text("silhouette of the conditions, last phase", SEPARATED)
                + "; at most partly unless above the first phase")
_VARIANCE_TEXT = _at_least_text("variance share, last phase, mean over runs", MOST_VARIANCE)


def _td_claim(applies: Callable[[TMazeRun], bool], source: str) -> Claim:
    return Claim("The TD error decreases over the episodes in all runs.", source,
                 _td_decreases(applies), at_most(*TD_DECREASE), _TD_TEXT)


def _memory_claim(applies: Callable[[TMazeRun], bool], source: str) -> Claim:
    return Claim("The reward predictor's memory at the T-junction separates by the initial "
                 "signal; the observation predictor's memory does not.", source,
                 _only_reward_memory_keeps_signal(applies), _only_reward_memory_separates,
                 _MEMORY_TEXT)


def _variance_claim(applies: Callable[[TMazeRun], bool], layer: str, n_pcs: int,
                    source: str) -> Claim:
    return Claim(f"Most of the variability of the actor's {layer} nodes is captured by the "
                 f"first {n_pcs} principal components.", source,
                 _leading_variance(applies, layer, n_pcs), at_least(*MOST_VARIANCE),
                 _VARIANCE_TEXT)


CH5_TMAZE_CLAIMS: list[Claim] = [
    Claim("The matching T-maze is solved near-optimally: 8 of 10 runs reach the optimal "
          "performance, two converge to sub-optimal ones.",
          "§5.3.1, Fig. 5.3", _solved(_BIT), at_least(*MOST_RUNS_SOLVED),
          _at_least_text("share of runs solved", MOST_RUNS_SOLVED)),
    Claim("The agent discriminates the correct goal at the T-junction in all runs, the "
          "sub-optimal ones included.",
          "§5.3.1, Fig. 5.5", _correct_goal(_BIT), at_least(*CORRECT_GOAL),
          _at_least_text("final correct-goal rate of the worst run", CORRECT_GOAL)),
    _td_claim(_BIT, "§5.3.1, Fig. 5.6(a)"),
    Claim("Predictable observations are well estimated by the observation predictor: its "
          "error falls rapidly in the first epochs and generalises to the test data and to "
          "longer sequences.",
          "§5.3.1, Fig. 5.2(a)", _predictor_learns(_BIT, "observation"),
          _learns_and_generalises, _learning_text(ERROR_DROP)),
    Claim("Predictable rewards are well estimated by the scalar-reward predictor, with the "
          "same generalisation to the test data and to longer sequences.",
          "§5.3.1, Fig. 5.2(b)", _predictor_learns(_BIT, "reward"), _learns_and_generalises,
          _learning_text(ERROR_DROP)),
    _memory_claim(_BIT, "§5.3.1, Figs. 5.7–5.8"),
    Claim("The four conditions are separately represented in the actor's state nodes.",
          "§5.3.1, Fig. 5.9", _conditions_separate(_BIT, "state"), _separated_in_both,
          _STATE_TEXT),
    _variance_claim(_BIT, "state", 3, "§5.3.1, Fig. 5.10(a)"),
    Claim("Distinct firing patterns of the actor's hidden nodes appear for each condition as "
          "the training proceeds.",
          "§5.3.1, Figs. 5.11–5.12", _conditions_separate(_BIT, "hidden"), _separates_more,
          _HIDDEN_TEXT),
    _variance_claim(_BIT, "hidden", 3, "§5.3.1, Fig. 5.13(a)"),
    Claim("The RBM preprocessor preserves the distribution of each digit class: the classes "
          "stay as separate in the processed observations as in the raw images.",
          "§5.3.2, Figs. 5.15(a)/5.16(a)", _class_structure_kept, at_least(*CLASS_STRUCTURE),
          _at_least_text("processed ÷ raw silhouette", CLASS_STRUCTURE)),
    Claim("Training the RBM preprocessor (contrastive divergence, CD-3) lowers its "
          "reconstruction error.",
          "§5.3.2, Observation preprocessor", _reconstruction_falls,
          at_most(*RECONSTRUCTION_DROP),
          _at_most_text("held-out error after ÷ before training", RECONSTRUCTION_DROP)),
    Claim("Despite the noise in the processed observations, the observation predictor "
          "improves, as in Fig. 5.2(a).",
          "§5.3.2, Fig. 5.17(a)", _predictor_learns(_PIXEL, "observation", NOISY_ERROR_DROP),
          _learns_and_generalises, _learning_text(NOISY_ERROR_DROP)),
    Claim("The scalar-reward predictor shows the trends of Fig. 5.2(b).",
          "§5.3.2, Fig. 5.17(b)", _predictor_learns(_PIXEL, "reward"), _learns_and_generalises,
          _learning_text(ERROR_DROP)),
    Claim("The positive discounted return in all 10 runs shows that the agent consistently "
          "learned to discriminate the correct goal.",
          "§5.3.2, Fig. 5.18(b)", _positive_return(_PIXEL), at_least(*SOLVED_RUNS),
          _at_least_text("share of runs with a positive final return", SOLVED_RUNS)),
    Claim("Steps to the goal and terminal reward improve toward their optimal values but never "
          "reach them, because of the noise in the observations.",
          "§5.3.2, Fig. 5.19(a–b)", _good_but_never_optimal(_PIXEL), _high_but_never_optimal,
          _at_least_text("final correct-goal rate, mean over runs", HIGH_CORRECT_GOAL)
          + "; held needs no run solved, else partly"),
    _td_claim(_PIXEL, "§5.3.2, Fig. 5.19(c)"),
    _memory_claim(_PIXEL, "§5.3.2, Figs. 5.20–5.21"),
    Claim("The actor's state nodes are well separated by condition, even before the learning "
          "started.",
          "§5.3.2, Figs. 5.22–5.23", _conditions_separate(_PIXEL, "state"),
          _separated_in_both, _STATE_TEXT),
    _variance_claim(_PIXEL, "state", 3, "§5.3.2, Fig. 5.23(a)"),
    Claim("Firing patterns of the actor's hidden nodes separate by condition as the training "
          "proceeds, regardless of the noisy observations.",
          "§5.3.2, Figs. 5.24–5.25(a)", _conditions_separate(_PIXEL, "hidden"),
          _separates_more, _HIDDEN_TEXT),
    _variance_claim(_PIXEL, "hidden", 2, "§5.3.2, Fig. 5.25(b)"),
]

TMAZE_CLAIMS = CH4_TMAZE_CLAIMS + CH5_TMAZE_CLAIMS


# ---- across the jobs of a sweep --------------------------------------------------

def _hidden_size_verdicts(sweep: Sweep) -> Measured | None:
    """The same-action-pair claim judged in jobs of one experiment that differ only in
    `actor.n_hidden` (the first such set with two sizes or more)."""
    for experiment in dict.fromkeys(j.experiment for j in sweep.jobs):
        for by_size in sweep.varying(experiment, "actor", "n_hidden"):
            found = {int(n): job.verdict(SAME_ACTION_PAIRS_SOURCE) for n, job in by_size.items()}
            found = {n: r.verdict for n, r in found.items() if r is not None}
            if len(found) >= 2:
                levels = [VERDICTS.index(v) for v in found.values()]
                text = "; ".join(f"{n} hidden: {v}" for n, v in sorted(found.items()))
                return Measured((max(levels) - min(levels), min(levels)),
                                f"`{experiment}`, verdict of the same-action-pair claim "
                                f"({SAME_ACTION_PAIRS_SOURCE}) by hidden size — {text}")
    return None


def _same_across_sizes(value: tuple[int, int]) -> str:
    spread, best = value
    if VERDICTS[best] == NOT_HELD:  # no size forms the clusters: nothing to compare
        return NOT_HELD
    return HELD if spread == 0 else PARTLY if spread == 1 else NOT_HELD


SWEEP_CLAIMS: list[Claim] = [
    Claim("The reward-dependent representations do not severely depend on the number of hidden "
          "nodes: with 10 and 40 hidden nodes the median firing patterns cluster as with 20.",
          "§3.5.3, Fig. 3.13", _hidden_size_verdicts, _same_across_sizes,
          "held: the same verdict (held or partly) at every size; partly: verdicts one level "
          "apart; not held otherwise, or not held at every size"),
]

# The order of the dissertation, for reports that gather claims from many runs.
CLAIM_ORDER: list[Claim] = FLOOR_CLAIMS + SWEEP_CLAIMS + TMAZE_CLAIMS


# ---- markdown ---------------------------------------------------------------

def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def claims_table(results: Sequence[ClaimResult]) -> list[str]:
    """One row per claim; a criterion column where any claim states its rule."""
    if not results:
        return ["No dissertation claim is addressed by this run's data."]
    criteria = any(r.claim.criterion for r in results)
    columns = ["claim", "source", "measured", *(["criterion"] if criteria else []), "verdict"]
    lines = [f"| {' | '.join(columns)} |", f"|{' --- |' * len(columns)}"]
    for r in results:
        cells = [r.claim.text, r.claim.source, r.measured.text,
                 *([r.claim.criterion or "—"] if criteria else [])]
        lines.append(f"| {' | '.join(map(_cell, cells))} | **{r.verdict}** |")
    return lines


def write_run_report(path: Path, analysis: RunAnalysis) -> None:
    """`analysis/report.md` of one run: header, claims table, figure and data links."""
    lines = [f"# {analysis.title}", ""]
    lines += [f"- **{key}**: {value}" for key, value in analysis.header]
    lines += ["", "## Claims", ""] + claims_table(analysis.results)
    lines += ["", "## Figures", ""]
    lines += [f"- [{name}.png]({name}.png) — {caption}"
              for name, (_, caption) in analysis.figures.items()]
    lines += ["", "## Data", ""] + [f"- [{name}]({name})" for name in analysis.data_files]
    path.write_text("\n".join(lines) + "\n")


@dataclass
class RunOutcome:
    """One line of a sweep report."""
    run_dir: Path
    experiment: str
    task: str
    status: str                       # "analyzed", "skipped: …" or "failed: …"
    verdicts: dict[str, int] = field(default_factory=dict)
    results: list[ClaimResult] = field(default_factory=list)
    figures: list[tuple[str, str]] = field(default_factory=list)  # (name, caption)


def jobs_table(sweep_dir: Path, out: Path, outcomes: Sequence[RunOutcome]) -> list[str]:
    """One row per job of a sweep, linking its report (from `out`) and counting its verdicts."""
    lines = ["| run | experiment | task | status | held | partly | not held |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for o in outcomes:
        name = os.path.relpath(o.run_dir, sweep_dir)
        if o.status == "analyzed":
            name = f"[{name}]({os.path.relpath(o.run_dir / 'analysis' / 'report.md', out)})"
        counts = " | ".join(str(o.verdicts.get(v, "")) for v in VERDICTS)
        lines.append(f"| {name} | {o.experiment} | {o.task} | {_cell(o.status)} | {counts} |")
    return lines
