"""Summary statistics over the runs of a batch, and the one flattening of metric names.

Every table, figure band and report sentence that says "mean ± s.d." or "mean ± s.e.m." over
runs uses these definitions (the terminal table of ``train.py``, TensorBoard's HParams metrics,
``ferl.runs``, the sweep tables and the reports of ``ferl.analysis``):

* the values are one per run; a run without a value — ``null`` in ``summary.json`` (nothing to
  score, e.g. no optimal action without reward) or NaN (a diverged run) — is left out, and ``n``
  counts the runs that remain;
* s.d. is the sample standard deviation, ``ddof = 1``: √(Σ (x − x̄)² / (n − 1));
* s.e.m. is s.d. / √n;
* both are undefined (NaN) for fewer than two runs: one run says nothing about the spread.

``summary.json`` metrics are per-run lists, or an object of per-run lists keyed by a level (the
digit floor's ``greedy_accuracy`` per test-noise level). Flattened, such a metric is one entry per
level named ``<metric>/<level>`` (``greedy_accuracy/0.125``): the name ``optimized_metric``
takes, the HParams column (``hparam/<metric>/<level>``) and the column of ``ferl.runs``.

The digit floor's greedy accuracy (Fig. 3.6) is here too: the trainer's summary and the analysis
of its records score the same counts with it.
"""
import math

import numpy as np

LEVEL_SEPARATOR = "/"


def flat_metrics(metrics: dict) -> dict[str, list]:
    """summary.json's ``metrics`` as flat name → per-run values (``<metric>/<level>`` for levels)."""
    flat = {}
    for name, values in metrics.items():
        if isinstance(values, dict):
            flat.update({f"{name}{LEVEL_SEPARATOR}{level}": v for level, v in values.items()})
        else:
            flat[name] = values
    return flat


def run_values(values) -> np.ndarray:
    """The runs' values as float64, without the runs that have none (null or NaN)."""
    x = np.asarray([np.nan if v is None else v for v in np.ravel(np.asarray(values, dtype=object))],
                   dtype=np.float64)
    return x[np.isfinite(x)]


def mean_sd(values) -> tuple[float, float, int]:
    """(mean, s.d., n) over the runs that have a value; NaN where undefined (see module doc)."""
    x = run_values(values)
    n = len(x)
    mean = float(x.mean()) if n else math.nan
    sd = float(x.std(ddof=1)) if n > 1 else math.nan
    return mean, sd, n


def mean_sem(values) -> tuple[float, float, int]:
    """(mean, s.e.m., n) over the runs that have a value; NaN where undefined (see module doc)."""
    mean, sd, n = mean_sd(values)
    return mean, sd / math.sqrt(n) if n > 1 else math.nan, n


def sem(values, axis: int = 0) -> np.ndarray:
    """s.e.m. along ``axis`` (the runs) of an array with a value for every run, such as a
    learning curve per run (R, T); NaN for fewer than two runs."""
    x = np.asarray(values, dtype=np.float64)
    n = x.shape[axis]
    if n < 2:
        return np.full(np.delete(x.shape, axis), np.nan)
    return x.std(axis=axis, ddof=1) / math.sqrt(n)


def greedy_accuracy(greedy_counts: np.ndarray, optimal_action) -> np.ndarray:
    """Fraction of test images whose greedy action is optimal (Fig. 3.6).

    ``greedy_counts`` is (R, L, C, nA): per run, test-noise level and class, how many of the n
    test images made each action greedy. Classes without a unique optimal action (the goal;
    every class without reward) are excluded. Returns (R, L); NaN when no class is scored.
    """
    counts = np.asarray(greedy_counts, dtype=np.float64)
    actions = np.asarray(optimal_action)
    scored = np.flatnonzero(actions >= 0)
    if scored.size == 0:
        return np.full(counts.shape[:2], np.nan)
    correct = counts[:, :, scored, actions[scored]].sum(axis=-1)
    return correct / counts[:, :, scored, :].sum(axis=(-1, -2))
