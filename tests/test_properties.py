"""Property tests (hypothesis) over the public API: random valid shapes and values keep
weights on the simplex, covariances symmetric positive definite and outputs finite;
invalid values raise the documented errors."""

from __future__ import annotations

import math

import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agsf_torch import GaussianMixture
from agsf_torch.filters import AdaptiveGaussianSumFilter, GaussianSumFilter, PenaltyWeightUpdate
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.qp import solve_simplex_qp
from tests.helpers import F64, assert_within, random_spd

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _assert_valid(mix: GaussianMixture) -> None:
    w = mix.weights
    assert bool(torch.isfinite(w).all()) and bool((w >= 0).all())
    assert_within(w.sum(-1), 1.0, 1e-12, "sum of the weights")
    assert bool(torch.isfinite(mix.means).all()) and bool(torch.isfinite(mix.covs).all())
    assert torch.equal(mix.covs, mix.covs.transpose(-1, -2))
    assert bool((torch.linalg.cholesky_ex(mix.covs).info == 0).all())


@SETTINGS
@given(
    n=st.integers(1, 6),
    N=st.integers(1, 9),
    batch=st.lists(st.integers(1, 3), max_size=2),
    log_scale=st.floats(-8, 2),
    spread=st.floats(0.05, 0.95),
    seed=st.integers(0, 2**31 - 1),
)
def test_split_preserves_moments_and_validity(n, N, batch, log_scale, spread, seed):
    shape = tuple(batch)
    cov = random_spd(torch.Generator().manual_seed(seed), *shape, n=n, scale=10.0**log_scale, floor=0.05)
    mean = torch.randn(*shape, n, generator=torch.Generator().manual_seed(seed + 1), dtype=F64)
    mix = GaussianMixture.from_gaussian(mean, cov, N, spread)
    _assert_valid(mix)
    m, P = mix.moments()
    assert_within(m, mean, 1e-12 * (1 + float(mean.abs().max())), "mixture mean")
    # the spread Σ wᵢdᵢdᵢᵀ comes from dᵢ = μᵢ − μ, differences of means of size |μ| that lie ~√P apart: each dᵢ
    # carries up to (N + 2)·ε·|μ| of rounding (μᵢ = μ + δᵢ, and the N-term mean), so P carries 2·max|dᵢ|·(N + 2)·ε·|μ|
    # beyond its own rounding: large against P itself for a small P about a large mean (|μ| ~ 1, P ~ 1e-8: 1e-12 P)
    eps = torch.finfo(F64).eps
    spread_rounding = 2 * float((mix.means - mean.unsqueeze(-2)).abs().max()) * (N + 2) * eps * float(mean.abs().max())
    assert_within(P, cov, 1e-12 * float(cov.abs().max()) + spread_rounding, "mixture covariance")


@SETTINGS
@given(
    B=st.integers(1, 4),
    N=st.integers(1, 5),
    estimate_bias=st.booleans(),
    log_sigma=st.floats(-7, -2),
    log_prior=st.floats(-8, -3),
    seed=st.integers(0, 2**31 - 1),
    gate=st.sampled_from([None, 0.99, 0.9999]),
    outlier=st.floats(0.0, 0.2),
    data=st.data(),
)
def test_gsf_steps_keep_the_belief_valid(B, N, estimate_bias, log_sigma, log_prior, seed, gate, outlier, data):
    g = torch.Generator().manual_seed(seed)
    model = AttitudeModel(estimate_bias=estimate_bias)
    n = model.state_dim
    p = 0.5 * torch.randn(B, 3, generator=g, dtype=F64)
    mean = torch.cat((p, torch.zeros(B, 3, dtype=F64)), -1)[:, :n]
    P0 = torch.diag(torch.tensor([10.0**log_prior] * 3 + [1e-12] * 3, dtype=F64)[:n])
    mix = GaussianMixture.from_gaussian(mean, P0.expand(B, n, n), N)
    filt = GaussianSumFilter(model, gate_probability=gate)
    u = 0.1 * torch.randn(B, 3, generator=g, dtype=F64)
    r = torch.randn(B, 5, 3, generator=g, dtype=F64)
    r = r / r.norm(dim=-1, keepdim=True)
    mask = torch.tensor(data.draw(st.lists(st.lists(st.booleans(), min_size=5, max_size=5), min_size=B, max_size=B)))
    sigma = 10.0**log_sigma
    meas = StarVectorMeasurement(r, mask, sigma)
    y = meas.predict(p) + sigma * torch.randn(B, 15, generator=g, dtype=F64)
    y[:, :3] += outlier  # star 0 may be an outlier of any size: a unit vector pointing elsewhere
    y[:, :3] = y[:, :3] / y[:, :3].norm(dim=-1, keepdim=True)
    for _ in range(2):
        mix = filt.predict(mix, u, 0.1)
        _assert_valid(mix)
        mix = filt.update(mix, y, meas)
        _assert_valid(mix)
        if gate is not None:
            d = filt.diagnostics
            assert d["gate_accepted"].shape == (B, 5) and d["gate_nis"].shape == (B, 5)
            assert bool(torch.isfinite(d["gate_nis"]).all()) and bool((d["gate_nis"] >= 0).all())
            assert bool((d["gate_rejected"] <= mask.sum(-1)).all())
            assert bool(d["gate_accepted"][~mask].all())  # masked stars are never counted as rejected


@SETTINGS
@given(
    B=st.integers(1, 3),
    N=st.integers(2, 5),
    reg=st.floats(0.0, 10.0),
    scaling=st.sampled_from(["trace", "none"]),
    weight_ref=st.sampled_from(["update", "previous"]),
    seed=st.integers(0, 2**31 - 1),
)
def test_adaptive_weights_stay_on_the_simplex(B, N, reg, scaling, weight_ref, seed):
    g = torch.Generator().manual_seed(seed)
    model = AttitudeModel()
    mean = 0.5 * torch.randn(B, 3, generator=g, dtype=F64)
    mix = GaussianMixture.from_gaussian(mean, 1e-3 * torch.eye(3, dtype=F64).expand(B, 3, 3), N)
    filt = AdaptiveGaussianSumFilter(
        model, weight_update=PenaltyWeightUpdate(reg=reg, scaling=scaling, weight_ref=weight_ref)
    )
    u = 0.1 * torch.randn(B, 3, generator=g, dtype=F64)
    for _ in range(2):
        mix = filt.predict(mix, u, 0.1)
        _assert_valid(mix)
        assert_within(filt.diagnostics["qp_kkt_residual"], 0.0, 1e-9, "KKT residual")


@SETTINGS
@given(N=st.integers(1, 8), log_scale=st.floats(-6, 6), seed=st.integers(0, 2**31 - 1))
def test_qp_solution_is_feasible_and_optimal(N, log_scale, seed):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(16, N, N, generator=g, dtype=F64)
    H = 10.0**log_scale * (A @ A.transpose(-1, -2))
    c = torch.randn(16, N, generator=g, dtype=F64)
    res = solve_simplex_qp(H, c)
    assert bool((res.w >= 0).all())
    assert_within(res.w.sum(-1), 1.0, 1e-12, "sum of the weights")
    assert_within(res.kkt_residual, 0.0, 1e-9, "KKT residual")


@SETTINGS
@given(
    field=st.sampled_from(["sigma_v", "sigma_u"]),
    bad=st.one_of(
        st.floats(max_value=-1e-300, allow_infinity=False, allow_nan=False), st.just(math.nan), st.just(math.inf)
    ),
)
def test_invalid_noise_raises(field, bad):
    try:
        AttitudeModel(**{field: bad})
    except ValueError as exc:
        assert field in str(exc)
    else:
        raise AssertionError(f"{field}={bad} was accepted")


@SETTINGS
@given(which=st.sampled_from(["u", "y"]), index=st.integers(0, 2), bad=st.sampled_from([math.nan, math.inf, -math.inf]))
def test_non_finite_inputs_raise_before_state_changes(which, index, bad):
    model = AttitudeModel()
    mix = GaussianMixture.from_gaussian(torch.zeros(3, 3, dtype=F64), 1e-4 * torch.eye(3, dtype=F64).expand(3, 3, 3), 2)
    before = (mix.means.clone(), mix.covs.clone(), mix.log_weights.clone())
    filt = GaussianSumFilter(model)
    r = torch.eye(3, dtype=F64).expand(3, 3, 3)
    u = torch.zeros(3, 3, dtype=F64)
    y = StarVectorMeasurement(r, sigma=1e-5).predict(mix.means[:, 0])
    (u if which == "u" else y)[index, 1] = bad
    try:
        filt.predict(mix, u, 0.1) if which == "u" else filt.update(mix, y, StarVectorMeasurement(r, sigma=1e-5))
    except ValueError as exc:
        assert f"{which} must be finite" in str(exc)
    else:
        raise AssertionError("non-finite input accepted")
    assert all(torch.equal(a, b) for a, b in zip(before, (mix.means, mix.covs, mix.log_weights)))
