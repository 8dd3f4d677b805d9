"""The log-likelihood a filter reports for star frames is the data's: two degrees of freedom per measured unit
vector, whatever noise model its gain uses (:meth:`StarVectorMeasurement.data_log_likelihood`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from agsf_torch.fused.star_update import fused_star_update
from agsf_torch.models import StarVectorMeasurement
from agsf_torch.models.star_vectors import tangent_basis
from agsf_torch.rotations import mrp_to_dcm
from agsf_torch.update import kalman_update
from tests.helpers import F64, assert_within, random_mrps, random_spd, random_unit_vectors

EPS = torch.finfo(F64).eps


def _frame(gen, B=3, N=2, M=4, n=6, sigma=1e-5):
    truth = random_mrps(B, gen, max_norm=0.8)
    means = truth[:, None, :] + 1e-3 * torch.randn(B, N, 3, generator=gen, dtype=F64)
    if n == 6:
        means = torch.cat((means, 1e-6 * torch.randn(B, N, 3, generator=gen, dtype=F64)), -1)
    scale = torch.tensor([1e-6] * 3 + [1e-12] * 3, dtype=F64)[:n].sqrt()
    covs = scale[:, None] * random_spd(gen, B, N, n=n) * scale[None, :]
    r = random_unit_vectors(gen, B, M)
    mask = torch.rand(B, M, generator=gen) > 0.3
    mask[:, 0] = True
    y = (mrp_to_dcm(truth)[:, None] @ r.unsqueeze(-1)).squeeze(-1) + sigma * torch.randn(
        B, M, 3, generator=gen, dtype=F64
    )
    y = y / y.norm(dim=-1, keepdim=True)
    y = torch.where(mask[..., None], y, torch.zeros_like(y))  # between frames an invalid star reads zeros
    log_w = torch.log_softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    return log_w, means, covs, y.flatten(-2), r, mask


def _projected_reference(log_w, means, covs, y, meas, mask):
    """``log Σᵢ wᵢ N(Tᵀνᵢ; 0, Tᵀ(HPHᵀ + R)T)`` with the covariance formed and scipy's log-density, and the scale
    of its terms (for the bound): ``|log wᵢ| + ½(νᵀS⁻¹ν + |log det S| + 2m log 2π)`` and the condition of ``S_t``."""
    B, N = log_w.shape
    M = mask.shape[-1]
    out, scale, cond = [], [], []
    for b in range(B):
        T = torch.zeros(3 * M, 0, dtype=F64)
        for j in range(M):
            if mask[b, j]:
                block = torch.zeros(3 * M, 2, dtype=F64)
                block[3 * j : 3 * j + 3] = tangent_basis(y[b, 3 * j : 3 * j + 3])
                T = torch.cat((T, block), -1)
        terms, sizes, kappas = [], [], []
        for i in range(N):
            x = means[b, i].expand(B, -1)
            nu = y[b] - meas.predict(x)[b]
            H = meas.jacobian(x)[b]
            R = meas.noise_cov()
            R = R[b] if R.dim() > 2 else R
            S_t = (T.T @ (H @ covs[b, i] @ H.T + R) @ T).numpy()
            v = (T.T @ nu).numpy()
            terms.append(float(log_w[b, i]) + multivariate_normal(np.zeros(len(v)), S_t).logpdf(v))
            nis = float(v @ np.linalg.solve(S_t, v))
            sizes.append(
                abs(float(log_w[b, i])) + 0.5 * (nis + abs(np.linalg.slogdet(S_t)[1]) + len(v) * math.log(2 * math.pi))
            )
            kappas.append(np.linalg.cond(S_t))
        out.append(np.logaddexp.reduce(terms))
        scale.append(max(sizes))
        cond.append(max(kappas))
    return np.array(out), np.array(scale), np.array(cond)


@pytest.mark.parametrize("noise_model", ["isotropic", "tangent"])
@pytest.mark.parametrize("n", [3, 6])
def test_the_reported_log_likelihood_is_the_projected_gaussian_of_the_data(gen, noise_model, n):
    """Both update paths against the projected Gaussian formed explicitly.  The information form and scipy's
    eigendecomposition evaluate the same quantity with backward-stable steps: each term to ``O(κ(S_t)ε)`` of the
    terms' size (``κ(S_t) ≤ 1 + ‖HPHᵀ‖/σ²``)."""
    log_w, means, covs, y, r, mask = _frame(gen, n=n)
    body = torch.where(mask[..., None], y.unflatten(-1, (-1, 3)), r)  # the tangent model needs a unit vector
    meas = StarVectorMeasurement(r, mask, 1e-5, noise_model=noise_model, body=body)
    want, scale, cond = _projected_reference(log_w, means, covs, y, meas, mask)
    bound = 64 * EPS * cond * scale
    got = kalman_update(log_w, means, covs, y, meas).log_likelihood
    assert_within(got, want, bound, f"the data's log-likelihood ({noise_model}, generic path)")
    if noise_model == "isotropic":
        fused = fused_star_update(log_w, means, covs, y, meas).log_likelihood
        assert_within(fused, want, bound, "the data's log-likelihood (fused path)")


def test_both_noise_models_report_the_same_likelihood_of_the_same_data(gen):
    """``TᵀRT = σ_s²I₂`` under both models: the data's likelihood does not depend on how the gain spreads the
    noise (the two paths differ only in the rounding of ``R``'s radial part, which ``T`` projects out)."""
    log_w, means, covs, y, r, mask = _frame(gen)
    body = torch.where(mask[..., None], y.unflatten(-1, (-1, 3)), r)
    iso = kalman_update(log_w, means, covs, y, StarVectorMeasurement(r, mask, 1e-5)).log_likelihood
    tan = kalman_update(
        log_w, means, covs, y, StarVectorMeasurement(r, mask, 1e-5, noise_model="tangent", body=body)
    ).log_likelihood
    _, scale, cond = _projected_reference(log_w, means, covs, y, StarVectorMeasurement(r, mask, 1e-5), mask)
    assert_within(tan, iso, 64 * EPS * cond * scale, "log-likelihood under the tangent against the isotropic model")


def test_the_tangent_basis_is_orthonormal_and_across_the_vector(gen):
    b = random_unit_vectors(gen, 1000)
    b = torch.cat((b, torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=F64)))
    T = tangent_basis(b)
    # each entry a sum of ≤ 3 products of entries ≤ 1, each rounded: a few ε
    assert_within(T.transpose(-1, -2) @ T, torch.eye(2, dtype=F64).expand(len(b), 2, 2), 16 * EPS, "TᵀT")
    assert_within((b.unsqueeze(-2) @ T).squeeze(-2), 0.0, 16 * EPS, "bᵀT")
