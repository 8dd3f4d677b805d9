"""Quadrature rules for the FPKE integrals: the model's exact rule, a user's rule, or a generic one."""

from __future__ import annotations

import torch
from torch import Tensor

from ..models.base import ContinuousModel
from ..quadrature import ProductRule, gauss_hermite, product_rule, smolyak_gauss_hermite

__all__ = ["residual_rule"]


def residual_rule(model: ContinuousModel, quadrature, factors: int) -> tuple[Tensor | ProductRule, Tensor | None]:
    """The quadrature rule for ``E[ℓᵢ]`` (``factors = 1``, Galerkin) or ``E[ℓᵢℓⱼ]`` (``factors = 2``, penalty).

    Args:
        model: supplies its exact rule through ``model.fpke_quadrature_points(factors)`` when
            ``quadrature`` is ``None``.
        quadrature: ``None`` (the model's exact rule if it has one, else 7 Gauss–Hermite
            points per axis for ``n ≤ 4`` and a level-7 Smolyak grid above); an int
            (points per axis); a tuple of ints (points per axis); or ``(nodes [K, n],
            weights [K])`` for ``N(0, I_n)``, finite, weights summing to 1 — applied as
            ``x = m + chol(S) ξ`` with the lower Cholesky factor.

    Returns:
        ``(nodes [K, n], weights [K])`` float64; for ``factors = 2`` and ``quadrature = None`` with a
        model that declares the polynomial space of ``ℓ`` (``fpke_polynomial_space``), ``(ProductRule, None)``.

    Raises:
        ValueError: naming what is wrong with a rule.
    """
    n = model.state_dim
    if quadrature is None and factors == 2:
        space = model.fpke_polynomial_space()
        if space is not None:
            return product_rule(space, n), None
    if quadrature is None:
        try:
            pts = model.fpke_quadrature_points(factors)
        except TypeError:  # a model written for the one-argument form, which declared the ℓᵢℓⱼ rule
            pts = model.fpke_quadrature_points() if factors == 2 else None
        if pts is not None:
            return gauss_hermite(tuple(pts))
        return gauss_hermite(7, n) if n <= 4 else smolyak_gauss_hermite(n, 7)
    if isinstance(quadrature, bool):
        raise ValueError(f"quadrature must be None, an int, a tuple of ints or (nodes, weights), got {quadrature!r}")
    if isinstance(quadrature, int):
        if quadrature < 1:
            raise ValueError(f"quadrature points per axis must be ≥ 1, got {quadrature}")
        return gauss_hermite(quadrature, n)
    if (
        isinstance(quadrature, tuple)
        and quadrature
        and all(isinstance(q, int) and not isinstance(q, bool) for q in quadrature)
    ):
        if len(quadrature) != n:
            raise ValueError(f"quadrature needs one point count per state axis ({n}), got {quadrature}")
        return gauss_hermite(quadrature)
    try:
        nodes, weights = quadrature
        nodes = torch.as_tensor(nodes, dtype=torch.float64)
        weights = torch.as_tensor(weights, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(
            f"quadrature must be None, an int, a tuple of ints or (nodes [K, {n}], weights [K]), got {type(quadrature).__name__}"
        ) from None
    if nodes.dim() != 2 or nodes.shape[1] != n or weights.shape != nodes.shape[:1] or nodes.shape[0] == 0:
        raise ValueError(
            f"quadrature (nodes [K, {n}], weights [K]) has shapes {tuple(nodes.shape)}, {tuple(weights.shape)}"
        )
    if not bool(torch.isfinite(nodes).all()):
        raise ValueError("quadrature nodes must be finite")
    if not bool(torch.isfinite(weights).all()):
        raise ValueError("quadrature weights must be finite")
    total = float(weights.sum())
    if abs(total - 1.0) > 1e-10:
        raise ValueError(f"quadrature weights must sum to 1 (a rule for N(0, I)), got {total!r}")
    return nodes, weights
