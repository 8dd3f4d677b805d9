"""The figures of an experiment (PNG), drawn from its ``summary.json`` alone.

One function per figure builds a :class:`matplotlib.figure.Figure` without
touching pyplot's global state (no backend is selected, no figure is left
open); :func:`write_figures` saves them:

* ``rms.png`` (:func:`rms_figure`): per filter, the RMS over the runs of the
  attitude error angle (deg, log scale);
* ``axes.png`` (:func:`axes_figure`): per filter, the RMS over the runs of the
  rotation error about each body axis of the truth (arcsec) beside 3× the RMS of
  the filter's own σ, log scale; with bias states also the gyro-bias error (deg/h);
* ``weights.png`` (:func:`weights_figure`): per mixture filter, run 0's
  component weights, stacked (each band's thickness one component's weight);
* ``fpke.png`` (:func:`fpke_figure`): the fraction of the FPKE residual ``wᵀLw`` the weight update leaves (mean over the
  runs) with the propagated weights (before the weight update) and the adapted
  weights (after it);
* ``mixture.png`` (:func:`mixture_figure`), only with a managed filter: the life of each managed filter's mixture,
  the components in use (mean and min–max over the runs) and the splits, merges and prunes so far (mean per run).

Panels, titles and the figure legends (``"outside lower center"``) are placed by matplotlib's constrained layout.

Lines carry a ``gid`` naming what they plot (``"GSF/rms_error/0"``,
``"GSF/3sigma/0"``, ``"AGSF/weight_top/2"``, …) so that tests and notebooks can
find them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ...storage.files import save_figure
from ..run.file_writer import FileWriter

__all__ = [
    "ARCSEC_PER_RAD",
    "DEG_PER_HOUR_PER_RAD_PER_S",
    "axes_figure",
    "fpke_figure",
    "mixture_figure",
    "rms_figure",
    "weights_figure",
    "runtime_rc_params",
    "write_figure",
    "write_figures",
]

#: rad → arcsec.
ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0
#: rad/s → deg/h.
DEG_PER_HOUR_PER_RAD_PER_S = 180.0 / math.pi * 3600.0

_BODY_AXES = ("x", "y", "z")
_LINESTYLES = ("-", (0, (6, 2)), (0, (4, 1.5, 1, 1.5)), (0, (1.5, 1.5)), (0, (8, 2, 1, 2, 1, 2)))
_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*", "<", ">")


def _figure(figsize: tuple[float, float]) -> Any:
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, layout="constrained")


def _nothing_to_show(message: str) -> Any:
    """A small figure holding only ``message``: a figure whose filters are absent from the experiment."""
    fig = _figure((6.0, 2.5))
    ax = fig.add_subplot()
    ax.axis("off")
    ax.text(0.5, 0.5, message, ha="center", va="center", transform=ax.transAxes)
    return fig


def _filter_colors(summary: dict[str, Any]) -> dict[str, str]:
    """One colour per filter, the same in every figure (in the summary's order)."""
    return {name: f"C{i % 10}" for i, name in enumerate(summary["filters"])}


def _star_times(summary: dict[str, Any]) -> np.ndarray:
    t = np.asarray(summary["time_s"], dtype=float)
    frames = np.asarray(summary.get("star_frame", np.zeros(len(t), bool)), dtype=bool)
    return t[frames] if frames.shape == t.shape else np.zeros(0)


def _mark_star_frames(ax: Any, times: np.ndarray, top: bool = False) -> Any:
    """The star frames: faint vertical lines, or with ``top`` (and on every plot whose frames could be
    taken for grid lines) downward triangles along the top edge of the axes; returns the artist for a
    legend, or ``None`` when there are no frames.  Each marks ``gid="star_frame"``."""
    if len(times) == 0:
        return None
    if top:
        (marks,) = ax.plot(
            times,
            np.ones(len(times)),
            ls="none",
            marker="v",
            markersize=5,
            color="0.15",
            clip_on=False,
            zorder=5,
            transform=ax.get_xaxis_transform(),  # x in data, y in axes coordinates: on the top edge
            gid="star_frame",
        )
        return marks
    first = None
    for k, s in enumerate(times):
        line = ax.axvline(s, color="0.55", lw=0.6, alpha=0.45, zorder=0, gid="star_frame")
        if k == 0:
            first = line
    return first


def _runs(summary: dict[str, Any]) -> int:
    return int(summary["config"]["runs"])


def rms_figure(summary: dict[str, Any]) -> Any:
    """``rms.png``: the RMS over the runs of the attitude error angle (deg) of every filter, log scale, from
    ``t = 0`` (the prior, every filter's estimate before its first step: ``summary["prior_rms_deg"]``)."""
    t = np.asarray(summary["time_s"], dtype=float)
    prior = summary.get("prior_rms_deg")
    if prior is not None:
        t = np.concatenate(([0.0], t))
    colors = _filter_colors(summary)
    fig = _figure((7.5, 4.4))
    ax = fig.add_subplot()
    star = _mark_star_frames(ax, _star_times(summary), top=True)
    for name, f in summary["filters"].items():
        rms = f["rms_deg"] if prior is None else [prior, *f["rms_deg"]]
        ax.plot(t, rms, color=colors[name], lw=1.4, label=name, gid=f"{name}/rms")
    if prior is not None:
        ax.plot([0.0], [prior], "o", color="0.25", ms=4, label="the prior (t = 0)", gid="prior")
    ax.set_yscale("log")
    ax.set(
        xlabel="time (s)",
        ylabel="RMS attitude error angle (deg)",
        title=f"{_label(summary)}: RMS over {_runs(summary)} runs of the attitude error angle",
    )
    ax.grid(True, which="both", alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if star is not None:
        handles.append(star)
        labels.append("star frame")
    ax.legend(handles, labels, fontsize=8)
    return fig


def _fmt_tick(v: float, _pos: Any = None) -> str:
    if v == 0:
        return "0"
    if abs(v) >= 1:
        return f"{v:,.0f}".replace("-", "−")
    return f"{v:.3g}".replace("-", "−")


def _set_range(axs: list[Any], values: np.ndarray, spread: np.ndarray) -> str:
    """One y range for ``axs`` that shows every value: linear when the band spans
    less than 1.5 decades, else symlog, linear within ±(the band's low end rounded
    to a power of 10) and labelled at whole decades.  Returns a note for the axis
    label (``""`` or ``"linear within ±1"``)."""
    from matplotlib.ticker import FixedLocator, FuncFormatter

    finite = np.abs(values[np.isfinite(values)])
    top = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    positive = spread[np.isfinite(spread) & (spread > 0)]
    low = float(np.percentile(positive, 5)) if positive.size else top
    if top / low < 30:
        for ax in axs:
            ax.set_ylim(-1.1 * top, 1.1 * top)
            ax.yaxis.set_major_formatter(FuncFormatter(_fmt_tick))
        return ""
    e0 = round(math.log10(low))
    linthresh = 10.0**e0
    lim = top * 10**0.15
    e1 = math.floor(math.log10(lim))  # the highest decade inside the range
    step = 1 if e1 - e0 <= 3 else 2  # at most ~4 labelled decades per sign
    major = [10.0**e for e in range(e0, e1 + 1, step)]
    minor = [10.0**e for e in range(e0, e1 + 1) if 10.0**e not in major]
    for ax in axs:
        ax.set_yscale("symlog", linthresh=linthresh, linscale=1.0)
        ax.set_ylim(-lim, lim)
        ax.yaxis.set_major_locator(FixedLocator([-v for v in reversed(major)] + [0.0] + major))
        ax.yaxis.set_minor_locator(FixedLocator([-v for v in reversed(minor)] + minor))
        ax.yaxis.set_major_formatter(FuncFormatter(_fmt_tick))
        ax.grid(True, which="minor", alpha=0.15)
    return f"linear within ±{_fmt_tick(linthresh)}"


def axes_figure(summary: dict[str, Any]) -> Any:
    """``axes.png``: per filter and state axis, the RMS over the runs of the error and 3× the RMS of the filter's
    own σ, on a log scale.

    Rows are filters; the first three columns the rotation error about body x, y, z (``rms_error_axes_rad`` →
    arcsec) with ``3·rms_sigma_axes_rad``; with bias states (``n = 6``) three more columns the gyro-bias error
    (rad/s → deg/h).  A consistent filter's error curve runs below its dashed 3σ curve; one run's trace would
    be a forest of sign changes at every frame, and its band would span decades.  Star frames are marked along
    the top edge.  Lines: ``"{filter}/rms_error/{k}"`` and ``"{filter}/3sigma/{k}"``.
    """
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter, LogLocator, NullLocator

    t = np.asarray(summary["time_s"], dtype=float)
    filters = summary["filters"]
    colors = _filter_colors(summary)
    names = list(filters)
    n = np.asarray(filters[names[0]]["rms_error_axes_rad"]).shape[-1]
    bias = n >= 6
    ncol = 6 if bias else 3
    stars = _star_times(summary)
    fig = _figure((3.5 * ncol, 2.4 * len(names) + 1.3))
    grid = fig.subplots(len(names), ncol, squeeze=False, sharex=True)
    groups: dict[str, tuple[list[Any], list[np.ndarray]]] = {"attitude": ([], []), "bias": ([], [])}
    star = None
    for row, name in enumerate(names):
        err_rad = np.asarray(filters[name]["rms_error_axes_rad"], dtype=float)
        sig_rad = np.asarray(filters[name]["rms_sigma_axes_rad"], dtype=float)
        for col in range(ncol):
            ax, k = grid[row, col], col
            if col < 3:
                scale, group = ARCSEC_PER_RAD, "attitude"
                title = f"{name}: rotation error about body {_BODY_AXES[col]}"
                ylabel = "RMS error (arcsec)"
            else:
                scale, group = DEG_PER_HOUR_PER_RAD_PER_S, "bias"
                title = f"{name}: gyro bias error, body {_BODY_AXES[col - 3]}"
                ylabel = "RMS error (deg/h)"
            err = err_rad[:, k] * scale
            band = 3.0 * sig_rad[:, k] * scale
            ax.plot(t, band, color="0.35", ls="--", lw=0.9, zorder=2, gid=f"{name}/3sigma/{k}")
            ax.plot(t, err, color=colors[name], lw=1.2, zorder=3, gid=f"{name}/rms_error/{k}")
            ax.set_yscale("log")
            star = _mark_star_frames(ax, stars, top=True)
            ax.set_title(title, fontsize=9)
            if col in (0, 3):
                ax.set_ylabel(ylabel)
            if row == len(names) - 1:
                ax.set_xlabel("time (s)")
            ax.grid(True, which="major", alpha=0.3)
            axs, vals = groups[group]
            axs.append(ax)
            vals.extend([err, band])
    for axs, vals in groups.values():
        if axs:
            v = np.concatenate(vals)
            v = v[np.isfinite(v) & (v > 0)]
            lo, hi = (float(v.min()), float(v.max())) if v.size else (1e-3, 1.0)
            for ax in axs:  # one range per group: every filter on the same scale, every value shown
                ax.set_ylim(lo / 1.5, hi * 1.5)
                ax.yaxis.set_major_locator(LogLocator(base=10.0, numticks=12))
                ax.yaxis.set_major_formatter(FuncFormatter(_fmt_tick))
                # no minor ticks: a decade is ~35 px here, so its eight marks stood 4 px apart (clutter, not a
                # scale), and they were 60 % of the figure's drawing time
                ax.yaxis.set_minor_locator(NullLocator())
    runs = _runs(summary)
    handles: list[Any] = [Line2D([], [], color=colors[name], lw=1.5) for name in names]
    labels = [f"{name}: RMS error over {runs} runs" for name in names]
    handles.append(Line2D([], [], color="0.35", ls="--", lw=0.9))
    labels.append("3 × RMS of the filter's σ")
    _figure_legend(fig, handles, labels, star, 3)
    what = "error about the true body axes" + (" and gyro bias error" if bias else "")
    state = "" if bias else "\n(the filters' state: the attitude alone, no gyro-bias states)"
    fig.suptitle(
        f"{_label(summary)}: RMS over {runs} runs of the {what}, and 3× the RMS of each filter's σ{state}",
        fontsize=11,
    )
    return fig


def weights_figure(summary: dict[str, Any]) -> Any:
    """``weights.png``: run 0's component weights of every mixture filter, one panel each, stacked.

    The weights sum to 1, so each component is drawn as a band whose thickness is its weight, stacked in
    component order (band ``i`` spans ``Σ_{j<i} w_j … Σ_{j≤i} w_j``): components with equal weights are
    bands of equal thickness side by side, never one line hidden under another.  The upper edge of band
    ``i`` is a line with ``gid`` ``"{filter}/weight_top/{i}"``; the band itself ``"{filter}/weight/{i}"``.
    """
    t = np.asarray(summary["time_s"], dtype=float)
    shown = {
        name: np.asarray(f["weights_run0"], dtype=float)
        for name, f in summary["filters"].items()
        if np.asarray(f["weights_run0"]).ndim == 2 and np.asarray(f["weights_run0"]).shape[1] > 1
    }
    stars = _star_times(summary)
    if not shown:
        return _nothing_to_show("no mixture filter in this experiment:\nno component weights to show")
    from matplotlib.patches import Patch

    ncomp = max(w.shape[1] for w in shown.values())
    fig = _figure((12.0, 2.6 * len(shown) + 1.0))
    grid = fig.subplots(len(shown), 1, squeeze=False, sharex=True)
    colors = [f"C{i % 10}" for i in range(ncomp)]
    star = None
    for row, (name, w) in enumerate(shown.items()):
        ax = grid[row, 0]
        top = np.cumsum(w, axis=1)
        bottom = np.concatenate((np.zeros_like(top[:, :1]), top[:, :-1]), axis=1)
        for i in range(w.shape[1]):
            ax.fill_between(
                t, bottom[:, i], top[:, i], color=colors[i], alpha=0.8, lw=0, step="post", gid=f"{name}/weight/{i}"
            )
            ax.plot(t, top[:, i], color="white", lw=0.6, drawstyle="steps-post", gid=f"{name}/weight_top/{i}")
        star = _mark_star_frames(ax, stars, top=True)
        ax.set(title=name, ylabel="weight (stacked, sum 1)", ylim=(0.0, 1.0), xlim=(float(t[0]), float(t[-1])))
        if row == len(shown) - 1:
            ax.set_xlabel("time (s)")
    handles: list[Any] = [Patch(facecolor=colors[i], alpha=0.8) for i in range(ncomp)]
    labels = [f"component {i}" for i in range(ncomp)]  # 0-based, as runs.npz, the event tags and the errors
    _figure_legend(fig, handles, labels, star, 8)
    fig.suptitle(
        f"{_label(summary)}: component weights of each mixture filter, run 0 "
        "(stacked: each band's thickness is one component's weight)",
        fontsize=11,
    )
    return fig


def _figure_legend(fig: Any, handles: list[Any], labels: list[str], star: Any, columns: int) -> None:
    """The figure's one legend below its axes: ``handles``/``labels``, then the star-frame mark if drawn, in at most
    ``columns`` columns."""
    if star is not None:
        handles, labels = [*handles, star], [*labels, "star frame"]
    fig.legend(handles, labels, loc="outside lower center", ncol=min(len(labels), columns), fontsize=9, frameon=False)


def fpke_figure(summary: dict[str, Any]) -> Any:
    """``fpke.png``: the fraction of the FPKE residual ``wᵀLw = ∫e² dx`` the weight update leaves,
    ``wᵀLw(after) / wᵀLw(before)`` (the adapted weights against the propagated ones at the same step), per
    run, then its mean and its 10–90 % range over the runs.  The residual itself scales with the
    covariances (``L`` grows as the components narrow) and cannot be compared across time; the ratio can:
    1 means the update removed nothing, 0.1 that it removed 90 %."""
    t = np.asarray(summary["time_s"], dtype=float)
    colors = _filter_colors(summary)
    fig = _figure((7.8, 4.6))
    ax = fig.add_subplot()
    star = _mark_star_frames(ax, _star_times(summary), top=True)
    recorded = [n for n, f in summary["filters"].items() if "fpke_ratio_mean" in f]
    others = [n for n, f in summary["filters"].items() if "fpke_ratio_mean" not in f]
    for name in recorded:
        f = summary["filters"][name]
        lo, hi = (np.asarray(v, dtype=float) for v in f["fpke_ratio_p10_p90"])
        ax.fill_between(t, lo, hi, color=colors[name], alpha=0.18, lw=0, gid=f"{name}/fpke_ratio_band")
        ax.plot(
            t,
            f["fpke_ratio_mean"],
            color=colors[name],
            lw=1.4,
            label=f"{name}: mean over runs (band: 10–90 % of runs)",
            gid=f"{name}/fpke_ratio",
        )
    ax.axhline(1.0, color="0.4", lw=0.8, ls=":", label="1: the update removed nothing")
    ax.set(xlabel="time (s)", ylabel="residual left by the weight update\nwᵀLw(adapted w) / wᵀLw(propagated w)")
    ax.set_title(
        f"{_label(summary)}: FPKE residual ∫e² dx after the weight update relative to before it, {_runs(summary)} runs",
        fontsize=10,
    )
    ax.grid(True, which="both", alpha=0.3)
    if recorded:
        ax.set_yscale("log")
        handles, labels = ax.get_legend_handles_labels()
        if star is not None:
            handles.append(star)
            labels.append("star frame")
        ax.legend(handles, labels, fontsize=8)
        if others:  # under the title, where no curve or legend runs
            ax.set_title(ax.get_title() + "\n(no FPKE residual recorded by: " + ", ".join(others) + ")", fontsize=10)
    else:
        ax.text(
            0.5,
            0.5,
            "no filter in this experiment records the FPKE residual",
            ha="center",
            va="center",
            transform=ax.transAxes,
        )
    return fig


#: The panels of :func:`mixture_figure` after the first: summary key, title and axis label of each event.
_MIXTURE_EVENTS = (
    ("splits", "splits so far: one component into three", "splits per run"),
    ("merges", "merges so far: a pair into one", "merges per run"),
    ("prunes", "prunes so far: a light component dropped", "prunes per run"),
)


def _managed(summary: dict[str, Any]) -> list[str]:
    """The filters of ``summary`` that manage their mixture (those with ``active_components_mean``)."""
    return [name for name, f in summary["filters"].items() if "active_components_mean" in f]


def mixture_figure(summary: dict[str, Any]) -> Any:
    """``mixture.png``: the life of each managed filter's mixture against time (s), four panels sharing the time axis.

    The first: the components in use at the end of each step (count), the mean over the runs
    (``active_components_mean [T]``) as a line and the fewest to the most (``active_components_min_max``, two
    ``[T]``) as a band.  Then one panel each for the splits, merges and prunes up to and including each step,
    per run, mean over the runs (``splits_cumulative_mean [T]`` and the like; count per trajectory).  Counts hold
    from one step to the next, so they are drawn as steps; each filter has its colour and its line style, so that
    filters whose curves coincide stay visible.  Lines: ``"{filter}/active_mean"`` (band
    ``"{filter}/active_band"``), ``"{filter}/splits_cumulative"``, ``"{filter}/merges_cumulative"``,
    ``"{filter}/prunes_cumulative"``.  Without a managed filter, a panel saying so.
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    managed = _managed(summary)
    if not managed:
        return _nothing_to_show("no managed filter in this experiment:\nno splits, merges or prunes to show")
    t = np.asarray(summary["time_s"], dtype=float)
    colors = _filter_colors(summary)
    styles = {name: _LINESTYLES[i % len(_LINESTYLES)] for i, name in enumerate(managed)}
    stars = _star_times(summary)
    runs = _runs(summary)
    fig = _figure((8.5, 9.0))
    axs = fig.subplots(1 + len(_MIXTURE_EVENTS), 1, sharex=True, squeeze=True)
    ax, tops = axs[0], [0.0] * len(axs)  # each panel's largest value
    for name in managed:
        f = summary["filters"][name]
        lo, hi = (np.asarray(v, dtype=float) for v in f["active_components_min_max"])
        tops[0] = max(tops[0], float(np.nanmax(hi)))
        ax.fill_between(t, lo, hi, color=colors[name], alpha=0.2, lw=0, step="post", gid=f"{name}/active_band")
        ax.plot(
            t,
            f["active_components_mean"],
            color=colors[name],
            ls=styles[name],
            lw=1.4,
            drawstyle="steps-post",
            gid=f"{name}/active_mean",
        )
    ax.set(title="components in use at the end of each step", ylabel="components (count)")
    for row, (key, title, ylabel) in enumerate(_MIXTURE_EVENTS, 1):
        ax = axs[row]
        for name in managed:
            cumulative = np.asarray(summary["filters"][name][f"{key}_cumulative_mean"], dtype=float)
            tops[row] = max(tops[row], float(np.nanmax(cumulative)))
            ax.plot(
                t,
                cumulative,
                color=colors[name],
                ls=styles[name],
                lw=1.4,
                drawstyle="steps-post",
                gid=f"{name}/{key}_cumulative",
            )
        ax.set(title=title, ylabel=f"{ylabel}\n(count, mean)")
    star = None
    for ax, top in zip(axs, tops, strict=True):
        star = _mark_star_frames(ax, stars, top=True)
        ax.yaxis.set_major_locator(MaxNLocator(integer=True, nbins=5))
        ax.set_xlim(float(t[0]), float(t[-1]))
        ax.set_ylim(0.0, 1.12 * top if top > 0 else 1.0)  # headroom below the star-frame marks on the top edge
        ax.grid(True, alpha=0.3)
        ax.title.set_fontsize(9)
    axs[-1].set_xlabel("time (s)")
    handles: list[Any] = [Line2D([], [], color=colors[name], ls=styles[name], lw=1.4) for name in managed]
    labels = [f"{name}: mean over {runs} runs" for name in managed]
    handles.append(Patch(facecolor="0.5", alpha=0.35))
    labels.append("fewest to most components over the runs")
    _figure_legend(fig, handles, labels, star, 3)
    fig.suptitle(
        f"{_label(summary)}: the mixture of each managed filter over {runs} runs:\n"
        "components in use, and splits, merges and prunes so far per run",
        fontsize=11,
    )
    return fig


#: file name → the function that builds it, the longest to draw first (the order a writer's workers take them in).
FIGURES = {
    "axes.png": axes_figure,
    "rms.png": rms_figure,
    "weights.png": weights_figure,
    "fpke.png": fpke_figure,
    "mixture.png": mixture_figure,
}
_DPI = {"rms.png": 110, "axes.png": 100, "weights.png": 100, "fpke.png": 110, "mixture.png": 100}


def _label(summary: dict[str, Any]) -> str:
    """What a figure's title calls the experiment: its label (a sweep's configuration: the preset and the
    parameters), else its configuration's name."""
    return summary.get("label") or summary["config"]["name"]


def write_figure(path: Path, summary: dict[str, Any], rc: dict[str, Any] | None = None) -> Path:
    """Draw the figure named by ``path``'s file name (a key of :data:`FIGURES`) from ``summary`` and save it there,
    with matplotlib's settings ``rc`` (:func:`runtime_rc_params`) applied over this process's."""
    import matplotlib

    path = Path(path)
    with matplotlib.rc_context(rc or {}):
        return save_figure(FIGURES[path.name](summary), path, dpi=_DPI[path.name])


def runtime_rc_params() -> dict[str, Any]:
    """The matplotlib settings this process changed since matplotlib read its ``matplotlibrc`` (none if it has not
    imported matplotlib), the backend left out: what a worker process, which reads the same file, needs to draw a
    figure as this process would."""
    import sys

    if "matplotlib" not in sys.modules:
        return {}
    import matplotlib

    changed = {}
    for key, value in matplotlib.rcParams.items():
        try:
            same = bool(value == matplotlib.rcParamsOrig[key])
        except (KeyError, ValueError, TypeError):
            same = False
        if key != "backend" and not same:
            changed[key] = value
    return changed


def write_figures(out: Path, summary: dict[str, Any], writer: FileWriter | None = None) -> list[Path]:
    """Write ``axes.png``, ``rms.png`` (these two with the truth only), ``weights.png``, ``fpke.png`` and, with a
    managed filter, ``mixture.png`` into ``out`` (each through ``writer``, a
    :class:`~agsf_torch.experiments.run.file_writer.FileWriter`, if given: then they may still be being drawn when this returns, by a process
    given this one's matplotlib settings); returns their paths."""
    truth = summary.get("scored_against_truth", True)  # rms.png and axes.png plot the errors against the truth
    skipped = set() if truth else {"rms.png", "axes.png"}
    if not _managed(summary):
        skipped.add("mixture.png")
    paths = [Path(out) / fname for fname in FIGURES if fname not in skipped]
    rc = runtime_rc_params() if writer is not None else None
    for path in paths:
        if writer is None:
            write_figure(path, summary)
        else:
            writer.submit(write_figure, path, summary, rc, path=path)
    return paths
