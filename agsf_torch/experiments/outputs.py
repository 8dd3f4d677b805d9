"""An experiment's output folder: who owns it, and the per-run data file (``runs.npz``) and its schema.

Folder layout (``out``)::

    experiment.json   the configuration and its digest (guards against overwriting another experiment)
    runs.npz          per-run data of every filter (the source of every number in summary.json)
    summary.json      the numbers behind every figure and the between-update statistics
    rms.png, axes.png, weights.png, fpke.png
    tensorboard/      event files (scalars per step, weight histograms)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .runner import MonteCarloResult

__all__ = ["OutputConflict", "prepare_output", "save_runs"]


class OutputConflict(ValueError):
    """The output folder holds a different experiment."""


def prepare_output(out: Path, kind: str, digest: str, config: dict[str, Any]) -> Path:
    """Create ``out`` for an experiment; refuse one that holds a different experiment."""
    out = Path(out)
    marker = out / "experiment.json"
    if marker.exists():
        prev = json.loads(marker.read_text())
        if prev.get("kind") != kind or prev.get("digest") != digest:
            raise OutputConflict(
                f"{out} already holds a different experiment ({prev.get('kind')} {prev.get('digest')}); "
                "choose another --out or remove it"
            )
    elif out.exists() and any(out.iterdir()):
        raise OutputConflict(f"{out} exists and is not an agsf experiment folder; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"kind": kind, "digest": digest, "config": config}, indent=2))
    return out


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
    np.savez_compressed(path, **data)
    return data


