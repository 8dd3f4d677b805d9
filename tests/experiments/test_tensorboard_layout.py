"""TensorBoard as a user opens it, read back with TensorBoard's own readers: a sweep's runs are named by
their parameters and each holds both its HParams session and its curves; the HParams experiment
knows every swept value and that it differs; time is simulated time; single-Gaussian filters log no
mixture scalars; ``agsf reproduce`` makes each case a session; resuming a sweep duplicates nothing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2

from agsf_torch.experiments.config import load_config
from agsf_torch.experiments.experiment import run_experiment
from agsf_torch.experiments.reproduce import reproduce
from agsf_torch.experiments.sweep import run_sweep
from agsf_torch.experiments.tensorboard_log import (
    EVENTS_GLOB,
    METRIC_PREFIX,
    hparam_domains,
    run_name,
    run_names,
    time_steps,
)

BASE = ["runs=2", "duration=0.5", 'filters=["EKF","GSF"]', "components=2"]
GRID = {"reg": [0.5, 1.0]}
MIXTURE_ONLY = ("weight_entropy", "weight_", "weights")


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


def tensorboard_view(logdir: Path):
    """What the HParams tab shows: the experiment and session groups from TensorBoard's HParams plugin."""
    from tensorboard import context
    from tensorboard.backend.event_processing import data_provider, plugin_event_multiplexer
    from tensorboard.plugins import base_plugin
    from tensorboard.plugins.hparams import backend_context, get_experiment, list_session_groups

    mux = plugin_event_multiplexer.EventMultiplexer()
    mux.AddRunsFromDirectory(str(logdir))
    mux.Reload()
    provider = data_provider.MultiplexerDataProvider(mux, str(logdir))
    ctx = backend_context.Context(base_plugin.TBContext(logdir=str(logdir), multiplexer=mux, data_provider=provider))
    request_context = context.RequestContext()
    experiment = get_experiment.Handler(request_context, ctx, "", api_pb2.GetExperimentRequest()).run()
    request = api_pb2.ListSessionGroupsRequest(
        start_index=0, slice_size=1000, allowed_statuses=[api_pb2.STATUS_SUCCESS]
    )
    groups = list_session_groups.Handler(request_context, ctx, "", request).run()
    return sorted(mux.Runs()), experiment, groups


def check_time_series(acc: EventAccumulator, data, summary: dict, filters: list[str]) -> None:
    """Curves against simulated time: step = integer ms of data["time"], walltime = data["time"] in s."""
    t = data["time"]
    scalars = acc.Tags()["scalars"]
    for name in filters:
        events = acc.Scalars(f"{name}/rms_deg_vs_ms")
        np.testing.assert_array_equal([e.step for e in events], np.rint(t * 1000).astype(int))
        np.testing.assert_allclose([e.step / 1000 for e in events], t, rtol=0, atol=1e-9)
        np.testing.assert_allclose([e.wall_time for e in events], t, rtol=0, atol=1e-9)
        np.testing.assert_allclose([e.value for e in events], summary["filters"][name]["rms_deg"], rtol=1e-6)
        assert len(acc.Scalars(f"{name}/nees_vs_ms")) == len(t)
        mixture = data[f"{name}/weights"].shape[-1] > 1
        own = [tag for tag in scalars + acc.Tags()["histograms"] if tag.startswith(f"{name}/")]
        assert all(tag.endswith("_vs_ms") for tag in own), own
        has_mixture_tags = any(tag[len(name) + 1 :].startswith(MIXTURE_ONLY) for tag in own)
        assert has_mixture_tags == mixture, (name, own)
    assert not [tag for tag in scalars if tag.startswith("EKF/") and "weight" in tag]
    for i in range(data["GSF/weights"].shape[-1]):
        events = acc.Scalars(f"GSF/weight_{i}_run0_vs_ms")
        np.testing.assert_allclose([e.value for e in events], data["GSF/weights"][0, :, i], rtol=1e-6)
    np.testing.assert_allclose(
        [e.value for e in acc.Scalars("GSF/weight_entropy_vs_ms")], data["GSF/weight_entropy"].mean(0), rtol=1e-6
    )


# -------------------------------------------------------------- a sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    base = load_config("case1", BASE)
    out = tmp_path_factory.mktemp("tb") / "sweep"
    rows = run_sweep(base, GRID, out, progress=False)
    return base, out, rows


def test_sweep_runs_are_named_by_their_parameters_and_hold_session_and_curves(sweep, capsys):
    base, out, rows = sweep
    tb = out / "tensorboard"
    assert sorted(p.name for p in tb.iterdir()) == ["reg=0.5", "reg=1.0"]
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
            assert [e.value for e in acc.Scalars(METRIC_PREFIX + key)] == [pytest.approx(value, rel=1e-6)]
        config = out / "configs" / row["digest"]
        summary = json.loads((config / "summary.json").read_text())
        check_time_series(acc, np.load(config / "runs.npz"), summary, list(base.filters))
        print(folder.relative_to(out), sorted(acc.Tags()["scalars"]), acc.Tags()["histograms"], sorted(hp))
    assert sorted(reg_values) == [0.5, 1.0]  # the sessions differ
    # every session carries the same experiment configuration: the whole grid, marked as differing
    assert all(e == experiments[0] for e in experiments)
    assert experiment_domains(experiments[0]) == {"reg": ([0.5, 1.0], True)}
    assert {m.name.tag for m in experiments[0].metric_infos} == {METRIC_PREFIX + k for k in rows[0]["metrics"]}
    with capsys.disabled():
        print("\n" + "\n".join(sorted(str(p.relative_to(out.parent)) for p in tb.rglob("*"))))


def test_the_hparams_tab_shows_each_configuration_with_its_values_and_metrics(sweep):
    _, out, rows = sweep
    runs, experiment, groups = tensorboard_view(out / "tensorboard")
    assert runs == ["reg=0.5", "reg=1.0"]
    assert [(i.name, i.differs) for i in experiment.hparam_infos] == [("reg", True)]
    assert all(len(g.sessions) == 1 and g.name == g.sessions[0].name for g in groups.session_groups)
    by_session = {g.sessions[0].name: g for g in groups.session_groups}
    assert sorted(by_session) == runs and groups.total_size == 2
    for row in rows:
        group = by_session[run_name(row["params"])]
        assert group.hparams["reg"].number_value == row["params"]["reg"]
        metrics = {m.name.tag: m.value for m in group.metric_values}
        assert metrics == pytest.approx({METRIC_PREFIX + k: v for k, v in row["metrics"].items()}, rel=1e-6)
    # with the whole output folder as logdir the runs are still the named ones only
    runs, _, groups = tensorboard_view(out)
    assert runs == ["tensorboard/reg=0.5", "tensorboard/reg=1.0"] and groups.total_size == 2


def test_resuming_a_sweep_duplicates_no_session_or_curve(sweep, tmp_path):
    base, out, rows = sweep
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
    acc = accumulate(out / "tensorboard" / run_name(last["params"]))
    assert len(list((out / "tensorboard" / run_name(last["params"])).glob(EVENTS_GLOB))) == 2  # curves + session
    assert len(acc.Scalars("GSF/rms_deg_vs_ms")) == len(np.load(out / "configs" / last["digest"] / "runs.npz")["time"])


# -------------------------------------------------------------- agsf reproduce


def test_reproduce_makes_each_case_an_hparams_session(tmp_path):
    out = tmp_path / "reproduce"
    reproduce(
        [1, 2],
        out,
        ["runs=2", "duration=2.0", 'filters=["EKF","GSF"]', "components=2", "compile=false"],
        progress=False,
    )
    combined = json.loads((out / "summary.json").read_text())
    runs, experiment, groups = tensorboard_view(out)
    assert runs == ["case1/tensorboard", "case2/tensorboard"]
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
            assert metrics[f"{METRIC_PREFIX}{f}/time_averaged_nees"] == pytest.approx(s["time_averaged_nees"], rel=1e-6)
            assert metrics[f"{METRIC_PREFIX}{f}/final_rms_deg"] == pytest.approx(s["final_rms_deg"], rel=1e-6)
        acc = accumulate(out / case / "tensorboard")
        data = np.load(out / case / "runs.npz")
        summary = json.loads((out / case / "summary.json").read_text())
        check_time_series(acc, data, summary, ["EKF", "GSF"])
        # star frames: NIS only at frame times, in ms
        nis = acc.Scalars("GSF/nis_vs_ms")
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
    assert unit == "_vs_ms" and steps.tolist() == [100, 200, 300, 400, 500]
    steps, unit = time_steps(np.arange(1, 4) * 2.5e-4)
    assert unit == "_vs_us" and steps.tolist() == [250, 500, 750]
    with pytest.raises(ValueError, match="1 µs"):
        time_steps(np.arange(1, 4) * 1e-7)
