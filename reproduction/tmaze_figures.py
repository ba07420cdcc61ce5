"""Figures of the T-junction (chapter 4, Figs. 4.14–4.19; chapter 5, Figs. 5.7–5.13, 5.20–5.25)
and of the RBM preprocessor (Figs. 5.15–5.16), drawn from run records.

Like ``floor_figures``, every function takes plain arrays and returns a
``matplotlib.figure.Figure`` built without pyplot. The numbers come from
``reproduction.tmaze`` and, for the RBM preprocessor of §5.3.2, ``reproduction.preprocessor``;
learning curves, TD errors and prediction errors are generic figures (``ferl.analysis.figures``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from ferl.analysis.figures import band
from ferl.analysis.layout import ONE_PANEL, Space, colorbar, grid

MARKER_SIZES = (6.0, 60.0)  # scatter area of the shortest / longest episode (Fig. 4.14b)
# Rows of an image of junction visits drawn at most: ≥ 3 per pixel row of its panel, which shows
# each pixel row's nearest visit either way; the rest only cost resampling time.
IMAGE_ROWS = 2000
MAX_WIDTH = 16.0  # inches: a layer of pixels (784 units) in a readable figure, not 180 inches wide

# The space of each figure below (``ferl.analysis.layout``), in inches.
ACTIVATIONS = Space(left=1.45, top=0.1, colorbar=0.95)  # two-line tick labels per condition
PCA = Space(left=0.85, top=0.5, wspace=0.85)  # two-line panel titles


def _condition_colors(n: int) -> list:
    return [colormaps["tab10"](k) for k in range(n)]


def junction_activations(
    acts: np.ndarray,
    condition: np.ndarray,
    episode: np.ndarray,
    condition_names: Sequence[str],
    condition_title: str,
    title: str,
) -> Figure:
    """Figs. 4.14(a)/4.15(a)/4.17(a): every junction visit, sorted by condition then episode."""
    order = np.lexsort((episode, condition))
    present, counts = np.unique(condition, return_counts=True)  # sorted, as the rows are
    ends = np.cumsum(counts) - 0.5
    n, units = acts.shape
    fig = Figure(figsize=(min(max(7.0, 0.22 * units + 2.5), MAX_WIDTH), 6))
    ax = grid(fig, 1, 1, ACTIVATIONS, title)[0, 0]
    shown = order[np.linspace(0, n - 1, min(n, IMAGE_ROWS)).round().astype(int)]  # only these rows are copied
    extent = (-0.5, units - 0.5, n - 0.5, -0.5)  # visit numbers, as without subsampling
    image = np.asarray(acts[shown], dtype=np.float64)
    im = ax.imshow(image, aspect="auto", interpolation="nearest", cmap="viridis", vmin=0, vmax=1, extent=extent)
    for b in ends[:-1]:
        ax.axhline(b, color="w", lw=1.5)
    ax.set_yticks(ends - counts / 2, [f"{condition_names[c]}\n{n} visits" for c, n in zip(present, counts)])
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("unit")
    ax.set_ylabel(f"junction visits by {condition_title}, then episode ↓")
    colorbar(fig, im, ax, ACTIVATIONS, label="activation")
    return fig


def _marker_sizes(steps: np.ndarray | float, shortest: float, longest: float) -> np.ndarray | float:
    return np.interp(steps, [shortest, longest], MARKER_SIZES)


def _condition_legend(ax, condition_names: Sequence[str], title: str, sizes=None) -> None:
    colors = _condition_colors(len(condition_names))
    handles = [Line2D([], [], ls="", marker="o", color=c, label=n) for c, n in zip(colors, condition_names)]
    if sizes is not None:
        handles += [
            Line2D([], [], ls="", marker="o", color="gray", markersize=np.sqrt(a), label=f"{s:g} steps")
            for s, a in sizes
        ]
    ax.legend(handles=handles, title=title, fontsize="x-small", title_fontsize="x-small", loc="best")


def junction_pca(
    panels: Sequence[tuple],
    explained: Sequence[tuple],
    condition_names: Sequence[str],
    legend_title: str,
    steps_range: tuple[float, float],
    title: str,
) -> Figure:
    """Figs. 4.14(b)/4.15(b)/4.17(b) with the variance bars of Figs. 4.16/4.19(a).

    ``panels`` holds (subtitle, scores (n, ≥2), condition (n,), steps_to_goal (n,)) per phase,
    ``explained`` (label, explained-variance ratio) per phase.
    """
    fig = Figure(figsize=(15, 4.6))
    axes = grid(fig, 1, len(panels) + 1, PCA, title)[0]
    colors = np.array(_condition_colors(len(condition_names)))
    for ax, (subtitle, scores, condition, steps) in zip(axes, panels):
        ax.scatter(
            scores[:, 0],
            scores[:, 1],
            s=_marker_sizes(steps, *steps_range),
            c=colors[condition],
            alpha=0.5,
            linewidths=0,
        )
        ax.set_xlabel("PC1")
        ax.set_ylabel("PC2")
        ax.set_title(subtitle, fontsize="small")
    _condition_legend(
        axes[0], condition_names, legend_title, sizes=[(s, float(_marker_sizes(s, *steps_range))) for s in steps_range]
    )
    ax = axes[-1]
    n_show = min(10, max(len(r) for _, r in explained))
    width = 0.8 / len(explained)
    for k, (label, ratio) in enumerate(explained):
        ax.bar(
            np.arange(1, n_show + 1) + (k - (len(explained) - 1) / 2) * width, ratio[:n_show], width=width, label=label
        )
    ax.set_xticks(range(1, n_show + 1))
    ax.set_xlabel("principal component")
    ax.set_ylabel("explained variance ratio")
    ax.set_title("contribution of each PC", fontsize="small")
    ax.legend(fontsize="x-small")
    return fig


def _pc3_scatter(ax, scores: np.ndarray, colors: np.ndarray, subtitle: str) -> None:
    ax.scatter(scores[:, 0], scores[:, 1], scores[:, 2], c=colors, s=8, alpha=0.6, linewidths=0, depthshade=False)
    ax.set_xlabel("PC1")
    ax.set_ylabel("PC2")
    ax.set_zlabel("PC3")
    ax.set_title(subtitle, fontsize="small")


def junction_pca3d(panels: Sequence[tuple], condition_names: Sequence[str], legend_title: str, title: str) -> Figure:
    """Figs. 4.19(b)/5.10(b)/5.13(b)/5.23(b): projection on PC1–3; ``panels`` holds
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


def class_pca(
    scores: np.ndarray,
    labels: np.ndarray,
    class_names: Sequence[str],
    subtitle: str,
    spectra: Sequence[tuple],
    title: str,
) -> Figure:
    """Figs. 5.15/5.16: (a) images projected on PC1–3, coloured by digit class; then one
    panel of explained-variance ratios per (label, ratios) in ``spectra`` (Figs. 5.15(b–c),
    5.16(b))."""
    n_panels = 1 + len(spectra)
    fig = Figure(figsize=(5.5 + 4.5 * len(spectra), 4.8), layout="constrained")
    ax = fig.add_subplot(1, n_panels, 1, projection="3d")
    _pc3_scatter(ax, scores, np.array(_condition_colors(len(class_names)))[labels], f"(a) {subtitle}")
    _condition_legend(ax, class_names, "digit class")
    for k, (label, ratio) in enumerate(spectra):
        ax = fig.add_subplot(1, n_panels, k + 2)
        ax.bar(np.arange(1, len(ratio) + 1), ratio, width=0.8 if len(ratio) <= 50 else 1.0)
        ax.set_xlabel("principal component")
        ax.set_ylabel("explained variance ratio")
        ax.set_title(f"({'bcd'[k]}) {label}", fontsize="small")
    fig.suptitle(title)
    return fig


def reconstruction_error(
    mean: np.ndarray, sem: np.ndarray, n_runs: int, held_out: tuple[float, float], title: str
) -> Figure:
    """The RBM preprocessor's training (§5.3.2): reconstruction error per sweep, mean ± s.e.m.
    over runs, with the mean held-out error before and after training as points."""
    fig = Figure(figsize=(7, 4.2))
    ax = grid(fig, 1, 1, ONE_PANEL, title)[0, 0]
    sweeps = np.arange(1, len(mean) + 1)
    band(ax, sweeps, mean, sem, None)
    ax.plot([0, sweeps[-1]], held_out, "o", color="tab:red", label="held-out images: before / after training")
    ax.legend(fontsize="small")
    ax.set_xlabel("sweep through the training images")
    ax.set_ylabel("mean squared reconstruction error")
    ax.set_title(f"mean ± s.e.m. over {n_runs} runs", fontsize="small")
    return fig
