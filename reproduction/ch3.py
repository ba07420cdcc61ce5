"""Chapter 3 (digit floor, §3.5.1–§3.5.3) as claims judged on a ``FloorRun``.

They apply to a run whose environment is the digit floor (``env.kind`` in run.json); the
reward-free condition of §3.5.3 is the floor's ``reward_condition`` "none".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ferl.analysis.claims import (
    HELD,
    NOT_HELD,
    PARTLY,
    Chapter,
    Claim,
    Measured,
    Numbering,
    all_or_some,
    at_least,
    at_most,
    mean_sd_text,
)
from ferl.analysis.records import Manifest
from reproduction.floor import ENV_KIND, PERCEPTUAL_PAIRS, FloorRun
from reproduction.scope import dissertation_components

# Thresholds of the verdict rules (fractions unless stated).
NEAR_OPTIMAL = (0.8, 0.5)  # reward/step ÷ optimum
MOST_IMAGES = (0.8, 0.5)  # greedy accuracy
CHANCE_TOLERANCE = (0.1, 0.2)  # |accuracy − 1/|A||
SATISFACTORY = 0.9  # accuracy ÷ accuracy at the training noise
OUTLIER_GAIN = (0.2, 0.05)  # rise of the median P(optimal | "1")
SELECTIVITY_GAIN = (2.0, 1.0)  # class selectivity after ÷ before
PAIR_RUNS = 0.6  # share of runs in which a pair must cluster
LOW_ACTIVATION = 0.1  # median activation counted as "very low"
# The jobs (experiments) that the sections describe: a sweep judges their claims there. §3.5.3's
# floor has noise tiles "N" in place of the "5"s (Fig. 3.8); CW is its default condition
# (Figs. 3.10(b), 3.11(a), 3.13 compare with it), the reward-free one Figs. 3.10(d), 3.11(c).
FLOOR_JOB, CODING_JOB, NO_REWARD_JOB = "ch3_floor", "ch3_coding_cw", "ch3_coding_noreward"


def _near_optimal(run: FloorRun) -> Measured | None:
    if run.reward_free:
        return None
    per_seed = np.asarray(run.summary["metrics"]["reward_per_step_last10pct"], dtype=float)
    ratio = per_seed.mean() / run.optimal_reward
    return Measured(ratio, f"{mean_sd_text(per_seed)} reward/step = {ratio:.2f} × optimum {run.optimal_reward:g}")


def _accuracy_at_training_noise(phase: str) -> Callable[[FloorRun], Measured | None]:
    def measure(run: FloorRun) -> Measured | None:
        if run.reward_free or not run.has_optimal_actions:
            return None
        acc = run.accuracy[phase][:, run.probe_level]
        text = f"greedy accuracy {mean_sd_text(acc)} at {100 * run.probe_noise:g} % test noise"
        if phase == "before":
            return Measured(abs(acc.mean() - run.chance), f"{text}; chance {run.chance:.2f}")
        return Measured(acc.mean(), text)

    return measure


def _noise_tolerance(train_noise: float, last_ok: float, first_bad: float) -> Callable[[FloorRun], Measured | None]:
    def measure(run: FloorRun) -> Measured | None:
        levels = run.noise_levels
        if (
            run.reward_free
            or not run.has_optimal_actions
            or not np.isclose(run.probe_noise, train_noise)
            or not np.isclose(levels, first_bad).any()
        ):
            return None
        acc = np.nanmean(run.accuracy["after"], axis=0)
        reference = acc[run.probe_level]
        ok = acc[(levels <= last_ok + 1e-9)].min() >= SATISFACTORY * reference
        bad = acc[np.isclose(levels, first_bad)][0] < SATISFACTORY * reference
        shown = "; ".join(f"{100 * x:g} %: {a:.2f}" for x, a in zip(levels, acc))
        return Measured(
            (ok, bad),
            f"mean greedy accuracy after training by test noise — {shown} "
            f"(satisfactory: ≥ {SATISFACTORY:g} × {reference:.2f})",
        )

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
    med = {phase: np.median(run.test[f"probs_{phase}"][:, c, :, a], axis=1) for phase in ("before", "after")}
    gain = float(np.mean(med["after"] - med["before"]))
    return Measured(
        gain,
        f"median P('{run.action_names[a]}' | \"1\") over test images: "
        f"before {mean_sd_text(med['before'])}, after {mean_sd_text(med['after'])}",
    )


def _class_selectivity(run: FloorRun) -> Measured | None:
    if run.reward_free:
        return None
    sel = {phase: run.selectivity(phase).mean() for phase in ("before", "after")}
    ratio = sel["after"] / sel["before"] if sel["before"] > 0 else np.inf
    return Measured(
        ratio,
        f"s.d. over classes of the median activation, mean over units and "
        f"runs: before {sel['before']:.3f}, after {sel['after']:.3f} "
        f"(ratio {ratio:.2f})",
    )


SOURCES = {
    "hidden": "MFR dendrogram (Eq. 3.12)",
    "hidden_marginal": "dendrogram of the policy-weighted activation of fn. 6",
}


def _pairs_cluster(
    pairs_of: Callable[[FloorRun], list[tuple[int, int]]], with_reward: bool, source: str = "hidden"
) -> Callable[[FloorRun], Measured | None]:
    def measure(run: FloorRun) -> Measured | None:
        pairs = pairs_of(run)
        if run.reward_free == with_reward or not pairs:
            return None
        hits = [run.cluster_hits(i, j, source) for i, j in pairs]
        text = "; ".join(
            f'("{run.classes[i]}", "{run.classes[j]}"): {sum(h)}/{len(h)} runs' for (i, j), h in zip(pairs, hits)
        )
        return Measured(
            [np.mean(h) >= PAIR_RUNS for h in hits],
            f"runs in which the pair is merged directly in the {SOURCES[source]}: {text}",
        )

    return measure


def _low_activation(run: FloorRun) -> Measured | None:
    if not run.reward_free:
        return None
    level = {
        phase: float(np.median(run.test[f"hidden_marginal_{phase}"], axis=2).mean()) for phase in ("before", "after")
    }
    verdict_value = (level["after"] <= LOW_ACTIVATION, level["after"] < level["before"])
    return Measured(
        verdict_value,
        f"median activation, mean over classes, units and runs: "
        f"before {level['before']:.3f}, after {level['after']:.3f}",
    )


def _low_rule(value: tuple[bool, bool]) -> str:
    very_low, lower = value
    return HELD if very_low else PARTLY if lower else NOT_HELD


def _mi_pairs(run: FloorRun) -> Measured | None:
    pairs = run.named_pairs(PERCEPTUAL_PAIRS)
    if not pairs or run.mi_linkage is None:
        return None
    labels = run.digit_classes
    flags = [run.mi_pair_clusters(run.classes[i], run.classes[j]) for i, j in pairs]
    text = "; ".join(
        f'("{run.classes[i]}", "{run.classes[j]}"): {"merged" if f else "not merged"}'
        for (i, j), f in zip(pairs, flags)
    )
    return Measured(flags, f"MI dendrogram of {len(labels)} digit classes — {text}")


def _noise_class_mi(run: FloorRun) -> Measured | None:
    if "N" not in run.classes or len(run.digit_classes) < 2:
        return None
    mi, n = run.mutual_information, run.classes.index("N")
    digits = [run.classes.index(c) for c in run.digit_classes]
    with_noise = mi[n, digits]
    among_digits = mi[np.ix_(digits, digits)][np.triu_indices(len(digits), 1)]
    value = (with_noise.min() > among_digits.max(), with_noise.mean() > among_digits.mean())
    return Measured(
        value,
        f'MI (nats) of "N" with digits: {with_noise.min():.3f}–'
        f"{with_noise.max():.3f}; among digits: {among_digits.min():.3f}–"
        f"{among_digits.max():.3f}",
    )


def _every_or_on_average(value: tuple[bool, bool]) -> str:
    every, on_average = value
    return HELD if every else PARTLY if on_average else NOT_HELD


SAME_ACTION_PAIRS_SOURCE = "§3.5.3, Figs. 3.11(a)/(b), 3.13"


_CLAIMS: list[Claim] = [
    Claim(
        "Despite the observation noise the agent performs at a nearly optimal level "
        "at the end of training (upper bound 8 reward/step).",
        "§3.5.1, Fig. 3.4, fn. 4",
        _near_optimal,
        at_least(*NEAR_OPTIMAL),
    ),
    Claim(
        "After training, most held-out test images at the training noise level make "
        "the optimal action greedy, for every digit.",
        "§3.5.1, Fig. 3.6(b)",
        _accuracy_at_training_noise("after"),
        at_least(*MOST_IMAGES),
    ),
    Claim(
        "Before training the agent has no behavioural tendency for a certain digit (greedy accuracy at chance).",
        "§3.5.1, Fig. 3.6(a)",
        _accuracy_at_training_noise("before"),
        at_most(*CHANCE_TOLERANCE),
    ),
    Claim(
        "Trained at 12.5 % noise, the agent performs satisfactorily up to 37.5 % test "
        "noise and deteriorates from 50 %.",
        "§3.5.1, fn. 5, Fig. 3.6(c)",
        _noise_tolerance(0.125, 0.375, 0.5),
        _robust_then_deteriorates,
    ),
    Claim(
        "Trained at 50 % noise, the agent performs satisfactorily up to 62.5 % test noise and deteriorates at 75 %.",
        "§3.5.1, Fig. 3.6(d)",
        _noise_tolerance(0.5, 0.625, 0.75),
        _robust_then_deteriorates,
    ),
    Claim(
        'Outlier detection: after training, typical "1"s make the optimal action '
        "(south) clearly more probable than before training.",
        "§3.5.2, Fig. 3.7",
        _outlier_detection,
        at_least(*OUTLIER_GAIN),
    ),
    Claim(
        "Before training hidden nodes show no preference for particular digits "
        "(vertical bands); after training their activation patterns differ between digits.",
        "§3.5.3, Fig. 3.10(a)–(c)",
        _class_selectivity,
        at_least(*SELECTIVITY_GAIN),
    ),
    Claim(
        "Pairs of tiles with the same optimal action form their own clusters of the median firing rates.",
        SAME_ACTION_PAIRS_SOURCE,
        _pairs_cluster(lambda run: run.same_action_pairs, with_reward=True),
        all_or_some,
    ),
    Claim(
        "Pairs of tiles with the same optimal action form their own clusters of the hidden "
        "activation defined in fn. 6 (actions weighted by the policy instead of uniformly).",
        "§3.5.3 fn. 6, Figs. 3.10–3.11",
        _pairs_cluster(lambda run: run.same_action_pairs, with_reward=True, source="hidden_marginal"),
        all_or_some,
    ),
    Claim(
        "Without reward, the activation of all hidden nodes becomes very low.",
        "§3.5.3, Fig. 3.10(d)",
        _low_activation,
        _low_rule,
    ),
    Claim(
        'Without reward, perceptually similar "1" and "7", and "3" and "8", are grouped together.',
        "§3.5.3, Fig. 3.11(c)",
        _pairs_cluster(lambda run: run.named_pairs(PERCEPTUAL_PAIRS), with_reward=False),
        all_or_some,
    ),
    Claim(
        'Clustering the digits by pixel–label mutual information groups "1" with "7" '
        'and "3" with "8", as in Fig. 3.11(c).',
        "§3.5.3, Fig. 3.12",
        _mi_pairs,
        all_or_some,
    ),
    Claim(
        'The noise tile "N" has a much higher mutual information with every digit than '
        "the digits have with each other.",
        "§3.5.3, Fig. 3.12",
        _noise_class_mi,
        _every_or_on_average,
    ),
]


def _job(source: str, text: str) -> str:
    if not source.startswith("§3.5.3"):
        return FLOOR_JOB  # §3.5.1–§3.5.2
    return NO_REWARD_JOB if text.startswith("Without reward") else CODING_JOB


CLAIMS: list[Claim] = [replace(c, experiment=_job(c.source, c.text)) for c in _CLAIMS]


def applies(manifest: Manifest) -> bool:
    return manifest.env_kind == ENV_KIND and dissertation_components(manifest)


CHAPTER = Chapter(
    "the FERL actor on the digit floor (chapter 3, §3.4–§3.5)",
    applies,
    lambda manifest: Numbering(learning_curves="Fig. 3.4"),
    CLAIMS,
)
