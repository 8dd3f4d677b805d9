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

For products ``E[f g]`` of two functions from a known polynomial space there is a
cheaper exact alternative to a quadrature rule of twice the degree:
:func:`product_rule` interpolates ``f`` and ``g`` at a unisolvent set of nodes and
returns their coefficients in an orthonormal Hermite basis, so that
``E[f g] = ĉ_f · ĉ_g`` and ``E[f] = ĉ_f[0]`` (:class:`ProductRule`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

__all__ = ["gauss_hermite", "smolyak_gauss_hermite", "six_n_plus_one", "QuadratureRule", "ProductRule", "product_rule"]

QuadratureRule = tuple[Tensor, Tensor]


@lru_cache(maxsize=64)
def _gh_1d(m: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.hermite_e.hermegauss(m)
    return x, w / math.sqrt(2.0 * math.pi)


#: Largest tensor-product rule :func:`gauss_hermite` builds (40 points per axis in 6 dimensions, 4.1e9 nodes, had
#: tried to allocate 30 GiB): beyond it a rule is refused before anything is allocated.
MAX_PRODUCT_NODES = 2_000_000


def gauss_hermite(
    points: int | tuple[int, ...], dim: int | None = None, dtype=torch.float64, device=None
) -> QuadratureRule:
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
    K = math.prod(points)
    if K > MAX_PRODUCT_NODES:
        raise ValueError(
            f"a tensor-product Gauss–Hermite rule with {points} points per axis has {K:,} nodes, more than "
            f"{MAX_PRODUCT_NODES:,}: use fewer points per axis or a sparse rule (smolyak_gauss_hermite)"
        )
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


def _exponents(k: int, degree: int) -> list[tuple[int, ...]]:
    """Multi-indices ``α ∈ Nᵏ`` with ``|α| ≤ degree``, graded (the constant first)."""
    return [a for d in range(degree + 1) for a in itertools.product(range(d + 1), repeat=k) if sum(a) == d]


def _hermite_basis(x: np.ndarray, exponents: list[tuple[int, ...]]) -> np.ndarray:
    """Orthonormal probabilists' Hermite polynomials ``Π He_{αᵢ}(xᵢ)/√αᵢ!`` at ``x [K, k]`` → ``[K, M]``."""
    top = max(max(a) for a in exponents)
    he = np.zeros((top + 1, *x.shape))
    he[0] = 1.0
    if top:
        he[1] = x
    for d in range(2, top + 1):
        he[d] = x * he[d - 1] - (d - 1) * he[d - 2]
    norms = np.array([math.sqrt(math.factorial(d)) for d in range(top + 1)])
    cols = [np.prod([he[a[i], :, i] / norms[a[i]] for i in range(len(a))], axis=0) for a in exponents]
    return np.stack(cols, -1)


@lru_cache(maxsize=32)
def _total_degree_set(k: int, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes ``[M, k]`` unisolvent for total degree ``≤ degree`` in ``k`` variables, and the map
    ``T [M, M]`` from values at them to orthonormal Hermite coefficients.

    The nodes are chosen from the ``(degree + 1)``-point Gauss–Hermite grid by QR with
    column pivoting on the basis matrix (approximate Fekete points), which keeps
    ``T`` well conditioned.
    """
    import scipy.linalg

    exps = _exponents(k, degree)
    m = degree + 1
    grid = np.stack([g.ravel() for g in np.meshgrid(*[_gh_1d(m)[0]] * k, indexing="ij")], -1)
    V = _hermite_basis(grid, exps)  # [K, M]
    weights = np.prod(np.stack([g.ravel() for g in np.meshgrid(*[_gh_1d(m)[1]] * k, indexing="ij")], -1), -1)
    _, _, piv = scipy.linalg.qr((V * np.sqrt(weights)[:, None]).T, pivoting=True)
    nodes = grid[np.sort(piv[: len(exps)])]
    T = np.linalg.solve(_hermite_basis(nodes, exps), np.eye(len(exps)))
    return nodes, T


@dataclass(frozen=True)
class ProductRule:
    """Interpolation at unisolvent nodes for a tensor product of total-degree polynomial spaces.

    A function ``f(ξ)`` in the space is known exactly from its values at ``nodes``;
    :meth:`coefficients` gives its coefficients ``ĉ`` in an orthonormal Hermite
    basis (``E[ψₐψ_b] = δₐ_b`` under ``N(0, I)``, ``ψ₀ = 1``), so ``E[f g] = ĉ_f · ĉ_g``
    and ``E[f] = ĉ_f[0]`` — exact products of two functions of the space with
    one value per node each.

    Attributes:
        nodes: ``[K, n]``, ``K = Π K_g``, ordered as the groups' nodes nested (first group outermost).
        groups: per group ``(axes, T_g [M_g, K_g])``.
    """

    nodes: Tensor
    groups: tuple[tuple[tuple[int, ...], Tensor], ...]

    def coefficients(self, values: Tensor) -> Tensor:
        """``[..., K]`` values at :attr:`nodes` → ``[..., M]`` coefficients (``M = Π M_g``)."""
        sizes = [T.shape[1] for _, T in self.groups]
        c = values.unflatten(-1, sizes)
        g = len(sizes)
        for i, (_, T) in enumerate(self.groups):
            c = torch.tensordot(c, T.to(c), dims=([c.dim() - g + i], [1])).movedim(-1, c.dim() - g + i)
        return c.flatten(-g)


def product_rule(
    groups: tuple[tuple[tuple[int, ...], int], ...], dim: int, dtype=torch.float64, device=None
) -> ProductRule:
    """:class:`ProductRule` for functions of total degree ``≤ d_g`` in the coordinates ``axes_g`` of each group.

    Args:
        groups: ``((axes, degree), ...)``, the axes of all groups partitioning ``range(dim)``.
        dim: ``n``.

    Raises:
        ValueError: groups that do not partition the axes, or a negative degree.
    """
    axes = [a for ax, _ in groups for a in ax]
    if sorted(axes) != list(range(dim)):
        raise ValueError(f"product_rule groups must partition the {dim} axes, got {[tuple(ax) for ax, _ in groups]}")
    if any(int(d) != d or d < 0 for _, d in groups):
        raise ValueError(f"product_rule degrees must be integers ≥ 0, got {[d for _, d in groups]}")
    sets = [_total_degree_set(len(ax), int(d)) for ax, d in groups]
    counts = [s[0].shape[0] for s in sets]
    nodes = np.zeros((int(np.prod(counts)), dim))
    for idx, combo in enumerate(itertools.product(*[range(c) for c in counts])):
        for (ax, _), (pts, _), k in zip(groups, sets, combo):
            nodes[idx, list(ax)] = pts[k]
    return ProductRule(
        torch.as_tensor(nodes, dtype=dtype, device=device),
        tuple((tuple(ax), torch.as_tensor(T, dtype=dtype, device=device)) for (ax, _), (_, T) in zip(groups, sets)),
    )
