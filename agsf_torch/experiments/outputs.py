"""An experiment's output folder: who owns it, and the per-run data file (``runs.npz``) and its schema.

Folder layout (``out``)::

    experiment.json   the configuration and its digest (guards against overwriting another experiment)
    runs.npz          per-run data of every filter (the source of every number in summary.json)
    summary.json      the numbers behind every figure and the between-update statistics
    rms.png, axes.png, weights.png, fpke.png
    tensorboard/      event files (scalars per step, weight histograms)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..files import atomic_open, read_json, write_json
from .runner import MonteCarloResult

__all__ = ["OutputConflict", "check_output", "prepare_output", "save_runs", "save_npz"]


class OutputConflict(ValueError):
    """The output folder holds a different experiment."""


def check_output(out: Path, kind: str, digest: str) -> None:
    """Refuse ``out`` if it holds a different experiment (or is not an experiment folder);
    creates nothing.  ``digest`` identifies the experiment by content: its configuration and
    the digests of its input files, never their paths.

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
            raise OutputConflict(
                f"{out} already holds a different experiment ({prev.get('kind')} {prev.get('digest')}); "
                "choose another --out or remove it"
            )
    elif out.exists() and any(out.iterdir()):
        raise OutputConflict(f"{out} exists and is not an agsf experiment folder; choose another --out")


def prepare_output(out: Path, kind: str, digest: str, config: dict[str, Any]) -> Path:
    """Create ``out`` for an experiment (after :func:`check_output`) and write its
    ``experiment.json`` atomically.  Callers validate every input first: a refused command
    creates nothing."""
    out = Path(out)
    check_output(out, kind, digest)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "experiment.json", {"kind": kind, "digest": digest, "config": config}, indent=2)
    return out


def save_npz(path: Path, data: dict[str, np.ndarray]) -> Path:
    """``np.savez_compressed`` written atomically to exactly ``path``."""
    with atomic_open(path) as fh:
        np.savez_compressed(fh, **data)
    return Path(path)


def save_runs(path: Path, res: MonteCarloResult) -> dict[str, np.ndarray]:
    """Write ``runs.npz``: ``time [T]``, ``star_frame [T]`` and per filter ``name/key`` arrays
    (:class:`~agsf_torch.experiments.runner.FilterTrace` fields, time first), plus every per-trajectory
    diagnostic ``[T, B]`` the filter reported (its ``diagnostic_keys``, e.g. ``fpke_error_before``,
    ``qp_kkt_residual``, ``gate_rejected``) and the input's (``gyro_held``); returns what it wrote."""
    data: dict[str, np.ndarray] = {"time": res.time, "star_frame": res.star_frame}
    for name, tr in res.traces.items():
        data[f"{name}/error_angle"] = tr.error_angle
        data[f"{name}/error"] = tr.error
        data[f"{name}/sigma"] = tr.sigma
        data[f"{name}/nees"] = tr.nees
        data[f"{name}/nis"] = tr.nis
        data[f"{name}/nis_dof"] = tr.nis_dof
        data[f"{name}/weights"] = tr.weights
        data[f"{name}/weight_entropy"] = tr.weight_entropy
        for key, values in tr.extra.items():
            if values.shape == tr.error_angle.shape:
                data[f"{name}/{key}"] = values
    save_npz(path, data)
    return data


