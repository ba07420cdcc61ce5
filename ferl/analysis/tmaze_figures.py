"""Figures of the T-mazes (chapter 4, Figs. 4.5–4.19; chapter 5, Figs. 5.2–5.25), drawn from
run records.

Like `floor_figures`, every function takes plain arrays and returns a
`matplotlib.figure.Figure` built without pyplot. The numbers come from
`ferl.analysis.tmaze` and, for the RBM preprocessor of §5.3.2, `ferl.analysis.preprocessor`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

ERROR_UNITS = {  # predictor → its recorded error measure (Eq. 4.8; Figs. 5.2/5.17 (a) and (b))
    "joint": "Eq. 4.8 weighted absolute error\nρ_y Σ|y − ŷ| + ρ_r Σ|r − r̂|",
    "observation": "absolute error Σ|y − ŷ|\n(processed observations)",
    "reward": "squared error (r − r̂)²\n(scalar reward)",
}
MARKER_SIZES = (6.0, 60.0)  # scatter area of the shortest / longest episode (Fig. 4.14b)


def _edges(centres: np.ndarray) -> np.ndarray:
    """Cell edges around sorted centres (pcolormesh), for unevenly logged epochs/episodes."""
    c = np.asarray(centres, dtype=np.float64)
    if len(c) == 1:
        return np.array([c[0] - 0.5, c[0] + 0.5])
    mid = 0.5 * (c[1:] + c[:-1])
    return np.concatenate([[2 * c[0] - mid[0]], mid, [2 * c[-1] - mid[-1]]])


def _condition_colors(n: int) -> list:
    return [colormaps["tab10"](k) for k in range(n)]


def prediction_errors(train: np.ndarray, test: np.ndarray, lengths: np.ndarray,
                      epochs: np.ndarray, trained_max: int, units: str, title: str) -> Figure:
    """Figs. 4.5/4.10/5.2/5.17: run-mean error (E, nT, Tmax+1); rows train/test, one column
    per T; `units` names the error measure on the colour bar."""
    n_lengths = len(lengths)
    # The untrained epoch 0 can be many times the rest; a 99th-percentile top (epoch 0
    # saturates) keeps the learning visible.
    both = np.concatenate([train.ravel(), test.ravel()])
    vmax = float(np.nanpercentile(both, 99))
    extend = "max" if np.nanmax(both) > vmax else "neither"
    fig = Figure(figsize=(1.6 * n_lengths + 1.5, 6), layout="constrained")
    axes = fig.subplots(2, n_lengths, sharey=True, squeeze=False)
    y_edges = _edges(epochs)
    for row, (split, err) in enumerate((("train", train), ("test", test))):
        for k, T in enumerate(lengths):
            ax = axes[row, k]
            im = ax.pcolormesh(np.arange(T + 2) - 0.5, y_edges, err[:, k, :T + 1],
                               cmap="viridis", vmin=0, vmax=vmax)
            ax.set_xticks(range(0, T + 1, 2 if T > 6 else 1))
            ax.set_title(f"{split}, T = {T}" + ("" if T <= trained_max else "\n(not trained)"),
                         fontsize="small")
            if row == 1:
                ax.set_xlabel("step t")
        axes[row, 0].set_ylabel("predictor epoch")
    fig.colorbar(im, ax=axes, label=units, shrink=0.8, extend=extend)
    fig.suptitle(title)
    return fig


def _curve(ax, episodes: np.ndarray, mean: np.ndarray, sem: np.ndarray,
           optimum: float | None, color: str = "tab:blue") -> None:
    ax.plot(episodes, mean, color=color, lw=1)
    ax.fill_between(episodes, mean - sem, mean + sem, color=color, alpha=0.3, lw=0)
    if optimum is not None:
        ax.axhline(optimum, color="k", ls=":", label=f"optimum {optimum:.5g}")
        ax.legend(loc="best", fontsize="small")


def learning_curves(episodes: np.ndarray, panels: Sequence[tuple], each_run: tuple,
                    window: int, n_runs: int, title: str) -> Figure:
    """Figs. 4.6–4.7 / 4.11–4.12 / 5.3–5.5 / 5.18–5.19(a–b): moving averages, mean ± s.e.m.
    over runs, and one measure in every run (Figs. 4.6(b), 5.3(b), 5.18(b)).

    `panels` holds (label, mean, sem, optimum or None) per measure, `each_run`
    (label, moving averages (R, len(episodes)), optimum or None).
    """
    ncols = 2
    nrows = -(-(len(panels) + 1) // ncols)
    fig = Figure(figsize=(11, 3.4 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, sharex=True).ravel()
    for ax, (label, mean, sem, optimum) in zip(axes, panels):
        _curve(ax, episodes, mean, sem, optimum)
        ax.set_ylabel(label)
    label, per_run, optimum = each_run
    ax = axes[len(panels)]
    for r, values in enumerate(per_run):
        ax.plot(episodes, values, lw=0.8, label=f"run {r}" if len(per_run) <= 10 else None)
    if optimum is not None:
        ax.axhline(optimum, color="k", ls=":")
    ax.set_ylabel(f"{label}, each run")
    if len(per_run) <= 10:
        ax.legend(fontsize="x-small", ncols=2, loc="best")
    for ax in axes[-ncols:]:
        ax.set_xlabel("actor episode")
    for k in range(len(panels) + 1, len(axes)):  # empty cells: label the panel above
        axes[k].set_axis_off()
        axes[k - ncols].xaxis.set_tick_params(labelbottom=True)
        axes[k - ncols].set_xlabel("actor episode")
    fig.suptitle(f"{title}\n{window}-episode moving average, mean ± s.e.m. over {n_runs} runs; "
                 "dotted: optimum")
    return fig


def td_errors(episodes: np.ndarray, mean: np.ndarray, sem: np.ndarray, window: int,
              n_runs: int, td_run0: np.ndarray, sampled_episodes: np.ndarray,
              title: str) -> Figure:
    """Figs. 4.8/4.13: (a) moving average of the episode-mean |δ|; (b) per-step δ of one run
    (the dissertation's 1st run, run 0 here)."""
    fig = Figure(figsize=(12, 4.2), layout="constrained")
    ax_a, ax_b = fig.subplots(1, 2)
    _curve(ax_a, episodes, mean, sem, None)
    ax_a.set_xlabel("actor episode")
    ax_a.set_ylabel(f"mean |δ| per episode ({window}-episode moving average)")
    ax_a.set_title(f"(a) mean ± s.e.m. over {n_runs} runs")
    # A signed δ: a symmetric diverging scale keeps 0 white.
    vmax = float(np.nanmax(np.abs(td_run0))) if np.isfinite(td_run0).any() else 1.0
    im = ax_b.pcolormesh(np.arange(td_run0.shape[1] + 1) - 0.5, _edges(sampled_episodes), td_run0,
                         cmap="RdBu_r", vmin=-vmax, vmax=vmax)
    ax_b.set_xlabel("step t of the episode (δ of the action at t)")
    ax_b.set_ylabel("actor episode")
    ax_b.set_title(f"(b) run 0, {len(sampled_episodes)} sampled episodes (blank: episode over)")
    fig.colorbar(im, ax=ax_b, label="TD error δ")
    fig.suptitle(title)
    return fig


def junction_activations(acts: np.ndarray, condition: np.ndarray, episode: np.ndarray,
                         condition_names: Sequence[str], condition_title: str,
                         title: str) -> Figure:
    """Figs. 4.14(a)/4.15(a)/4.17(a): every junction visit, sorted by condition then episode."""
    order = np.lexsort((episode, condition))
    acts, condition = acts[order], condition[order]
    present, counts = np.unique(condition, return_counts=True)  # sorted, as the rows are
    ends = np.cumsum(counts) - 0.5
    fig = Figure(figsize=(max(7.0, 0.22 * acts.shape[1] + 2.5), 6), layout="constrained")
    ax = fig.add_subplot()
    im = ax.imshow(acts, aspect="auto", interpolation="nearest", cmap="viridis", vmin=0, vmax=1)
    for b in ends[:-1]:
        ax.axhline(b, color="w", lw=1.5)
    ax.set_yticks(ends - counts / 2, [f"{condition_names[c]}\n{n} visits"
                                      for c, n in zip(present, counts)])
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("unit")
    ax.set_ylabel(f"junction visits by {condition_title}, then episode ↓")
    fig.colorbar(im, ax=ax, label="activation")
    ax.set_title(title)
    return fig


def _marker_sizes(steps: np.ndarray, shortest: float, longest: float) -> np.ndarray:
    return np.interp(steps, [shortest, longest], MARKER_SIZES)


def _condition_legend(ax, condition_names: Sequence[str], title: str, sizes=None) -> None:
    colors = _condition_colors(len(condition_names))
    handles = [Line2D([], [], ls="", marker="o", color=c, label=n)
               for c, n in zip(colors, condition_names)]
    if sizes is not None:
        handles += [Line2D([], [], ls="", marker="o", color="gray", markersize=np.sqrt(a),
                           label=f"{s:g} steps") for s, a in sizes]
    ax.legend(handles=handles, title=title, fontsize="x-small", title_fontsize="x-small",
              loc="best")


def junction_pca(panels: Sequence[tuple], explained: Sequence[tuple],
                 condition_names: Sequence[str], legend_title: str,
                 steps_range: tuple[float, float], title: str) -> Figure:
    """Figs. 4.14(b)/4.15(b)/4.17(b) with the variance bars of Figs. 4.16/4.19(a).

    `panels` holds (subtitle, scores (n, ≥2), condition (n,), steps_to_goal (n,)) per phase,
    `explained` (label, explained-variance ratio) per phase.
    """
    fig = Figure(figsize=(15, 4.6), layout="constrained")
    axes = fig.subplots(1, len(panels) + 1)
    colors = np.array(_condition_colors(len(condition_names)))
    for ax, (subtitle, scores, condition, steps) in zip(axes, panels):
        ax.scatter(scores[:, 0], scores[:, 1], s=_marker_sizes(steps, *steps_range),
                   c=colors[condition], alpha=0.5, linewidths=0)
        ax.set_xlabel("PC1")
        ax.set_ylabel("PC2")
        ax.set_title(subtitle, fontsize="small")
    _condition_legend(axes[0], condition_names, legend_title,
                      sizes=[(s, float(_marker_sizes(s, *steps_range))) for s in steps_range])
    ax = axes[-1]
    n_show = min(10, max(len(r) for _, r in explained))
    width = 0.8 / len(explained)
    for k, (label, ratio) in enumerate(explained):
        ax.bar(np.arange(1, n_show + 1) + (k - (len(explained) - 1) / 2) * width,
               ratio[:n_show], width=width, label=label)
    ax.set_xticks(range(1, n_show + 1))
    ax.set_xlabel("principal component")
    ax.set_ylabel("explained variance ratio")
    ax.set_title("contribution of each PC", fontsize="small")
    ax.legend(fontsize="x-small")
    fig.suptitle(title)
    return fig


def _pc3_scatter(ax, scores: np.ndarray, colors: np.ndarray, subtitle: str) -> None:
    ax.scatter(scores[:, 0], scores[:, 1], scores[:, 2], c=colors, s=8, alpha=0.6,
               linewidths=0, depthshade=False)
    ax.set_xlabel("PC1")
    ax.set_ylabel("PC2")
    ax.set_zlabel("PC3")
    ax.set_title(subtitle, fontsize="small")


def junction_pca3d(panels: Sequence[tuple], condition_names: Sequence[str],
                   legend_title: str, title: str) -> Figure:
    """Figs. 4.19(b)/5.10(b)/5.13(b)/5.23(b): projection on PC1–3; `panels` holds
    (subtitle, scores (n, 3), condition)."""
    fig = Figure(figsize=(12, 5.5), layout="constrained")
    colors = np.array(_condition_colors(len(condition_names)))
    for k, (subtitle, scores, condition) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        _pc3_scatter(ax, scores, colors[condition], subtitle)
        if k == 0:
            _condition_legend(ax, condition_names, legend_title)
    fig.suptitle(title)
    return fig


def class_pca(scores: np.ndarray, labels: np.ndarray, class_names: Sequence[str],
              subtitle: str, spectra: Sequence[tuple], title: str) -> Figure:
    """Figs. 5.15/5.16: (a) images projected on PC1–3, coloured by digit class; then one
    panel of explained-variance ratios per (label, ratios) in `spectra` (Figs. 5.15(b–c),
    5.16(b))."""
    n_panels = 1 + len(spectra)
    fig = Figure(figsize=(5.5 + 4.5 * len(spectra), 4.8), layout="constrained")
    ax = fig.add_subplot(1, n_panels, 1, projection="3d")
    _pc3_scatter(ax, scores, np.array(_condition_colors(len(class_names)))[labels],
                 f"(a) {subtitle}")
    _condition_legend(ax, class_names, "digit class")
    for k, (label, ratio) in enumerate(spectra):
        ax = fig.add_subplot(1, n_panels, k + 2)
        ax.bar(np.arange(1, len(ratio) + 1), ratio, width=0.8 if len(ratio) <= 50 else 1.0)
        ax.set_xlabel("principal component")
        ax.set_ylabel("explained variance ratio")
        ax.set_title(f"({'bcd'[k]}) {label}", fontsize="small")
    fig.suptitle(title)
    return fig


def reconstruction_error(mean: np.ndarray, sem: np.ndarray, n_runs: int,
                         held_out: tuple[float, float], title: str) -> Figure:
    """The RBM preprocessor's training (§5.3.2): reconstruction error per sweep, mean ± s.e.m.
    over runs, with the mean held-out error before and after training as points."""
    fig = Figure(figsize=(7, 4.2), layout="constrained")
    ax = fig.add_subplot()
    sweeps = np.arange(1, len(mean) + 1)
    _curve(ax, sweeps, mean, sem, None)
    ax.plot([0, sweeps[-1]], held_out, "o", color="tab:red",
            label="held-out images: before / after training")
    ax.legend(fontsize="small")
    ax.set_xlabel("sweep through the training images")
    ax.set_ylabel("mean squared reconstruction error")
    ax.set_title(f"mean ± s.e.m. over {n_runs} runs", fontsize="small")
    fig.suptitle(title)
    return fig
