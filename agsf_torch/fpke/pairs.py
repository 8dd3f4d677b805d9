"""The products ``pᵢ pⱼ`` of a mixture's components, one Gaussian per pair (method.md §3)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from ..models.base import sum_last
from .residual import ComponentRates

__all__ = ["ProductGaussians", "product_gaussians"]


@dataclass(frozen=True)
class ProductGaussians:
    """The products ``pᵢ pⱼ = z_ij N(x; m_ij, S_ij)`` of every pair ``i ≤ j`` of components.

    Attributes:
        index: ``[2, P]`` the pairs ``(i, j)``, ``P = N(N+1)/2`` (``torch.triu_indices``).
        mean: ``m_ij`` ``[..., P, n]``; cov: ``S_ij`` ``[..., P, n, n]``.
        log_z: ``log z_ij = log N(μᵢ; μⱼ, Pᵢ + Pⱼ)`` ``[..., P]``.
        first, second: the components ``i`` and ``j`` of each pair (:class:`ComponentRates`, ``[..., P, ...]``).
        sides: both, stacked in front as ``[2, ..., P, ...]`` (``first`` then ``second``; views).
        sum_precision: ``Σ⁻¹ = (Pᵢ + Pⱼ)⁻¹`` ``[..., P, n, n]``; gain: ``Kᵀ = Σ⁻¹Pᵢ``; y: ``Σ⁻¹(μᵢ − μⱼ)`` ``[..., P, n]``.

    The pair's moments seen from each component follow from these without
    multiplying by a component's precision (which loses every digit in the directions
    where ``Pᵢ`` is tiny): ``Πᵢ(m − μᵢ) = −y``, ``Πⱼ(m − μⱼ) = y``, ``ΠᵢS = I − Kᵀ``,
    ``ΠⱼS = Kᵀ`` and ``ΠSΠ − Π = −Σ⁻¹`` for both (:meth:`side_moments`).
    """

    index: Tensor
    mean: Tensor
    cov: Tensor
    log_z: Tensor
    first: ComponentRates
    second: ComponentRates
    sides: ComponentRates
    sum_precision: Tensor
    gain: Tensor
    y: Tensor

    def side_moments(self) -> tuple[Tensor, Tensor, Tensor]:
        """``(Πδ [2, ..., P, n], ΠS [2, ..., P, n, n], ΠSΠ − Π [..., P, n, n])`` for the two sides (class docstring)."""
        eye = torch.eye(self.gain.shape[-1], dtype=self.gain.dtype, device=self.gain.device)
        return torch.stack((-self.y, self.y)), torch.stack((eye - self.gain, self.gain)), -self.sum_precision

    def flat(self, t: Tensor, event: int) -> Tensor:
        """``t [..., P, *event]`` (its leading dims broadcasting against the pairs') as ``[Q, *event]``: one row
        per pair of every trajectory, ``event`` the number of trailing dims."""
        tail = t.shape[t.dim() - event :]
        return t.expand(*self.mean.shape[:-1], *tail).reshape(-1, *tail)

    @cached_property
    def chol(self) -> Tensor:
        """Lower Cholesky factor of ``S_ij`` ``[..., P, n, n]`` (for quadrature nodes ``m + chol ξ``)."""
        return torch.linalg.cholesky(self.cov)


def product_gaussians(rates: ComponentRates) -> ProductGaussians:
    """``m_ij``, ``S_ij`` and ``log z_ij`` for every pair ``i ≤ j`` (method.md §3).

    With ``Σ = Pᵢ + Pⱼ`` (Cholesky factor ``L_Σ``), ``d = μᵢ − μⱼ`` and one Cholesky
    solve ``[Kᵀ | y] = Σ⁻¹[Pᵢ | d]``: ``m_ij = μᵢ − Pᵢy``, ``S_ij = Pᵢ − PᵢKᵀ``,
    ``log z_ij = −½dᵀy − ½log det Σ − (n/2) log 2π`` — the same as
    ``S_ij = (Πᵢ + Πⱼ)⁻¹``, ``m_ij = S_ij(Πᵢμᵢ + Πⱼμⱼ)`` without inverting a covariance.
    """
    mu = rates.means
    N, n = mu.shape[-2:]
    iu = torch.triu_indices(N, N, device=mu.device)
    P = iu.shape[1]
    both = rates.select(iu.reshape(-1))  # [..., 2P, ...]
    ri, rj = both.split([P, P])  # [..., P, ...] each
    Pi = ri.covs
    d = ri.means - rj.means
    Ls = torch.linalg.cholesky(Pi + rj.covs)
    eye = torch.eye(n, dtype=mu.dtype, device=mu.device).expand_as(Pi)
    X = torch.cholesky_solve(torch.cat((Pi, d.unsqueeze(-1), eye), -1), Ls)
    Kt, y, Sinv = X[..., :n], X[..., n], X[..., n + 1 :]
    m = ri.means - sum_last(Pi * y.unsqueeze(-2))
    S = Pi - Pi @ Kt
    S = 0.5 * (S + S.transpose(-1, -2))
    log_det = 2.0 * sum_last(torch.log(Ls.diagonal(dim1=-2, dim2=-1)))
    log_z = -0.5 * (sum_last(d * y) + log_det + n * math.log(2.0 * math.pi))
    sides = both.map(lambda t, dim: t.unflatten(t.dim() + dim, (2, P)).movedim(t.dim() + dim, 0))
    return ProductGaussians(iu, m, S, log_z, ri, rj, sides, 0.5 * (Sinv + Sinv.transpose(-1, -2)), Kt, y)
