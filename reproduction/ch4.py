"""Chapter 4 (Algorithm 1, §4.3.1–§4.3.3) as claims judged on a ``TMazeRun``, and its figure
numbers.

They apply to a T-maze run (``env.kind`` in run.json) whose only predictor predicts the
observation and the reward bits together (role ``joint``, Eq. 4.8); each claim is about one maze
variant: regular, matching, or digit matching (image observations).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

from ferl.analysis.claims import (
    Chapter,
    Claim,
    LayerFigures,
    Measured,
    Numbering,
    at_least,
    at_most,
    mean_sd_text,
    only,
)
from ferl.analysis.records import JOINT, Manifest
from reproduction.scope import dissertation_algorithm
from reproduction.tmaze import ENV_KIND, TMazeRun
from reproduction.tmaze_claims import (
    CORRECT_GOAL,
    GENERALISATION_TEXT,
    SEPARATED,
    SEPARATED_AFTER_TEXT,
    SEPARATED_IN_BOTH_TEXT,
    SOLVED_RUNS,
    STEPS_RATIO,
    TD_TEXT,
    TD_TO_ZERO_TEXT,
    Applies,
    correct_goal,
    learns_and_generalises,
    optimal_steps,
    phase_means,
    predictor_learns,
    separated_after_learning,
    separated_in_both,
    separates_more,
    separation_claim,
    solved,
    td_decreases,
    td_falls,
    td_falls_in_all_runs,
    td_to_zero,
    variance_claim,
)

ABOVE_CHANCE = (0.6, 0.55)  # final correct-goal rate, mean over runs (chance 0.5)
# The jobs (experiments) that the sections describe: a sweep judges their claims there.
REGULAR_JOB, MATCHING_JOB, DIGIT_JOB = "table4_1_regular", "table4_1_matching", "table4_2_digit"

LAYERS = {
    "memory": LayerFigures("Fig. 4.14(a)", "Fig. 4.14(b)"),
    "state": LayerFigures("Fig. 4.15(a)", "Figs. 4.15(b)/4.16"),
    "hidden": LayerFigures("Fig. 4.17(a)", "Figs. 4.17(b)/4.19(a)", "Fig. 4.19(b)"),
}
REGULAR = Numbering("Figs. 4.6–4.7", "Fig. 4.8", "Fig. 4.5", {}, "Tables 4.1/4.2", LAYERS)
MATCHING = Numbering("Figs. 4.11–4.12", "Fig. 4.13", "Fig. 4.10", {}, "Tables 4.1/4.2", LAYERS)


def variant_is(variant: str) -> Applies:
    """A chapter-4 claim is about one T-maze variant."""
    return lambda run: run.variant == variant


def _memory_keeps_signal(run: TMazeRun) -> Measured | None:
    if not (run.matching and run.memory_layers):
        return None
    kept = {layer: phase_means(run, layer, "initial_signal") for layer in run.memory_layers}
    kept = {layer: v for layer, v in kept.items() if v is not None}
    if not kept:
        return None
    # Kept = separated in both phases, in any recorded memory layer.
    best = max(means.min() for means, _ in kept.values())
    text = "; ".join(
        f"`{layer}`: first {means[0]:.2f}, last {means[1]:.2f}{note}" for layer, (means, note) in kept.items()
    )
    return Measured(
        best, f"silhouette of the initial signal on PC1–3 of the memory at the junction, mean over runs — {text}"
    )


def _digit_correct_goal(run: TMazeRun) -> Measured:
    rate, runs_solved = run.metric("final_correct_goal_rate"), run.metric("solved")
    ret = run.metric("final_discounted_return")
    return Measured(
        rate.mean(),
        f"final correct-goal rate {mean_sd_text(rate)} (chance 0.5); "
        f"{int(runs_solved.sum())}/{len(runs_solved)} runs solved; final "
        f"discounted return {mean_sd_text(ret)}, optimum "
        f"{run.optimal_return:.4f}",
    )


_REGULAR, _MATCHING = variant_is("regular"), variant_is("matching")


def _maze_results(applies: Applies, job: str, texts: list[tuple[str, str]], to_zero: bool) -> list[Claim]:
    """The five results that §4.3.1 and §4.3.2 each report for their maze, from its texts and
    sources: solved in every run, optimal steps, the correct goal, a decreasing TD error
    (Figs. 4.6–4.8, 4.11–4.13; ``to_zero``: §4.3.2's "decreases to zero") and the predictor's
    learning (Figs. 4.5, 4.10), judged on the maze's ``job``."""
    judged: list[tuple[Callable[[TMazeRun], Measured | None], Callable[[Any], str], str]] = [
        (solved, at_least(*SOLVED_RUNS), ""),
        (optimal_steps, at_most(*STEPS_RATIO), ""),
        (correct_goal, at_least(*CORRECT_GOAL), ""),
        (td_decreases, td_to_zero, TD_TO_ZERO_TEXT) if to_zero else (td_falls, td_falls_in_all_runs, TD_TEXT),
        (predictor_learns(JOINT), learns_and_generalises, GENERALISATION_TEXT),
    ]
    return [
        Claim(text, source, only(applies, measure), rule, criterion, experiment=job)
        for (text, source), (measure, rule, criterion) in zip(texts, judged, strict=True)
    ]


CLAIMS: list[Claim] = (
    _maze_results(
        _REGULAR,
        REGULAR_JOB,
        [
            ("The regular T-maze is solved optimally in all 10 runs.", "§4.3.1, Fig. 4.6"),
            ("The agent learns to reach the goal in the optimal number of steps (3).", "§4.3.1, Fig. 4.7(a)"),
            ("The agent learns to reach the correct goal (terminal reward +5) in all 10 runs.", "§4.3.1, Fig. 4.7(b)"),
            ("The TD error decreases over the episodes in all runs.", "§4.3.1, Fig. 4.8(a)"),
            (
                "The predictor's error decreases rapidly in the first epochs and generalises to the test "
                "set and to longer, untrained sequences.",
                "§4.3.1, Fig. 4.5",
            ),
        ],
        to_zero=False,
    )
    + _maze_results(
        _MATCHING,
        MATCHING_JOB,
        [
            ("The matching T-maze is solved optimally in all 10 runs.", "§4.3.2, Fig. 4.11"),
            ("The agent reaches the goal in the optimal number of steps (3).", "§4.3.2, Fig. 4.12(a)"),
            ("The agent reaches the correct goal (terminal reward +5) in all runs.", "§4.3.2, Fig. 4.12(b)"),
            ("The TD error decreases to zero in all runs.", "§4.3.2, Fig. 4.13(a)"),
            (
                "Predictable observations and rewards are well estimated after training; the learning "
                "generalises to the test set and to longer sequences.",
                "§4.3.2, Fig. 4.10",
            ),
        ],
        to_zero=True,
    )
    + [
        replace(claim, experiment=MATCHING_JOB)
        for claim in [
            Claim(
                "The initial signal is kept in the predictor's memory at the T-junction, in the "
                "first and in the last 1000 episodes.",
                "§4.3.2, Fig. 4.14; §4.3.3",
                _memory_keeps_signal,
                at_least(*SEPARATED),
            ),
            separation_claim(
                _MATCHING,
                "state",
                separated_after_learning,
                "The four conditions are separately represented in the actor's state nodes.",
                "§4.3.2, Fig. 4.15",
                SEPARATED_AFTER_TEXT,
                (separated_in_both, SEPARATED_IN_BOTH_TEXT),
            ),
            variance_claim(_MATCHING, "state", 2, "§4.3.2, Fig. 4.16", "two"),
            separation_claim(
                _MATCHING,
                "hidden",
                separates_more,
                "The four conditions separate in the "
                "actor's hidden nodes in the last 1000 episodes, more than in the first "
                "1000.",
                "§4.3.2, Figs. 4.17–4.19",
            ),
            variance_claim(_MATCHING, "hidden", 3, "§4.3.2, Fig. 4.19(a)", "three"),
        ]
    ]
    + [
        Claim(
            "Digit matching T-maze: performance stays suboptimal, but the agent chooses the "
            "correct goal more often than chance.",
            "§4.3.3, Fig. 4.21",
            only(variant_is("digit matching"), _digit_correct_goal),
            at_least(*ABOVE_CHANCE),
            experiment=DIGIT_JOB,
        ),
    ]
)


def applies(manifest: Manifest) -> bool:
    return (
        manifest.env_kind == ENV_KIND and list(manifest.roles.values()) == [JOINT] and dissertation_algorithm(manifest)
    )


CHAPTER = Chapter(
    "Algorithm 1, one joint predictor (chapter 4)",
    applies,
    lambda manifest: MATCHING if manifest.env.get("matching") else REGULAR,
    CLAIMS,
)
