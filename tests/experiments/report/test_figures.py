"""The experiment figures state what they plot: units on the axes, every filter and
component in a legend, and the data of ``summary.json`` converted to the stated units."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.report.figures import (
    axes_figure,
    fpke_figure,
    mixture_figure,
    rms_figure,
    weights_figure,
    write_figures,
)
from agsf_torch.experiments.report.statistics import summarize
from tests.helpers import assert_within, relative_bound

ARCSEC = 180.0 / math.pi * 3600.0  # rad → arcsec, written out independently of the module
DEG_PER_HOUR = 180.0 / math.pi * 3600.0  # rad/s → deg/h
FILTERS = ["EKF", "GSF", "AGSF"]
MANAGED = ["GSF-managed", "AGSF-managed"]


def _management_counts(runs: int, steps: int, frames: np.ndarray, components: int, managed: int) -> dict:
    """Synthetic counts of the ``managed``-th managed filter (``[runs, steps]`` int64 each, the keys ``runs.npz``
    holds): every run merges all but two of its components at the first step; some runs (the even ones for the
    first filter, run 1 alone for the second) split one component at every star frame and, the step after, merge
    one pair and prune one component.  ``active_components`` follows: a split makes one component three."""
    splits, merges, prunes = (np.zeros((runs, steps), np.int64) for _ in range(3))
    merges[:, 0] = components - 2
    busy = np.arange(runs) % 2 == 0 if managed == 0 else np.arange(runs) == 1
    at = np.flatnonzero(frames)
    after = at[at + 1 < steps] + 1
    splits[np.ix_(busy, at)] = 1
    merges[np.ix_(busy, after)] += 1
    prunes[np.ix_(busy, after)] = 1
    active = components + np.cumsum(2 * splits - merges - prunes, 1)
    return {"active_components": active, "splits": splits, "merges": merges, "prunes": prunes}


def _summary(n: int = 3, components: int = 3, runs: int = 4, steps: int = 40, filters=FILTERS) -> dict:
    """A summary from ``summarize`` of synthetic per-run data (the keys ``runs.npz`` holds)."""
    cfg = load_config(
        "case1",
        [
            f"runs={runs}",
            "duration=4.0",
            f"filters={filters!r}".replace("'", '"'),
            f"components={components}",
            f"estimate_bias={'true' if n == 6 else 'false'}",
        ],
    )
    rng = np.random.default_rng(3)
    dt = 0.1
    time = dt * np.arange(1, steps + 1)
    frames = np.zeros(steps, bool)
    frames[9::10] = True
    decay = np.exp(-time / 0.8)[None, :, None]
    data = {"time": time, "star_frame": frames, "prior_error_angle": np.full(runs, 0.12)}
    for name in filters:
        N = 1 if name == "EKF" else components
        sigma = (2e-6 + 0.05 * decay) * np.ones((runs, steps, n))
        if n == 6:
            sigma[..., 3:] = 1e-7 * (1 + decay[..., :3] * np.ones((runs, steps, 3)))
        error = sigma * rng.normal(size=(runs, steps, n)) * 2.0
        weights = np.full((runs, steps, N), 1.0 / N)  # equal (overlapping) weights
        if N > 1:
            weights[:, frames, 0] = 1.0
            weights[:, frames, 1:] = 0.0
        data |= {
            f"{name}/error_angle": np.linalg.norm(error[..., :3], axis=-1),
            f"{name}/error": error,
            f"{name}/sigma": sigma,
            f"{name}/nees": rng.chisquare(n, size=(runs, steps)),
            f"{name}/weights": weights,
            f"{name}/weight_entropy": np.zeros((runs, steps)),
        }
        if name in MANAGED:
            counts = _management_counts(runs, steps, frames, components, MANAGED.index(name))
            data |= {f"{name}/{key}": values for key, values in counts.items()}
        if name == "AGSF":
            data[f"{name}/fpke_error_before"] = rng.uniform(1.0, 10.0, size=(runs, steps))
            data[f"{name}/fpke_error_after"] = data[f"{name}/fpke_error_before"] / 2
    return summarize(data, cfg)


def _plotted(actual, expected, what: str, rtol: float = 1e-7) -> None:
    """What a figure plots against the summary's data, converted independently: the data pass through unchanged
    or through one product, so ``rtol`` relative (numpy's assert_allclose default 1e-7 unless stated); an entry 0
    on both sides (t = 0) is exact.  An array is compared with one of its own shape."""
    if np.ndim(expected):
        assert np.shape(actual) == np.shape(expected), what
    assert_within(actual, expected, relative_bound(expected, rtol, 0.0), what)


def _lines(fig) -> dict:
    return {line.get_gid(): line for ax in fig.axes for line in ax.get_lines() if line.get_gid()}


def _legend_texts(fig) -> list[str]:
    legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    return [t.get_text() for leg in legends for t in leg.get_texts()]


@pytest.fixture(scope="module")
def summary3():
    return _summary()


@pytest.fixture(scope="module")
def summary6():
    return _summary(n=6)


@pytest.fixture(scope="module")
def summary_managed():
    return _summary(filters=["EKF", *MANAGED])


def test_axes_figure_plots_the_rms_error_of_each_filter_in_arcsec_beside_3_rms_sigma(summary3):
    """Per filter and body axis, log scale: the RMS over runs of the error and 3× the RMS of the filter's σ."""
    fig = axes_figure(summary3)
    lines = _lines(fig)
    t = np.array(summary3["time_s"])
    for name in FILTERS:
        err = np.array(summary3["filters"][name]["rms_error_axes_rad"])
        sig = np.array(summary3["filters"][name]["rms_sigma_axes_rad"])
        for k in range(3):
            _plotted(lines[f"{name}/rms_error/{k}"].get_xdata(), t, "time (s)")
            _plotted(lines[f"{name}/rms_error/{k}"].get_ydata(), err[:, k] * ARCSEC, "RMS error (arcsec)", 1e-12)
            _plotted(lines[f"{name}/3sigma/{k}"].get_ydata(), 3 * sig[:, k] * ARCSEC, "3 × RMS σ (arcsec)", 1e-12)
    grid = np.array(fig.axes).reshape(len(FILTERS), 3)
    for row, name in enumerate(FILTERS):
        for k, axis in enumerate("xyz"):
            ax = grid[row, k]
            assert name in ax.get_title() and f"about body {axis}" in ax.get_title()
            assert ax.get_yscale() == "log" and ax.get_legend() is None  # one legend for the figure
        assert "arcsec" in grid[row, 0].get_ylabel()
    assert all(ax.get_xlabel() == "time (s)" for ax in grid[-1])
    texts = _legend_texts(fig)
    assert len(fig.legends) == 1
    assert all(any(name in s and "RMS error over 4 runs" in s for s in texts) for name in FILTERS)
    assert any("3 × RMS" in s and "σ" in s for s in texts) and "star frame" in texts
    assert "the attitude alone, no gyro-bias states" in fig.get_suptitle()


def test_axes_figure_range_shows_every_value_with_a_label_at_every_decade(summary3):
    fig = axes_figure(summary3)
    FigureCanvasAgg(fig).draw()
    values = np.concatenate(
        [line.get_ydata() for ax in fig.axes for line in ax.get_lines() if "rms_error" in str(line.get_gid())]
    )
    for ax in fig.axes:
        lo, hi = ax.get_ylim()
        assert lo < values.min() and hi > values.max()  # one range for every filter: all values shown
        ticks = [v for v in ax.get_yticks() if lo <= v <= hi]
        exponents = np.log10(ticks)
        # every decade labelled, none skipped (log10 of powers of ten, to rounding)
        assert_within(np.diff(exponents), 1.0, 1e-7, "decades between labelled ticks")
        labels = [t.get_text() for t in ax.get_yticklabels() if lo <= t.get_position()[1] <= hi]
        assert not any("$" in s or "^" in s for s in labels), labels  # no mathtext powers like 10^0


def test_axes_figure_shows_the_bias_error_in_deg_per_hour_for_six_states(summary6):
    fig = axes_figure(summary6)
    lines = _lines(fig)
    grid = np.array(fig.axes).reshape(len(FILTERS), 6)
    for row, name in enumerate(FILTERS):
        err = np.array(summary6["filters"][name]["rms_error_axes_rad"])
        sig = np.array(summary6["filters"][name]["rms_sigma_axes_rad"])
        for k in range(3, 6):
            _plotted(lines[f"{name}/rms_error/{k}"].get_ydata(), err[:, k] * DEG_PER_HOUR, "bias error (deg/h)", 1e-12)
            _plotted(lines[f"{name}/3sigma/{k}"].get_ydata(), 3 * sig[:, k] * DEG_PER_HOUR, "3 × bias σ (deg/h)", 1e-12)
            assert "bias" in grid[row, k].get_title() and f"body {'xyz'[k - 3]}" in grid[row, k].get_title()
        assert "deg/h" in grid[row, 3].get_ylabel()
        assert "arcsec" in grid[row, 0].get_ylabel()
    assert "bias" in fig.get_suptitle()


def test_weights_figure_stacks_the_weights_so_that_equal_ones_stay_visible(summary3):
    """Each component a band whose thickness is its weight: the bands' upper edges are the cumulative sums
    (so equal weights are equal bands side by side, none hidden under another), and they fill [0, 1]."""
    fig = weights_figure(summary3)
    lines = _lines(fig)
    texts = _legend_texts(fig)
    assert [t for t in texts if t.startswith("component")] == ["component 0", "component 1", "component 2"]  # 0-based
    assert "star frame" in texts
    assert not any(gid.startswith("EKF/") for gid in lines)  # one component: no panel
    for name in ("GSF", "AGSF"):
        w = np.array(summary3["filters"][name]["weights_run0"])
        tops = np.stack([lines[f"{name}/weight_top/{i}"].get_ydata() for i in range(3)], axis=1)
        thickness = np.diff(np.concatenate((np.zeros((len(w), 1)), tops), axis=1), axis=1)
        # a difference of cumulative sums ≤ 1: 1e-15 absolute (a few ε of 1), beside numpy's default rtol 1e-7
        assert_within(thickness, w, relative_bound(w, 1e-7, 1e-15), "band thickness against the weight")
        assert_within(tops[:, -1], 1.0, relative_bound(1.0, 1e-7, 1e-12), "top edge of the last band")
        bands = {c.get_gid() for ax in fig.axes for c in ax.collections}
        assert {f"{name}/weight/{i}" for i in range(3)} <= bands
    frames = np.array(summary3["time_s"])[np.array(summary3["star_frame"])]
    (marks,) = [line for line in fig.axes[0].get_lines() if line.get_gid() == "star_frame"]
    _plotted(marks.get_xdata(), frames, "star frame times (s)")
    assert fig.axes[-1].get_xlabel() == "time (s)"
    assert all("weight" in ax.get_ylabel() for ax in fig.axes)


def test_weights_figure_without_mixture_filters_says_so():
    fig = weights_figure(_summary(filters=["EKF"]))
    assert any("no mixture filter" in t.get_text() for ax in fig.axes for t in ax.texts)


def test_rms_figure_states_what_it_plots(summary3):
    fig = rms_figure(summary3)
    (ax,) = fig.axes
    assert ax.get_yscale() == "log"
    assert "deg" in ax.get_ylabel() and ax.get_xlabel() == "time (s)"
    assert "RMS over 4 runs" in ax.get_title() and "attitude error angle" in ax.get_title()
    lines = _lines(fig)
    prior = np.degrees(0.12)  # the fixture's prior error in every run
    # the RMS of four equal values: relative (a sum of squares, no terms cancel)
    assert_within(summary3["prior_rms_deg"], prior, relative_bound(prior, 1e-12, 0.0), "prior RMS error (deg)")
    for name in FILTERS:  # every curve starts at the prior, t = 0
        _plotted(lines[f"{name}/rms"].get_ydata(), [prior, *summary3["filters"][name]["rms_deg"]], "RMS error (deg)")
        _plotted(lines[f"{name}/rms"].get_xdata(), [0.0, *summary3["time_s"]], "time (s)")
        assert name in _legend_texts(fig)
    _plotted(lines["prior"].get_xydata(), [[0.0, prior]], "the prior's mark")
    assert "the prior (t = 0)" in _legend_texts(fig)
    # star frames as marks on the top edge (vertical lines at whole seconds would read as grid lines)
    frames = np.array(summary3["time_s"])[np.array(summary3["star_frame"])]
    marks = lines["star_frame"]
    _plotted(marks.get_xdata(), frames, "star frame times (s)")
    assert marks.get_linestyle() == "None" and marks.get_marker() == "v"
    _plotted(marks.get_ydata(), 1.0, "star frame marks' height")  # in axes coordinates: the top edge
    assert marks.get_transform() == ax.get_xaxis_transform()
    assert "star frame" in _legend_texts(fig)


def test_fpke_figure_shows_the_fraction_of_the_residual_the_update_leaves(summary3):
    """The fixture's update halves every residual: the ratio is 0.5 in every run, its band collapses there."""
    fig = fpke_figure(summary3)
    (ax,) = fig.axes
    lines = _lines(fig)
    f = summary3["filters"]["AGSF"]
    _plotted(lines["AGSF/fpke_ratio"].get_ydata(), 0.5, "mean FPKE residual ratio")
    _plotted(f["fpke_ratio_p10_p90"], 0.5, "10–90 % range of the FPKE residual ratio")
    band = next(c for c in ax.collections if c.get_gid() == "AGSF/fpke_ratio_band")
    assert band.get_paths()  # the 10–90 % band is drawn
    texts = _legend_texts(fig)
    assert any("AGSF" in s and "mean over runs" in s for s in texts)
    assert any("removed nothing" in s for s in texts)
    assert "relative to before it" in ax.get_title() and "4 runs" in ax.get_title()
    assert ax.get_yscale() == "log" and ax.get_xlabel() == "time (s)" and "wᵀLw(adapted w)" in ax.get_ylabel()
    assert "no FPKE residual recorded by: EKF, GSF" in ax.get_title()  # who does not record it


def test_mixture_figure_draws_each_managed_filters_count_and_its_events_so_far(summary_managed):
    """The count in use, mean and fewest–most over the runs, and the splits, merges and prunes up to each step per
    run, mean over the runs: the fixture's counts (:func:`_management_counts`) summed here step by step."""
    fig = mixture_figure(summary_managed)
    lines = _lines(fig)
    t = np.array(summary_managed["time_s"])
    frames = np.array(summary_managed["star_frame"])
    runs, steps = 4, len(t)
    for i, name in enumerate(MANAGED):
        counts = {k: v.tolist() for k, v in _management_counts(runs, steps, frames, 3, i).items()}
        active = counts["active_components"]
        mean = [sum(active[b][k] for b in range(runs)) / runs for k in range(steps)]
        _plotted(lines[f"{name}/active_mean"].get_xdata(), t, "time (s)")
        _plotted(lines[f"{name}/active_mean"].get_ydata(), mean, "mean count in use")
        lo, hi = summary_managed["filters"][name]["active_components_min_max"]
        assert lo == [min(active[b][k] for b in range(runs)) for k in range(steps)]
        assert hi == [max(active[b][k] for b in range(runs)) for k in range(steps)]
        band = next(c for ax in fig.axes for c in ax.collections if c.get_gid() == f"{name}/active_band")
        ys = np.concatenate([p.vertices[:, 1] for p in band.get_paths()])
        assert (ys.min(), ys.max()) == (2.0, 4.0)  # two components, four at the frames of the busy runs
        for key in ("splits", "merges", "prunes"):
            so_far = [sum(counts[key][b][j] for b in range(runs) for j in range(k + 1)) / runs for k in range(steps)]
            _plotted(lines[f"{name}/{key}_cumulative"].get_ydata(), so_far, f"{key} so far per run")
    # by hand: the first filter's two busy runs split at 4 frames, merge and prune after 3 of them; the second's one
    for name, (splits, merges, prunes, at_frame) in zip(MANAGED, [(2.0, 2.5, 1.5, 3.0), (1.0, 1.75, 0.75, 2.5)]):
        assert lines[f"{name}/splits_cumulative"].get_ydata()[-1] == splits
        assert lines[f"{name}/merges_cumulative"].get_ydata()[-1] == merges
        assert lines[f"{name}/prunes_cumulative"].get_ydata()[-1] == prunes
        assert set(np.asarray(lines[f"{name}/active_mean"].get_ydata())[frames]) == {at_frame}
        assert set(np.asarray(lines[f"{name}/active_mean"].get_ydata())[~frames]) == {2.0}
    assert not any(gid.startswith("EKF/") for gid in lines)  # not managed: not drawn
    top, *events = fig.axes
    assert top.get_ylabel() == "components (count)" and "in use" in top.get_title()
    for ax, key in zip(events, ("splits", "merges", "prunes"), strict=True):
        assert key in ax.get_title() and f"{key} per run" in ax.get_ylabel() and "count" in ax.get_ylabel()
    assert fig.axes[-1].get_xlabel() == "time (s)"
    texts = _legend_texts(fig)
    assert len(fig.legends) == 1 and [f"{name}: mean over 4 runs" for name in MANAGED] == texts[:2]
    assert "fewest to most components over the runs" in texts and "star frame" in texts
    assert "4 runs" in fig.get_suptitle()


def test_mixture_figure_without_managed_filters_says_so(summary3):
    fig = mixture_figure(summary3)
    assert any("no managed filter" in t.get_text() for ax in fig.axes for t in ax.texts)


def test_write_figures_adds_the_mixture_figure_when_a_filter_is_managed(summary_managed, tmp_path):
    paths = write_figures(tmp_path, summary_managed)
    assert sorted(p.name for p in paths) == ["axes.png", "fpke.png", "mixture.png", "rms.png", "weights.png"]
    assert (tmp_path / "mixture.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_write_figures_writes_the_four_pngs_and_leaves_no_pyplot_figure_open(summary6, tmp_path):
    import matplotlib.pyplot as plt

    before = plt.get_fignums()
    paths = write_figures(tmp_path, summary6)
    assert sorted(p.name for p in paths) == ["axes.png", "fpke.png", "rms.png", "weights.png"]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert plt.get_fignums() == before


def test_a_figure_drawn_by_a_worker_follows_the_callers_matplotlib_settings(summary3, tmp_path, monkeypatch):
    """Settings changed at run time (a notebook's, say) reach the worker: its PNG is the caller's byte for byte."""
    from agsf_torch.experiments.run.file_writer import FileWriter
    from agsf_torch.experiments.run.worker_pool import fork_available

    if not fork_available():
        pytest.skip("worker processes are forked (Linux)")
    plain, here, worker = tmp_path / "plain", tmp_path / "here", tmp_path / "worker"
    for folder in (plain, here, worker):
        folder.mkdir()
    write_figures(plain, summary3)
    with FileWriter(1) as writer:  # its worker forked before the settings change
        assert writer.background
        with matplotlib.rc_context({"lines.linewidth": 4.0, "axes.facecolor": "#eeeeff"}):
            write_figures(here, summary3)
            write_figures(worker, summary3, writer)
    for name in ("rms.png", "axes.png", "weights.png", "fpke.png"):
        assert (worker / name).read_bytes() == (here / name).read_bytes(), name
    assert (here / "rms.png").read_bytes() != (plain / "rms.png").read_bytes()


def _overlap(a, b, slack: float = 1.0) -> bool:
    """Whether two display boxes (pixels) overlap by more than ``slack`` pixels each way."""
    return min(a.x1, b.x1) - max(a.x0, b.x0) > slack and min(a.y1, b.y1) - max(a.y0, b.y0) > slack


def _inside(box, fig_box, slack: float = 1.0) -> bool:
    return (
        box.x0 >= fig_box.x0 - slack
        and box.y0 >= fig_box.y0 - slack
        and box.x1 <= fig_box.x1 + slack
        and (box.y1 <= fig_box.y1 + slack)
    )


@pytest.mark.parametrize("n", [3, 6])
@pytest.mark.parametrize("figure", [axes_figure, rms_figure, weights_figure, fpke_figure])
def test_every_text_is_inside_the_figure_and_clear_of_the_other_panels(figure, n, summary3, summary6):
    """Placed by matplotlib's constrained layout: each panel's tick labels, axis labels and title, the figure legend
    and the figure title lie inside the figure, and none runs into another panel or, for the figure's title and
    legend, into any panel's texts."""
    _assert_texts_clear(figure(summary3 if n == 3 else summary6), figure)


def test_every_text_of_the_mixture_figure_is_inside_it_and_clear_of_the_other_panels(summary_managed):
    """As every figure (the test above), for the mixture figure of two managed filters."""
    _assert_texts_clear(mixture_figure(summary_managed), mixture_figure)


def _assert_texts_clear(fig, figure) -> None:
    """The texts of ``fig`` (drawn by ``figure``) inside it and clear of the other panels (the tests above)."""
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    fig_box = fig.bbox
    texts = {}
    for ax in fig.axes:
        boxes = [ax.yaxis.get_tightbbox(renderer), ax.xaxis.get_tightbbox(renderer)]
        if ax.get_title():
            boxes.append(ax.title.get_window_extent(renderer))
        texts[ax] = [b for b in boxes if b is not None and b.width > 0]
        for box in texts[ax]:
            assert _inside(box, fig_box), (figure.__name__, ax.get_title(), box, fig_box)
    for ax, boxes in texts.items():
        for other in fig.axes:
            if other is not ax:
                assert not any(_overlap(box, other.get_window_extent(renderer)) for box in boxes), (
                    figure.__name__,
                    ax.get_title(),
                    other.get_title(),
                )
    figure_texts = [leg.get_window_extent(renderer) for leg in fig.legends]
    figure_texts += [text.get_window_extent(renderer) for text in fig.texts if text.get_text()]  # the suptitle
    for box in figure_texts:
        assert _inside(box, fig_box), (figure.__name__, box)
        for ax, boxes in texts.items():
            assert not _overlap(box, ax.get_window_extent(renderer)), (figure.__name__, ax.get_title())
            assert not any(_overlap(box, b) for b in boxes), (figure.__name__, ax.get_title())
