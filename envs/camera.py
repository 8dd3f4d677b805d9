"""Pinhole star camera (method.md §1).

Boresight along body z, focal length f, principal point (x₀, y₀).  With
``v = C r`` the body-frame direction of a catalogue star (C inertial → body),

    x = −f v₁/v₃ + x₀,     y = −f v₂/v₃ + y₀                       (image plane, m)

and the star is *visible* when ``v₃ > 0``, ``|x − x₀| ≤ f tan(fov_x/2)`` and
``|y − y₀| ≤ f tan(fov_y/2)`` (evaluated division-free as ``|v₁| ≤ tan(fov_x/2) v₃``
etc.).  Of the visible stars the M brightest are kept (the catalogue is sorted
brightest first, so these are the M visible stars of smallest catalogue index),
in brightness order.  The measured unit vector is

    b = [−(x − x₀), −(y − y₀), f] / sqrt((x − x₀)² + (y − y₀)² + f²),

equal to ``C r`` without noise.  Noise models (``noise=``):

* ``"focal_plane"`` (default): ``x, y`` receive independent ``N(0, (f σ)²)`` errors
  before ``b`` is formed.  Near the boresight this is an angular error of σ rad per
  axis; at an off-axis angle θ the radial error shrinks to ``σ cos²θ`` and the
  tangential one to ``σ cos θ`` (≥ 0.99 σ over an 8°×8° field).
* ``"unit_vector"``: ``b = (v + e)/|v + e|`` with ``e = σ (I − v vᵀ) n``,
  ``n ~ N(0, I₃)``, i.e. σ per axis in the plane perpendicular to ``v``.

Visibility is decided on the noise-free projection.  Rows beyond the number of
visible stars are padding: zero vectors and ``mask = False`` (a frame with no star is
an all-false mask, not an error).

Memory: a sky index (a cube map of cells, each with the list of stars that can be
visible from any boresight in the cell) limits the work to ``[B, L]`` with L a few
times the stars per field (186 for the default camera and cut) instead of ``[B, K]``; the
batch is processed in chunks so that no intermediate exceeds ~2¹⁷ elements per
tensor.  ``index="dense"`` tests every star (same results, bit for bit).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from agsf_torch.rotations import quat_to_dcm

from ._checks import MAX_STARS, check_camera_bounds, check_count, check_real, check_vector
from .catalog import StarCatalog
from .random import CounterKey, counter_normal
from .sky_index import cube_cell, stored_grid

__all__ = [
    "NOISE_MODES",
    "StarObservation",
    "StarCamera",
    "random_attitude_quat",
    "star_count_distribution",
]

NOISE_MODES = ("focal_plane", "unit_vector")

_CHUNK_ELEMENTS = 1 << 17
_STREAM_RANDOM_ATTITUDE = 7001


class StarObservation(NamedTuple):
    """One star frame per trajectory.

    Attributes:
        star_body: ``[..., M, 3]`` measured unit vectors (body frame); zeros where padded.
        star_inertial: ``[..., M, 3]`` catalogue unit vectors (inertial); zeros where padded.
        mask: ``[..., M]`` bool, True for a real star.
    """

    star_body: Tensor
    star_inertial: Tensor
    mask: Tensor


def _finite_positive(name: str, value: float) -> float:
    return check_real("StarCamera", name, value, positive=True)


class StarCamera:
    """Pinhole star camera with a magnitude-sorted catalogue.

    Args:
        catalog: the stars (sorted brightest first).
        fov_deg: full field of view ``(fov_x, fov_y)`` in degrees, each in ``(0, 180)``;
            a single number means square.
        focal_length: f (m), in ``[1e-6, 1e3]``.
        max_stars: M, the number of brightest visible stars reported, in ``[1, 117 955]``.
        sigma: σ (rad per axis), in ``[0, 1]``.
        noise: ``"focal_plane"`` or ``"unit_vector"`` (module docstring).
        principal_point: ``(x₀, y₀)`` (m), where the boresight meets the focal plane, within the imaged field
            (``|x₀| ≤ f tan(fov_x/2)``, likewise y); the ranges are explained in
            :func:`envs._checks.check_camera_bounds`.  A calibrated camera: the tracker knows ``(x₀, y₀)`` and
            subtracts it, so it shifts the pixel coordinates but not the star vectors (nor which stars are
            seen); a miscalibration (a boresight error) is not modelled.
        index: ``"grid"`` (cube-map sky index, default) or ``"dense"`` (test every star).

    Raises:
        ValueError: naming the field and value of any bad setting.
    """

    def __init__(
        self,
        catalog: StarCatalog,
        fov_deg: float | Sequence[float] = (8.0, 8.0),
        focal_length: float = 0.065,
        max_stars: int = 5,
        sigma: float = 10e-6,
        noise: str = "focal_plane",
        principal_point: Sequence[float] = (0.0, 0.0),
        index: str = "grid",
    ) -> None:
        if not isinstance(catalog, StarCatalog):
            raise ValueError(f"StarCamera: catalog must be a StarCatalog, got {type(catalog).__name__}")
        if isinstance(fov_deg, (int, float)) and not isinstance(fov_deg, bool):
            fov_deg = (fov_deg, fov_deg)
        fov = tuple(fov_deg)
        if len(fov) != 2:
            raise ValueError(f"StarCamera: fov_deg must hold 2 values (x, y), got {fov_deg!r}")
        fov = tuple(_finite_positive("fov_deg", v) for v in fov)
        for v in fov:
            if v >= 180.0:
                raise ValueError(f"StarCamera: fov_deg must be < 180 degrees, got {fov_deg!r}")
        self.fov_deg: tuple[float, float] = fov  # type: ignore[assignment]
        self.focal_length = _finite_positive("focal_length", focal_length)
        self.max_stars = check_count("StarCamera", "max_stars", max_stars, upper=MAX_STARS)
        self.sigma = check_real("StarCamera", "sigma", sigma)
        if noise not in NOISE_MODES:
            raise ValueError(f"StarCamera: noise must be one of {NOISE_MODES}, got {noise!r}")
        self.noise = noise
        pp = check_vector("StarCamera", "principal_point", principal_point, 2, unit=" (m)")
        self.principal_point: tuple[float, float] = pp  # type: ignore[assignment]
        check_camera_bounds("StarCamera", self.focal_length, fov, self.sigma, pp)  # type: ignore[arg-type]
        if index not in ("grid", "dense"):
            raise ValueError(f"StarCamera: index must be 'grid' or 'dense', got {index!r}")
        self.index = index
        self.catalog = catalog
        self.tan_half = (
            math.tan(math.radians(fov[0]) / 2.0),
            math.tan(math.radians(fov[1]) / 2.0),
        )
        # Angle from the boresight to a field corner: no visible star lies farther.
        self.half_diagonal = math.atan(math.hypot(*self.tan_half))
        self._grid: tuple[int, Tensor, Tensor] | None = None

    # ------------------------------------------------------------------ sky index
    def _grid_index(self) -> tuple[int, Tensor, Tensor]:
        """Cube-map index ``(n, table [6n², L], xyz [3, 6n², L])`` (cached on the catalogue).

        ``table`` holds candidate star indices (padding K), ``xyz`` their inertial
        vector components (padding 0), stored contiguously per row for fast gathers.
        """
        if self._grid is not None:
            return self._grid
        n = int(min(48, max(1, round(180.0 / math.degrees(self.half_diagonal)))))
        key = (n, round(self.half_diagonal, 12), str(self.catalog.r.device))
        cache = self.catalog.__dict__.setdefault("_grid_cache", {})
        if key not in cache:
            table = stored_grid(self.catalog.r, n, self.half_diagonal)
            xyz = self._r_ext(self.catalog.r)[table].permute(2, 0, 1).contiguous()
            cache[key] = (table, xyz)
        table, xyz = cache[key]
        self._grid = (n, table, xyz)
        return self._grid

    def _width(self) -> int:
        return len(self.catalog) if self.index == "dense" else self._grid_index()[1].shape[1]

    def _visible_chunk(self, C: Tensor) -> tuple[Tensor, Tensor]:
        """Candidates ``[c, L]`` (index K = padding) and their visibility ``[c, L]`` for ``C [c, 3, 3]``."""
        k = len(self.catalog)
        if self.index == "dense":
            r = self._r_ext(C)[:k]
            cand = torch.arange(k, device=C.device).expand(C.shape[0], k)
            x, y, z = (r[:, i].contiguous()[None, :] for i in range(3))
        else:
            n, table, xyz = self._grid_index()
            cell = cube_cell(C[:, 2, :], n)  # the boresight (body z) in inertial axes
            cand = table[cell]
            x, y, z = xyz[0][cell], xyz[1][cell], xyz[2][cell]
            if xyz.dtype != C.dtype:
                x, y, z = x.to(C.dtype), y.to(C.dtype), z.to(C.dtype)
        v1, v2, v3 = self._body(C, x, y, z)
        tx, ty = self.tan_half
        vis = (v3 > 0) & (v1.abs() <= tx * v3) & (v2.abs() <= ty * v3)
        return cand, vis

    # ------------------------------------------------------------------ core
    @staticmethod
    def _body(C: Tensor, x: Tensor, y: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``v = C r`` component-wise: ``v_i = C_i1 x + C_i2 y + C_i3 z``.

        Elementwise operations only, so a star's result does not depend on the batch
        it is computed in.  ``C [c, 3, 3]``; ``x, y, z`` ``[c, L]`` (or ``[1, L]``).
        """
        out = []
        for i in range(3):
            out.append(C[:, i, 0:1] * x + C[:, i, 1:2] * y + C[:, i, 2:3] * z)
        return out[0], out[1], out[2]

    def _select_chunk(self, C: Tensor) -> tuple[Tensor, Tensor]:
        """Indices ``[c, M]`` (K where padded) and mask of the M brightest visible stars."""
        k, m = len(self.catalog), self.max_stars
        cand, vis = self._visible_chunk(C)
        rank = torch.where(vis, cand, torch.full_like(cand, k))
        if rank.shape[1] < m:
            pad = torch.full((rank.shape[0], m - rank.shape[1]), k, dtype=rank.dtype, device=rank.device)
            rank = torch.cat((rank, pad), 1)
        # Candidates are catalogue indices (brightness ranks): the M smallest visible.
        idx = torch.topk(rank, m, dim=1, largest=False, sorted=True).values
        return idx, idx < k

    def _r_ext(self, like: Tensor) -> Tensor:
        """Catalogue vectors ``[K+1, 3]`` with a zero row appended (the padding index K)."""
        r = self.catalog.r
        if r.device != like.device or r.dtype != like.dtype:
            r = r.to(device=like.device, dtype=like.dtype)
        return torch.cat((r, torch.zeros(1, 3, dtype=r.dtype, device=r.device)), 0)

    def _chunks(self, C: Tensor):
        step = max(1, _CHUNK_ELEMENTS // max(self._width(), 1))
        return [C[i : i + step] for i in range(0, C.shape[0], step)]

    def select(self, C: Tensor) -> tuple[Tensor, Tensor]:
        """Catalogue indices of the M brightest visible stars.

        Args:
            C: attitude matrices ``[..., 3, 3]`` (inertial → body).

        Returns:
            ``(index [..., M] int64, mask [..., M] bool)``; padded slots hold index K
            (one past the last star) and mask False.  Slots are in brightness order.
        """
        lead, m = C.shape[:-2], self.max_stars
        parts = [self._select_chunk(c) for c in self._chunks(C.reshape(-1, 3, 3))]
        if not parts:
            e = torch.empty(*lead, m, dtype=torch.int64, device=C.device)
            return e, torch.zeros(*lead, m, dtype=torch.bool, device=C.device)
        idx = torch.cat([p[0] for p in parts]).reshape(*lead, m)
        mask = torch.cat([p[1] for p in parts]).reshape(*lead, m)
        return idx, mask

    def count_visible(self, C: Tensor) -> Tensor:
        """Number of visible stars (no cap at M).

        Args:
            C: ``[..., 3, 3]``.

        Returns:
            ``[...]`` int64.
        """
        lead = C.shape[:-2]
        counts = [self._visible_chunk(c)[1].sum(1) for c in self._chunks(C.reshape(-1, 3, 3))]
        if not counts:
            return torch.zeros(lead, dtype=torch.int64, device=C.device)
        return torch.cat(counts).reshape(lead)

    def observe(self, C: Tensor, noise: Tensor | CounterKey | None = None) -> StarObservation:
        """One star frame for each attitude.

        Args:
            C: attitude matrices ``[..., 3, 3]`` (inertial → body), float64.
            noise: ``None`` (noise-free), standard normals ``[..., M, 3]`` (slot j, axis a;
                focal-plane mode uses axes 0, 1 as the x, y errors in units of f σ,
                unit-vector mode all three before projection), or a
                :class:`~envs.random.CounterKey` whose seed has shape ``[...]`` (the
                normals are then ``key.normal((M, 3))``).

        Returns:
            :class:`StarObservation` ``(star_body [..., M, 3], star_inertial [..., M, 3],
            mask [..., M])``.  Noise-free, ``star_body = C star_inertial`` (to rounding).
        """
        if C.shape[-2:] != (3, 3):
            raise ValueError(f"StarCamera.observe: C must have shape [..., 3, 3], got {tuple(C.shape)}")
        m = self.max_stars
        idx, mask = self.select(C)
        r_sel = self._r_ext(C)[idx]  # [..., M, 3], zero rows where padded
        lead = C.shape[:-2]
        Cf = C.reshape(-1, 3, 3)
        rf = r_sel.reshape(-1, m, 3)
        v1, v2, v3 = self._body(Cf, rf[..., 0], rf[..., 1], rf[..., 2])
        v1, v2, v3 = (t.reshape(*lead, m) for t in (v1, v2, v3))

        normals = None
        if isinstance(noise, CounterKey):
            normals = noise.normal((m, 3), dtype=C.dtype)
        elif noise is not None:
            normals = noise
        if normals is not None:
            if normals.shape != (*lead, m, 3):
                raise ValueError(
                    f"StarCamera.observe: noise must have shape {(*lead, m, 3)}, got {tuple(normals.shape)}"
                )
            normals = normals.to(C.dtype)

        safe_v3 = torch.where(mask, v3, torch.ones_like(v3))
        if self.noise == "focal_plane":
            f = self.focal_length
            x0, y0 = self.principal_point
            x = -f * v1 / safe_v3 + x0
            y = -f * v2 / safe_v3 + y0
            if normals is not None and self.sigma > 0.0:
                x = x + (f * self.sigma) * normals[..., 0]
                y = y + (f * self.sigma) * normals[..., 1]
            dx, dy = x - x0, y - y0
            b = torch.stack((-dx, -dy, torch.full_like(dx, f)), -1)
        else:
            b = torch.stack((v1, v2, v3), -1)
            if normals is not None and self.sigma > 0.0:
                u = b / torch.linalg.vector_norm(b, dim=-1, keepdim=True).clamp_min(1e-300)
                e = normals - (normals * u).sum(-1, keepdim=True) * u
                b = u + self.sigma * e
        b = b / torch.linalg.vector_norm(b, dim=-1, keepdim=True).clamp_min(1e-300)
        b = torch.where(mask[..., None], b.clamp(-1.0, 1.0), torch.zeros_like(b))
        return StarObservation(b, r_sel, mask)


# ---------------------------------------------------------------------- statistics
def random_attitude_quat(seed: int, num: int, stream: int = _STREAM_RANDOM_ATTITUDE) -> Tensor:
    """Attitudes uniform on SO(3): normalised 4-D standard normals (counter RNG).

    Args:
        seed: int seed; draw ``i`` uses element ``4i … 4i+3`` of ``(seed, step 0, stream)``.
        num: number of attitudes.

    Returns:
        Unit quaternions ``[num, 4]`` (scalar-last), float64.
    """
    z = counter_normal(seed, 0, stream, (num, 4))
    return z / torch.linalg.vector_norm(z, dim=-1, keepdim=True)


def star_count_distribution(
    num_attitudes: int = 100_000,
    seed: int = 0,
    camera: StarCamera | None = None,
) -> np.ndarray:
    """Histogram of the number of reported stars per frame over uniform random attitudes.

    Args:
        num_attitudes: number of attitudes, drawn uniformly on SO(3) by
            :func:`random_attitude_quat`.
        seed: RNG seed.
        camera: default: the default :class:`StarCamera` on the default Hipparcos cut.

    Returns:
        ``[M + 1]`` float64 numpy array: entry m is the fraction of frames reporting m
        stars (``min(visible, M)``); sums to 1.
    """
    if int(num_attitudes) < 1:
        raise ValueError(f"star_count_distribution: num_attitudes must be ≥ 1, got {num_attitudes}")
    if camera is None:
        camera = StarCamera(StarCatalog.from_hipparcos())
    C = quat_to_dcm(random_attitude_quat(seed, int(num_attitudes)))
    counts = camera.count_visible(C).clamp(max=camera.max_stars)
    hist = torch.bincount(counts, minlength=camera.max_stars + 1).double()
    return (hist / hist.sum()).numpy()
