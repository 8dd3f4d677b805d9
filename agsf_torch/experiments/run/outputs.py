"""An experiment's output folder: who owns it, and the per-run data file (``runs.npz``) and its schema.

Folder layout (``out``)::

    experiment.json   the configuration and its digest (guards against overwriting another experiment)
    runs.npz          per-run data of every filter (the source of every number in summary.json)
    summary.json      the numbers behind every figure and the between-update statistics
    rms.png, axes.png, weights.png, fpke.png, and mixture.png with a managed filter
    tensorboard/      event files (scalars per step, weight histograms)
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Collection
from pathlib import Path
from typing import Any

import numpy as np

from ...storage.files import atomic_open, read_json, write_json
from .file_writer import FileWriter, too_large_to_hand_over
from .runner import MonteCarloResult

__all__ = [
    "OutputConflict",
    "OutputBusy",
    "check_output",
    "prepare_output",
    "release_outputs",
    "save_runs",
    "save_npz",
    "load_filter_runs",
]


#: The lock file of an output folder (one writer per folder).
LOCK_NAME = ".agsf.lock"


class OutputConflict(ValueError):
    """The output folder holds a different experiment."""


def _flat(config: Any, prefix: str = "") -> dict[str, Any]:
    """A configuration (nested mappings) as ``{"dotted.key": value}``."""
    if not isinstance(config, dict):
        return {prefix: config}
    flat: dict[str, Any] = {}
    for key, value in config.items():
        flat.update(_flat(value, f"{prefix}.{key}" if prefix else str(key)))
    return flat


def _what_differs(theirs: Any, ours: Any, ignored: Collection[str] = (), limit: int = 4) -> str:
    """Words naming how the configuration ``ours`` differs from ``theirs`` (the folder's): the first ``limit``
    differing keys (but ``ignored``: keys that do not make another experiment) with both values, or that the
    configurations agree (then another input differs)."""
    a, b = _flat(theirs), _flat(ours)
    keys = [k for k in sorted(set(a) | set(b)) if a.get(k, "—") != b.get(k, "—") and k not in ignored]
    if not keys:
        return "the same configuration with another input (a recording's contents, the filters named, an option)"
    text = lambda v: json.dumps(v, ensure_ascii=False, default=str)  # noqa: E731
    shown = "; ".join(f"{k}: {text(a.get(k, '—'))} there, {text(b.get(k, '—'))} here" for k in keys[:limit])
    more = f"; and {len(keys) - limit} more" if len(keys) > limit else ""
    return f"its configuration differs in {shown}{more}"


def check_output(
    out: Path, kind: str, digest: str, config: dict[str, Any] | None = None, ignored: Collection[str] = ()
) -> None:
    """Refuse ``out`` if it holds a different experiment (or is not an experiment folder);
    creates nothing.  ``digest`` identifies the experiment by content: its configuration and
    the digests of its input files, never their paths.

    With ``config`` (the experiment's configuration) a conflict names the keys whose values differ from the
    folder's (but ``ignored``, keys that do not enter ``digest``).

    Raises:
        OutputConflict: another experiment, or a non-empty folder without ``experiment.json``.
        ValueError: ``out`` is a file, or its ``experiment.json`` is corrupt.
    """
    out = Path(out)
    marker = out / "experiment.json"
    if out.exists() and not out.is_dir():
        raise ValueError(f"output folder {out} is a file; choose another --out")
    if marker.exists():
        try:
            prev = read_json(marker, "experiment marker")
        except ValueError as exc:
            raise ValueError(f"{exc}; remove {out} or choose another --out") from None
        if not isinstance(prev, dict) or prev.get("kind") != kind or prev.get("digest") != digest:
            prev = prev if isinstance(prev, dict) else {}
            why = ""
            if config is not None and prev.get("kind") == kind and "config" in prev:
                why = f": {_what_differs(prev['config'], config, ignored)}"
            raise OutputConflict(
                f"{out} already holds a different experiment ({prev.get('kind')} {prev.get('digest')}){why}; "
                "choose another --out or remove it"
            )
    elif out.exists() and any(p.name != LOCK_NAME for p in out.iterdir()):
        raise OutputConflict(f"{out} exists and is not an agsf experiment folder; choose another --out")


class OutputBusy(ValueError):
    """Another command (process) is writing the output folder."""


#: Output folders this process writes, with their locks (held until :func:`release_outputs`).
_HELD: dict[Path, Any] = {}


def _claim(out: Path) -> None:
    """Hold ``out/.agsf.lock`` (:mod:`filelock`) for this process; refuse if another process holds it."""
    from filelock import FileLock, Timeout

    key = out.resolve()
    if key in _HELD:
        return
    lock = FileLock(str(out / LOCK_NAME))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        raise OutputBusy(
            f"another agsf command is writing {out}; wait for it to finish or choose another --out"
        ) from None
    _HELD[key] = lock


def release_outputs() -> None:
    """Release every output folder this process claimed (:func:`prepare_output`); the CLI calls it when
    a command ends."""
    while _HELD:
        _, lock = _HELD.popitem()
        lock.release()


def prepare_output(out: Path, kind: str, digest: str, config: dict[str, Any], ignored: Collection[str] = ()) -> Path:
    """Create ``out`` for an experiment (after :func:`check_output`), claim it for this process (one writer
    per folder: a second command on it is refused with :class:`OutputBusy` until :func:`release_outputs`)
    and write its ``experiment.json`` atomically.  Callers validate every input first: a refused command
    creates nothing."""
    out = Path(out)
    check_output(out, kind, digest, config, ignored)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        _claim(out)
        write_json(out / "experiment.json", {"kind": kind, "digest": digest, "config": config}, indent=2)
    except BaseException:
        if created:  # a folder this call made and could not claim (a full disk, say) is not left behind
            lock = _HELD.pop(out.resolve(), None)
            if lock is not None:
                lock.release()
            shutil.rmtree(out, ignore_errors=True)
        raise
    return out


def save_npz(path: Path, data: dict[str, np.ndarray]) -> Path:
    """:func:`numpy.savez` of ``data`` written atomically to exactly ``path`` (what :func:`numpy.load` reads with
    ``allow_pickle=False``; entries dated 1980-01-01, so the file's bytes depend on ``data`` alone).

    Stored, not deflated (:func:`numpy.savez_compressed`): most of the bytes are the filters' float64 outputs,
    whose low bits are rounding noise that deflate shrinks by a third at many times the writing time."""
    with atomic_open(path) as fh:
        np.savez(fh, allow_pickle=False, **data)
    return Path(path)


#: The :class:`~agsf_torch.experiments.run.runner.FilterTrace` arrays ``runs.npz`` holds per filter (``error_angle``,
#: ``error`` and ``nees`` only with the truth).
TRACE_KEYS = (
    "estimate",
    "error_angle",
    "error",
    "sigma",
    "cov",
    "nees",
    "nis",
    "nis_dof",
    "weights",
    "weight_entropy",
)

#: Units of the ``runs.npz`` arrays (per filter: the key after ``name/``); diagnostics not listed are counts or ratios.
RUN_UNITS = {
    "time": "s",
    "star_frame": "bool",
    "prior_error_angle": "rad",
    "estimate": "MRP (attitude, inertial to body), rad/s (bias): the filter's estimate, its mixture's mean",
    "error_angle": "rad",
    "error": "rad (attitude: rotation-error vector, body axes of the truth), rad/s (bias)",
    "sigma": "rad (attitude: 1σ of the rotation error), rad/s (bias)",
    "cov": "MRP² (attitude), (rad/s)² (bias): the filter's own chart",
    "nees": "1 (χ² with n degrees of freedom)",
    "nis": "1 (νᵀS⁻¹ν at star frames, NaN between them; for star unit vectors its expectation is 2 per star, "
    "⅔·nis_dof: the noise lies across each star vector, agsf_torch.consistency)",
    "nis_dof": "count (the innovation's valid entries, 3 per star)",
    "weights": "1",
    "weight_entropy": "nat",
    "gyro_held": "0/1 (1: the gyro sample was bridged)",
    "gate_rejected": "count (star blocks the gate rejected)",
    "fpke_error_before": "FPKE residual (1/s) before the weight update",
    "fpke_error_after": "FPKE residual (1/s) after the weight update",
    "active_components": "count (managed filters: components in use at the step's end)",
    "splits": "count (managed filters: components split in the step's predict and update)",
    "merges": "count (managed filters: pairs merged in the step's predict and update)",
    "prunes": "count (managed filters: components pruned in the step's predict and update)",
}


#: The arrays of ``runs.npz`` that belong to the simulation, not to a filter.
SHARED_KEYS = ("time", "star_frame", "prior_error_angle")


def save_runs(
    path: Path,
    res: MonteCarloResult | None,
    reused: dict[str, tuple[dict, dict]] | None = None,
    writer: FileWriter | None = None,
) -> dict[str, np.ndarray]:
    """Write ``runs.npz`` and return what it writes (with ``writer``, a :class:`~agsf_torch.experiments.run.file_writer.FileWriter`, by one of
    its workers, or by a thread of the caller if the arrays exceed :data:`~agsf_torch.experiments.run.file_writer.HANDOVER_BYTES`: the file is
    complete when the writer is closed).

    Layout (batch first, as everywhere in the package): ``time [T]`` (s), ``star_frame [T]``,
    ``prior_error_angle [B]`` (rad: the prior mean's attitude error at ``t = 0``), and per filter ``name/key`` the :class:`~agsf_torch.experiments.run.runner.FilterTrace` fields
    ``[B, T, ...]`` (:data:`TRACE_KEYS`) — ``estimate``, ``error_angle``, ``error`` and ``sigma`` (rotation error
    and its 1σ; without the truth, a replay of flight data: no ``prior_error_angle``, ``error_angle``, ``error``
    and ``nees``),
    ``cov [B, T, n, n]`` (the filter's covariance), ``nees``, ``nis``, ``nis_dof``,
    ``weights [B, T, N]``, ``weight_entropy`` — plus every per-trajectory diagnostic
    ``[B, T]`` the filter reported (its ``diagnostic_keys``, e.g. ``fpke_error_before``,
    ``qp_kkt_residual``, ``gate_rejected``) and the input's (``gyro_held``).  ``units`` holds
    a JSON object: key (without the filter prefix) → unit (:data:`RUN_UNITS`).

    ``reused``: filters whose arrays come from an earlier experiment with the same simulation and options
    (:func:`load_filter_runs`: name → ``(arrays, units)``), written beside the ones run now; with ``res``
    ``None`` every filter is reused and ``time``/``star_frame`` are taken from the first of them.
    """
    reused = reused or {}
    if res is not None:
        data: dict[str, np.ndarray] = {"time": res.time, "star_frame": res.star_frame}
        if res.prior_error_angle is not None:
            data["prior_error_angle"] = res.prior_error_angle
        traces = res.traces
    else:
        first = next(iter(reused.values()))[0]
        data, traces = {k: first[k] for k in SHARED_KEYS if k in first}, {}
    units = {k: RUN_UNITS[k] for k in SHARED_KEYS if k in data}
    for name, tr in traces.items():
        for key in TRACE_KEYS:
            if getattr(tr, key) is not None:  # the scores against the truth are absent without it
                data[f"{name}/{key}"] = getattr(tr, key)
                units[key] = RUN_UNITS[key]
        for key, values in tr.extra.items():
            if values.shape == tr.weight_entropy.shape:
                data[f"{name}/{key}"] = values
                units[key] = RUN_UNITS.get(key, "1")
    for name, (arrays, their_units) in reused.items():
        for key in SHARED_KEYS:
            if (key in arrays) != (key in data) or (key in data and not np.array_equal(arrays[key], data[key])):
                raise RuntimeError(
                    f"the reused results of {name} do not match this experiment's simulation ({key} differs)"
                )
        data.update({k: v for k, v in arrays.items() if k.startswith(f"{name}/")})
        units.update(their_units)
    arrays = {**data, "units": np.array(json.dumps(units, sort_keys=True))}
    if writer is None:
        save_npz(path, arrays)
    else:  # handed to a worker, or too large to copy: a thread (writing releases the interpreter lock)
        writer.submit(save_npz, path, arrays, path=path, thread=too_large_to_hand_over(arrays.values()))
    return data


def load_filter_runs(path: Path, name: str) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Filter ``name``'s arrays of a ``runs.npz`` (with ``time`` and ``star_frame``) and the units of its keys."""
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files if k.startswith(f"{name}/") or k in SHARED_KEYS}
        units = json.loads(str(f["units"]))
    if not any("/" in k for k in arrays):
        raise ValueError(f"{path} holds no results of the filter {name}")
    keys = {k.split("/", 1)[1] for k in arrays if "/" in k}
    return arrays, {k: v for k, v in units.items() if k in keys}
