"""Quadrature rules for expectations under a standard normal, ``E[g(ξ)]``, ``ξ ~ N(0, I_n)``.

* :func:`gauss_hermite` — tensor product of probabilists' Gauss–Hermite rules
  with a (possibly different) number of points per axis; ``m`` points on an axis
  integrate polynomials of degree ``≤ 2m − 1`` in that coordinate exactly.
* :func:`smolyak_gauss_hermite` — a Smolyak sparse grid built from the same 1-D
  rules, exact for polynomials of total degree ``≤ 2·level − 1``, for generic
  models in higher dimension where a tensor grid is too large.

A rule is returned as ``(nodes [K, n], weights [K])`` with ``Σ weights = 1``.
"""

from __future__ import annotations

import itertools
import math
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

__all__ = ["gauss_hermite", "smolyak_gauss_hermite", "QuadratureRule"]

QuadratureRule = tuple[Tensor, Tensor]


@lru_cache(maxsize=64)
def _gh_1d(m: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.hermite_e.hermegauss(m)
    return x, w / math.sqrt(2.0 * math.pi)


def gauss_hermite(points: int | tuple[int, ...], dim: int | None = None, dtype=torch.float64, device=None) -> QuadratureRule:
    """Tensor-product Gauss–Hermite rule for ``N(0, I)``.

    Args:
        points: points per axis (an int for all axes, or one per axis).
        dim: number of axes when ``points`` is an int.

    Returns:
        ``(nodes [K, n], weights [K])``, ``K = Π points``.
    """
    if isinstance(points, int):
        if dim is None:
            raise ValueError("dim is required when points is an int")
        points = (points,) * dim
    points = tuple(int(m) for m in points)
    if any(m < 1 for m in points):
        raise ValueError(f"points per axis must be ≥ 1, got {points}")
    rules = [_gh_1d(m) for m in points]
    grids = np.meshgrid(*[r[0] for r in rules], indexing="ij")
    wgrids = np.meshgrid(*[r[1] for r in rules], indexing="ij")
    nodes = np.stack([g.ravel() for g in grids], -1)
    weights = np.prod(np.stack([g.ravel() for g in wgrids], -1), -1)
    return torch.as_tensor(nodes, dtype=dtype, device=device), torch.as_tensor(weights, dtype=dtype, device=device)


def smolyak_gauss_hermite(dim: int, level: int, dtype=torch.float64, device=None) -> QuadratureRule:
    """Smolyak sparse grid from 1-D Gauss–Hermite rules with ``l`` points at level ``l``.

    .. math:: A(q, n) = Σ_{q-n+1 ≤ |l| ≤ q} (-1)^{q-|l|} \\binom{n-1}{q-|l|} U_{l_1} ⊗ … ⊗ U_{l_n},\\quad q = n + \\text{level} - 1

    exact for polynomials of total degree ``≤ 2·level − 1``.  Coinciding nodes
    are merged; some weights are negative.

    Returns:
        ``(nodes [K, n], weights [K])``.
    """
    if dim < 1 or level < 1:
        raise ValueError(f"dim and level must be ≥ 1, got {dim}, {level}")
    q = dim + level - 1
    acc: dict[tuple[float, ...], float] = {}
    for lvl in itertools.product(range(1, level + 1), repeat=dim):
        s = sum(lvl)
        if not q - dim + 1 <= s <= q:
            continue
        coeff = (-1) ** (q - s) * math.comb(dim - 1, q - s)
        nodes, weights = gauss_hermite(tuple(lvl), dtype=torch.float64)
        for x, w in zip(np.round(nodes.numpy(), 14).tolist(), weights.numpy().tolist()):
            key = tuple(x)
            acc[key] = acc.get(key, 0.0) + coeff * w
    keys = [k for k, v in acc.items() if v != 0.0]
    nodes = torch.tensor(keys, dtype=dtype, device=device)
    weights = torch.tensor([acc[k] for k in keys], dtype=dtype, device=device)
    return nodes, weights
