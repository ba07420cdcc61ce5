"""Fixed figure layouts: the space around and between panels is stated in inches, not measured.

Matplotlib's constrained layout measures every text of a figure (tick labels, titles) in two
passes before the figure is drawn, and the drawing measures them again. On the reproduction
sweep those passes were ~28 % of the time ``analyze.py`` spends building and drawing figures
(docs/performance.md, "Fixed layouts, checked by a test"). The figures of a run have a known structure (a grid of panels,
one or two lines of title, tick labels of a few characters, at most a colour bar at the right),
so their space can be stated once here: a ``Space`` per kind of figure, in inches, so that it
does not shrink or grow with the figure's size. Tick labels of matplotlib's default formatter stay
short (large or small values move to an offset text), which is what makes fixed margins safe;
``tests/test_analysis_layout.py`` draws every figure that uses them and checks that no text leaves
the figure or runs into another panel.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from matplotlib.figure import Figure

TITLE_PT = 12.0  # the suptitle's font size ("large" at matplotlib's default 10 pt)
LINE = 1.3  # line height / font size
PAD = 0.08  # inches between the figure's edge and its title
BAR = 0.15  # inches: a colour bar's width, and its gap to the panels


@dataclass(frozen=True)
class Space:
    """Inches around a grid of panels: margins, gaps between panels, and a colour bar column.

    ``top`` is the room for the panels' own titles (the figure's title is added to it by
    ``grid``); ``colorbar`` the width kept right of the panels for a bar, its ticks and label
    (0: no bar).
    """

    left: float = 0.8
    right: float = 0.2
    bottom: float = 0.55
    top: float = 0.3
    wspace: float = 0.75
    hspace: float = 0.75
    colorbar: float = 0.0

    def but(self, **changes) -> Space:
        return replace(self, **changes)


ONE_PANEL = Space(left=0.85, top=0.35)  # one panel with labelled axes and a one-line title


def title_height(title: str, points: float = TITLE_PT) -> float:
    """Inches taken by a title of ``title``'s lines at ``points`` (none for an empty title)."""
    return 0.0 if not title else PAD + (title.count("\n") + 1) * points * LINE / 72


def grid(fig: Figure, nrows: int, ncols: int, space: Space, title: str = "", **subplot_kw) -> np.ndarray:
    """A (nrows, ncols) array of axes placed by ``space`` on ``fig`` (whose size is fixed), under
    the figure's title ``title`` (``fig.suptitle``; none when empty). ``subplot_kw``: sharex,
    sharey, and the like, as ``Figure.subplots`` takes them."""
    width, height = fig.get_size_inches()
    top = space.top + title_height(title)
    right = space.right + space.colorbar
    panel_w = (width - space.left - right - (ncols - 1) * space.wspace) / ncols
    panel_h = (height - space.bottom - top - (nrows - 1) * space.hspace) / nrows
    if panel_w <= 0 or panel_h <= 0:
        raise ValueError(f"a {width:g} × {height:g} in figure has no room for {nrows} × {ncols} panels: {space}")
    spec = fig.add_gridspec(
        nrows,
        ncols,
        left=space.left / width,
        right=1 - right / width,
        bottom=space.bottom / height,
        top=1 - top / height,
        wspace=space.wspace / panel_w,
        hspace=space.hspace / panel_h,
    )
    axes = spec.subplots(squeeze=False, **subplot_kw)
    if title:
        fig.suptitle(title, y=1 - PAD / height, va="top", fontsize=TITLE_PT)
    return axes


def colorbar(fig: Figure, mappable, axes: np.ndarray, space: Space, shrink: float = 1.0, **kwargs):
    """A colour bar in ``space``'s column right of ``axes`` (their full height × ``shrink``,
    centred); ``kwargs`` go to ``Figure.colorbar`` (label, extend, …)."""
    width, _ = fig.get_size_inches()
    boxes = [ax.get_position() for ax in np.ravel(axes)]
    y0, y1 = min(b.y0 for b in boxes), max(b.y1 for b in boxes)
    x0 = max(b.x1 for b in boxes) + BAR / width
    h = (y1 - y0) * shrink
    cax = fig.add_axes((x0, y0 + (y1 - y0 - h) / 2, BAR / width, h))
    return fig.colorbar(mappable, cax=cax, **kwargs)


def collisions(fig: Figure) -> list[str]:
    """What a fixed layout got wrong, drawn and measured once (for tests and for a new figure):
    each panel's extent with its ticks, labels, title and legend (``Axes.get_tightbbox``), the
    figure's title and legends, named where one leaves the figure or two of them overlap. Empty:
    every text is inside the figure and apart from the other panels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw_without_rendering()
    parts = [
        (f"panel {k} ({ax.get_title() or ax.get_ylabel()!r})", ax.get_tightbbox(renderer))
        for k, ax in enumerate(fig.axes)
    ]
    title = getattr(fig, "_suptitle", None)  # matplotlib keeps the figure's title here only
    if title is not None:
        parts.append(("the figure's title", title.get_window_extent(renderer)))
    parts += [(f"figure legend {k}", legend.get_window_extent(renderer)) for k, legend in enumerate(fig.legends)]
    found = [f"{name} leaves the figure" for name, box in parts if not _inside(box, fig.bbox)]
    for i, (a, box_a) in enumerate(parts):
        found += [f"{a} overlaps {b}" for b, box_b in parts[i + 1 :] if _overlap(box_a, box_b)]
    return found


def _inside(box, frame, tolerance: float = 1.0) -> bool:
    return (
        box.x0 >= frame.x0 - tolerance
        and box.y0 >= frame.y0 - tolerance
        and box.x1 <= frame.x1 + tolerance
        and box.y1 <= frame.y1 + tolerance
    )


def _overlap(a, b, tolerance: float = 1.0) -> bool:
    return min(a.x1, b.x1) - max(a.x0, b.x0) > tolerance and min(a.y1, b.y1) - max(a.y0, b.y0) > tolerance
