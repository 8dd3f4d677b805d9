"""Noise per trajectory: the attitude model's σ_v, σ_u and bias and the star measurement's σ_s may hold one value
per trajectory (how learning fits independent data sets in one program).  Each trajectory then gets exactly what a
model built with its own value gives it; the paths that take one value for all give way (the fused kernels) or
refuse (the FPKE terms), naming the shapes."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.attitude.gyro_hold import GyroHold
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from tests.helpers import F64, assert_within, random_mrps, random_unit_vectors, relative_bound

EPS = torch.finfo(F64).eps
B, N = 3, 2
# Both sides build each entry from the same numbers in a handful of roundings (products, a square, a sum of squares,
# a normalisation); another machine may order or fuse them differently.  16 ε of the magnitude of the terms that
# make up an entry bounds the difference with room for that.
FEW_ROUNDINGS = 16 * EPS


def _models(estimate_bias):
    sigma_v = torch.tensor([1e-7, 3e-7, 1e-6], dtype=F64)
    sigma_u = torch.tensor([1e-10, 3e-10, 1e-9], dtype=F64)
    bias = torch.tensor([[1e-6, 0.0, -1e-6], [0.0, 2e-6, 0.0], [5e-7, 5e-7, 5e-7]], dtype=F64)
    together = AttitudeModel(
        estimate_bias=estimate_bias, sigma_v=sigma_v[:, None], sigma_u=sigma_u[:, None], bias=bias[:, None]
    )
    alone = [
        AttitudeModel(estimate_bias=estimate_bias, sigma_v=sigma_v[b], sigma_u=sigma_u[b], bias=bias[b])
        for b in range(B)
    ]
    return together, alone


def _states(gen, estimate_bias):
    p = random_mrps(B * N, gen, max_norm=1.0).reshape(B, N, 3)
    if estimate_bias:
        p = torch.cat((p, 1e-5 * torch.randn(B, N, 3, generator=gen, dtype=F64)), -1)
    return p


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_each_trajectory_gets_the_drift_and_noise_of_its_own_values(gen, estimate_bias):
    """The same formula on the same numbers, one value per trajectory or one for all: equal to a few roundings of
    the terms of each entry.  ``gQgᵀ`` and ``Q`` are sums of positive terms (their entries bound the terms); each
    entry of ``A`` sums terms no larger than ``(1 + |p|)²|ω|`` (the ``F`` block) and ``1 + |p|²`` (the ``−¼B(p)``
    block), which cancel on the diagonal."""
    together, alone = _models(estimate_bias)
    x = _states(gen, estimate_bias)
    u = 1e-2 * torch.randn(B, 1, 3, generator=gen, dtype=F64)
    Q = torch.stack([m.process_noise(x[b]) for b, m in enumerate(alone)])
    assert_within(together.process_noise(x), Q, relative_bound(Q, FEW_ROUNDINGS, 0.0), "gQgᵀ per trajectory")
    A = torch.stack([m.drift_jacobian(x[b], u[b]) for b, m in enumerate(alone)])
    p = torch.linalg.vector_norm(x[..., :3], dim=-1)[..., None, None]  # [B, N, 1, 1]
    w = torch.linalg.vector_norm(u - together.bias, dim=-1)[..., None, None]  # [B, 1, 1, 1]: ω = ω̃ − b
    terms = (1 + p) ** 2 * w + (1 + p**2 if estimate_bias else 0.0)
    assert_within(together.drift_jacobian(x, u), A, FEW_ROUNDINGS * terms, "A per trajectory")
    psd = torch.stack([m.noise_psd() for m in alone])[:, None]  # [B, 1, q, q]
    assert_within(together.noise_psd(), psd, relative_bound(psd, FEW_ROUNDINGS, 0.0), "Q per trajectory")
    together.check_contract(x, u)  # the contract's probes broadcast the values from the right


def test_the_fused_propagation_gives_way_and_the_fpke_terms_refuse():
    together, _ = _models(True)
    x = torch.zeros(B, N, 6, dtype=F64)
    P = torch.eye(6, dtype=F64).expand(B, N, 6, 6)
    u = torch.zeros(B, 1, 3, dtype=F64)
    assert together.fused_propagation(x, P, u, 0.1, compile=True) is None
    assert together.per_trajectory_noise
    assert not AttitudeModel().per_trajectory_noise
    for call in (
        lambda: together.fokker_planck_terms(x, u),
        lambda: together.fokker_planck_moments(x, P, u),
        lambda: together.fused_galerkin_pairs(x.flatten(0, 1), P.flatten(0, 1), u[0], compile=True),
    ):
        with pytest.raises(ValueError, match=r"take one sigma_v, sigma_u and bias for all trajectories.*\(3, 1\)"):
            call()


def test_a_bias_of_another_shape_is_refused():
    with pytest.raises(ValueError, match=r"bias must be a scalar, \[3\] or \[\.\.\., 3\] per trajectory"):
        AttitudeModel(bias=torch.zeros(3, 2, dtype=F64))


@pytest.mark.parametrize("noise_model", ["isotropic", "tangent"])
def test_star_noise_per_trajectory_gives_each_its_own_covariance_and_likelihood(gen, noise_model):
    """``R`` per trajectory to a few roundings of its terms (every entry is built from terms no larger than
    ``σ_s² + σ_r²``: ``|b_i b_j| ≤ 1``); the data's log-likelihood to the rounding of its Cholesky solve (a
    well-conditioned ``G``: 64 ε relative to its terms, ≈ |log β| here)."""
    M = 4
    r = random_unit_vectors(gen, B, M)
    body = random_unit_vectors(gen, B, M)
    sigma = torch.tensor([5e-6, 1e-5, 2e-5], dtype=F64)
    together = StarVectorMeasurement(r, None, sigma, noise_model=noise_model, body=body)
    alone = [StarVectorMeasurement(r[b], None, sigma[b], noise_model=noise_model, body=body[b]) for b in range(B)]
    R = torch.stack([m.noise_cov() for m in alone])
    terms = (sigma**2 + together.radial_sigma**2)[:, None, None]  # [B, 1, 1]
    assert_within(together.noise_cov(), R, FEW_ROUNDINGS * terms, "R per trajectory")
    y = body.flatten(-2)
    nu = 1e-5 * torch.randn(B, N, 3 * M, generator=gen, dtype=F64)
    HL = 1e-5 * torch.randn(B, N, 3 * M, 3, generator=gen, dtype=F64)
    logw = torch.log(torch.full((B, N), 1.0 / N, dtype=F64))
    valid = torch.ones(B, N, 3 * M, dtype=torch.bool)
    got = together.data_log_likelihood(logw, nu, HL, y, valid)
    want = torch.stack([m.data_log_likelihood(logw[b], nu[b], HL[b], y[b], valid[b]) for b, m in enumerate(alone)])
    assert_within(got, want, relative_bound(want, 64 * EPS, 0.0), "the data's log-likelihood per trajectory")
    assert together.fused_update(logw, torch.zeros(B, N, 3, dtype=F64), torch.eye(3, dtype=F64), y) is None
    together.check_measurement(y)
    one_sky = StarVectorMeasurement(r[0], None, sigma)  # one catalogue for all, σ_s per trajectory
    with pytest.raises(ValueError, match=r"the measurement's sigma has leading dims \(3,\), y has \(2,\)"):
        one_sky.check_measurement(y[:2])


@pytest.mark.parametrize("sigma", [torch.ones(2, 2, dtype=F64), torch.tensor([1e-5, -1e-5], dtype=F64)])
def test_a_star_noise_of_another_shape_or_sign_is_refused(gen, sigma):
    with pytest.raises(ValueError, match=r"sigma must be a positive finite scalar or \[B\]"):
        StarVectorMeasurement(random_unit_vectors(gen, 2, 3), None, sigma)


def test_the_gyro_hold_takes_a_rate_sigma_per_trajectory_and_round_trips_it():
    sigma = torch.tensor([1e-4, 2e-4], dtype=F64)
    hold = GyroHold(sigma)
    gyro = torch.zeros(2, 3, dtype=F64)
    hold.step(gyro, None, 0.1)
    _, var = hold.step(gyro, torch.tensor([False, False]), 0.1)
    want = (sigma * 0.1) ** 2  # the first held step: (σ_h Δt)²·(2·1 − 1)
    assert_within(var, want, relative_bound(want, FEW_ROUNDINGS, 0.0), "held variance per trajectory")
    again = GyroHold(0.0)
    again.load_state_dict(hold.state_dict())
    assert torch.equal(torch.as_tensor(again.rate_sigma), sigma)
    with pytest.raises(ValueError, match=r"rate_sigma must be finite and ≥ 0 \(rad/s\), a number or \[B\]"):
        GyroHold(torch.tensor([1e-4, -1.0], dtype=F64))
