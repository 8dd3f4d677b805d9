"""The FPKE residual factor ``ℓᵢ`` of a Gaussian component and the pointwise residual of a mixture (method.md §3).

For a mixture whose components follow the moment equations ``μ̇ᵢ, Ṗᵢ``, the
FPKE residual ``e(t, x) = ∂p̂/∂t − L_FP(p̂)`` is linear in the weights,
``e = Σᵢ wᵢ Lᵢ(x)``, with ``Lᵢ = pᵢ ℓᵢ`` and, for ``dᵢ = x − μᵢ``,
``zᵢ = Pᵢ⁻¹ dᵢ`` (a Cholesky solve):

.. math::

    ℓ_i(x) = z_i^T \\dot μ_i + ½\\left(z_i^T \\dot P_i z_i - \\operatorname{tr}(P_i^{-1}\\dot P_i)\\right)
             + \\operatorname{div} f - f^T z_i
             - \\left(Σ_{jk} ∂^2_{jk} D_{jk} - 2 a^T z_i + z_i^T D z_i - \\operatorname{tr}(D P_i^{-1})\\right)

with ``aₖ = Σⱼ ∂Dⱼₖ/∂xⱼ``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from ..models.base import ContinuousModel, FokkerPlanckTerms, sum_last
from ..shapes import broadcast_shapes

__all__ = ["ComponentRates", "residual_factor", "fpke_residual", "log_normal"]


@dataclass(frozen=True)
class ComponentRates:
    """A mixture's components and their moment rates at one time.

    Attributes:
        means: ``μᵢ`` ``[..., N, n]``.
        chol: Cholesky factors of ``Pᵢ`` ``[..., N, n, n]``.
        mean_rates: ``μ̇ᵢ`` ``[..., N, n]``.
        cov_rates: ``Ṗᵢ`` ``[..., N, n, n]``.
        precision: ``Πᵢ = Pᵢ⁻¹`` (it appears in ``ℓᵢ`` itself), formed from the Cholesky factor
            (``cholesky_inverse``) when first read, unless given as ``_precision``.
        covs: ``Pᵢ`` ``[..., N, n, n]``, formed as ``LLᵀ`` unless given.
    """

    means: Tensor
    chol: Tensor
    mean_rates: Tensor
    cov_rates: Tensor
    _precision: Tensor | None = None
    covs: Tensor | None = None

    def __post_init__(self) -> None:
        if self.covs is None:
            object.__setattr__(self, "covs", self.chol @ self.chol.transpose(-1, -2))

    @cached_property
    def precision(self) -> Tensor:
        """``Πᵢ`` ``[..., N, n, n]``, symmetrised."""
        if self._precision is not None:
            return self._precision
        Pi = torch.cholesky_inverse(self.chol)
        return 0.5 * (Pi + Pi.transpose(-1, -2))

    def with_precision(self) -> ComponentRates:
        """These components with ``Πᵢ`` formed now (once per component, before pairs are selected from them)."""
        if self._precision is not None:
            return self
        return ComponentRates(self.means, self.chol, self.mean_rates, self.cov_rates, self.precision, self.covs)

    _EVENT_DIMS = (("means", 1), ("chol", 2), ("mean_rates", 1), ("cov_rates", 2), ("_precision", 2), ("covs", 2))

    def map(self, fn) -> ComponentRates:
        """Apply ``fn(tensor, component_dim)`` to every field (``component_dim`` counted from the end); a
        precision not yet formed stays so."""
        return ComponentRates(
            *(
                None if getattr(self, name) is None else fn(getattr(self, name), -event - 1)
                for name, event in self._EVENT_DIMS
            )
        )

    def select(self, index: Tensor) -> ComponentRates:
        """The components ``index`` (along the component dim)."""
        return self.map(lambda t, dim: t.index_select(t.dim() + dim, index))

    def split(self, sizes: list[int]) -> list[ComponentRates]:
        """Split along the component dim into consecutive groups of ``sizes``."""
        parts = [
            [None] * len(sizes) if getattr(self, name) is None else getattr(self, name).split(sizes, dim=-event - 1)
            for name, event in self._EVENT_DIMS
        ]
        return [ComponentRates(*fields) for fields in zip(*parts)]


def residual_factor(terms: FokkerPlanckTerms, x: Tensor, rates: ComponentRates) -> Tensor:
    """``ℓᵢ(x)`` of the module equation at ``K`` points per component.

    Args:
        terms: model terms at ``x`` (leading dims broadcastable to ``[..., C, K]``);
            ``terms.diffusion`` may be a full ``[..., n, n]`` or, for a diagonal
            ``D``, its diagonal ``[..., n]``.
        x: points ``[..., C, K, n]``.
        rates: the component paired with each row of points, ``[..., C, ...]``.

    Returns:
        ``ℓ`` ``[..., C, K]``.
    """
    Pi = rates.precision  # [..., C, n, n]
    z = (x - rates.means.unsqueeze(-2)) @ Pi  # Π d for every point (Π symmetric)
    Pdot = rates.cov_rates
    # every z-weighted term in one reduction: Σₐ zₐ (μ̇ₐ − fₐ + 2aₐ + ½(Ṗz)ₐ − (Dz)ₐ)
    per_axis = rates.mean_rates.unsqueeze(-2) - terms.drift + 2.0 * terms.diffusion_divergence + 0.5 * (z @ Pdot)
    D = terms.diffusion
    if D.dim() == x.dim() or D.shape[-2:] != (x.shape[-1], x.shape[-1]):  # diagonal D, [..., n]
        per_axis = per_axis - D * z
        tr_D_Pinv = sum_last(D * Pi.diagonal(dim1=-2, dim2=-1).unsqueeze(-2))
    else:
        per_axis = per_axis - (D @ z.unsqueeze(-1)).squeeze(-1)
        tr_D_Pinv = (D * Pi.unsqueeze(-3)).sum((-2, -1))
    scalars = terms.drift_divergence - terms.diffusion_second_divergence - 0.5 * (Pi * Pdot).sum((-2, -1)).unsqueeze(-1)
    return sum_last(per_axis * z) + tr_D_Pinv + scalars


def fpke_residual(
    model: ContinuousModel, x: Tensor, u: Tensor | None, log_weights: Tensor, rates: ComponentRates
) -> Tensor:
    """Pointwise FPKE residual of the mixture, ``e(x) = Σᵢ wᵢ pᵢ(x) ℓᵢ(x)``.

    Args:
        x: ``[..., K, n]``; u: input ``[..., m]`` or ``None``;
        log_weights: ``[..., N]``; rates: components ``[..., N, ...]``.

    Returns:
        ``[..., K]``.
    """
    N = rates.means.shape[-2]
    xi = x.unsqueeze(-3).expand(*x.shape[:-2], N, *x.shape[-2:])  # [..., N, K, n]
    terms = model.fokker_planck_terms(x.unsqueeze(-3), None if u is None else u[..., None, None, :])
    ell = residual_factor(terms, xi, rates)  # [..., N, K]
    logp = log_normal(xi, rates.means.unsqueeze(-2), rates.chol.unsqueeze(-3))
    return (torch.exp(log_weights.unsqueeze(-1) + logp) * ell).sum(-2)


def log_normal(x: Tensor, mean: Tensor, chol: Tensor) -> Tensor:
    """``log N(x; μ, LLᵀ)`` with broadcasting: x ``[..., n]``, mean ``[..., n]``, chol ``[..., n, n]``."""
    d = x - mean
    shape = broadcast_shapes(d.shape[:-1], chol.shape[:-2])
    Lb = chol.expand(*shape, *chol.shape[-2:])
    z = torch.linalg.solve_triangular(Lb, d.expand(*shape, d.shape[-1]).unsqueeze(-1), upper=False).squeeze(-1)
    logdet = torch.log(chol.diagonal(dim1=-2, dim2=-1)).sum(-1)
    return -0.5 * (z * z).sum(-1) - logdet - 0.5 * x.shape[-1] * math.log(2.0 * math.pi)
