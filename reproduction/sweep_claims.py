"""The claims that only a comparison of a sweep's jobs can judge (§3.5.3, Fig. 3.13)."""

from __future__ import annotations

from ferl.analysis.claims import HELD, NOT_HELD, PARTLY, VERDICTS, Claim, Measured
from ferl.analysis.sweep import Sweep
from reproduction.ch3 import CODING_JOB, SAME_ACTION_PAIRS_SOURCE


def _hidden_size_verdicts(sweep: Sweep) -> Measured | None:
    """The same-action-pair claim judged in jobs of one experiment that differ only in
    ``actor.n_hidden`` (the first such set with two sizes or more; §3.5.3's job first)."""
    experiments = dict.fromkeys(j.experiment for j in sweep.jobs)
    for experiment in sorted(experiments, key=lambda name: name != CODING_JOB):
        for by_size in sweep.varying(experiment, "actor", "n_hidden"):
            found = {int(n): job.verdict(SAME_ACTION_PAIRS_SOURCE) for n, job in by_size.items()}
            found = {n: r.verdict for n, r in found.items() if r is not None}
            if len(found) >= 2:
                levels = [VERDICTS.index(v) for v in found.values()]
                text = "; ".join(f"{n} hidden: {v}" for n, v in sorted(found.items()))
                return Measured(
                    (max(levels) - min(levels), min(levels)),
                    f"`{experiment}`, verdict of the same-action-pair claim "
                    f"({SAME_ACTION_PAIRS_SOURCE}) by hidden size — {text}",
                )
    return None


def _same_across_sizes(value: tuple[int, int]) -> str:
    spread, best = value
    if VERDICTS[best] == NOT_HELD:  # no size forms the clusters: nothing to compare
        return NOT_HELD
    return HELD if spread == 0 else PARTLY if spread == 1 else NOT_HELD


SWEEP_CLAIMS: list[Claim] = [
    Claim(
        "The reward-dependent representations do not severely depend on the number of hidden "
        "nodes: with 10 and 40 hidden nodes the median firing patterns cluster as with 20.",
        "§3.5.3, Fig. 3.13",
        _hidden_size_verdicts,
        _same_across_sizes,
        "held: the same verdict (held or partly) at every size; partly: verdicts one level "
        "apart; not held otherwise, or not held at every size",
    ),
]
