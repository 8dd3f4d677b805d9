"""An experiment's TensorBoard events, and the HParams sessions that compare experiments.

Layout
------
One run per filter, tags per metric, so that one chart overlays the filters and TensorBoard's
run filter selects cases or configurations (``tensorboard --logdir runs/reproduce``, then
``case1`` in the run filter compares case 1's filters; ``GSF`` compares the GSF across cases)::

    <experiment>/tensorboard/            the experiment's HParams session (reproduce, sweeps)
    <experiment>/tensorboard/EKF/        one run per filter, each with the tags
        rms_deg                  RMS attitude error over the runs (deg)
        nees                     mean NEES over the runs
        nis                      mean NIS, at star frames only
        fpke/error_before        FPKE residual wᵀLw before / after the weight update
        fpke/error_after         (filters that record it: the paper's update)
        fpke/ratio               after ÷ before, mean over the runs
        weights/entropy          mean entropy of the mixture weights (nat)  ┐ mixtures only:
        weights/component_<i>    weight of component i in the first run     │ not for one
        weights/all_runs         histogram of the weights over the runs     ┘ Gaussian
        mixture/active_components                                           ┐ managed filters
                                 components in use at the step's end, mean  │ only (count):
        mixture/splits           the step's splits (predict and update),    │ means over the
        mixture/merges           merges and prunes; per run, mean           │ runs
        mixture/prunes                                                      ┘
        time_axis                (text, shown as time_axis/text_summary) what the step counts

Time axis
---------
The **step** is the simulated time in integer milliseconds (``rms_deg`` at step 1500 is the RMS
error at t = 1.5 s), or in integer microseconds when ``dt`` < 1 ms keeps times apart
(:func:`time_steps`); each run's ``time_axis`` text says which.  Use TensorBoard's ``STEP``
x-axis.  Every event's wall time is the clock time at which it was written, curves and
HParams sessions alike, so the ``WALL`` and ``RELATIVE`` axes mean one thing: when the
events were written.

HParams
-------
:func:`write_hparams_session` makes one run directory an HParams *session*: its
hyperparameter values (``_hparams_/session_start_info``), its end
(``_hparams_/session_end_info``), one scalar per metric (``summary/<metric>``) and
the experiment-level configuration (``_hparams_/experiment``): every compared
hyperparameter with the complete domain of values over all sessions and
``differs`` set when they differ, and the metrics.  Every session carries the same
experiment configuration, so no run exists only to hold it.  The session and the
experiment's curves share the run directory: the HParams tab links each session to
its curves.  :func:`run_name` names such a directory by its parameters.

Writers
-------
Every record is written by :class:`torch.utils.tensorboard.SummaryWriter` (its scalars, text, histograms and event
files) and the HParams summaries are built by :mod:`tensorboard.plugins.hparams.summary_v2`.  This module adds only
what neither does: the layout above (a run per filter, the step as simulated time), a run written whole (in a hidden
folder moved into place, so that an interrupted run leaves no truncated curves), the experiment's ``differs`` flags
(TensorBoard's domains leave them unset; the HParams tab lists the differing hyperparameters first), and the
session's end (TensorBoard builds it only through TensorFlow).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ...storage.files import temporary_name
from ..run.file_writer import too_large_to_hand_over

if TYPE_CHECKING:
    from ..run.file_writer import FileWriter

__all__ = [
    "write_tensorboard",
    "filter_events",
    "write_filter_run",
    "time_steps",
    "run_name",
    "run_names",
    "hparam_value",
    "hparam_domains",
    "write_hparams_session",
    "clear_events",
    "clear_runs",
    "move_events",
    "METRIC_PREFIX",
    "EVENTS_GLOB",
]

METRIC_PREFIX = "summary/"
EVENTS_GLOB = "events.out.tfevents.*"
_MAX_NAME = 200  # characters of a run directory name (file systems allow 255 bytes)


def time_steps(time_s: np.ndarray) -> tuple[np.ndarray, str]:
    """Integer TensorBoard steps of the simulated times ``time_s`` (s) and their unit, ``"ms"`` when milliseconds
    keep every time distinct, else ``"µs"``."""
    t = np.asarray(time_s, dtype=np.float64)
    for scale, unit in ((1e3, "ms"), (1e6, "µs")):
        steps = np.rint(t * scale).astype(np.int64)
        if len(steps) < 2 or (np.diff(steps) > 0).all():
            return steps, unit
    raise ValueError("simulated times closer than 1 µs cannot be TensorBoard steps")


def clear_events(folder: Path) -> None:
    """Remove the event files directly in ``folder`` (left by an earlier writing of the same run)."""
    for p in Path(folder).glob(EVENTS_GLOB):
        if p.is_file():
            p.unlink()


def clear_runs(folder: Path) -> None:
    """Remove an experiment's earlier events: those in ``folder`` and in its per-filter runs (subfolders left
    empty are removed), so that a rerun replaces them and a filter no longer run leaves no run behind."""
    folder = Path(folder)
    clear_events(folder)
    if folder.is_dir():
        for sub in folder.iterdir():
            if sub.is_dir():
                clear_events(sub)
                if not any(sub.iterdir()):
                    sub.rmdir()


def write_tensorboard(
    out: Path, data: dict[str, np.ndarray], summary: dict[str, Any], writer: FileWriter | None = None
) -> None:
    """Write the events of one experiment under ``out/tensorboard``, one run per filter (module docstring).

    Events of an earlier writing of the same experiment folder are replaced, not added to: they are removed here,
    before the runs are written — by ``writer`` (a :class:`~agsf_torch.experiments.run.file_writer.FileWriter`, one task per filter) if given,
    from :func:`filter_events`' arrays, not ``data`` (here if they exceed :data:`~agsf_torch.experiments.run.file_writer.HANDOVER_BYTES`: the
    weight histograms of a very large run).
    """
    folder = out / "tensorboard"
    clear_runs(folder)
    for name, events in filter_events(data, summary).items():
        arrays = [a for pair in events["scalars"].values() for a in pair] + list(events["histograms"] or ())
        if writer is None or too_large_to_hand_over(arrays):
            write_filter_run(folder / name, events)
        else:
            writer.submit(write_filter_run, folder / name, events, path=folder / name)


def filter_events(data: dict[str, np.ndarray], summary: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """What each filter's run holds, from the experiment's arrays and summary: per filter ``{"text": the time axis
    text, "scalars": {tag: (steps [k], values [k])}, "histograms": (steps [h], values [h, B·N])}`` (histograms
    ``None`` for one Gaussian); the steps are the simulated times of :func:`time_steps`.  A managed filter's
    ``mixture/…`` scalars are the means over the runs of its ``[B, T]`` counts (module docstring)."""
    frames = np.asarray(data["star_frame"], dtype=bool)
    t = np.asarray(data["time"], dtype=np.float64)
    steps, unit = time_steps(t)
    text = (
        f"step = simulated time in {unit} (t = {t[0]:g} s … {t[-1]:g} s); weights/component_<i> is the "
        "first run's; every other curve is over all runs"
    )
    events = {}
    for name, f in summary["filters"].items():
        series: dict[str, np.ndarray] = {}
        if "rms_deg" in f:  # scored against the truth (a replay of flight data is not)
            series["rms_deg"] = np.asarray(f["rms_deg"], dtype=np.float64)
            series["nees"] = np.asarray(f["nees_mean"], dtype=np.float64)
        if "fpke_error_before_mean" in f:
            series["fpke/error_before"] = np.asarray(f["fpke_error_before_mean"], dtype=np.float64)
            series["fpke/error_after"] = np.asarray(f["fpke_error_after_mean"], dtype=np.float64)
            series["fpke/ratio"] = np.asarray(f["fpke_ratio_mean"], dtype=np.float64)
        weights = data.get(f"{name}/weights")
        mixture = weights is not None and weights.shape[-1] > 1  # one Gaussian: weight 1, entropy 0
        if mixture:
            series["weights/entropy"] = np.asarray(data[f"{name}/weight_entropy"], dtype=np.float64).mean(0)
            for i in range(weights.shape[-1]):
                series[f"weights/component_{i}"] = np.asarray(weights[0, :, i], dtype=np.float64)
        if f"{name}/active_components" in data:  # a managed filter: its mixture's life, [B, T] counts each
            for key in ("active_components", "splits", "merges", "prunes"):
                series[f"mixture/{key}"] = np.asarray(data[f"{name}/{key}"], dtype=np.float64).mean(0)
        scalars = {key: (steps, values) for key, values in series.items()}
        nis = data.get(f"{name}/nis")
        if nis is not None:
            at = np.flatnonzero(frames)
            scalars["nis"] = (steps[at], np.array([np.nanmean(nis[:, k]) for k in at], dtype=np.float64))
        histograms = None
        if mixture:
            at = np.flatnonzero(frames | (np.arange(len(t)) % 10 == 0))
            histograms = (steps[at], np.ascontiguousarray(weights[:, at].transpose(1, 0, 2).reshape(len(at), -1)))
        events[name] = {"text": text, "scalars": scalars, "histograms": histograms}
    return events


def write_filter_run(run: Path, events: dict[str, Any]) -> None:
    """Write one filter's run ``run`` (a folder) from its :func:`filter_events` entry with a
    :class:`~torch.utils.tensorboard.SummaryWriter`: the ``time_axis`` text at step 0, one event per step holding
    every tag's scalar at that step (``simple_value``, as ``add_scalar`` writes it; one summary of all tags, as
    TensorFlow's merged summaries are written, since the writer checksums each record in Python), then the weight
    histograms.  The event file is written in a hidden folder beside ``run`` (``.{name}.{hex}.tmp``) and moved into
    ``run`` when whole, in place of any event file ``run`` held (a task written again after its worker died leaves one
    run, not two): an interrupted run leaves no truncated curves."""
    from tensorboard.compat.proto.summary_pb2 import Summary
    from torch.utils.tensorboard import SummaryWriter

    run = Path(run)
    tmp = temporary_name(run)
    try:
        with SummaryWriter(str(tmp)) as writer:
            writer.add_text("time_axis", events["text"], 0)
            by_step: dict[int, list[Any]] = {}
            for key, (steps, values) in events["scalars"].items():
                for step, value in zip(np.asarray(steps).tolist(), np.asarray(values, dtype=np.float64).tolist()):
                    by_step.setdefault(int(step), []).append(Summary.Value(tag=key, simple_value=value))
            for step in sorted(by_step):
                writer.file_writer.add_summary(Summary(value=by_step[step]), step)
            if events["histograms"] is not None:
                for step, values in zip(*events["histograms"]):
                    writer.add_histogram("weights/all_runs", values, int(step))
        run.mkdir(parents=True, exist_ok=True)
        for earlier in run.glob(EVENTS_GLOB):  # a retaken task's first write: the run is this one
            earlier.unlink()
        for event_file in sorted(tmp.iterdir()):
            os.replace(event_file, run / event_file.name)
        tmp.rmdir()
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


# ----------------------------------------------------------------------------
# HParams sessions


def hparam_value(value: Any) -> bool | int | float | str:
    """A parameter as an HParams value: booleans, numbers and strings as they are, anything else as JSON."""
    if isinstance(value, (bool, int, float, str)):
        return value
    return json.dumps(value)


def _name_part(value: Any) -> str:
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, float):
        text = repr(value)
    elif isinstance(value, (int, str)):
        text = str(value)
    else:
        text = json.dumps(value, separators=(",", ":"))
    return re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9.+-]", "_", text)).strip("_") or "_"


def run_name(params: Mapping[str, Any]) -> str:
    """A run directory named by its parameters: ``{"reg": 0.5, "scaling": "trace"}`` → ``reg=0.5,scaling=trace``.

    Values are written as in a configuration (floats by ``repr``, booleans ``true``/``false``,
    lists as JSON); every character other than letters, digits, ``. + -`` becomes ``_``.
    """
    text = ",".join(f"{_name_part(k)}={_name_part(v)}" for k, v in params.items())
    return text.lstrip(".") or "_"


def run_names(configs: Iterable[tuple[Mapping[str, Any], str]]) -> dict[str, str]:
    """Digest → unique run directory name of ``(params, digest)`` pairs.

    A name shared by configurations (after sanitizing) or too long for a file name
    gets the digest's first characters appended, so that names depend only on the set
    of configurations and stay the same when a sweep is resumed.
    """
    configs = list(configs)
    plain = {digest: run_name(params) for params, digest in configs}
    counts: dict[str, int] = {}
    for name in plain.values():
        counts[name] = counts.get(name, 0) + 1
    names = {}
    for digest, name in plain.items():
        if counts[name] > 1 or len(name) > _MAX_NAME:
            name = f"{name[: _MAX_NAME - 17]}-{digest[:16]}"
        names[digest] = name
    return names


def hparam_domains(sessions: Iterable[Mapping[str, Any]]) -> dict[str, list[Any]]:
    """Every hyperparameter's distinct values (in first-seen order) over the sessions' hparams."""
    domains: dict[str, list[Any]] = {}
    for hp in sessions:
        for k, v in hp.items():
            values = domains.setdefault(k, [])
            v = hparam_value(v)
            if not any(type(v) is type(u) and v == u for u in values):
                values.append(v)
    return domains


def _experiment_summary(domains: Mapping[str, list[Any]], metrics: Iterable[str]):
    """The ``_hparams_/experiment`` summary: each hyperparameter's discrete domain (booleans, numbers, or else
    strings) with ``differs`` set when it holds two values or more, and the metrics ``summary/<metric>``."""
    from tensorboard.plugins.hparams import summary_v2 as hp

    class Compared(hp.Discrete):
        def update_hparam_info(self, hparam_info) -> None:
            super().update_hparam_info(hparam_info)
            hparam_info.differs = len(self.values) > 1

    def domain(values: list[Any]) -> Compared:
        if all(isinstance(v, bool) for v in values):
            return Compared(values)
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            return Compared([float(v) for v in values])
        return Compared([str(v) for v in values])

    return hp.hparams_config_pb(
        [hp.HParam(k, domain([hparam_value(v) for v in values]), display_name=k) for k, values in domains.items()],
        [hp.Metric(METRIC_PREFIX + k, display_name=k) for k in metrics],
    )


def _session_end_summary():
    """The ``_hparams_/session_end_info`` summary of a successful session ending now."""
    from tensorboard.compat.proto import summary_pb2
    from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2

    end = plugin_data_pb2.SessionEndInfo(status=api_pb2.STATUS_SUCCESS, end_time_secs=time.time())
    summary = summary_pb2.Summary()
    content = metadata.create_summary_metadata(plugin_data_pb2.HParamsPluginData(session_end_info=end))
    summary.value.add(tag=metadata.SESSION_END_INFO_TAG, metadata=content, tensor=metadata.NULL_TENSOR)
    return summary


def write_hparams_session(
    run_dir: Path,
    hparams: Mapping[str, Any],
    metrics: Mapping[str, float],
    domains: Mapping[str, list[Any]],
    *,
    start_time_secs: float | None = None,
) -> None:
    """Make ``run_dir`` an HParams session with ``hparams`` and ``metrics`` (see the module docstring).

    ``domains`` holds every compared hyperparameter's values over all sessions of the
    experiment (:func:`hparam_domains`); it must cover ``hparams``.  The metrics are
    scalars ``summary/<metric>`` at step 0 in ``run_dir``, shown under their own names.
    """
    from tensorboard.plugins.hparams import summary_v2 as hp
    from torch.utils.tensorboard import SummaryWriter

    values = {k: hparam_value(v) for k, v in hparams.items()}
    missing = [k for k in values if k not in domains]
    if missing:
        raise ValueError(f"hparams {missing} have no domain")
    # no group name: each session is its own group, named by its run
    start = hp.hparams_pb(values, trial_id="", start_time_secs=start_time_secs)
    with SummaryWriter(str(run_dir)) as writer:
        writer.file_writer.add_summary(_experiment_summary(domains, metrics))
        writer.file_writer.add_summary(start)
        for k, v in metrics.items():
            writer.add_scalar(METRIC_PREFIX + k, float(v), 0)
        writer.file_writer.add_summary(_session_end_summary())


def move_events(source: Path, run_dir: Path) -> None:
    """Make ``run_dir`` hold exactly the event files of ``source`` (which is removed).

    A ``run_dir`` left by an interrupted writing is replaced.  Without ``source``,
    ``run_dir`` is created empty.
    """
    source, run_dir = Path(source), Path(run_dir)
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    if source.is_dir():
        source.rename(run_dir)
    else:
        run_dir.mkdir()
