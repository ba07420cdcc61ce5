"""Fig. 3.6 across jobs: the greedy accuracy after training on a grid of training noise × test
noise, from the jobs of one experiment that differ only in the environment's ``noise``
(records/run.json) and test every noise level (a ``greedy_accuracy`` per level in summary.json).
``make reproduce``'s noise_grid sweep runs such jobs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ferl import stats
from ferl.analysis.io import fmt, write_csv
from ferl.analysis.report import RunAnalysis
from ferl.analysis.sweep import Job, Sweep
from reproduction.floor_figures import noise_grid_heatmap


@dataclass(frozen=True)
class NoiseGrid:
    experiment: str
    train: np.ndarray  # (T,) training noise levels, ascending
    test: np.ndarray  # (L,) test noise levels, ascending
    mean: np.ndarray  # (T, L) greedy accuracy after training, mean over runs
    sem: np.ndarray  # (T, L) s.e.m. over runs


def noise_grids(sweep: Sweep) -> list[NoiseGrid]:
    """One grid per set of jobs that differ only in ``env.noise``, at ≥ 2 levels, and record a
    greedy accuracy per test-noise level."""
    grids = []
    for experiment in dict.fromkeys(j.experiment for j in sweep.jobs):
        for by_level in sweep.varying(experiment, "env", "noise"):
            by_level = {float(k): j for k, j in by_level.items() if "greedy_accuracy" in j.summary.get("metrics", {})}
            if len(by_level) >= 2:
                grids.append(_noise_grid(experiment, by_level))
    return grids


def _noise_grid(experiment: str, by_level: dict[float, Job]) -> NoiseGrid:
    train = np.array(sorted(by_level))
    accuracy = {level: job.summary["metrics"]["greedy_accuracy"] for level, job in by_level.items()}
    test = np.array(sorted({float(k) for acc in accuracy.values() for k in acc}))
    mean, sem = np.full((len(train), len(test)), np.nan), np.full((len(train), len(test)), np.nan)
    for t, level in enumerate(train):
        for key, values in accuracy[level].items():
            k = int(np.flatnonzero(np.isclose(test, float(key)))[0])
            mean[t, k], sem[t, k], _ = stats.mean_sem(values)
    return NoiseGrid(experiment, train, test, mean, sem)


def report(sweep: Sweep, out: Path, analysis: RunAnalysis) -> list[str]:
    """Write each grid's CSV and add its heatmap to the sweep's figures; no lines of its own (the
    figures are listed with the sweep's others)."""
    for g in noise_grids(sweep):
        name = f"fig3_6_noise_grid_{g.experiment}"
        write_csv(
            out / f"{name}.csv",
            ["train_noise", "test_noise", "accuracy_mean", "accuracy_sem"],
            [
                (fmt(tr), fmt(te), fmt(g.mean[t, k]), fmt(g.sem[t, k]))
                for t, tr in enumerate(g.train)
                for k, te in enumerate(g.test)
            ],
        )
        analysis.data_files.append(f"{name}.csv")
        analysis.figures[name] = (
            noise_grid_heatmap(g.train, g.test, g.mean, g.experiment),
            f"Fig. 3.6 (all panels' noise pairs): greedy accuracy after "
            f"training, `{g.experiment}`, training × test noise",
        )
    return []
