"""The closed-form ``E[ℓ]`` under a Gaussian (fpke.moments) against quadrature, and the model moments it uses."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.fpke import ComponentRates, product_gaussians, residual_factor
from agsf_torch.fpke.moments import component_moments, residual_mean
from agsf_torch.models import AttitudeModel, LorenzModel
from agsf_torch.propagation import moment_derivatives
from agsf_torch.quadrature import gauss_hermite
from tests.helpers import F64, assert_within, relative_bound


def _rates(model, gen, B=4, N=3):
    n = model.state_dim
    mu = 0.5 * torch.randn(B, N, n, generator=gen, dtype=F64)
    A = 0.1 * torch.randn(B, N, n, n, generator=gen, dtype=F64)
    P = A @ A.transpose(-1, -2) + 1e-3 * torch.eye(n, dtype=F64)
    u = 0.1 * torch.randn(B, 1, 3, generator=gen, dtype=F64)
    r = moment_derivatives(model, mu, P, u)
    return ComponentRates(mu, torch.linalg.cholesky(P), r.mean_rate, r.cov_rate), u


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_residual_mean_equals_quadrature_under_any_gaussian(gen, estimate_bias):
    """E[ℓⱼ] under the pair Gaussians, both sides, from component_moments: equal to a 7-point-per-axis rule (exact)."""
    model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=1e-3, sigma_u=1e-4)  # noise large enough to matter
    rates, u = _rates(model, gen)
    prod = product_gaussians(rates)
    moments = model.fokker_planck_moments(prod.mean, prod.cov, u)
    nodes, w = gauss_hermite((7,) * model.state_dim)
    x = prod.mean.unsqueeze(-2) + nodes @ prod.chol.transpose(-1, -2)
    terms = model.fokker_planck_terms(x, u.unsqueeze(-2))
    for side in (prod.first, prod.second):
        closed = residual_mean(moments, prod.cov, side, *component_moments(prod.mean, prod.cov, side))
        quad = (residual_factor(terms, x, side) * w).sum(-1)
        bound = relative_bound(quad, 1e-12, 1e-12 * float(quad.abs().max()))
        assert_within(closed, quad, bound, "E[ℓ] in closed form against the exact 7-point rule")
    # the pair's own form of the same moments (side_moments) gives the same numbers
    both = residual_mean(moments, prod.cov, prod.sides, *prod.side_moments())
    direct = torch.stack(
        [
            residual_mean(moments, prod.cov, s, *component_moments(prod.mean, prod.cov, s))
            for s in (prod.first, prod.second)
        ]
    )
    bound = relative_bound(direct, 1e-10, 1e-10 * float(direct.abs().max()))
    assert_within(both, direct, bound, "E[ℓ] from the pair's side moments against each side's own")


def test_models_without_moments_fall_back_to_quadrature():
    from agsf_torch.filters.weight_updates.base import has_gaussian_moments

    assert has_gaussian_moments(AttitudeModel()) and not has_gaussian_moments(LorenzModel())
    with pytest.raises(ValueError, match="gives no Gaussian moments"):
        from agsf_torch.fpke import galerkin_matrices

        model = LorenzModel()
        rates, _ = _rates(model, torch.Generator().manual_seed(0))
        galerkin_matrices(model, None, rates)
