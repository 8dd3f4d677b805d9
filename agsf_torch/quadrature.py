"""Quadrature rules for expectations under a standard normal, ``E[g(ξ)]``, ``ξ ~ N(0, I_n)``.

* :func:`gauss_hermite` — tensor product of probabilists' Gauss–Hermite rules
  with a (possibly different) number of points per axis; ``m`` points on an axis
  integrate polynomials of degree ``≤ 2m − 1`` in that coordinate exactly.
* :func:`smolyak_gauss_hermite` — a Smolyak sparse grid built from the same 1-D
  rules, exact for polynomials of total degree ``≤ 2·level − 1``, for generic
  models in higher dimension where a tensor grid is too large.
* :func:`six_n_plus_one` — the ``6n + 1``-point rule of the adaptive Gaussian sum
  filter's authors (the centre and ``±1, ±2, ±3`` along each axis), exact for
  degree ≤ 3 and for the second moments.

A rule is returned as ``(nodes [K, n], weights [K])`` with ``Σ weights = 1``.
"""

from __future__ import annotations

import itertools
import math
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

__all__ = ["gauss_hermite", "smolyak_gauss_hermite", "six_n_plus_one", "QuadratureRule"]

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


def six_n_plus_one(dim: int, dtype=torch.float64, device=None) -> QuadratureRule:
    """The ``6n + 1``-point rule of the adaptive Gaussian sum filter's public code.

    Nodes: the origin and ``±e_k, ±2e_k, ±3e_k`` for each axis ``k``; with
    ``α = φ(2)/φ(1)``, ``β = φ(3)/φ(1)`` (``φ`` the standard normal density) and
    ``s = 2 + 8α + 18β`` the weights are ``1/s``, ``α/s``, ``β/s`` on the
    ``±1, ±2, ±3`` nodes and ``1 − n(1 + α + β)/(1 + 4α + 9β)`` at the origin, so
    the weights sum to 1 and every axis has unit variance.  Exact for
    polynomials of degree ≤ 3 and for ``E[ξ_k²] = 1``; not for the fourth moments
    (``E[ξ_k⁴] ≈ 2.94`` instead of 3).  Used as ``x = m + chol(S) ξ`` with the lower
    Cholesky factor, as in the authors' code.

    Returns:
        ``(nodes [6n + 1, n], weights [6n + 1])``.
    """
    if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
        raise ValueError(f"dim must be a positive integer, got {dim!r}")
    alpha, beta = math.exp(-1.5), math.exp(-4.0)  # φ(2)/φ(1), φ(3)/φ(1)
    s = 2.0 + 8.0 * alpha + 18.0 * beta
    eye = np.eye(dim)
    nodes = [np.zeros((1, dim))] + [sign * k * eye for k in (1, 2, 3) for sign in (1.0, -1.0)]
    per_axis = {1: 1.0 / s, 2: alpha / s, 3: beta / s}
    weights = [np.array([1.0 - dim * (1.0 + alpha + beta) / (1.0 + 4.0 * alpha + 9.0 * beta)])]
    weights += [np.full(dim, per_axis[k]) for k in (1, 2, 3) for _ in (1.0, -1.0)]
    return (
        torch.as_tensor(np.concatenate(nodes), dtype=dtype, device=device),
        torch.as_tensor(np.concatenate(weights), dtype=dtype, device=device),
    )
