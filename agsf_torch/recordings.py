"""Recorded sensor data: a documented file format for gyro and star-camera logs.

A recording is a NumPy ``.npz`` archive (read with ``allow_pickle=False``: data
only) holding, for ``B`` trajectories of ``T`` samples and up to ``M`` stars per
frame (a single trajectory may omit the leading ``B``):

==================  ==================  ======  =====================================================
key                 shape               dtype   meaning
==================  ==================  ======  =====================================================
``time``            ``[T]``             float   sample times (s), strictly increasing
``gyro``            ``[B, T, 3]``       float   measured body rate ω̃ over the interval ending at ``time`` (rad/s)
``star_body``       ``[B, T, M, 3]``    float   measured star unit vectors, body frame
``star_inertial``   ``[B, T, M, 3]``    float   catalogue unit vectors, inertial frame
``star_mask``       ``[B, T, M]``       bool    valid stars (all false between frames)
``gyro_valid``      ``[B, T]``          bool    optional: false for a missing or saturated gyro sample (default all true)
``truth_mrp``       ``[B, T, 3]``       float   optional: true attitude (MRP) at ``time``
``truth_bias``      ``[B, T, 3]``       float   optional: true gyro bias (rad/s)
``format``          ``[]``              str     ``"agsf-recording-1"``
==================  ==================  ======  =====================================================

Entries of ``star_body`` / ``star_inertial`` under a false mask are ignored but
must be finite (zeros by convention).  Valid star vectors must have unit norm:
within ``UNIT_TOLERANCE`` they are normalised with a warning; beyond it the file
is rejected.  Every error names the key, the trajectory, the row (sample) and
the column where it found the problem.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

__all__ = ["Recording", "FORMAT", "UNIT_TOLERANCE"]

FORMAT = "agsf-recording-1"
#: Largest |‖v‖ − 1| of a star vector that is normalised (with a warning) instead of rejected.
UNIT_TOLERANCE = 1e-3
_REQUIRED = ("time", "gyro", "star_body", "star_inertial", "star_mask")
_OPTIONAL = ("gyro_valid", "truth_mrp", "truth_bias")


@dataclass(frozen=True)
class Recording:
    """Batched sensor logs (numpy arrays, batch first; see the module table)."""

    time: np.ndarray
    gyro: np.ndarray
    star_body: np.ndarray
    star_inertial: np.ndarray
    star_mask: np.ndarray
    gyro_valid: np.ndarray | None = None
    truth_mrp: np.ndarray | None = None
    truth_bias: np.ndarray | None = None

    def __post_init__(self) -> None:
        arrays = {f.name: getattr(self, f.name) for f in fields(self)}
        if arrays["gyro"] is not None and np.ndim(arrays["gyro"]) == 2:  # one trajectory: add B = 1
            for k, v in arrays.items():
                if k != "time" and v is not None:
                    arrays[k] = np.asarray(v)[None]
        _validate(arrays)
        for k, v in arrays.items():
            object.__setattr__(self, k, v)

    @property
    def num_trajectories(self) -> int:
        return int(self.gyro.shape[0])

    @property
    def num_samples(self) -> int:
        return int(self.time.shape[0])

    def observation(self, k: int) -> dict:
        """Sample ``k`` as the environment's observation dict (torch tensors, batch first):
        ``gyro [B, 3]``, ``gyro_valid [B, 1]`` (all true without the column), ``star_body`` /
        ``star_inertial [B, M, 3]``, ``star_mask [B, M]``, ``time [B, 1]`` (s)."""
        B, t = self.num_trajectories, torch.as_tensor
        return {
            "gyro": t(self.gyro[:, k]),
            "gyro_valid": torch.ones(B, 1, dtype=torch.bool) if self.gyro_valid is None else t(self.gyro_valid[:, k, None]),
            "star_body": t(self.star_body[:, k]),
            "star_inertial": t(self.star_inertial[:, k]),
            "star_mask": t(self.star_mask[:, k]),
            "time": torch.full((B, 1), float(self.time[k]), dtype=torch.float64),
        }

    def star_frames(self) -> np.ndarray:
        """``[T]`` bool: samples at which any trajectory has a valid star."""
        return self.star_mask.any(axis=(0, 2))

    def save(self, path: str | Path) -> Path:
        """Write the archive (``.npz``, compressed); returns the path written."""
        path = Path(path)
        data = {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}
        np.savez_compressed(path, format=np.array(FORMAT), **data)
        return path if path.suffix == ".npz" else path.with_suffix(path.suffix + ".npz")

    @classmethod
    def load(cls, path: str | Path) -> "Recording":
        """Read and validate an archive written by :meth:`save` or by the user's own tools."""
        with np.load(Path(path), allow_pickle=False) as npz:
            keys = set(npz.files)
            missing = [k for k in _REQUIRED if k not in keys]
            if missing:
                raise ValueError(f"recording {path}: missing column(s) {', '.join(missing)}")
            fmt = str(npz["format"]) if "format" in keys else FORMAT
            if fmt != FORMAT:
                raise ValueError(f"recording {path}: format {fmt!r} is not {FORMAT!r}")
            data = {k: npz[k] for k in _REQUIRED + _OPTIONAL if k in keys}
        return cls(**data)


def _validate(a: dict[str, np.ndarray | None]) -> None:
    time = np.asarray(a["time"], dtype=np.float64)
    if time.ndim != 1 or time.size == 0:
        raise ValueError(f"recording: column 'time' must be a non-empty 1-D array, got shape {time.shape}")
    T = time.size
    bad = ~np.isfinite(time)
    if bad.any():
        raise ValueError(f"recording: column 'time' is not finite at row {int(np.argmax(bad))}")
    steps = np.diff(time)
    if (steps <= 0).any():
        row = int(np.argmax(steps <= 0)) + 1
        raise ValueError(f"recording: column 'time' is not strictly increasing at row {row} ({time[row - 1]} → {time[row]})")
    a["time"] = time
    gyro = np.asarray(a["gyro"], dtype=np.float64)
    if gyro.ndim != 3 or gyro.shape[1:] != (T, 3):
        raise ValueError(f"recording: column 'gyro' must have shape [B, {T}, 3], got {gyro.shape}")
    B = gyro.shape[0]
    a["gyro"] = gyro
    mask = np.asarray(a["star_mask"])
    if mask.dtype != np.bool_:
        raise ValueError(f"recording: column 'star_mask' must be boolean, got {mask.dtype}")
    if mask.ndim != 3 or mask.shape[:2] != (B, T):
        raise ValueError(f"recording: column 'star_mask' must have shape [{B}, {T}, M], got {mask.shape}")
    M = mask.shape[2]
    if a.get("gyro_valid") is not None:
        gv = np.asarray(a["gyro_valid"])
        if gv.dtype != np.bool_:
            raise ValueError(f"recording: column 'gyro_valid' must be boolean, got {gv.dtype}")
        if gv.shape != (B, T):
            raise ValueError(f"recording: column 'gyro_valid' must have shape [{B}, {T}], got {gv.shape}")
        a["gyro_valid"] = gv
    for key in ("star_body", "star_inertial"):
        v = np.asarray(a[key], dtype=np.float64)
        if v.shape != (B, T, M, 3):
            raise ValueError(f"recording: column '{key}' must have shape [{B}, {T}, {M}, 3], got {v.shape}")
        a[key] = v
    for key in ("truth_mrp", "truth_bias"):
        if a[key] is not None:
            v = np.asarray(a[key], dtype=np.float64)
            if v.shape != (B, T, 3):
                raise ValueError(f"recording: column '{key}' must have shape [{B}, {T}, 3], got {v.shape}")
            a[key] = v
    for key in ("gyro", "star_body", "star_inertial", "truth_mrp", "truth_bias"):
        v = a[key]
        if v is None:
            continue
        bad = ~np.isfinite(v)
        if bad.any():
            idx = [int(i) for i in np.argwhere(bad)[0]]
            raise ValueError(f"recording: column '{key}' is not finite at trajectory {idx[0]}, row {idx[1]}, entry {tuple(idx[2:])}")
    mask = a["star_mask"]
    for key in ("star_body", "star_inertial"):
        v = a[key]
        norm = np.linalg.norm(v, axis=-1)
        off = np.abs(norm - 1.0) * mask
        if (off > UNIT_TOLERANCE).any():
            b, t, m = np.argwhere(off > UNIT_TOLERANCE)[0]
            raise ValueError(
                f"recording: column '{key}' star {m} at trajectory {b}, row {t} is not a unit vector (norm {norm[b, t, m]:.6g})"
            )
        if (off > 1e-12).any():
            b, t, m = np.argwhere(off > 1e-12)[0]
            warnings.warn(
                f"recording: column '{key}' has star vectors off unit norm by up to {off.max():.2e} "
                f"(first at trajectory {b}, row {t}, star {m}); normalised",
                stacklevel=3,
            )
            safe = np.where(mask[..., None], norm[..., None], 1.0)
            a[key] = np.where(mask[..., None], v / safe, v)
