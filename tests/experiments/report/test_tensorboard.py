"""TensorBoard as a user opens it, read back with TensorBoard's own readers (its data provider, as the
server uses it): one run per (case, filter) and per (configuration, filter), tags per metric so one chart
overlays the filters; a sweep's configurations are named by their parameters and each is an HParams
session over its filters' runs; the HParams experiment knows every swept value and that it differs; the
step is simulated time and every wall time the clock's; single-Gaussian filters log no mixture scalars;
``agsf reproduce`` makes each case a session; resuming a sweep duplicates nothing."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2

from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.report.tensorboard import (
    EVENTS_GLOB,
    METRIC_PREFIX,
    hparam_domains,
    run_name,
    run_names,
    time_steps,
)
from agsf_torch.experiments.run.experiment import run_experiment
from agsf_torch.experiments.studies.reproduce import reproduce
from agsf_torch.experiments.sweep import run_sweep
from tests.helpers import EAGER, assert_within, event_records, relative_bound

BASE = ["runs=2", "duration=0.5", 'filters=["EKF","GSF"]', "components=2"]
GRID = {"reg": [0.5, 1.0]}
MIXTURE_ONLY = ("weight_entropy", "weight_", "weights")


def assert_recorded(recorded, values, what: str) -> None:
    """A TensorBoard scalar (stored as float32) against the float64 value it records: 1e-6 relative (a rounding
    to float32 moves a value by at most 2⁻²⁴ ≈ 6e-8 of it) and, below float32's normal range, its smallest
    subnormal (an entry that rounds to a subnormal or to 0); the same number of points."""
    assert np.shape(recorded) == np.shape(values), what
    assert_within(recorded, values, relative_bound(values, 1e-6, np.finfo(np.float32).smallest_subnormal), what)


def accumulate(folder: Path) -> EventAccumulator:
    acc = EventAccumulator(str(folder), size_guidance={"scalars": 0, "histograms": 0, "tensors": 0})
    acc.Reload()
    return acc


def hparams_data(acc: EventAccumulator) -> dict[str, plugin_data_pb2.HParamsPluginData]:
    """The run's HParams plugin data by tag (``_hparams_/experiment``, ``…/session_start_info``, …)."""
    return {
        tag: plugin_data_pb2.HParamsPluginData.FromString(content)
        for tag, content in acc.PluginTagToContent(metadata.PLUGIN_NAME).items()
    }


def experiment_domains(experiment: api_pb2.Experiment) -> dict[str, tuple[list, bool]]:
    out = {}
    for info in experiment.hparam_infos:
        values = [v.number_value if v.HasField("number_value") else v.string_value for v in info.domain_discrete.values]
        out[info.name] = (values, info.differs)
    return out


def _provider(logdir: Path):
    from tensorboard.backend.event_processing import data_provider, plugin_event_multiplexer

    mux = plugin_event_multiplexer.EventMultiplexer()
    mux.AddRunsFromDirectory(str(logdir))
    mux.Reload()
    return mux, data_provider.MultiplexerDataProvider(mux, str(logdir))


def tensorboard_view(logdir: Path):
    """What the HParams tab shows: the experiment and session groups from TensorBoard's HParams plugin."""
    from tensorboard import context
    from tensorboard.plugins import base_plugin
    from tensorboard.plugins.hparams import backend_context, get_experiment, list_session_groups

    mux, provider = _provider(logdir)
    ctx = backend_context.Context(base_plugin.TBContext(logdir=str(logdir), multiplexer=mux, data_provider=provider))
    request_context = context.RequestContext()
    experiment = get_experiment.Handler(request_context, ctx, "", api_pb2.GetExperimentRequest()).run()
    request = api_pb2.ListSessionGroupsRequest(
        start_index=0, slice_size=1000, allowed_statuses=[api_pb2.STATUS_SUCCESS]
    )
    groups = list_session_groups.Handler(request_context, ctx, "", request).run()
    return sorted(mux.Runs()), experiment, groups


def scalars_view(logdir: Path) -> dict[str, dict[str, list]]:
    """What the Scalars tab shows: ``{run: {tag: [ScalarDatum(step, wall_time, value)]}}`` from TensorBoard's
    data provider (every point, no downsampling), the HParams metrics (``summary/…``) included."""
    from tensorboard import context

    _, provider = _provider(logdir)
    return provider.read_scalars(context.RequestContext(), experiment_id="", plugin_name="scalars", downsample=10**9)


def texts_view(logdir: Path) -> dict[str, dict[str, str]]:
    """The Text tab: ``{run: {tag: text at step 0}}``."""
    from tensorboard import context

    _, provider = _provider(logdir)
    data = provider.read_tensors(context.RequestContext(), experiment_id="", plugin_name="text", downsample=10**9)
    return {
        run: {tag: points[0].numpy.reshape(-1)[0].decode() for tag, points in tags.items()}
        for run, tags in data.items()
    }


def check_time_series(logdir: Path, data, summary: dict, filters: list[str], written_after: float) -> None:
    """One run per filter under ``logdir`` with a tag per metric; step = integer ms of data["time"]; every wall
    time the clock's (written after ``written_after``), none simulated."""
    t = data["time"]
    view, texts = scalars_view(logdir), texts_view(logdir)
    for name in filters:
        run = view[name]
        events = run["rms_deg"]
        np.testing.assert_array_equal([e.step for e in events], np.rint(t * 1000).astype(int))
        assert all(written_after <= e.wall_time <= time.time() for e in events)
        assert_recorded([e.value for e in events], summary["filters"][name]["rms_deg"], f"{name} RMS error (deg)")
        assert len(run["nees"]) == len(t)
        assert "step = simulated time in ms" in texts[name]["time_axis/text_summary"]
        mixture = data[f"{name}/weights"].shape[-1] > 1
        assert mixture == any(tag.startswith("weights/") for tag in run), (name, sorted(run))
        assert not [tag for tag in run if "_vs_" in tag or tag.startswith(name)]  # per-metric tags
    for i in range(data["GSF/weights"].shape[-1]):
        events = view["GSF"][f"weights/component_{i}"]
        assert_recorded([e.value for e in events], data["GSF/weights"][0, :, i], f"GSF weight of component {i}")
    assert_recorded(
        [e.value for e in view["GSF"]["weights/entropy"]], data["GSF/weight_entropy"].mean(0), "GSF weight entropy"
    )


# -------------------------------------------------------------- a sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    base = load_config("case1", BASE)
    out = tmp_path_factory.mktemp("tb") / "sweep"
    started = time.time()
    rows = run_sweep(base, GRID, out, progress=False)
    return base, out, rows, started


def test_sweep_runs_are_named_by_their_parameters_and_hold_session_and_curves(sweep, capsys):
    base, out, rows, started = sweep
    tb = out / "tensorboard"
    assert sorted(p.name for p in tb.iterdir()) == ["reg=0.5", "reg=1.0"]
    for folder in tb.iterdir():  # the session, and a run per filter beneath it
        assert sorted(p.name for p in folder.iterdir() if p.is_dir()) == sorted(base.filters)
    assert not list(tb.glob(EVENTS_GLOB))  # no run at the root
    assert not list((out / "configs").rglob(EVENTS_GLOB))  # the curves live only in the named runs
    experiments, reg_values = [], []
    for row in rows:
        folder = tb / run_name(row["params"])
        acc = accumulate(folder)
        hp = hparams_data(acc)
        assert set(hp) == {metadata.EXPERIMENT_TAG, metadata.SESSION_START_INFO_TAG, metadata.SESSION_END_INFO_TAG}
        start = hp[metadata.SESSION_START_INFO_TAG].session_start_info
        assert dict(start.hparams.items()).keys() == {"reg"}
        assert start.hparams["reg"].number_value == row["params"]["reg"]
        reg_values.append(start.hparams["reg"].number_value)
        assert hp[metadata.SESSION_END_INFO_TAG].session_end_info.status == api_pb2.STATUS_SUCCESS
        experiments.append(hp[metadata.EXPERIMENT_TAG].experiment)
        # the session's metrics, next to the configuration's curves
        for key, value in row["metrics"].items():
            assert_recorded([e.value for e in acc.Scalars(METRIC_PREFIX + key)], [value], f"session metric {key}")
        config = out / "configs" / row["digest"]
        summary = json.loads((config / "summary.json").read_text())
        check_time_series(folder, np.load(config / "runs.npz"), summary, list(base.filters), started)
        print(folder.relative_to(out), sorted(acc.Tags()["scalars"]), acc.Tags()["histograms"], sorted(hp))
    assert sorted(reg_values) == [0.5, 1.0]  # the sessions differ
    # every session carries the same experiment configuration: the whole grid, marked as differing
    assert all(e == experiments[0] for e in experiments)
    assert experiment_domains(experiments[0]) == {"reg": ([0.5, 1.0], True)}
    assert {m.name.tag for m in experiments[0].metric_infos} == {METRIC_PREFIX + k for k in rows[0]["metrics"]}
    with capsys.disabled():
        print("\n" + "\n".join(sorted(str(p.relative_to(out.parent)) for p in tb.rglob("*"))))


def test_the_hparams_tab_shows_each_configuration_with_its_values_and_metrics(sweep):
    base, out, rows, _ = sweep
    runs, experiment, groups = tensorboard_view(out / "tensorboard")
    assert runs == sorted(r for s in ("reg=0.5", "reg=1.0") for r in [s, *(f"{s}/{f}" for f in base.filters)])
    runs = [r for r in runs if "/" not in r]  # the sessions
    assert [(i.name, i.differs) for i in experiment.hparam_infos] == [("reg", True)]
    assert all(len(g.sessions) == 1 and g.name == g.sessions[0].name for g in groups.session_groups)
    by_session = {g.sessions[0].name: g for g in groups.session_groups}
    assert sorted(by_session) == runs and groups.total_size == 2
    for row in rows:
        group = by_session[run_name(row["params"])]
        assert group.hparams["reg"].number_value == row["params"]["reg"]
        metrics = {m.name.tag: m.value for m in group.metric_values}
        expected = {METRIC_PREFIX + k: v for k, v in row["metrics"].items()}
        assert metrics.keys() == expected.keys()
        assert_recorded([metrics[k] for k in expected], list(expected.values()), "session group metrics")
    # with the whole output folder as logdir the runs are still the named ones only
    runs, _, groups = tensorboard_view(out)
    assert [r for r in runs if r.count("/") == 1] == ["tensorboard/reg=0.5", "tensorboard/reg=1.0"]
    assert all(r.startswith("tensorboard/reg=") for r in runs) and groups.total_size == 2


def test_resuming_a_sweep_duplicates_no_session_or_curve(sweep, tmp_path):
    base, out, rows, _ = sweep
    ran = []
    again = run_sweep(base, GRID, out, progress=False, runner=lambda cfg, *a, **k: ran.append(cfg))
    assert again == rows and not ran
    # interrupted after the last configuration's run was written, before its row: the rerun replaces it
    results = out / "results.jsonl"
    lines = results.read_text().splitlines()
    results.write_text("\n".join(lines[:-1]) + "\n")
    last = json.loads(lines[-1])

    def counting(cfg, folder, **kw):
        ran.append(cfg.digest())
        return run_experiment(cfg, folder, **kw)

    run_sweep(base, GRID, out, progress=False, runner=counting)
    assert ran == [last["digest"]]
    _, _, groups = tensorboard_view(out / "tensorboard")
    assert groups.total_size == 2
    session = out / "tensorboard" / run_name(last["params"])
    assert len(list(session.glob(EVENTS_GLOB))) == 1  # the session
    assert all(len(list((session / f).glob(EVENTS_GLOB))) == 1 for f in base.filters)  # one file of curves each
    view = scalars_view(session)
    assert len(view["GSF"]["rms_deg"]) == len(np.load(out / "configs" / last["digest"] / "runs.npz")["time"])


# -------------------------------------------------------------- agsf reproduce


def test_reproduce_makes_each_case_an_hparams_session(tmp_path):
    out = tmp_path / "reproduce"
    started = time.time()
    reproduce(
        [1, 2],
        out,
        ["runs=2", "duration=2.0", 'filters=["EKF","GSF"]', "components=2", *EAGER],
        progress=False,
    )
    combined = json.loads((out / "summary.json").read_text())
    runs, experiment, groups = tensorboard_view(out)
    assert runs == [f"case{k}/tensorboard{f}" for k in (1, 2) for f in ("", "/EKF", "/GSF")]  # a run per (case, filter)
    runs = [r for r in runs if r.endswith("tensorboard")]  # the sessions
    infos = {i.name: i for i in experiment.hparam_infos}
    assert {"case", "star_period", "runs", "components", "reg", "dt", "duration"} <= set(infos)
    assert "compile" not in infos and "name" not in infos
    differing = sorted(n for n, i in infos.items() if i.differs)
    assert differing == ["case", "star_period"]
    assert all(len(g.sessions) == 1 and g.name == g.sessions[0].name for g in groups.session_groups)
    by_session = {g.sessions[0].name: g for g in groups.session_groups}
    assert sorted(by_session) == runs
    for case, star_period in (("case1", 1.0), ("case2", 2.0)):
        group = by_session[f"{case}/tensorboard"]
        assert group.hparams["case"].string_value == case
        assert group.hparams["star_period"].number_value == star_period
        assert group.hparams["runs"].number_value == 2 and group.hparams["components"].number_value == 2
        metrics = {m.name.tag: m.value for m in group.metric_values}
        for f in ("EKF", "GSF"):
            s = combined[case]["filters"][f]
            for key in ("time_averaged_nees", "final_rms_deg", "nis_per_expected"):
                assert_recorded(metrics[f"{METRIC_PREFIX}{f}/{key}"], s[key], f"{case} {f} {key}")
        data = np.load(out / case / "runs.npz")
        summary = json.loads((out / case / "summary.json").read_text())
        check_time_series(out / case / "tensorboard", data, summary, ["EKF", "GSF"], started)
        # star frames: NIS only at frame times, in ms
        nis = scalars_view(out / case / "tensorboard")["GSF"]["nis"]
        assert [e.step for e in nis] == list(np.rint(data["time"][data["star_frame"]] * 1000).astype(int))
        assert nis and len(nis) < len(data["time"])


# -------------------------------------------------------------- names and steps


def test_run_names_are_the_parameters_sanitized_and_unique():
    assert run_name({"reg": 0.5, "scaling": "trace"}) == "reg=0.5,scaling=trace"
    assert run_name({"reg": 1.0, "estimate_bias": True, "components": 3}) == "reg=1.0,estimate_bias=true,components=3"
    assert run_name({"rate_axes": [1.0, 0.0, -1.0]}) == "rate_axes=1.0_0.0_-1.0"
    assert run_name({"name": "../a b/c"}) == "name=.._a_b_c"
    assert "/" not in run_name({"faults": [{"kind": "gyro/dropout"}]})
    names = run_names([({"x": "a b"}, "1" * 16), ({"x": "a_b"}, "2" * 16), ({"x": "c"}, "3" * 16)])
    assert names == {"1" * 16: "x=a_b-" + "1" * 16, "2" * 16: "x=a_b-" + "2" * 16, "3" * 16: "x=c"}
    long = run_names([({"x": "y" * 500}, "f" * 16)])["f" * 16]
    assert len(long) <= 200 and long.endswith("-" + "f" * 16)
    assert hparam_domains([{"reg": 0.5, "axes": [1, 0]}, {"reg": 1.0, "axes": [1, 0]}]) == {
        "reg": [0.5, 1.0],
        "axes": ["[1, 0]"],
    }


def test_time_steps_are_integer_milliseconds_or_microseconds_when_finer():
    steps, unit = time_steps(np.arange(1, 6) * 0.1)
    assert unit == "ms" and steps.tolist() == [100, 200, 300, 400, 500]
    steps, unit = time_steps(np.arange(1, 4) * 2.5e-4)
    assert unit == "µs" and steps.tolist() == [250, 500, 750]
    with pytest.raises(ValueError, match="1 µs"):
        time_steps(np.arange(1, 4) * 1e-7)


def test_a_filter_run_that_fails_leaves_no_events_and_no_temporary_folder(tmp_path):
    from agsf_torch.experiments.report.tensorboard import write_filter_run

    steps = np.arange(3)
    events = {
        "text": "t",
        "scalars": {"rms_deg": (steps, np.ones(3)), "nees": (steps, np.array(["1", "2", "not a number"]))},
        "histograms": None,
    }
    with pytest.raises(ValueError):
        write_filter_run(tmp_path / "tensorboard" / "GSF", events)
    assert sorted(p.name for p in (tmp_path / "tensorboard").iterdir()) == []  # no run, no hidden folder


class _Submissions:
    def __init__(self):
        self.calls = []

    def submit(self, write, *args, path, thread=False):
        self.calls.append(Path(path).name)


@pytest.mark.parametrize(("limit", "handed"), [(2**40, ["EKF", "GSF"]), (1, [])])
def test_event_series_go_to_the_writer_unless_they_exceed_the_handover_limit(tmp_path, monkeypatch, limit, handed):
    from agsf_torch.experiments.report import tensorboard as tensorboard_log
    from agsf_torch.experiments.run import file_writer

    T = 4
    data = {
        "time": np.arange(T) * 0.1,
        "star_frame": np.array([False, True, False, True]),
        "GSF/weights": np.full((2, T, 2), 0.5),
        "GSF/weight_entropy": np.zeros((2, T)),
    }
    summary = {
        "filters": {name: {"rms_deg": np.ones(T).tolist(), "nees_mean": np.ones(T).tolist()} for name in ("EKF", "GSF")}
    }
    monkeypatch.setattr(file_writer, "HANDOVER_BYTES", limit)
    writer = _Submissions()
    tensorboard_log.write_tensorboard(tmp_path, data, summary, writer)
    assert writer.calls == handed
    written = sorted(p.parent.name for p in (tmp_path / "tensorboard").rglob("events.out.tfevents.*"))
    assert written == sorted({"EKF", "GSF"} - set(handed))  # what was not handed over is written here


def test_a_filter_run_written_again_holds_one_event_file(tmp_path):
    """A task taken back from a worker that died after writing the run writes it again: the run is replaced, its
    curves not doubled."""
    from agsf_torch.experiments.report.tensorboard import write_filter_run
    from tests.helpers import event_records

    events = {"text": "time: simulated s", "scalars": {"rms_deg": (np.arange(3), np.array([1.0, 0.5, 0.25]))}}
    events["histograms"] = None
    write_filter_run(tmp_path / "GSF", events)
    once = event_records(tmp_path)
    write_filter_run(tmp_path / "GSF", events)
    assert len(list((tmp_path / "GSF").glob("events.out.tfevents.*"))) == 1
    assert event_records(tmp_path) == once and not list(tmp_path.glob(".*.tmp"))


def test_a_filter_run_holds_its_text_scalars_and_histograms_as_tensorboard_reads_them(tmp_path):
    """``write_filter_run``: one event file in the run, read back by TensorBoard's accumulator with every tag, every
    step and every value (scalars to float32), the text at step 0 and a histogram of every run's weights per step."""
    from tensorboard.util import tensor_util

    from agsf_torch.experiments.report.tensorboard import write_filter_run
    from tests.helpers import event_records

    rng = np.random.default_rng(1)
    steps = np.arange(100, 3100, 100)
    events = {
        "text": "step = simulated time in ms",
        "scalars": {
            "rms_deg": (steps, rng.lognormal(size=30)),
            "nis": (steps[9::10], rng.chisquare(3, size=3)),
            "weights/component_0": (steps, rng.uniform(size=30)),
        },
        "histograms": (steps[::10], rng.dirichlet(np.ones(4), size=(3, 8)).reshape(3, -1)),
    }
    write_filter_run(tmp_path / "GSF", events)
    assert len(list((tmp_path / "GSF").glob(EVENTS_GLOB))) == 1 and not list(tmp_path.glob(".*.tmp"))
    (records,) = event_records(tmp_path).values()
    assert set(records) == {*events["scalars"], "weights/all_runs", "time_axis/text_summary"}
    for key, (s, values) in events["scalars"].items():
        assert [step for step, _ in records[key]] == s.tolist()
        assert_recorded([value for _, value in records[key]], values, key)
    assert [step for step, _ in records["weights/all_runs"]] == events["histograms"][0].tolist()
    acc = accumulate(tmp_path / "GSF")
    for event, values in zip(acc.Histograms("weights/all_runs"), events["histograms"][1]):
        h = event.histogram_value
        assert (h.num, h.min, h.max, h.sum) == (values.size, values.min(), values.max(), values.sum())
        assert sum(h.bucket) == values.size
    (text,) = acc.Tensors("time_axis/text_summary")
    assert text.step == 0 and tensor_util.make_ndarray(text.tensor_proto).item().decode() == events["text"]


# -------------------------------------------------------------- managed filters: the mixture's life


def _mixture_means(data, name: str) -> dict[str, list[float]]:
    """The ``mixture/…`` curves of a managed filter as this test computes them: each step's count summed over the
    runs by hand and divided by their number (small integers over a power of two or a few runs: exact in float32
    for the counts used here, so compared exactly)."""
    out = {}
    for key in ("active_components", "splits", "merges", "prunes"):
        counts = np.asarray(data[f"{name}/{key}"]).tolist()
        out[f"mixture/{key}"] = [sum(run[k] for run in counts) / len(counts) for k in range(len(counts[0]))]
    return out


def test_a_managed_filters_run_holds_its_mixtures_count_and_events_per_step(tmp_path):
    """``mixture/active_components`` and ``mixture/splits``, ``merges``, ``prunes``: per step (simulated ms) the mean
    over the runs of the counts in ``data``; a filter without management has none."""
    from agsf_torch.experiments.report.tensorboard import write_tensorboard

    T, B = 5, 4
    data = {
        "time": np.arange(1, T + 1) * 0.1,
        "star_frame": np.array([False, True, False, True, False]),
        "GSF/weights": np.full((B, T, 2), 0.5),
        "GSF/weight_entropy": np.zeros((B, T)),
        "GSF-managed/weights": np.full((B, T, 3), 1 / 3),
        "GSF-managed/weight_entropy": np.zeros((B, T)),
        "GSF-managed/active_components": np.array([[3, 7, 5, 5, 4], [3, 3, 2, 2, 2], [2, 4, 4, 6, 1], [3, 3, 3, 3, 3]]),
        "GSF-managed/splits": np.array([[0, 2, 0, 0, 0], [0, 0, 0, 0, 0], [0, 1, 0, 1, 0], [0, 0, 0, 0, 0]]),
        "GSF-managed/merges": np.array([[0, 0, 1, 0, 1], [0, 0, 1, 0, 0], [1, 0, 0, 0, 2], [0, 0, 0, 0, 0]]),
        "GSF-managed/prunes": np.array([[0, 0, 1, 0, 0], [0, 0, 0, 0, 0], [0, 0, 0, 0, 3], [0, 0, 0, 0, 0]]),
    }
    summary = {"filters": {name: {} for name in ("GSF", "GSF-managed")}}
    write_tensorboard(tmp_path, data, summary)
    records = event_records(tmp_path / "tensorboard")
    assert not [tag for tag in records["GSF"] if tag.startswith("mixture/")]
    managed = records["GSF-managed"]
    expected = _mixture_means(data, "GSF-managed")
    assert expected["mixture/active_components"] == [2.75, 4.25, 3.5, 4.0, 2.5]  # by hand, as a check of the sums
    assert expected["mixture/prunes"] == [0.0, 0.0, 0.25, 0.0, 0.75]
    for tag, values in expected.items():
        assert [step for step, _ in managed[tag]] == [100, 200, 300, 400, 500], tag
        assert [value for _, value in managed[tag]] == values, tag


def test_an_experiment_with_a_managed_filter_logs_what_runs_npz_records(tmp_path):
    """End to end (runner, ``runs.npz``, events): the GSF-managed's ``mixture/…`` curves are the means over the runs
    of its ``runs.npz`` counts, and at the first star frame the update's splits are among them."""
    cfg = load_config("case1", ["runs=2", "duration=1.5", 'filters=["GSF-managed"]', *EAGER])
    run_experiment(cfg, tmp_path / "run", progress=False)
    data = np.load(tmp_path / "run" / "runs.npz")
    records = event_records(tmp_path / "run" / "tensorboard")["GSF-managed"]
    steps = np.rint(data["time"] * 1000).astype(int).tolist()
    for tag, values in _mixture_means(data, "GSF-managed").items():
        assert [step for step, _ in records[tag]] == steps, tag
        assert [value for _, value in records[tag]] == values, tag
    first_frame = int(np.argmax(data["star_frame"]))
    assert data["GSF-managed/splits"][:, first_frame].min() > 0  # split before the update (predict splits none here)
    assert (tmp_path / "run" / "mixture.png").exists()
