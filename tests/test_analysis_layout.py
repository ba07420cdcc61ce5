"""Fixed figure layouts (ferl/analysis/layout.py): panels where the stated inches put them, and
every figure that uses them drawn with no text outside the figure or over another panel, at the
smallest and largest sizes the analyses make."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure
from scipy.cluster.hierarchy import linkage

from ferl.analysis import figures as figs
from ferl.analysis import layout
from reproduction import floor_figures as ff
from reproduction import tmaze_figures as tf

RNG = np.random.default_rng(0)


def test_grid_puts_panels_where_the_inches_say():
    fig = Figure(figsize=(10, 6))
    space = layout.Space(left=1.0, right=0.5, bottom=0.8, top=0.4, wspace=0.6, hspace=0.9, colorbar=1.2)
    axes = layout.grid(fig, 2, 3, space, "a title\nof two lines")
    top = 0.4 + layout.PAD + 2 * layout.TITLE_PT * layout.LINE / 72
    width, height = (10 - 1.0 - 0.5 - 1.2 - 2 * 0.6) / 3, (6 - 0.8 - top - 0.9) / 2
    for (r, c), ax in np.ndenumerate(axes):
        box = ax.get_position()
        x0, y1 = 1.0 + c * (width + 0.6), 6 - top - r * (height + 0.9)
        np.testing.assert_allclose(
            [box.x0 * 10, box.y1 * 6, box.width * 10, box.height * 6], [x0, y1, width, height], atol=1e-9
        )


def test_grid_refuses_a_figure_too_small_for_its_panels():
    with pytest.raises(ValueError, match="no room for 1 × 4 panels"):
        layout.grid(Figure(figsize=(3, 3)), 1, 4, layout.Space())


def test_collisions_names_a_label_outside_and_panels_that_overlap():
    fig = Figure(figsize=(6, 3))
    axes = layout.grid(fig, 1, 2, layout.Space(left=0.05, wspace=0.05))[0]
    axes[0].set_ylabel("a label with no room")
    axes[1].set_ylabel("another")
    axes[1].plot([0, 1e4], [0, 1e4])
    found = layout.collisions(fig)
    assert any("panel 0 ('a label with no room') leaves the figure" in f for f in found)
    assert any("panel 0 ('a label with no room') overlaps panel 1 ('another')" in f for f in found)
    roomy = Figure(figsize=(6, 3))
    for ax in layout.grid(roomy, 1, 2, layout.Space(left=0.8, wspace=0.9))[0]:
        ax.set_ylabel("fits")
    assert layout.collisions(roomy) == []


def _curves(n: int):
    x = np.arange(1, n + 1, dtype=float)
    mean, sem = RNG.random(n), 0.1 * RNG.random(n)
    return x, mean, sem


def _generic_figures():
    for n_panels in (1, 2, 3):
        x, mean, sem = _curves(500)
        panels = [(f"measure {k}", mean * 10**k, sem, 1.0 if k == 0 else None) for k in range(n_panels)]
        yield figs.learning_curves(x, panels, ("reward", RNG.random((10, 500)), 1.0), 100, 10, "episode", "Fig. 4.6")
    x, mean, sem = _curves(300)
    yield figs.td_errors(x, mean, sem, 50, 10, "episode", "Fig. 4.8: TD errors", None)
    yield figs.td_errors(x, mean, sem, 50, 10, "episode", "Fig. 4.8", (RNG.normal(size=(40, 12)), np.arange(40) * 250))
    units = "Eq. 4.8 weighted absolute error\nρ_y Σ|y − ŷ| + ρ_r Σ|r − r̂|"
    long_title = "Fig. 4.10: prediction errors of the `joint` predictor, mean over 10 runs (table4_2_digit)"
    for n in (1, 8):
        lengths, epochs = np.arange(3, 3 + n), np.arange(0, 401, 20)
        err = RNG.random((len(epochs), n, lengths[-1] + 1)) * 400
        yield figs.prediction_errors(err, err / 2, lengths, epochs, 7, units, long_title)


def _floor_figures():
    classes = [str(k) for k in range(9)]
    arrangement = np.array(classes).reshape(3, 3)
    counts = RNG.integers(0, 400, (10, 9, 4)).astype(float)
    title = "Fig. 3.6(a): greedy actions of the test images, before training\n(train noise 12.5 %, test noise 12.5 %)"
    yield ff.greedy_count_grid(counts, classes, arrangement, [0, 1, 2, 1, -1, 3, 0, 0, 3], list("NESW"), title)
    for hidden in (10, 40):
        yield ff.weight_images(RNG.normal(size=(784, hidden)), RNG.normal(size=(784, hidden)))
        yield ff.median_activation(RNG.random((9, hidden)), RNG.random((9, hidden)), classes)
    levels = np.array([0.0, 0.125, 0.25, 0.5])
    yield ff.accuracy_vs_noise(levels, RNG.random((10, 4)), RNG.random((10, 4)), 0.125, 0.25)
    yield ff.noise_grid_heatmap(levels, levels, RNG.random((4, 4)), "ch3_floor")
    yield ff.outlier_images(RNG.random((90, 784)), RNG.random(90), RNG.random(90), "3", "N")
    tree = linkage(RNG.random((9, 20)), "average")
    yield ff.mfr_dendrogram(
        tree, classes, "Fig. 3.11/3.13: clustered MFRs after training\n(run 0; ch3_floor, 20 hidden)"
    )
    yield ff.mi_dendrogram(tree, classes, 16)
    for n_runs in (3, 10):
        yield ff.mfr_dendrogram_grid([tree] * (n_runs - 1) + [None], classes, "Fig. 3.11/3.13: every run\n(ch3_floor)")


def _tmaze_figures():
    names = ["(0, 0)", "(0, 1)", "(1, 0)", "(1, 1)"]
    for units in (13, 804):
        visits = 5000
        yield tf.junction_activations(
            RNG.random((visits, units)),
            RNG.integers(0, 4, visits),
            np.arange(visits),
            names,
            "(initial, junction) signal",
            "observation-predictor memory m^y at the T-junction, run 0",
        )
    phase = ("first 1000 episodes (0–999)\nsilhouette on PC1–3: conditions 0.13, initial signal 0.50",)
    panels = [(*phase, RNG.normal(size=(300, 3)) * 100, RNG.integers(0, 4, 300), RNG.integers(3, 11, 300))] * 2
    explained = [("first", np.sort(RNG.random(20))[::-1]), ("last", np.sort(RNG.random(20))[::-1])]
    title = "Figs. 4.17(b)/4.19(a): actor hidden ĥ at the T-junction, run 0: PCA fit separately on each phase's visits"
    yield tf.junction_pca(panels, explained, names, "(initial, junction) signal", (3.0, 10.0), title)
    yield tf.reconstruction_error(RNG.random(30), RNG.random(30) / 10, 10, (0.2, 0.05), "§5.3.2: the RBM preprocessor")


@pytest.mark.parametrize("make", [_generic_figures, _floor_figures, _tmaze_figures], ids=lambda f: f.__name__[1:])
def test_every_fixed_layout_figure_keeps_its_texts_inside_and_apart(make):
    for fig in make():
        assert fig.get_layout_engine() is None  # the figure states its space: no engine measures it
        assert layout.collisions(fig) == [], fig.get_suptitle() or fig.axes[0].get_title()
