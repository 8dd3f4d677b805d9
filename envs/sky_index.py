"""The star camera's sky index: a cube map of cells, each with the catalogue stars that can be visible from any
boresight in the cell (:class:`~envs.camera.StarCamera` looks only at its boresight's cell), built once per
catalogue and field of view and kept on disk beside the parsed catalogue."""

from __future__ import annotations

import hashlib
import math
import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .catalog import cache_dir

__all__ = ["build_grid", "cube_cell", "stored_grid"]

_GRID_ELEMENTS = 1 << 20  # cells × stars compared per chunk while the index is built

_FACE_AXES = ((0, 1, 2), (1, 2, 0), (2, 0, 1))  # (major, u, v) per axis pair of faces


def cube_cell(d: Tensor, n: int) -> Tensor:
    """Cube-map cell ``face·n² + i·n + j`` of directions ``d [c, 3]`` (any norm > 0)."""
    a = d.abs()
    major = a.argmax(-1)  # 0, 1, 2
    comp = torch.gather(d, 1, major[:, None]).squeeze(1)
    face = 2 * major + (comp < 0).long()
    perm = torch.tensor(_FACE_AXES, device=d.device)[major]  # [c, 3]
    den = comp.abs()
    u = torch.gather(d, 1, perm[:, 1:2]).squeeze(1) / den
    v = torch.gather(d, 1, perm[:, 2:3]).squeeze(1) / den
    i = ((u + 1.0) * (0.5 * n)).floor().long().clamp(0, n - 1)
    j = ((v + 1.0) * (0.5 * n)).floor().long().clamp(0, n - 1)
    return face * (n * n) + i * n + j


def stored_grid(r: Tensor, n: int, cap: float) -> Tensor:
    """:func:`build_grid`, kept on disk beside the parsed catalogue (:func:`~envs.catalog.cache_dir`) under a key
    of the star directions (their bytes, dtype and shape), ``n`` and ``cap``: the first star frame of every process
    had rebuilt it (0.1–0.5 s for the default catalogue).  The file holds the table and a digest of its bytes; a file
    that cannot be read, or whose table does not match its digest or is not a candidate table of this catalogue
    (indices in ``[0, K]``, rows ascending), is built again and replaced.  A disk that cannot be written leaves the
    table in memory only."""
    stars = r.detach().cpu().contiguous()
    key = hashlib.sha256(stars.view(torch.uint8).numpy().tobytes())
    key.update(f"|{stars.dtype}|{tuple(stars.shape)}|{n}|{cap!r}|v1".encode())
    path = cache_dir() / f"sky-grid-{key.hexdigest()[:20]}.npz"
    try:
        with np.load(path, allow_pickle=False) as stored:
            table, digest = stored["table"], str(stored["digest"])
        if (
            table.dtype == np.int64
            and table.ndim == 2
            and table.shape[0] == 6 * n * n
            and hashlib.sha256(table.tobytes()).hexdigest() == digest
            and table.min() >= 0
            and table.max() <= r.shape[0]
            and bool((table[:, 1:] >= table[:, :-1]).all())
        ):
            return torch.from_numpy(table).to(r.device)
    except Exception:  # noqa: BLE001 - absent, torn or not this format: built and written below
        pass
    table = build_grid(r, n, cap)
    values = table.cpu().numpy()
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, table=values, digest=np.array(hashlib.sha256(values.tobytes()).hexdigest()))
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)  # a concurrent reader never sees a partial file
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError:
        pass  # a read-only or full disk: the table lives in memory only
    return table


def build_grid(r: Tensor, n: int, cap: float) -> Tensor:
    """Candidate table ``[6 n², L]`` (padded with K, rows sorted ascending).

    A star can be visible from a boresight in a cell only if its angle to the cell's
    centre is ≤ (cell radius) + (field half-diagonal): the cell radius is the largest
    angle from the centre to the cell's corners (cells are gnomonic squares on the
    cube faces, whose farthest points from the centre are corners).
    """
    dtype, device = r.dtype, r.device
    edges = torch.linspace(-1.0, 1.0, n + 1, dtype=dtype, device=device)
    mids = 0.5 * (edges[1:] + edges[:-1])
    centres, radii = [], []
    for major, ua, va in _FACE_AXES:
        for sign in (1.0, -1.0):

            def direction(u: Tensor, v: Tensor) -> Tensor:
                d = torch.zeros(*u.shape, 3, dtype=dtype, device=device)
                d[..., major] = sign
                d[..., ua] = u
                d[..., va] = v
                return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)

            uc, vc = torch.meshgrid(mids, mids, indexing="ij")
            c = direction(uc, vc)  # [n, n, 3]
            worst = torch.zeros(n, n, dtype=dtype, device=device)
            for du in (0, 1):
                for dv in (0, 1):
                    ue, ve = torch.meshgrid(edges[du : n + du], edges[dv : n + dv], indexing="ij")
                    corner = direction(ue, ve)
                    ang = torch.acos((c * corner).sum(-1).clamp(-1.0, 1.0))
                    worst = torch.maximum(worst, ang)
            centres.append(c.reshape(-1, 3))
            radii.append(worst.reshape(-1))
    centre = torch.cat(centres)  # [6n², 3], face order 2·major + (sign < 0)
    radius = torch.cat(radii)
    limit = torch.cos((radius + cap + 1e-6).clamp(max=math.pi))  # [cells]
    k = r.shape[0]
    cells = centre.shape[0]
    pairs: list[Tensor] = []
    step = max(1, _GRID_ELEMENTS // max(k, 1))
    for s in range(0, cells, step):
        near = (centre[s : s + step] @ r.T) >= limit[s : s + step, None]  # [c, K]
        nz = near.nonzero()  # row-major: rows ascending, stars ascending within a row
        nz[:, 0] += s
        pairs.append(nz)
    nz = torch.cat(pairs)
    counts = torch.bincount(nz[:, 0], minlength=cells)
    width = max(1, int(counts.max()))
    start = torch.cumsum(counts, 0) - counts
    pos = torch.arange(nz.shape[0], device=device) - start[nz[:, 0]]
    table = torch.full((cells, width), k, dtype=torch.int64, device=device)
    table[nz[:, 0], pos] = nz[:, 1]
    return table.contiguous()
