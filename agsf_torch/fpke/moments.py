"""``E[ℓⱼ]`` under a Gaussian in closed form, from the model's Gaussian moments (method.md §3b).

For ``x ~ N(m, S)``, a component ``(μ, Π = P⁻¹, μ̇, Ṗ)``, ``δ = m − μ`` and
``w̄ = Πδ`` (the mean of ``z = Π(x − μ)``), Gaussian integration by parts
(``E[e g(e)] = S E[∇g]``, ``E[e eᵀ g] = S E[g] + S E[∇²g] S`` for ``e = x − m``)
gives every term of ``ℓ`` from a few moments of the model's terms
(:class:`~agsf_torch.models.base.FokkerPlanckMoments`, ``D = φD₁ + D₀``, ``v = f − 2a``):

.. math::

    E[ℓ] = w̄^Tμ̇ + ½\\big(w̄^T\\dot P w̄ + \\operatorname{tr}(Π\\dot PΠS) - \\operatorname{tr}(Π\\dot P)\\big)
           + E[\\operatorname{div} f - Σ∂^2D] - E[v]^T w̄ - \\operatorname{tr}(E[∂v/∂x]\\,SΠ)
           - E[z^TDz] + E[φ]\\operatorname{tr}(D_1Π) + \\operatorname{tr}(D_0Π),

    E[z^TDz] = E[φ]\\big(w̄^TD_1w̄ + \\operatorname{tr}(D_1ΠSΠ)\\big) + 2w̄^TD_1ΠS\\,E[∇φ]
               + \\operatorname{tr}(D_1ΠS\\,E[∇^2φ]\\,SΠ) + w̄^TD_0w̄ + \\operatorname{tr}(D_0ΠSΠ).

Exact for any model that supplies exact moments; ``O(n³)`` per pair and side.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..models.base import FokkerPlanckMoments, sum_last
from .residual import ComponentRates

__all__ = ["component_moments", "residual_mean"]


def component_moments(mean: Tensor, cov: Tensor, rates: ComponentRates) -> tuple[Tensor, Tensor, Tensor]:
    """``(w̄ = Πδ, ΠS, ΠSΠ − Π)`` of a Gaussian ``N(mean, cov)`` seen from the component(s) ``rates``,
    formed directly (for product Gaussians :meth:`ProductGaussians.side_moments` keeps every digit)."""
    Pi = rates.precision
    wbar = sum_last(Pi * (mean - rates.means).unsqueeze(-2))
    PiS = Pi @ cov
    return wbar, PiS, PiS @ Pi - Pi


def residual_mean(
    moments: FokkerPlanckMoments, cov: Tensor, rates: ComponentRates, wbar: Tensor, PiS: Tensor, PiSPi_minus_Pi: Tensor
) -> Tensor:
    """``E_{N(mean, cov)}[ℓ]`` of the component(s) ``rates`` (module equation).

    Args:
        moments: the model's moments under ``N(mean, cov)`` (leading dims broadcastable to ``[...]``).
        cov: ``S`` ``[..., n, n]``; rates: the components, ``means [..., n]`` etc.
        wbar, PiS, PiSPi_minus_Pi: ``Π(mean − μ)`` ``[..., n]``, ``ΠS`` and ``ΠSΠ − Π`` ``[..., n, n]``
            (:func:`component_moments`, or :meth:`~agsf_torch.fpke.pairs.ProductGaussians.side_moments`).

    Returns:
        ``[...]``.
    """
    Pdot = rates.cov_rates

    def quad(A: Tensor, x: Tensor) -> Tensor:  # xᵀAx
        return sum_last((A * x.unsqueeze(-1) * x.unsqueeze(-2)).flatten(-2))

    def inner(A: Tensor, B: Tensor) -> Tensor:  # tr(AᵀB)
        return sum_last((A * B).flatten(-2))

    rate_terms = sum_last(wbar * rates.mean_rates) + 0.5 * (quad(Pdot, wbar) + inner(Pdot, PiSPi_minus_Pi))
    transport = sum_last(moments.transport * wbar) + inner(moments.transport_jacobian, PiS)  # tr(J SΠ) = Σ J∘(ΠS)
    g = sum_last(PiS * moments.field_gradient.unsqueeze(-2))  # ΠS E[∇φ]
    Y = PiS @ moments.field_hessian  # ΠS E[∇²φ]; tr(D₁ΠS H SΠ) = Σ D₁ ∘ (Y (ΠS)ᵀ)
    D1, D0 = moments.pattern.to(cov), moments.constant.to(cov)
    if D1.dim() == 1 and D0.dim() == 1:  # diagonal D₁, D₀: elementwise
        base = wbar * wbar + PiSPi_minus_Pi.diagonal(dim1=-2, dim2=-1)
        field_part = sum_last(D1 * base)
        field_extra = 2.0 * sum_last(D1 * wbar * g) + sum_last((D1.unsqueeze(-1) * Y * PiS).flatten(-2))
        constant_part = sum_last(D0 * base)
    else:
        D1 = torch.diag_embed(D1) if D1.dim() == 1 else D1
        D0 = torch.diag_embed(D0) if D0.dim() == 1 else D0
        field_part = quad(D1, wbar) + inner(D1, PiSPi_minus_Pi)
        field_extra = 2.0 * (wbar * (D1 @ g.unsqueeze(-1)).squeeze(-1)).sum(-1) + inner(D1, Y @ PiS.transpose(-1, -2))
        constant_part = quad(D0, wbar) + inner(D0, PiSPi_minus_Pi)
    # −E[zᵀDz] + E[tr(DΠ)]
    diffusion = moments.field * field_part + field_extra + constant_part
    return rate_terms + moments.scalar - transport - diffusion
