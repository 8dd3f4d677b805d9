"""GaussianSumFilter / EKF on the attitude models: masks, batching, robustness, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch import rotations as rot
from agsf_torch.filters import ExtendedKalmanFilter, GaussianSumFilter
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from tests.helpers import F64, assert_statistic, assert_within, random_mrps, random_unit_vectors, relative_bound


def _setup(gen, B=6, N=5, estimate_bias=True, sigma=1e-5, prior_attitude_var=1e-3):
    model = AttitudeModel(estimate_bias=estimate_bias)
    n = model.state_dim
    truth = random_mrps(B, gen, max_norm=0.9)
    prior_var = torch.tensor([prior_attitude_var] * 3 + [1e-12] * 3, dtype=F64)[:n]
    noise = torch.randn(B, n, generator=gen, dtype=F64) * prior_var.sqrt()
    mean0 = torch.cat((truth, torch.zeros(B, 3, dtype=F64)), -1)[:, :n] + noise
    mix = GaussianMixture.from_gaussian(mean0, torch.diag(prior_var).expand(B, n, n), N)
    r = random_unit_vectors(gen, B, 5)
    y = StarVectorMeasurement(r, sigma=sigma).predict(truth) + sigma * torch.randn(B, 15, generator=gen, dtype=F64)
    return model, mix, r, y


def test_batched_equals_one_at_a_time(gen):
    model, mix, r, y = _setup(gen)
    gsf = GaussianSumFilter(model, substeps=2)
    u = 0.05 * torch.randn(6, 3, generator=gen, dtype=F64)
    mask = torch.rand(6, 5, generator=gen) > 0.3
    meas = StarVectorMeasurement(r, mask, 1e-5)
    post = gsf.update(gsf.predict(mix, u, 0.1), y, meas)
    for b in range(6):
        one = GaussianMixture(log_weights=mix.log_weights[b], means=mix.means[b], covs=mix.covs[b])
        one = gsf.predict(one, u[b], 0.1)
        one = gsf.update(one, y[b], StarVectorMeasurement(r[b], mask[b], 1e-5))
        # 1e-12 of each entry, and at least of the state axis' scale across the components (a mean entry near 0 is
        # the sum of terms of that size)
        scale = post.means[b].abs().amax(-2, keepdim=True)
        assert_within(
            one.means, post.means[b], relative_bound(post.means[b], 1e-12, 1e-12 * scale), "means, one at a time"
        )
        covs_bound = relative_bound(post.covs[b], 1e-12, 1e-12 * float(one.covs.abs().max()))
        assert_within(one.covs, post.covs[b], covs_bound, "covariances, one at a time")
        weights_bound = relative_bound(post.log_weights[b], 1e-12, 1e-12)
        assert_within(one.log_weights, post.log_weights[b], weights_bound, "log-weights, one at a time")


def test_masked_stars_contribute_nothing(gen):
    # well-conditioned S (cond ~ 1e2): the masked and the reduced problem take different BLAS
    # paths, so a cond(S) ~ 1e7 case would differ by rounding × cond, not by the masking logic
    model, mix, r, y = _setup(gen, B=3, sigma=1e-3, prior_attitude_var=1e-5)
    gsf = GaussianSumFilter(model)
    mask = torch.tensor([[True, True, False, True, False], [False] * 5, [True] * 5])
    post = gsf.update(mix, y, StarVectorMeasurement(r, mask, 1e-3))
    dof = gsf.diagnostics["dof"]
    # trajectory 0: same as a measurement holding only its valid stars (masked entries may hold anything)
    keep = mask[0]
    y0 = y[0].reshape(5, 3)
    ref = gsf.update(
        GaussianMixture(log_weights=mix.log_weights[0], means=mix.means[0], covs=mix.covs[0]),
        y0[keep].flatten(),
        StarVectorMeasurement(r[0, keep], sigma=1e-3),
    )
    scale = ref.means.abs().amax(-2, keepdim=True)  # a mean entry near 0 is the sum of terms of its axis' scale
    assert_within(post.means[0], ref.means, relative_bound(ref.means, 1e-12, 1e-12 * scale), "means with masked stars")
    covs_bound = relative_bound(ref.covs, 1e-12, 1e-12 * float(ref.covs.abs().max()))
    assert_within(post.covs[0], ref.covs, covs_bound, "covariances with masked stars")
    weights_bound = relative_bound(ref.log_weights, 1e-12, 1e-12)
    assert_within(post.log_weights[0], ref.log_weights, weights_bound, "log-weights with masked stars")
    # trajectory 1: no valid star, bit-identical
    assert torch.equal(post.means[1], mix.means[1])
    assert torch.equal(post.covs[1], mix.covs[1])
    assert torch.equal(post.log_weights[1], mix.log_weights[1])
    assert dof.tolist() == [9.0, 0.0, 15.0]


def test_update_pulls_estimate_to_truth(gen):
    # prior 0.23° per axis: the linearisation error of one update is below the star noise
    model, mix, r, y = _setup(gen, B=20, N=5, prior_attitude_var=1e-6)
    gsf = GaussianSumFilter(model)
    post = gsf.update(mix, y, StarVectorMeasurement(r, sigma=1e-5))
    mean, cov = gsf.estimate(post)
    b_est = (rot.mrp_to_dcm(mean[:, :3]).unsqueeze(1) @ r.unsqueeze(-1)).squeeze(-1)
    # star residuals at the noise level: y − C(p̂) r is the noise v (σ = 1e-5 per axis) less its part the update
    # absorbed, R − H P⁺ Hᵀ ≤ R, so σ per axis is a standard error on the safe side (the linearisation error is
    # ~1e-6 = 0.1σ at this prior)
    assert_statistic(b_est, y.reshape(20, 5, 3), 1e-5, "star residuals after the update", false_failure=1e-6)


@pytest.mark.parametrize("sigma", [1e-7, 1e-6])
def test_tiny_star_noise_keeps_weights_finite(gen, sigma):
    model, mix, r, y = _setup(gen, B=8, N=9, sigma=sigma)
    gsf = GaussianSumFilter(model)
    post = gsf.update(gsf.predict(mix, torch.zeros(8, 3, dtype=F64), 0.1), y, StarVectorMeasurement(r, sigma=sigma))
    assert bool(torch.isfinite(post.means).all()) and bool(torch.isfinite(post.covs).all())
    assert bool(torch.isfinite(post.weights).all())
    assert_within(post.weights.sum(-1), torch.ones(8, dtype=F64), relative_bound(1.0, 1e-7, 1e-7), "sum of the weights")
    # at least one component of each mixture survives with weight > 0, and the update is strongly selective
    assert bool((post.weights.max(-1).values > 0.5).all())
    assert bool(torch.isfinite(gsf.diagnostics["log_likelihood"]).all())


def test_ekf_requires_one_component(gen):
    model, mix, r, y = _setup(gen, N=3)
    with pytest.raises(ValueError, match="one-component"):
        ExtendedKalmanFilter(model).predict(mix, torch.zeros(6, 3, dtype=F64), 0.1)


def test_bad_inputs_raise_before_state_changes(gen):
    model, mix, r, y = _setup(gen)
    gsf = GaussianSumFilter(model)
    before = mix.means.clone()
    u = torch.zeros(6, 3, dtype=F64)
    u_bad = u.clone()
    u_bad[2, 1] = float("nan")
    with pytest.raises(ValueError, match="u must be finite"):
        gsf.predict(mix, u_bad, 0.1)
    with pytest.raises(ValueError, match="u has shape"):
        gsf.predict(mix, torch.zeros(4, 3, dtype=F64), 0.1)
    for dt in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="dt"):
            gsf.predict(mix, u, dt)
    y_bad = y.clone()
    y_bad[0, 4] = float("inf")
    with pytest.raises(ValueError, match="y must be finite"):
        gsf.update(mix, y_bad, StarVectorMeasurement(r, sigma=1e-5))
    with pytest.raises(ValueError, match="predicts 15"):
        gsf.update(mix, y[:, :12], StarVectorMeasurement(r, sigma=1e-5))
    with pytest.raises(ValueError, match="state dimension"):
        GaussianSumFilter(AttitudeModel(estimate_bias=False)).predict(mix, u, 0.1)
    assert torch.equal(mix.means, before)


def _all_filters(model):
    from agsf_torch.filters import AdaptiveGaussianSumFilter, MultiplicativeEKF

    return {
        "EKF": ExtendedKalmanFilter(model),
        "GSF": GaussianSumFilter(model),
        "AGSF": AdaptiveGaussianSumFilter(model),
        "AGSF-galerkin": AdaptiveGaussianSumFilter(model, weight_update="galerkin"),
        "MEKF": MultiplicativeEKF(model),
    }


@pytest.mark.parametrize("name", ["EKF", "GSF", "AGSF", "AGSF-galerkin", "MEKF"])
def test_one_trajectory_input_is_not_broadcast_over_a_batch(gen, name):
    """A gyro reading, a star frame or a measurement model of one trajectory given to a batch's belief (or a batch's
    to one belief) is refused, naming the shapes, before anything changes: broadcast, it was applied to every
    trajectory and gave wrong estimates without a word (or a raw torch error, or a belief expanded to the batch)."""
    model, mix, r, y = _setup(gen, B=4, N=1 if name in ("EKF", "MEKF") else 3)
    filt = _all_filters(model)[name]
    u = 1e-3 * torch.randn(4, 3, generator=gen, dtype=F64)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    before = (mix.means.clone(), mix.covs.clone(), mix.log_weights.clone())
    for bad in (u[0], u[:1], u[None]):
        with pytest.raises(ValueError, match=r"u has shape .* batch shape is \(4,\).* one entry per trajectory"):
            filt.predict(mix, bad, 0.1)
    prior = filt.predict(mix, u, 0.1)
    for bad in (y[0], y[:1]):
        with pytest.raises(ValueError, match=r"y has shape .* batch shape is \(4,\)"):
            filt.update(prior, bad, meas)
    with pytest.raises(ValueError, match=r"r_inertial .* leading dims \(1,\), y has \(4,\)"):
        filt.update(prior, y, StarVectorMeasurement(r[:1], sigma=1e-5))
    one = GaussianMixture(log_weights=mix.log_weights[0], means=mix.means[0], covs=mix.covs[0])  # batch ()
    filt.reset()
    with pytest.raises(ValueError, match=r"u has shape \(4, 3\); the mixture's batch shape is \(\)"):
        filt.predict(one, u, 0.1)
    assert all(torch.equal(a, b) for a, b in zip(before, (mix.means, mix.covs, mix.log_weights)))
    # shared parts built once for every trajectory are accepted: one catalogue for all, u expanded by the caller
    filt.reset()
    shared = filt.predict(mix, u[:1].expand(4, 3), 0.1)
    filt.update(
        shared,
        StarVectorMeasurement(r[0], sigma=1e-5).predict(shared.means[:, 0]),
        StarVectorMeasurement(r[0], sigma=1e-5),
    )


@pytest.mark.parametrize(
    "sigma",
    [
        -1e-5,
        0.0,
        float("nan"),
        float("inf"),
        True,
        np.bool_(True),
        "a",
        1 + 0j,
        torch.full((2, 2), 1e-5),
        torch.tensor([1e-5, -1e-5]),
    ],
)
def test_star_noise_must_be_positive_finite_numbers_one_for_all_or_one_per_trajectory(sigma):
    r = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64)
    with pytest.raises(ValueError, match=r"sigma must be a positive finite scalar or \[B\] \(rad\), got"):
        StarVectorMeasurement(r, sigma=sigma)
    assert StarVectorMeasurement(r, sigma=1e-5).sigma.item() == 1e-5  # a float is kept in float64


def test_function_measurement_parts_are_one_per_trajectory_or_one_for_all(gen):
    from agsf_torch.models import FunctionMeasurement

    model, mix, _, _ = _setup(gen, B=4, N=2)
    gsf = GaussianSumFilter(model)
    fn = lambda x: x[..., :2]  # noqa: E731
    y = torch.zeros(4, 2, dtype=F64)
    gsf.update(mix, y, FunctionMeasurement(fn, 1e-4 * torch.eye(2, dtype=F64)))  # one R for all
    gsf.update(mix, y, FunctionMeasurement(fn, 1e-4 * torch.eye(2, dtype=F64).expand(4, 2, 2)))  # one each
    with pytest.raises(ValueError, match=r"noise_cov has leading dims \(1,\), y has \(4,\)"):
        gsf.update(mix, y, FunctionMeasurement(fn, 1e-4 * torch.eye(2, dtype=F64)[None]))
    mask = torch.ones(1, 2, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"mask has leading dims \(1,\), y has \(4,\)"):
        gsf.update(mix, y, FunctionMeasurement(fn, 1e-4 * torch.eye(2, dtype=F64), mask=mask))


def test_loss_of_positive_definiteness_is_named_or_repaired(gen):
    model, mix, r, y = _setup(gen, B=3, N=2)
    covs = mix.covs.clone()
    covs[1, 1] = torch.diag(torch.tensor([1e-3, 1e-3, -1e-3, 1e-12, 1e-12, 1e-12], dtype=F64))
    broken = mix.replace(covs=covs, validate=False)  # bypasses validation, as a corrupted run state would
    with pytest.raises(ValueError, match=r"trajectory index \(1,\), component 1"):
        GaussianSumFilter(model).predict(broken, torch.zeros(3, 3, dtype=F64), 0.1)
    gsf = GaussianSumFilter(model, repair_covariance=True)
    out = gsf.predict(broken, torch.zeros(3, 3, dtype=F64), 0.1)
    assert gsf.diagnostics["covariance_repairs"] == 1
    assert bool((torch.linalg.eigvalsh(out.covs) > 0).all())
    # a covariance that is not finite is refused even with the repair on (its eigenvalue clip returned NaN)
    covs[1, 1, 0, 0] = float("inf")
    lost = mix.replace(covs=covs, validate=False)
    for fused in (True, False):
        with pytest.raises(
            ValueError, match=r"covariance is not finite during propagation at trajectory index \(1,\), component 1"
        ):
            GaussianSumFilter(model, repair_covariance=True, fused=fused).predict(
                lost, torch.zeros(3, 3, dtype=F64), 0.1
            )
