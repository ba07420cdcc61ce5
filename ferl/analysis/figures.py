"""The figures every run gets, whatever trained it: learning curves, TD errors and prediction
errors (Figs. 3.4; 4.5–4.8, 4.10–4.13; 5.2–5.6, 5.17–5.19 where a chapter applies).

Every function takes plain arrays and returns a ``matplotlib.figure.Figure`` built without pyplot
(so no global figure state; rendered by the Agg canvas when saved). ``band`` and ``edges`` are the
drawing helpers the chapter figures share.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from ferl.analysis.layout import TITLE_PT, Space, colorbar, grid


def edges(centres: np.ndarray) -> np.ndarray:
    """Cell edges around sorted centres (pcolormesh), for unevenly logged epochs/episodes."""
    c = np.asarray(centres, dtype=np.float64)
    if len(c) == 1:
        return np.array([c[0] - 0.5, c[0] + 0.5])
    mid = 0.5 * (c[1:] + c[:-1])
    return np.concatenate([[2 * c[0] - mid[0]], mid, [2 * c[-1] - mid[-1]]])


def fitted_title(fig: Figure, title: str) -> str:
    """``title`` with its lines wrapped at spaces until it fits the figure's width as its title. A
    figure sized for its panels (the prediction errors: one column per episode length) can be
    narrower than its title: with one length only, 3.1 inches against a title of 7."""
    text, lines = fig.suptitle(title, fontsize=TITLE_PT), title.splitlines()
    chars = max(map(len, lines))
    while text.get_window_extent().width > 0.98 * fig.bbox.width and chars > 12:
        chars = int(chars * 0.85)
        text.set_text("\n".join(textwrap.fill(line, chars, break_long_words=False) for line in lines))
    return text.get_text()


# The space of each figure below (``ferl.analysis.layout``), in inches.
CURVES = Space(left=0.85, wspace=0.9, hspace=0.6, top=0.15)  # no panel titles
TD_ERRORS = Space(left=0.85, wspace=0.9, colorbar=1.0)
PREDICTION_ERRORS = Space(left=0.8, wspace=0.15, hspace=0.75, top=0.45, colorbar=1.3)


def band(ax, x: np.ndarray, mean: np.ndarray, sem: np.ndarray, optimum: float | None, color: str = "tab:blue") -> None:
    """A mean curve with its ± s.e.m. band (none where undefined), the optimum dotted."""
    ax.plot(x, mean, color=color, lw=1)
    ax.fill_between(x, mean - sem, mean + sem, color=color, alpha=0.3, lw=0)
    if optimum is not None:
        ax.axhline(optimum, color="k", ls=":", label=f"optimum {optimum:.5g}")
        ax.legend(loc="best", fontsize="small")


def learning_curves(
    x: np.ndarray, panels: Sequence[tuple], each_run: tuple, window: int, n_runs: int, xlabel: str, title: str
) -> Figure:
    """Figs. 3.4, 4.6–4.7 / 4.11–4.12 / 5.3–5.5 / 5.18–5.19(a–b): moving averages, mean ±
    s.e.m. over runs, and one measure in every run (Figs. 4.6(b), 5.3(b), 5.18(b)).

    ``panels`` holds (label, mean, sem, optimum or None) per measure, ``each_run``
    (label, moving averages (R, len(x)), optimum or None).
    """
    ncols = 2
    nrows = -(-(len(panels) + 1) // ncols)
    fig = Figure(figsize=(11, 3.4 * nrows))
    title = f"{title}\n{window}-point moving average, mean ± s.e.m. over {n_runs} runs; dotted: optimum"
    axes = grid(fig, nrows, ncols, CURVES, title, sharex=True).ravel()
    for ax, (label, mean, sem, optimum) in zip(axes, panels):
        band(ax, x, mean, sem, optimum)
        ax.set_ylabel(label)
    label, per_run, optimum = each_run
    ax = axes[len(panels)]
    for r, values in enumerate(per_run):
        ax.plot(x, values, lw=0.8, label=f"run {r}" if len(per_run) <= 10 else None)
    if optimum is not None:
        ax.axhline(optimum, color="k", ls=":")
    ax.set_ylabel(f"{label}, each run")
    if len(per_run) <= 10:
        ax.legend(fontsize="x-small", ncols=2, loc="best")
    for ax in axes[-ncols:]:
        ax.set_xlabel(xlabel)
    for k in range(len(panels) + 1, len(axes)):  # empty cells: label the panel above
        axes[k].set_axis_off()
        axes[k - ncols].xaxis.set_tick_params(labelbottom=True)
        axes[k - ncols].set_xlabel(xlabel)
    return fig


def td_errors(
    x: np.ndarray,
    mean: np.ndarray,
    sem: np.ndarray,
    window: int,
    n_runs: int,
    xlabel: str,
    title: str,
    sampled: tuple[np.ndarray, np.ndarray] | None = None,
) -> Figure:
    """Figs. 4.8/4.13/5.6/5.19(c–d): (a) moving average of the mean |δ|; (b) where recorded,
    the per-step δ of sampled episodes of one run (the dissertation's 1st run, run 0 here):
    ``sampled`` = (δ (episodes, steps), episode numbers)."""
    fig = Figure(figsize=(12 if sampled is not None else 7, 4.2))
    space = TD_ERRORS if sampled is not None else TD_ERRORS.but(colorbar=0.0)
    axes = grid(fig, 1, 2 if sampled is not None else 1, space, title).ravel()
    band(axes[0], x, mean, sem, None)
    axes[0].set_xlabel(xlabel)
    axes[0].set_ylabel(f"mean |δ| ({window}-point moving average)")
    axes[0].set_title(f"(a) mean ± s.e.m. over {n_runs} runs")
    if sampled is not None:
        td_run0, episodes = sampled
        # A signed δ: a symmetric diverging scale keeps 0 white.
        vmax = float(np.nanmax(np.abs(td_run0))) if np.isfinite(td_run0).any() else 1.0
        im = axes[1].pcolormesh(
            np.arange(td_run0.shape[1] + 1) - 0.5, edges(episodes), td_run0, cmap="RdBu_r", vmin=-vmax, vmax=vmax
        )
        axes[1].set_xlabel("step t of the episode (δ of the action at t)")
        axes[1].set_ylabel("episode")
        axes[1].set_title(f"(b) run 0, {len(episodes)} sampled episodes (blank: episode over)")
        colorbar(fig, im, axes[1:], space, label="TD error δ")
    return fig


def prediction_errors(
    train: np.ndarray,
    test: np.ndarray,
    lengths: np.ndarray,
    epochs: np.ndarray,
    trained_max: int,
    units: str,
    title: str,
) -> Figure:
    """Figs. 4.5/4.10/5.2/5.17: run-mean error (E, nT, Tmax+1); rows train/test, one column
    per T; ``units`` names the error measure on the colour bar."""
    n_lengths = len(lengths)
    # The untrained epoch 0 can be many times the rest; a 99th-percentile top (epoch 0
    # saturates) keeps the learning visible.
    both = np.concatenate([train.ravel(), test.ravel()])
    vmax = float(np.nanpercentile(both, 99))
    extend = "max" if np.nanmax(both) > vmax else "neither"
    fig = Figure(figsize=(1.6 * n_lengths + 1.5, 6))
    axes = grid(fig, 2, n_lengths, PREDICTION_ERRORS, fitted_title(fig, title), sharey=True)
    y_edges = edges(epochs)
    for row, (split, err) in enumerate((("train", train), ("test", test))):
        for k, T in enumerate(lengths):
            ax = axes[row, k]
            im = ax.pcolormesh(np.arange(T + 2) - 0.5, y_edges, err[:, k, : T + 1], cmap="viridis", vmin=0, vmax=vmax)
            ax.set_xticks(range(0, T + 1, 2 if T > 6 else 1))
            ax.set_title(f"{split}, T = {T}" + ("" if T <= trained_max else "\n(not trained)"), fontsize="small")
            if row == 1:
                ax.set_xlabel("step t")
        axes[row, 0].set_ylabel("predictor epoch")
    colorbar(fig, im, axes, PREDICTION_ERRORS, shrink=0.8, label=units, extend=extend)
    return fig
