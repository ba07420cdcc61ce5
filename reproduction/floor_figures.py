"""Figures of chapter 3 (digit floor, Figs. 3.5–3.13), drawn from run records.

Every function takes plain arrays and returns a ``matplotlib.figure.Figure``
built without pyplot (so no global figure state; rendered by the Agg canvas
when saved). The numbers come from ``ferl.analysis.coding``; the reward curve of
Fig. 3.4 is a generic figure (``ferl.analysis.figures``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from scipy.cluster.hierarchy import dendrogram

from ferl import stats
from ferl.analysis.figures import fitted_title
from ferl.analysis.layout import ONE_PANEL, Space, colorbar, grid

OPTIMAL_COLOR, OTHER_COLOR, GOAL_COLOR = "tab:orange", "tab:blue", "lightgray"
PHASE_COLOR = {"before": "tab:gray", "after": "tab:red"}

# The space of each figure below (``ferl.analysis.layout``), in inches.
IMAGES = Space(left=0.1, right=0.1, bottom=0.1, top=0.35, hspace=0.45)  # titled panels, no ticks
WEIGHTS = IMAGES.but(colorbar=1.0)
GREEDY = Space(left=0.85, bottom=1.2, top=0.35, wspace=0.2, hspace=0.65)  # the legend below
MEDIAN = Space(left=0.85, top=0.35, wspace=0.2, colorbar=1.0)
DENDROGRAMS = Space(left=0.75, bottom=0.35, top=0.3, wspace=0.55, hspace=0.6)
HEATMAP = Space(left=0.85, top=0.1, colorbar=1.0)


def _mosaic(tiles: np.ndarray, ncols: int, pad_x: int = 2, pad_y: int = 2) -> np.ndarray:
    """(k, 28, 28) tiles → one 2-D image, row-major, NaN in the gaps."""
    side = tiles.shape[-1]  # 28: MNIST (§3.4)
    nrows = -(-len(tiles) // ncols)
    out = np.full((nrows * (side + pad_y), ncols * (side + pad_x)), np.nan)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, ncols)
        out[r * (side + pad_y) + pad_y : (r + 1) * (side + pad_y), c * (side + pad_x) : c * (side + pad_x) + side] = (
            tile
        )
    return out


def _square(pixels: int) -> tuple[int, int]:
    """The (side, side) of square images of ``pixels`` pixels (28 × 28: MNIST, §3.4)."""
    side = math.isqrt(pixels)
    return side, side


def _no_ticks(ax) -> None:
    ax.set_xticks([])
    ax.set_yticks([])


def weight_images(w_before: np.ndarray, w_after: np.ndarray, ncols: int = 10) -> Figure:
    """Fig. 3.5: observation→hidden weights (784, H) as 28×28 images, before over after."""
    n_hidden = w_before.shape[1]
    ncols = min(ncols, n_hidden)
    fig = Figure(figsize=(1.0 * ncols + 1, 2.2 * -(-n_hidden // ncols) + 1))
    title = "Fig. 3.5: connection weights from observations\nto hidden nodes (run 0)"
    axes = grid(fig, 2, 1, WEIGHTS, title)[:, 0]
    for ax, w, phase in zip(axes, (w_before, w_after), ("before", "after")):
        tiles = w.T.reshape(n_hidden, *_square(w.shape[0]))
        # Each unit is scaled to its own max |w| so that untrained (small) weights stay visible.
        scale = np.abs(tiles).max(axis=(1, 2), keepdims=True)
        tiles = tiles / np.where(scale > 0, scale, 1.0)
        im = ax.imshow(_mosaic(tiles, ncols), cmap="gray", vmin=-1, vmax=1)
        _no_ticks(ax)
        ax.set_title(f"{phase} training: hidden units 1–{n_hidden} (row-major)")
    colorbar(fig, im, axes, WEIGHTS, shrink=0.6, label="weight / max |weight| of the unit")
    return fig


def greedy_count_grid(
    counts: np.ndarray,
    classes: Sequence[str],
    arrangement: np.ndarray,
    optimal_action: Sequence[int],
    action_names: Sequence[str],
    title: str,
) -> Figure:
    """Fig. 3.6 (a)/(b): greedy-action counts per class, laid out as the 3×3 patch.

    ``counts`` is (R, C, nA); bars are the mean over runs with ±1 s.d. error bars,
    dots the individual runs; the optimal action's bar is highlighted.
    """
    n_runs, _, n_actions = counts.shape
    index = {c: k for k, c in enumerate(classes)}
    fig = Figure(figsize=(8, 7))
    axes = grid(fig, *arrangement.shape, GREEDY, title, sharey=True)
    x = np.arange(n_actions)
    jitter = np.linspace(-0.2, 0.2, n_runs) if n_runs > 1 else np.zeros(1)
    for ax, name in zip(axes.flat, arrangement.flat):
        if name not in index:
            ax.set_axis_off()
            continue
        c = index[name]
        colors = [
            GOAL_COLOR if optimal_action[c] < 0 else OPTIMAL_COLOR if a == optimal_action[c] else OTHER_COLOR for a in x
        ]
        mean, sd, _ = zip(*(stats.mean_sd(counts[:, c, a]) for a in x))
        ax.bar(x, mean, yerr=sd, color=colors, capsize=2)
        # One line of dots per panel, not one per action: the same pixels, fewer artists to draw.
        ax.plot((x[None, :] + jitter[:, None]).ravel(), counts[:, c].ravel(), "k.", ms=2)
        ax.set_xticks(x, action_names)
        ax.set_title(f'"{name}"' + (" (goal)" if optimal_action[c] < 0 else ""))
    for ax in axes[:, 0]:
        ax.set_ylabel("count (test images)")
    for ax in axes[-1]:
        ax.set_xlabel("greedy action")
    fig.legend(
        handles=[
            Patch(color=OPTIMAL_COLOR, label="optimal action"),
            Patch(color=OTHER_COLOR, label="other actions"),
            Patch(color=GOAL_COLOR, label="goal tile (no optimal action)"),
        ],
        loc="lower center",
        bbox_to_anchor=(0.5, 0.01),
        ncols=3,
        title=f"bars: mean over {n_runs} runs ± 1 s.d.; dots: single runs",
    )
    return fig


def accuracy_vs_noise(
    noise_levels: np.ndarray, acc_before: np.ndarray, acc_after: np.ndarray, train_noise: float, chance: float
) -> Figure:
    """Fig. 3.6 (c)/(d) as a curve: greedy accuracy vs test noise, mean ± s.e.m. over runs."""
    fig = Figure(figsize=(6.5, 4))
    ax = grid(fig, 1, 1, ONE_PANEL)[0, 0]
    for phase, acc in (("before", acc_before), ("after", acc_after)):
        ax.errorbar(
            100 * noise_levels,
            acc.mean(axis=0),
            yerr=stats.sem(acc),
            marker="o",
            capsize=3,
            color=PHASE_COLOR[phase],
            label=f"{phase} training",
        )
    ax.axhline(chance, color="k", ls=":", label=f"chance (1/{round(1 / chance)})")
    ax.axvline(100 * train_noise, color="tab:green", ls="--", label=f"training noise ({100 * train_noise:g} %)")
    ax.set_xlabel("test noise level (% of pixels replaced by white noise)")
    ax.set_ylabel("fraction of test images with optimal greedy action")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"Fig. 3.6: greedy accuracy vs test noise (mean ± s.e.m., {len(acc_after)} runs)")
    ax.legend(loc="upper right", fontsize="small")
    return fig


def noise_grid_heatmap(train: np.ndarray, test: np.ndarray, accuracy: np.ndarray, experiment: str) -> Figure:
    """Fig. 3.6 over every pair of noise levels: greedy accuracy after training (mean over
    runs) by training noise (rows) and test noise (columns); the diagonal is test = training."""
    fig = Figure(figsize=(2.4 + 0.75 * len(test), 1.8 + 0.5 * len(train)))
    title = fitted_title(fig, f"Fig. 3.6: greedy accuracy after training, {experiment}, mean over runs")
    ax = grid(fig, 1, 1, HEATMAP, title)[0, 0]
    im = ax.imshow(accuracy, vmin=0, vmax=1, cmap="viridis", aspect="auto")
    for (t, k), value in np.ndenumerate(accuracy):
        if np.isfinite(value):
            ax.text(k, t, f"{value:.2f}", ha="center", va="center", fontsize="small", color="k" if value > 0.6 else "w")
    ax.set_xticks(range(len(test)), [f"{100 * x:g}" for x in test])
    ax.set_yticks(range(len(train)), [f"{100 * x:g}" for x in train])
    ax.set_xlabel("test noise (% of pixels replaced by white noise)")
    ax.set_ylabel("training noise (% of pixels)")
    colorbar(fig, im, ax, HEATMAP, label="greedy accuracy (fraction optimal)")
    return fig


def _sorted_probe_panel(ax, images: np.ndarray, prob: np.ndarray, n_show: int, ncols: int, title: str) -> None:
    """n_show images spanning the whole sorted range of P(optimal), probability on top."""
    order = np.argsort(prob, kind="stable")
    spread = np.linspace(0, len(order) - 1, min(n_show, len(order))).round().astype(int)
    picks = order[np.unique(spread)]
    pad_y = 9  # room for the printed probability
    side = math.isqrt(images.shape[-1])  # 28: MNIST (§3.4)
    ax.imshow(_mosaic(images[picks].reshape(-1, side, side), ncols, pad_y=pad_y), cmap="gray_r", vmin=0, vmax=1)
    for k, i in enumerate(picks):
        r, c = divmod(k, ncols)
        ax.text(
            c * (side + 2) + side / 2,
            r * (side + pad_y) + pad_y - 1,
            f"{prob[i]:.2f}",
            ha="center",
            va="bottom",
            fontsize=6,
        )
    _no_ticks(ax)
    ax.set_title(title)


def outlier_images(
    images: np.ndarray,
    prob_before: np.ndarray,
    prob_after: np.ndarray,
    class_name: str,
    action_name: str,
    n_show: int = 40,
    ncols: int = 10,
) -> Figure:
    """Fig. 3.7: test images sorted by P(optimal action | z), before and after training."""
    nrows = -(-min(n_show, len(images)) // ncols)
    fig = Figure(figsize=(ncols * 0.7 + 0.5, 2 * nrows * 0.85 + 1.2))
    title = (
        f'Fig. 3.7: outlier detection, test images of "{class_name}" (run 0)\n'
        f"{min(n_show, len(images))} of {len(images)} spanning the sorted order"
    )
    axes = grid(fig, 2, 1, IMAGES, title)[:, 0]
    for ax, prob, phase in zip(axes, (prob_before, prob_after), ("(a) before", "(b) after")):
        _sorted_probe_panel(
            ax, images, prob, n_show, ncols, f"{phase} training: P(a = '{action_name}' | z), ascending row-major"
        )
    return fig


def median_activation(med_before: np.ndarray, med_after: np.ndarray, classes: Sequence[str]) -> Figure:
    """Fig. 3.10: median hidden activation (footnote 6) per class, before and after."""
    fig = Figure(figsize=(10, 0.3 * len(classes) + 2))
    axes = grid(
        fig, 1, 2, MEDIAN, "Fig. 3.10: median activation of hidden nodes over the test images (run 0)", sharey=True
    )
    axes = axes[0]
    for ax, med, phase in zip(axes, (med_before, med_after), ("before", "after")):
        im = ax.imshow(med, cmap="viridis", vmin=0, vmax=1, aspect="auto")
        ax.set_yticks(range(len(classes)), [f'"{c}"' for c in classes])
        ax.set_xticks(range(med.shape[1]), range(1, med.shape[1] + 1), fontsize="small")
        ax.set_xlabel("hidden unit k")
        ax.set_title(f"{phase} training")
    axes[0].set_ylabel("tile class")
    colorbar(fig, im, axes, MEDIAN, label="median activation Σ_a P(h_k=1|z,a)P(a|z)")
    return fig


def _dendrogram(ax, linkage_matrix: np.ndarray, labels: Sequence[str]) -> None:
    dendrogram(linkage_matrix, labels=[f'"{c}"' for c in labels], ax=ax, color_threshold=0, above_threshold_color="k")


def mfr_dendrogram(linkage_matrix: np.ndarray, labels: Sequence[str], title: str) -> Figure:
    """Figs. 3.11/3.13: hierarchical clustering of the MFR distance D of one run."""
    fig = Figure(figsize=(6, 4))
    ax = grid(fig, 1, 1, ONE_PANEL.but(top=0.1), title)[0, 0]
    _dendrogram(ax, linkage_matrix, labels)
    ax.set_xlabel("tile class")
    ax.set_ylabel("distance D = 2 − 2 cos(MFR_i, MFR_j)")
    return fig


def mfr_dendrogram_grid(
    linkages: Sequence[np.ndarray | None], labels: Sequence[str], title: str, ncols: int = 5
) -> Figure:
    """Figs. 3.11/3.13 for every run: one small dendrogram per run (None: a diverged run)."""
    ncols = min(ncols, len(linkages))
    nrows = -(-len(linkages) // ncols)
    fig = Figure(figsize=(3 * ncols, 2.6 * nrows))
    axes = grid(fig, nrows, ncols, DENDROGRAMS, title).ravel()
    for r, ax in enumerate(axes):
        if r >= len(linkages):
            ax.set_axis_off()
            continue
        if linkages[r] is None:
            ax.text(
                0.5,
                0.5,
                "diverged\n(non-finite activations)",
                ha="center",
                va="center",
                transform=ax.transAxes,
                fontsize="small",
            )
            _no_ticks(ax)
        else:
            _dendrogram(ax, linkages[r], labels)
        ax.set_title(f"run {r}", fontsize="small")
        ax.tick_params(labelsize="x-small")
    for ax in axes[::ncols]:
        ax.set_ylabel("distance D")
    return fig


def mi_dendrogram(linkage_matrix: np.ndarray, labels: Sequence[str], bins: int) -> Figure:
    """Fig. 3.12: classes clustered by pairwise pixel–label mutual information."""
    fig = Figure(figsize=(6, 4))
    ax = grid(fig, 1, 1, ONE_PANEL)[0, 0]
    _dendrogram(ax, linkage_matrix, labels)
    ax.set_xlabel("digit class (clean test images)")
    ax.set_ylabel(f"mean pixel mutual information I(Z_i; C) (nats, {bins} bins)")
    ax.set_title("Fig. 3.12: digits clustered by pairwise mutual information")
    return fig
