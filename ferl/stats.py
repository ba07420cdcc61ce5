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

So are the episodic tasks' final-window metrics (docs/records.md): ``final_metrics`` over the last
W episodes, the ``solved`` criterion, ``sample_efficiency`` (the first window of W episodes that
meets it) and ``window_means``. W is the run's ``trainer.final_window``, recorded with its episodes
(``episodes.npz``'s ``final_window``, and ``records/run.json``); the analysis reads it back from
there. ``FINAL_WINDOW`` (200 episodes: the moving average of Figs. 4.6–4.8 and 4.11–4.13) is only
the window of runs that recorded none.
"""

import math
from collections.abc import Sequence

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
    x = np.asarray([np.nan if v is None else v for v in np.ravel(np.asarray(values, dtype=object))], dtype=np.float64)
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


FINAL_WINDOW = 200  # episodes; the window of a run that recorded none (module doc)
SOLVED_SHARE = 0.95  # solved: return ≥ 0.95 × optimum and every outcome rate ≥ 0.95 (docs/records.md)


def window_means(x: np.ndarray, window: int) -> np.ndarray:
    """Means of every full window of ``window`` episodes (R, N) → (R, N − window + 1), in float64."""
    c = np.cumsum(np.pad(x.astype(np.float64), ((0, 0), (1, 0))), 1)
    return (c[:, window:] - c[:, :-window]) / window


def meets_solved(returns: np.ndarray, rates: dict, optimal_return: float) -> np.ndarray:
    """The ``solved`` criterion on window means: return ≥ 0.95 × optimum and every outcome rate
    (the correct-goal rate) ≥ 0.95."""
    solved = returns >= SOLVED_SHARE * optimal_return
    for values in rates.values():
        solved &= values >= SOLVED_SHARE
    return solved


def sample_efficiency(
    episodes: dict, random_steps: np.ndarray, optimum: tuple[str, float] | None, window: int, rates: list
) -> dict:
    """Environment steps per run (random collection included: ``random_steps`` (R,)): all of them,
    and, where there is an ``optimum`` (record, optimal value), those until the first window of
    ``window`` episodes that meets the ``solved`` criterion (its last episode included; None if
    none does), with that episode's number (1-based)."""
    steps = episodes["steps"].astype(np.int64)
    used = np.asarray(random_steps)[:, None] + np.cumsum(steps, 1)  # (R, N) steps after each episode
    if optimum is None:
        return {"env_steps_total": used[:, -1].tolist()}
    key, best = optimum
    solved = meets_solved(
        window_means(episodes[key], window), {n: window_means(episodes[n], window) for n in rates}, best
    )
    first = [int(np.argmax(row)) + window - 1 if row.any() else None for row in solved]
    return {
        "env_steps_total": used[:, -1].tolist(),
        "env_steps_to_solve": [int(used[r, k]) if k is not None else None for r, k in enumerate(first)],
        "episodes_to_solve": [k + 1 if k is not None else None for k in first],
    }


def final_metrics(
    episodes: dict,
    optimum: tuple[str, float] | None,
    window: int,
    rates: list,
    averages: Sequence[str] = (),
    goal: bool = True,
) -> dict:
    """The episodic metrics of summary.json over the last ``window`` episodes, one value per run:
    discounted return, steps to the goal (``goal``: an environment that has one, ``has_goal``), the
    rate of every boolean outcome (``final_correct_goal_rate``), the mean of every float one
    (``final_return``) and its best window mean over all episodes (``best_return``) and, given an
    optimum, solved."""
    last = slice(-window, None)

    def final(name: str) -> np.ndarray:
        # in float64: NumPy sums float32 in an order that depends on the CPU's vector width (AVX-512
        # or AVX2); a float64 sum of float32 numbers is exact, in any order, unless they span more
        # than ~29 binary orders of magnitude
        return episodes[name][:, last].mean(1, dtype=np.float64)

    rate = {name: final(name) for name in rates}
    metrics = {
        "final_discounted_return": final("discounted_return").tolist(),
        **({"final_steps_to_goal": final("steps").tolist()} if goal else {}),
        **{f"final_{name}_rate": values.tolist() for name, values in rate.items()},
        **{f"final_{name}": final(name).tolist() for name in averages},
        # the best window mean over the training: POPGym's "mean maximum episodic return" (MMER,
        # Morad et al. 2023) with a window of episodes as its batch
        **{
            f"best_{name}": window_means(episodes[name], min(window, episodes[name].shape[1])).max(1).tolist()
            for name in averages
        },
    }
    if optimum is not None:
        key, best = optimum
        metrics["solved"] = meets_solved(final(key), rate, best).astype(int).tolist()
    return metrics


def has_goal(optimal: dict) -> bool:
    """Whether an environment's episodes end at a goal, which it states by the optimal steps to
    reach it (the T-mazes' ``steps_to_goal``): only then is an episode's length a
    ``final_steps_to_goal``. A Gymnasium task states none (a CartPole's episode ends by falling)."""
    return optimal.get("steps_to_goal") is not None


def solved_against(optimal: dict) -> tuple[str, float] | None:
    """(record, optimum) that ``solved`` compares a run's final return with: the discounted return
    where the environment states its optimum (the T-mazes), else the undiscounted ``return`` where
    it states that (a Gymnasium id with ``optimal_return``), else None: no ``solved`` metric."""
    for key in ("discounted_return", "return"):
        if optimal.get(key) is not None:
            return key, float(optimal[key])
    return None
