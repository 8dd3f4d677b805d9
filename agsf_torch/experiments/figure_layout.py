"""Placing a figure's panels from the sizes of their texts, without a layout engine.

matplotlib's ``tight_layout`` (and the constrained layout alike) finds the margins by measuring the full extent of
every artist of every panel, which lays out every tick and text once more before the figure is drawn: half of the
time an experiment's four figures took (measured on an AMD EPYC VM: 1.09 s a case with it, 0.57 s without).  The
figures of :mod:`.figures` are grids of panels whose margins depend on a few texts only: the widest y tick label of
each column, the axis labels, the panel titles, the figure's title and the legend band below.  :func:`fit_grid`
measures those strings with the renderer's font metrics (no drawing) and places the grid with the same paddings
``tight_layout`` leaves (:data:`PAD_IN`), so that no text is clipped or overlaps a neighbouring panel.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

__all__ = ["fit_grid", "PAD_IN"]

#: The padding around the texts at the figure's edges and between panels, inches (``tight_layout``'s default
#: ``pad=1.08`` font sizes of 10 pt, 0.15 in).
PAD_IN = 0.15
_PT = 1.0 / 72.0  # inches per point


@functools.lru_cache(maxsize=1)
def _metrics():
    """A renderer that measures text at 72 dpi (one pixel a point), and nothing else."""
    from matplotlib.backends.backend_agg import RendererAgg

    return RendererAgg(1, 1, 72)


@functools.lru_cache(maxsize=4096)
def _size(text: str, size: float) -> tuple[float, float]:
    """Width and height of ``text`` (lines separated by ``\n``; mathtext between ``$``) at ``size`` points, inches:
    the widest line, and the lines at matplotlib's line spacing (1.2).  Remembered: a figure's tick labels repeat
    from panel to panel (a mathtext label takes a millisecond to lay out)."""
    from matplotlib import cbook
    from matplotlib.font_manager import FontProperties

    if not text:
        return 0.0, 0.0
    prop = FontProperties(size=size)
    lines = text.split("\n")
    width = 0.0
    for line in lines:
        w, _, _ = _metrics().get_text_width_height_descent(line, prop, ismath=cbook.is_math_text(line))
        width = max(width, w)
    return width * _PT, 1.2 * size * len(lines) * _PT


def _points(key: str) -> float:
    from matplotlib import rcParams
    from matplotlib.font_manager import FontProperties

    return FontProperties(size=rcParams[key]).get_size_in_points()


def _ytick_labels(ax: Any) -> list[str]:
    """The y tick labels ``ax`` will draw, major and minor (a log axis spanning less than a decade labels minor
    ticks, ``6×10⁻¹``): each locator's ticks inside the view, through its formatter."""
    axis = ax.yaxis
    if not axis.get_tick_params().get("labelleft", True) or not axis.get_visible():
        return []
    lo, hi = sorted(axis.get_view_interval())
    tol = 1e-9 * max(abs(lo), abs(hi), 1e-300)
    labels = []
    for locator, formatter in (
        (axis.get_major_locator(), axis.get_major_formatter()),
        (axis.get_minor_locator(), axis.get_minor_formatter()),
    ):
        locs = np.asarray(locator(), dtype=float)
        locs = locs[(locs >= lo - tol) & (locs <= hi + tol)]
        labels += [s for s in formatter.format_ticks(locs) if s]
    return labels


def _xticks_shown(ax: Any) -> bool:
    return bool(ax.xaxis.get_tick_params().get("labelbottom", True)) and ax.xaxis.get_visible()


def fit_grid(fig: Any, grid: Any, *, bottom_band: float = 0.0) -> None:
    """Place the panels ``grid`` (``[rows, columns]`` of axes, from :meth:`Figure.subplots`) of ``fig`` from the sizes
    of their texts: the left margin and the gap before each column hold its y label and its widest y tick label,
    the top margin the figure's title (``suptitle``) and the first row's panel titles, the gap above each row its
    titles and the x tick labels and x label of the row above, the bottom margin the last row's x tick labels and
    x label above a band of ``bottom_band`` inches (a figure legend), each text :data:`PAD_IN` from its neighbour.

    Call it when everything is on the panels (limits, scales, labels, titles); ``fig``'s layout engine is not used.
    """
    from matplotlib import rcParams

    grid = np.asarray(grid, dtype=object).reshape(np.shape(grid)[0], -1)
    rows, cols = grid.shape
    width, height = fig.get_size_inches()
    ytick = _points("ytick.labelsize")
    xtick = _points("xtick.labelsize")
    label = _points("axes.labelsize")
    ticks = (max(rcParams["ytick.major.size"], 0.0) + rcParams["ytick.major.pad"]) * _PT
    xticks = (max(rcParams["xtick.major.size"], 0.0) + rcParams["xtick.major.pad"]) * _PT
    labelpad = rcParams["axes.labelpad"] * _PT
    titlepad = rcParams["axes.titlepad"] * _PT

    def column_left(c: int) -> float:
        """What lies left of column ``c``'s panels: its y tick labels, its y label."""
        tick_w = max((_size(s, ytick)[0] for r in range(rows) for s in _ytick_labels(grid[r, c])), default=0)
        label_h = max((_size(grid[r, c].get_ylabel(), label)[1] for r in range(rows)), default=0)
        return (tick_w + ticks if tick_w else 0.0) + (label_h + labelpad if label_h else 0.0)

    def row_title(r: int) -> float:
        heights = [_size(ax.get_title(), ax.title.get_fontsize())[1] for ax in grid[r]]
        return max(heights, default=0) + titlepad if max(heights, default=0) else 0.0

    def row_below(r: int) -> float:
        """What lies below row ``r``'s panels: its x tick labels, its x label."""
        below = xticks + _size("0", xtick)[1] if any(_xticks_shown(ax) for ax in grid[r]) else 0.0
        label_h = max((_size(ax.get_xlabel(), label)[1] for ax in grid[r]), default=0)
        return below + (label_h + labelpad if label_h else 0.0)

    suptitle = getattr(fig, "_suptitle", None)
    top_text = 0.0
    if suptitle is not None and suptitle.get_text():
        top_text = (1.0 - suptitle.get_position()[1]) * height + _size(suptitle.get_text(), suptitle.get_fontsize())[1]
    left = PAD_IN + column_left(0)
    right = PAD_IN
    top = PAD_IN + top_text + row_title(0)
    bottom = PAD_IN + bottom_band + row_below(rows - 1)
    gaps_x = [column_left(c) + PAD_IN for c in range(1, cols)]
    gaps_y = [row_below(r - 1) + row_title(r) + PAD_IN for r in range(1, rows)]
    # matplotlib's grid spaces its gaps evenly: the widest gap each way, as a fraction of a panel
    gap_x, gap_y = max(gaps_x, default=0.0), max(gaps_y, default=0.0)
    panel_w = (width - left - right - (cols - 1) * gap_x) / cols
    panel_h = (height - top - bottom - (rows - 1) * gap_y) / rows
    if panel_w <= 0 or panel_h <= 0:
        raise ValueError(f"the texts of a {rows}×{cols} figure of {width:g}×{height:g} in leave no room for its panels")
    fig.subplots_adjust(
        left=left / width,
        right=1.0 - right / width,
        bottom=bottom / height,
        top=1.0 - top / height,
        wspace=gap_x / panel_w,
        hspace=gap_y / panel_h,
    )
