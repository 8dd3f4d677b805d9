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
``initial_mrp``     ``[B, 3]``          float   optional: an attitude estimate at row 0 (MRP), where the filters start without the truth
``initial_bias``    ``[B, 3]``          float   optional: a gyro-bias estimate (rad/s) for that start (default zero)
``format``          ``[]``              str     ``"agsf-recording-1"``
==================  ==================  ======  =====================================================

Float columns hold real numbers (integers are converted to float64; bool, complex,
string and object arrays are refused, naming the column and the dtype).  Entries of
``star_body`` / ``star_inertial`` under a false mask are ignored but must be finite
(zeros by convention).  Valid star vectors must have unit norm: within
``UNIT_TOLERANCE`` they are normalised with a warning; beyond it the file is
rejected.  Every error names the key, the trajectory, the row (sample) and the
column where it found the problem; a file that is not a readable ``.npz`` archive
(missing: ``FileNotFoundError``; a directory, an empty, foreign, truncated or
corrupt file: ``ValueError``) is named by its path.

:meth:`Recording.save` writes atomically (a temporary file in the destination folder,
renamed into place), and :meth:`Recording.content_digest` identifies the contents.
"""

from __future__ import annotations

import errno
import hashlib
import struct
import warnings
import zipfile
import zlib
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from ..models.star_vectors import UNIT_ROUNDING, UNIT_TOLERANCE  # the filters' rule for star unit vectors
from ..storage.files import atomic_open

__all__ = ["Recording", "FORMAT", "UNIT_TOLERANCE"]

FORMAT = "agsf-recording-1"
_REQUIRED = ("time", "gyro", "star_body", "star_inertial", "star_mask")
_OPTIONAL = ("gyro_valid", "truth_mrp", "truth_bias", "initial_mrp", "initial_bias")
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a member's header, or an empty archive's directory (numpy's test)
# What reading a damaged archive raises from inside zipfile / zlib / numpy.
_READ_ERRORS = (
    OSError,
    EOFError,
    ValueError,
    zipfile.BadZipFile,
    zlib.error,
    NotImplementedError,
    struct.error,
    KeyError,
)


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
    initial_mrp: np.ndarray | None = None
    initial_bias: np.ndarray | None = None

    def __post_init__(self) -> None:
        arrays = {f.name: getattr(self, f.name) for f in fields(self)}
        if arrays["gyro"] is not None and np.ndim(arrays["gyro"]) == 2:  # one trajectory: add B = 1
            for k, v in arrays.items():
                if k != "time" and v is not None and not (k.startswith("initial_") and np.ndim(v) == 2):
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
            "gyro_valid": torch.ones(B, 1, dtype=torch.bool)
            if self.gyro_valid is None
            else t(self.gyro_valid[:, k, None]),
            "star_body": t(self.star_body[:, k]),
            "star_inertial": t(self.star_inertial[:, k]),
            "star_mask": t(self.star_mask[:, k]),
            "time": torch.full((B, 1), float(self.time[k]), dtype=torch.float64),
        }

    def trajectories(self, rows) -> Recording:
        """The recording of the trajectories ``rows`` (an index array, a boolean mask ``[B]`` or a slice), every
        sample of each."""
        arrays = {f.name: getattr(self, f.name) for f in fields(self)}
        return Recording(**{k: v if k == "time" or v is None else v[rows] for k, v in arrays.items()})

    def star_frames(self) -> np.ndarray:
        """``[T]`` bool: samples at which any trajectory has a valid star."""
        return self.star_mask.any(axis=(0, 2))

    def save(self, path: str | Path) -> Path:
        """Write the archive (``.npz``, compressed) atomically; returns the path written.

        ``.npz`` is appended to a path without it (as :func:`numpy.savez` does).  The
        archive is written by :func:`agsf_torch.storage.files.atomic_open` (a temporary file in the
        destination folder, flushed and renamed over the destination), so an interruption leaves
        either the previous file or the complete new one, never a torn archive (an
        exception removes the temporary file; a killed process may leave a hidden
        ``.NAME.*.tmp`` beside the destination).
        """
        path = Path(path)
        final = path if path.suffix == ".npz" else path.with_suffix(path.suffix + ".npz")
        data = {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}
        with atomic_open(final) as fh:
            np.savez_compressed(fh, format=np.array(FORMAT), **data)
        return final

    @classmethod
    def load(cls, path: str | Path) -> Recording:
        """Read and validate an archive written by :meth:`save` or by the user's own tools.

        Raises:
            FileNotFoundError: no file at ``path`` (naming it).
            ValueError: ``"recording {path}: …"`` for a directory, an empty file, a file that
                is not an ``.npz`` (zip) archive, a truncated or corrupt archive, a column that
                cannot be read (e.g. pickled objects), a missing column, another format, or
                any invalid content (:class:`Recording`).
        """
        path = Path(path)
        _check_archive_file(path)
        data: dict[str, np.ndarray] = {}
        try:
            with np.load(path, allow_pickle=False) as npz:
                keys = set(npz.files)
                missing = [k for k in _REQUIRED if k not in keys]
                if not missing:
                    data = {k: _read_column(path, npz, k) for k in ("format",) + _REQUIRED + _OPTIONAL if k in keys}
        except _ColumnError:
            raise
        except _READ_ERRORS as exc:
            raise ValueError(f"recording {path}: corrupt .npz archive ({type(exc).__name__}: {exc})") from exc
        if missing:
            raise ValueError(f"recording {path}: missing column(s) {', '.join(missing)}")
        fmt = str(data.pop("format")) if "format" in data else FORMAT
        if fmt != FORMAT:
            raise ValueError(f"recording {path}: format {fmt!r} is not {FORMAT!r}")
        with warnings.catch_warnings(record=True) as caught:  # the content checks' warnings: name the file too
            warnings.simplefilter("always")
            try:
                recording = cls(**data)
            except ValueError as exc:  # the content checks: name the file too
                message = str(exc).removeprefix("recording: ")
                raise ValueError(f"recording {path}: {message}") from None
        for w in caught:
            warnings.warn(f"recording {path}: {str(w.message).removeprefix('recording: ')}", w.category, stacklevel=2)
        return recording

    def content_digest(self) -> str:
        """Short hash of the contents (16 hex digits of a SHA-256).

        Covers the format name and, in the fixed order of the module table, every column
        present (optional ones included): its name, dtype, shape and bytes.  Two
        recordings with equal arrays have equal digests wherever they are stored; any
        changed value (one bit suffices), a column added or removed, or the same values
        under another column change it.
        """
        h = hashlib.sha256(FORMAT.encode())
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            arr = np.ascontiguousarray(value)
            h.update(f"\n{f.name}|{arr.dtype.str}|{arr.shape}\n".encode())
            h.update(arr.tobytes())
        return h.hexdigest()[:16]


def _check_archive_file(path: Path) -> None:
    """Refuse, naming ``path``, what cannot be an ``.npz`` archive: nothing there
    (``FileNotFoundError``), a directory, an empty file, or a file without a zip
    directory (text, ``.npy``, pickle, a truncated archive) (``ValueError``)."""
    if not path.exists():
        raise FileNotFoundError(errno.ENOENT, "no such recording file", str(path))
    if path.is_dir():
        raise ValueError(f"recording {path}: is a directory, not an .npz archive")
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(4)
        is_zip = zipfile.is_zipfile(path)
    except OSError as exc:
        raise ValueError(f"recording {path}: cannot be read ({exc.strerror or exc})") from exc
    if size == 0:
        raise ValueError(f"recording {path}: empty file, not an .npz archive")
    if head not in _ZIP_MAGIC:  # numpy would try to unpickle it, or read it as .npy
        raise ValueError(f"recording {path}: not an .npz archive (it starts with {head!r}, not a zip signature)")
    if not is_zip:
        raise ValueError(f"recording {path}: not an .npz archive (a truncated or damaged zip file: no zip directory)")


class _ColumnError(ValueError):
    """A member of an archive that cannot be read (the message names the file and the column)."""


def _read_column(path: Path, npz, key: str) -> np.ndarray:
    """One member of an open archive; a member that cannot be read (damaged, or pickled
    objects, which are never loaded) becomes a ``ValueError`` naming the file and the column."""
    try:
        return npz[key]
    except _READ_ERRORS as exc:
        raise _ColumnError(f"recording {path}: column '{key}' cannot be read ({type(exc).__name__}: {exc})") from exc


def _real_column(key: str, value) -> np.ndarray:
    """A float column as float64: integers are converted; bool, complex, string and object
    arrays are refused naming the column and the dtype (casting complex to float would drop
    the imaginary part, object or string arrays would fail or be parsed)."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"recording: column '{key}' must hold real numbers, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)


def _validate(a: dict[str, np.ndarray | None]) -> None:
    time = _real_column("time", a["time"])
    if time.ndim != 1 or time.size == 0:
        raise ValueError(f"recording: column 'time' must be a non-empty 1-D array, got shape {time.shape}")
    T = time.size
    bad = ~np.isfinite(time)
    if bad.any():
        raise ValueError(f"recording: column 'time' is not finite at row {int(np.argmax(bad))}")
    steps = np.diff(time)
    if (steps <= 0).any():
        row = int(np.argmax(steps <= 0)) + 1
        raise ValueError(
            f"recording: column 'time' is not strictly increasing at row {row} ({time[row - 1]} → {time[row]})"
        )
    a["time"] = time
    gyro = _real_column("gyro", a["gyro"])
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
        v = _real_column(key, a[key])
        if v.shape != (B, T, M, 3):
            raise ValueError(f"recording: column '{key}' must have shape [{B}, {T}, {M}, 3], got {v.shape}")
        a[key] = v
    for key in ("truth_mrp", "truth_bias"):
        if a[key] is not None:
            v = _real_column(key, a[key])
            if v.shape != (B, T, 3):
                raise ValueError(f"recording: column '{key}' must have shape [{B}, {T}, 3], got {v.shape}")
            a[key] = v
    for key in ("initial_mrp", "initial_bias"):
        if a.get(key) is not None:
            v = _real_column(key, a[key])
            if v.shape != (B, 3):
                raise ValueError(f"recording: column '{key}' must have shape [{B}, 3], got {v.shape}")
            bad = ~np.isfinite(v)
            if bad.any():
                raise ValueError(f"recording: column '{key}' is not finite at trajectory {int(np.argwhere(bad)[0][0])}")
            a[key] = v
    if a.get("initial_bias") is not None and a.get("initial_mrp") is None:
        raise ValueError("recording: column 'initial_bias' needs 'initial_mrp' (the estimate the filters start from)")
    for key in ("gyro", "star_body", "star_inertial", "truth_mrp", "truth_bias"):
        v = a[key]
        if v is None:
            continue
        bad = ~np.isfinite(v)
        if bad.any():
            idx = [int(i) for i in np.argwhere(bad)[0]]
            raise ValueError(
                f"recording: column '{key}' is not finite at trajectory {idx[0]}, row {idx[1]}, entry {tuple(idx[2:])}"
            )
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
        if (off > UNIT_ROUNDING).any():
            b, t, m = np.argwhere(off > UNIT_ROUNDING)[0]
            warnings.warn(
                f"recording: column '{key}' has star vectors off unit norm by up to {off.max():.2e} "
                f"(first at trajectory {b}, row {t}, star {m}); normalised",
                stacklevel=3,
            )
            safe = np.where(mask[..., None], norm[..., None], 1.0)
            a[key] = np.where(mask[..., None], v / safe, v)
