"""The fused Galerkin pair integrals against the generic closed-form route of :func:`agsf_torch.fpke.galerkin_matrices`.

Both evaluate ``log z_ij``, ``E[ℓᵢ]`` and ``E[ℓⱼ]`` from the same Cholesky factorisation of
``Σ = Pᵢ + Pⱼ`` and the same terms, in a different order.  The solves ``Σ⁻¹[Pᵢ | d | I]`` agree to
``O(κ(Σ)ε)`` relative and every term of ``E[ℓ]`` is at most quadratic in their results, so the two
differ by ``O((κ(Σ) + n²)ε)`` times the sum of the terms' magnitudes ``T`` (:func:`_term_scale`, computed
here from the generic pieces); the tolerance is 64× that.  ``M̃`` is a ratio of exponentials of
``log z`` (absolute error ``O(nε·|log det Σ|)``).
"""

from __future__ import annotations

import math

import pytest
import torch

import agsf_torch.fused.lanes as lanes
from agsf_torch.fpke import galerkin_matrices
from agsf_torch.fpke.pairs import product_gaussians
from agsf_torch.fpke.residual import ComponentRates
from agsf_torch.models import AttitudeModel
from agsf_torch.propagation import moment_derivatives
from tests.helpers import F64, assert_within, random_mrps

EPS = torch.finfo(F64).eps


def _components(gen, B, N, n, condition):
    """Random components ``[B, N]`` with their moment rates, covariances of the given condition number."""
    model = AttitudeModel(estimate_bias=n == 6, bias=torch.tensor([1e-6, -2e-6, 3e-6]))
    centre = random_mrps(B, gen, max_norm=0.8)[:, None, :]
    means = centre + 0.05 * torch.randn(B, N, 3, generator=gen, dtype=F64)
    if n == 6:
        means = torch.cat((means, 1e-5 * torch.randn(B, N, 3, generator=gen, dtype=F64)), -1)
    Q, _ = torch.linalg.qr(torch.randn(B, N, n, n, generator=gen, dtype=F64))
    eig = torch.logspace(0, -math.log10(condition), n, dtype=F64) * 1e-3
    eig = eig * torch.exp(torch.randn(B, N, 1, generator=gen, dtype=F64))  # components of different sizes
    covs = Q @ torch.diag_embed(eig) @ Q.transpose(-1, -2)
    covs = 0.5 * (covs + covs.transpose(-1, -2))
    u = 0.05 * torch.randn(B, 3, generator=gen, dtype=F64)
    rates = moment_derivatives(model, means, covs, u.unsqueeze(-2))
    comp = ComponentRates(means, torch.linalg.cholesky(covs), rates.mean_rate, rates.cov_rate, covs=covs)
    return model, u, comp


def _term_scale(model, u, comp):
    """``[2, B, P]``: the sum of the magnitudes of the terms of ``E[ℓ]`` for each pair and side
    (:func:`agsf_torch.fpke.moments.residual_mean`, every product taken in absolute value)."""
    prod = product_gaussians(comp)
    mom = model.fokker_planck_moments(prod.mean, prod.cov, u.unsqueeze(-2))
    wbar, PiS, Q = prod.side_moments()
    mu_dot, P_dot = prod.sides.mean_rates, prod.sides.cov_rates
    a = torch.abs
    ww = a(wbar.unsqueeze(-1) * wbar.unsqueeze(-2))
    rate = (a(wbar * mu_dot)).sum(-1) + 0.5 * ((a(P_dot) * ww).sum((-1, -2)) + (a(P_dot) * a(Q)).sum((-1, -2)))
    transport = a(mom.transport * wbar).sum(-1) + (a(mom.transport_jacobian) * a(PiS)).sum((-1, -2))
    g = (a(PiS) * a(mom.field_gradient).unsqueeze(-2)).sum(-1)
    Y = a(PiS) @ a(mom.field_hessian)
    D1, D0 = mom.pattern.to(F64), mom.constant.to(F64)
    base = wbar * wbar + a(Q.diagonal(dim1=-2, dim2=-1))
    diffusion = (
        a(mom.field) * (D1 * base).sum(-1)
        + 2.0 * (D1 * a(wbar) * g).sum(-1)
        + (D1.unsqueeze(-1) * Y * a(PiS)).sum((-1, -2))
        + (D0 * base).sum(-1)
    )
    return rate + a(mom.scalar) + transport + diffusion, prod


def _assert_agree(got, want, model, u, comp, n):
    """``got`` equals ``want`` (both :class:`GalerkinMatrices`) to the bounds of the module docstring."""
    scale, prod = _term_scale(model, u, comp)
    Sigma = prod.first.covs + prod.second.covs
    kappa = torch.linalg.cond(Sigma)  # [B, P]
    # log z = −½(dᵀΣ⁻¹d + log det Σ + n log 2π): the solve to κε of dᵀΣ⁻¹d, log det Σ to nκε (backward stability)
    log_det = torch.linalg.slogdet(Sigma)[1].abs()
    maha = (prod.y * (prod.first.means - prod.second.means)).sum(-1).abs()
    tol_log_z = 64 * EPS * (n * kappa + log_det + kappa * maha + n * math.log(2 * math.pi))  # [B, P]
    tol_scale = tol_log_z.amax(-1)
    assert_within(got.log_scale, want.log_scale, tol_scale, "log scale (the largest log z)")
    z = torch.exp(prod.log_z - want.log_scale[..., None])
    tol_z = tol_log_z + tol_scale[..., None]  # relative, of z_ij / max z
    i, j = prod.index
    # a z̃ in the subnormal range rounds to the absolute spacing 2⁻¹⁰⁷⁴ of its own (where its relative bound underflows)
    tiny = 16 * 2.0**-1074
    assert_within(got.mass[..., i, j], want.mass[..., i, j], 2 * z * tol_z + tiny, "mass matrix M̃ (pairs i ≤ j)")
    # K̃ = z̃ E[ℓ]: E[ℓ] to 64(κ + n²)ε of its terms' magnitudes, z̃ to tol_z
    tol = 64 * (kappa + n * n) * EPS * scale * z  # [2, B, P]: K̃_ji (E[ℓᵢ]) and K̃_ij (E[ℓⱼ])
    for side, (a, b) in enumerate(((j, i), (i, j))):
        bound = tol[side] + 2 * want.drift[..., a, b].abs() * tol_z + tiny
        assert_within(got.drift[..., a, b], want.drift[..., a, b], bound, f"drift matrix K̃ (side {side})")


@pytest.mark.parametrize("n", [3, 6])
@pytest.mark.parametrize(
    ("B", "N", "condition"),
    [(1, 1, 10.0), (3, 5, 1e3), (2, 64, 1e6), (667, 5, 1e12), (4, 7, 1e12)],  # 667 · 15 = 10,005 pairs
)
def test_fused_pairs_equal_the_generic_route(gen, monkeypatch, n, B, N, condition):
    monkeypatch.setattr(lanes, "EAGER_MIN_LANES", 0)  # the fused path at every size
    model, u, comp = _components(gen, B, N, n, condition)
    want = galerkin_matrices(model, u, comp, fused=False)
    _assert_agree(galerkin_matrices(model, u, comp), want, model, u, comp, n)


def test_the_weight_update_takes_the_fused_path_with_the_same_weights(gen, monkeypatch):
    """The adaptive filter (Galerkin) with the fused pairs chooses the generic route's weights, to the
    sensitivity of its QP: ``‖Δw‖ ≤ (‖Δc‖ + ‖ΔH‖)/λ_min(H)`` plus the QP's own rounding ``κ(H)ε``."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import AdaptiveGaussianSumFilter
    from agsf_torch.filters.weight_updates.base import component_rates

    monkeypatch.setattr(lanes, "EAGER_MIN_LANES", 0)
    model, u, comp = _components(gen, 6, 5, 6, 1e4)
    log_w = torch.log_softmax(torch.randn(6, 5, generator=gen, dtype=F64), -1)
    mix = GaussianMixture(log_weights=log_w, means=comp.means, covs=comp.covs)
    out = {}
    for fused in (True, False):
        agsf = AdaptiveGaussianSumFilter(model, weight_update="galerkin", fused=fused)
        out[fused] = (agsf.predict(mix, u, 1.0), agsf.diagnostics)
    assert out[True][1]["weights_adapted"]
    rates = component_rates(model, mix, u)
    Gf, Gg = galerkin_matrices(model, u, rates), galerkin_matrices(model, u, rates, fused=False)
    w0 = mix.weights.unsqueeze(-1)
    dc = (((Gf.drift - Gf.mass) - (Gg.drift - Gg.mass)) @ w0).squeeze(-1).norm(dim=-1)
    dH = torch.linalg.matrix_norm(Gf.mass - Gg.mass, ord=2)
    eig = torch.linalg.eigvalsh(
        Gg.mass + 1e-9 * Gg.mass.diagonal(dim1=-2, dim2=-1).amax(-1)[..., None, None] * torch.eye(5, dtype=F64)
    )
    bound = 8 * ((dc + dH) / eig[..., 0] + eig[..., -1] / eig[..., 0] * EPS)
    # every entry moves by at most the 2-norm of the move
    assert_within(out[True][0].weights, out[False][0].weights, bound[..., None], "Galerkin weights, fused and generic")


def test_the_model_declines_small_eager_batches_and_takes_the_generic_route(gen):
    model, u, comp = _components(gen, 2, 5, 6, 10.0)  # 30 pairs, eager: not worth fusing
    assert model.fused_galerkin_pairs(comp.means, comp.covs, u) is None
    G, want = galerkin_matrices(model, u, comp), galerkin_matrices(model, u, comp, fused=False)
    assert torch.equal(G.drift, want.drift) and torch.equal(G.mass, want.mass)  # the same code ran


@pytest.mark.slow
def test_the_compiled_pair_kernel_equals_the_eager_one(gen):
    model, u, comp = _components(gen, 300, 5, 6, 1e6)  # 4500 pairs: one chunk of 4096 and a padded one
    eager = galerkin_matrices(model, u, comp)
    _assert_agree(galerkin_matrices(model, u, comp, compile=True), eager, model, u, comp, 6)
