"""AttitudeModel: closed forms against torch.func, kinematics, shadow switching."""

from __future__ import annotations

import re

import pytest
import torch

from agsf_torch import rotations as rot
from agsf_torch.models import AttitudeModel, ContinuousModel
from agsf_torch.models.attitude import SHADOW_FORCED, SHADOW_SPREAD
from tests.helpers import assert_within, random_mrps, relative_bound

EPS = torch.finfo(torch.float64).eps


def _states(gen, num, estimate_bias, max_norm=1.3):
    p = random_mrps(num, gen, max_norm=max_norm)
    if not estimate_bias:
        return p
    return torch.cat((p, 1e-3 * torch.randn(num, 3, generator=gen, dtype=torch.float64)), -1)


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_drift_jacobian_matches_autograd(gen, estimate_bias):
    model = AttitudeModel(estimate_bias=estimate_bias, bias=torch.tensor([1e-4, -2e-4, 3e-4], dtype=torch.float64))
    x = _states(gen, 2000, estimate_bias)
    u = 0.1 * torch.randn(2000, 3, generator=gen, dtype=torch.float64)
    A = model.drift_jacobian(x, u)
    A_ad = ContinuousModel.drift_jacobian(model, x, u)  # the generic torch.func path
    assert_within(A, A_ad, 1e-10, "closed-form drift Jacobian against torch.func")
    assert A.shape == (2000, model.state_dim, model.state_dim)


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_drift_divergence_is_the_trace_of_the_autograd_jacobian(gen, estimate_bias):
    model = AttitudeModel(estimate_bias=estimate_bias, bias=torch.tensor([1e-4, -2e-4, 3e-4], dtype=torch.float64))
    x = _states(gen, 2000, estimate_bias)
    u = 0.1 * torch.randn(2000, 3, generator=gen, dtype=torch.float64)
    div = model.drift_divergence(x, u)
    trace = torch.func.vmap(torch.func.jacrev(model.drift))(x, u).diagonal(dim1=-2, dim2=-1).sum(-1)
    # ∂fₖ/∂pₖ sums terms of size |p||ω| and |p|²|ω| (the MRP rate's ¼(1 − s)ω, ½[p×]ω and ½ppᵀω): each side
    # rounds them to a few ulps
    w = u - (x[:, 3:] if estimate_bias else model.bias)
    p = x[:, :3].norm(dim=-1)
    scale = w.norm(dim=-1) * (1 + p + p**2)
    assert_within(div, trace, 32 * EPS * scale, "closed-form ∇·f against the trace of torch.func's Jacobian")
    assert div.shape == (2000,)


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_process_noise_closed_form_matches_generic(gen, estimate_bias):
    model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=3e-6, sigma_u=2e-8)
    x = _states(gen, 500, estimate_bias)
    G = model.process_noise(x)
    # off-diagonal entries are exact zeros in the closed form, rounding (~1e-16 relative) in the generic one
    generic = ContinuousModel.process_noise(model, x)
    assert_within(G, generic, relative_bound(generic, 1e-12, 1e-12 * float(G.abs().max())), "closed-form g Q gᵀ")
    # D = ½ g Q gᵀ to a few roundings of each entry, and of the matrix's scale where an entry is 0 (entries are
    # ~1e-12 and 1e-16: assert_close's default atol of 1e-7 had compared nothing)
    half = 0.5 * model.process_noise(x)
    bound = relative_bound(half, 16 * EPS, 16 * EPS * half.abs().amax((-1, -2), keepdim=True))
    assert_within(model.diffusion(x), half, bound, "diffusion against ½ g Q gᵀ")


def test_drift_is_mrp_kinematics(gen):
    """f(p, ω̃) integrated over a step equals the exact quaternion rotation at constant rate."""
    model = AttitudeModel()
    p0 = random_mrps(64, gen, max_norm=0.8)
    w = 0.05 * torch.randn(64, 3, generator=gen, dtype=torch.float64)
    dt, steps = 1.0, 200
    h = dt / steps
    p = p0.clone()
    for _ in range(steps):  # RK4 on ṗ = ¼B(p)ω
        k1 = model.drift(p, w)
        k2 = model.drift(p + 0.5 * h * k1, w)
        k3 = model.drift(p + 0.5 * h * k2, w)
        k4 = model.drift(p + h * k3, w)
        p = p + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    q_exact = rot.quat_multiply(rot.rotvec_to_quat(w * dt), rot.mrp_to_quat(p0))
    assert_within(rot.mrp_to_dcm(p), rot.quat_to_dcm(q_exact), 1e-12, "attitude after RK4 on the MRP kinematics")


def test_six_state_structure(gen):
    model = AttitudeModel(estimate_bias=True, sigma_v=1e-6, sigma_u=1e-9)
    x = _states(gen, 10, True)
    u = torch.randn(10, 3, generator=gen, dtype=torch.float64)
    f = model.drift(x, u)
    assert torch.equal(f[:, 3:], torch.zeros(10, 3, dtype=torch.float64))
    f3 = AttitudeModel().drift(x[:, :3], u - x[:, 3:])
    assert_within(f[:, :3], f3, relative_bound(f3, 1e-7, 1e-7), "MRP rate at the bias-corrected rate")
    Q = model.noise_psd()
    # σ² of a rounded σ against the rounded literal: a few ε relative (assert_close's default atol of 1e-7 had
    # compared nothing at 1e-12 and 1e-18)
    psd = torch.tensor([1e-12] * 3 + [1e-18] * 3, dtype=torch.float64)
    assert_within(torch.diag(Q), psd, relative_bound(psd, 16 * EPS, 0.0), "noise spectral density")


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_canonicalize_switches_to_shadow(gen, estimate_bias):
    model = AttitudeModel(estimate_bias=estimate_bias)
    n = model.state_dim
    x = _states(gen, 300, estimate_bias, max_norm=2.0)
    L = torch.randn(300, n, n, generator=gen, dtype=torch.float64)
    P = 1e-4 * (L @ L.transpose(-1, -2) + torch.eye(n, dtype=torch.float64))
    m2, P2 = model.canonicalize(x, P)
    s = (x[:, :3] ** 2).sum(-1)
    switched = s > 1
    assert switched.any() and (~switched).any()
    assert bool(((m2[:, :3] ** 2).sum(-1) <= 1 + 1e-15).all())
    assert torch.equal(m2[~switched], x[~switched]) and torch.equal(P2[~switched], P[~switched])  # untouched
    # switched means describe the same attitude; covariance maps with T = blockdiag(J, I)
    assert_within(rot.mrp_to_dcm(m2[switched, :3]), rot.mrp_to_dcm(x[switched, :3]), 1e-12, "attitude of the shadow")
    J = rot.mrp_shadow_jacobian(x[switched, :3])
    T = torch.eye(n, dtype=torch.float64).repeat(int(switched.sum()), 1, 1)
    T[:, :3, :3] = J
    mapped = T @ P[switched] @ T.transpose(-1, -2)
    assert_within(P2[switched], mapped, relative_bound(mapped, 1e-12, 1e-18), "covariance mapped to the shadow set")
    if estimate_bias:
        assert torch.equal(P2[:, 3:, 3:], P[:, 3:, 3:]) and torch.equal(m2[:, 3:], x[:, 3:])  # the bias untouched


def test_canonicalize_keeps_a_component_too_wide_for_the_linearised_switch(gen):
    # the shadow map bends by about √tr P_pp / |p| over one standard deviation: a wider component than
    # SHADOW_SPREAD·|p| stays in its own set (its linearised switch would misplace most of its mass) until
    # |p| > SHADOW_FORCED, where it switches whatever its spread
    model = AttitudeModel(estimate_bias=True)
    p = torch.tensor([[1.7, 0.0, 0.0], [1.7, 0.0, 0.0], [0.0, 3.5, 0.0], [0.6, 0.0, 0.0]], dtype=torch.float64)
    x = torch.cat((p, torch.zeros(4, 3, dtype=torch.float64)), -1)
    variance = torch.tensor([0.17, (0.09 * 1.7) ** 2 / 3, 0.17, 0.17], dtype=torch.float64)
    P = torch.diag_embed(
        torch.cat((variance[:, None].expand(4, 3), torch.full((4, 3), 1e-10, dtype=torch.float64)), -1)
    )
    m2, P2 = model.canonicalize(x, P)
    assert torch.equal(m2[0], x[0]) and torch.equal(P2[0], P[0])  # wide (√tr = 0.71 > 0.17): kept
    assert_within(m2[1, :3], rot.mrp_shadow(p[1]), 1e-15, "narrow: switched")
    assert_within(m2[2, :3], rot.mrp_shadow(p[2]), 1e-15, "beyond |p| = 3: switched")
    assert torch.equal(m2[3], x[3])  # inside the unit ball: never switched
    assert (SHADOW_SPREAD, SHADOW_FORCED) == (0.1, 3.0)


def test_state_error_uses_nearest_set(gen):
    model = AttitudeModel()
    p = random_mrps(100, gen, max_norm=0.99)
    p = p[p.norm(dim=-1) > 0.5]
    err = model.state_error(p, rot.mrp_shadow(p))
    assert_within(err, torch.zeros_like(p), 1e-15, "state error between an MRP and its shadow")


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"sigma_v": -1.0}, "sigma_v"),
        ({"sigma_u": float("nan")}, "sigma_u"),
        ({"sigma_v": float("inf")}, "sigma_v"),
        ({"bias": [1.0, 2.0]}, "bias"),
        ({"bias": [float("nan")] * 3}, "bias"),
    ],
)
def test_bad_configuration_raises(kwargs, field):
    with pytest.raises(ValueError, match=field):
        AttitudeModel(**kwargs)


@pytest.mark.parametrize("estimate_bias", [False, True])
@pytest.mark.parametrize("shape", [(4, 1), (4, 2), (4, 4), (1,)])
def test_gyro_input_must_have_three_axes(gen, estimate_bias, shape):
    """A rate of shape [B, 1] (or any last dim ≠ 3) is refused by every path, never broadcast over the axes."""
    model = AttitudeModel(estimate_bias=estimate_bias)
    n = model.state_dim
    x = _states(gen, 4, estimate_bias)
    u = torch.ones(shape, dtype=torch.float64)
    match = rf"u must have shape \[\.\.\., 3\] \(AttitudeModel's input: the gyro reading ω̃, rad/s\), got {re.escape(str(tuple(shape)))}"
    for call in (
        lambda: model.drift(x, u),
        lambda: model.drift_jacobian(x, u),
        lambda: model.fokker_planck_terms(x, u),
        lambda: model.fokker_planck_moments(x, 1e-3 * torch.eye(n, dtype=torch.float64).expand(4, n, n), u),
    ):
        with pytest.raises(ValueError, match=match):
            call()
    with pytest.raises(
        ValueError, match=r"AttitudeModel needs an input u \[\.\.\., 3\] \(the gyro reading ω̃, rad/s\), got None"
    ):
        model.drift(x, None)


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_filters_refuse_a_one_axis_gyro_before_any_change(gen, estimate_bias):
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import AdaptiveGaussianSumFilter, GaussianSumFilter, PenaltyWeightUpdate

    model = AttitudeModel(estimate_bias=estimate_bias)
    n = model.state_dim
    mix = GaussianMixture.from_gaussian(
        _states(gen, 2, estimate_bias), 1e-4 * torch.eye(n, dtype=torch.float64).expand(2, n, n), 3
    )
    agsf = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(cadence=1))
    for filt in (GaussianSumFilter(model), agsf):
        with pytest.raises(
            ValueError,
            match=r"u must have shape \[\.\.\., 3\] \(AttitudeModel's input: the gyro reading ω̃, rad/s\), got \(2, 1\)",
        ):
            filt.predict(mix, torch.full((2, 1), 0.01, dtype=torch.float64), 0.1)
        with pytest.raises(
            ValueError, match=r"AttitudeModel needs an input u \[\.\.\., 3\] \(the gyro reading ω̃, rad/s\), got None"
        ):
            filt.predict(mix, None, 0.1)
    assert agsf.weight_update.state_dict()["step"] == 0
