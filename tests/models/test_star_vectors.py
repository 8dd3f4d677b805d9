"""StarVectorMeasurement: prediction, closed-form Jacobian, masks, validation."""

from __future__ import annotations

import warnings

import pytest
import torch

from agsf_torch import rotations as rot
from agsf_torch.models import MeasurementModel, StarVectorMeasurement
from tests.helpers import assert_within, random_mrps, random_unit_vectors, relative_bound

EPS = torch.finfo(torch.float64).eps


def test_predict_is_C_r(gen):
    p = random_mrps(50, gen)
    r = random_unit_vectors(gen, 50, 5)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    y = meas.predict(p).reshape(50, 5, 3)
    C = rot.mrp_to_dcm(p)
    ref = torch.einsum("bij,bmj->bmi", C, r)
    # the same C, two 3-term dot products: each within 3·ε/2 of Σⱼ|Cᵢⱼ rⱼ| (≤ √3), whatever the order of the sum
    scale = torch.einsum("bij,bmj->bmi", C.abs(), r.abs())
    assert_within(y, ref, 8 * EPS * scale, "predicted star vectors C r")


@pytest.mark.parametrize("n", [3, 6])
def test_jacobian_matches_autograd(gen, n):
    x = random_mrps(1000, gen, max_norm=1.5)
    if n == 6:
        x = torch.cat((x, torch.randn(1000, 3, generator=gen, dtype=torch.float64)), -1)
    r = random_unit_vectors(gen, 1000, 4)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    H = meas.jacobian(x)
    H_ad = MeasurementModel.jacobian(meas, x)
    assert H.shape == (1000, 12, n)
    assert_within(H, H_ad, 1e-10, "closed-form star Jacobian against autograd")


def test_component_first_broadcast(gen):
    """States [N, B, n] broadcast against stars [B, M, 3] (the filters' layout)."""
    x = random_mrps(12, gen).reshape(4, 3, 3)
    r = random_unit_vectors(gen, 3, 5)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    assert meas.predict(x).shape == (4, 3, 15)
    assert meas.jacobian(x).shape == (4, 3, 15, 3)
    one = StarVectorMeasurement(r[1], sigma=1e-5).predict(x[2, 1])
    assert_within(meas.predict(x)[2, 1], one, relative_bound(one, 1e-7, 1e-7), "broadcast prediction")


def test_mask_and_noise(gen):
    r = random_unit_vectors(gen, 2, 3)
    mask = torch.tensor([[True, False, True], [False, False, False]])
    meas = StarVectorMeasurement(r, mask, sigma=2e-5)
    assert meas.mask().tolist() == [[True] * 3 + [False] * 3 + [True] * 3, [False] * 9]
    # σ² of a rounded σ against the rounded 4e-10: a few ε of it, also where an entry is 0 (assert_close's default
    # atol of 1e-7 had compared nothing at 4e-10)
    R = 4e-10 * torch.eye(9, dtype=torch.float64)
    assert_within(meas.noise_cov(), R, relative_bound(R, 16 * EPS, 16 * EPS * 4e-10), "star noise covariance")


def test_from_observation(gen):
    r = random_unit_vectors(gen, 2, 3)
    obs = {"star_body": r.flip(-1), "star_inertial": r, "star_mask": torch.ones(2, 3, dtype=torch.bool)}
    y, meas = StarVectorMeasurement.from_observation(obs, sigma=1e-5)
    assert y.shape == (2, 9)
    assert_within(y.reshape(2, 3, 3), r.flip(-1), relative_bound(r.flip(-1), 1e-7, 1e-7), "measured star vectors")
    with pytest.raises(ValueError, match=r"the observation has no star_mask: a star frame needs .* got keys"):
        StarVectorMeasurement.from_observation({k: v for k, v in obs.items() if k != "star_mask"}, sigma=1e-5)


@pytest.mark.parametrize(
    "args, match",
    [
        ((torch.ones(2, 3, 2),), "r_inertial"),
        ((torch.full((2, 3, 3), float("nan")),), "r_inertial"),
        ((torch.ones(2, 3, 3), torch.ones(2, 4, dtype=torch.bool)), "mask"),
        ((torch.ones(2, 3, 3), None, -1.0), "sigma"),
        ((torch.ones(2, 3, 3), None, 0.0), "sigma"),
    ],
)
def test_bad_input_raises(args, match):
    with pytest.raises(ValueError, match=match):
        StarVectorMeasurement(*args)


def test_tangent_noise_model(gen):
    r = random_unit_vectors(gen, 2, 3)
    body = random_unit_vectors(gen, 2, 3)
    meas = StarVectorMeasurement(r, sigma=1e-5, noise_model="tangent", body=body, radial_sigma=1e-3)
    R = meas.noise_cov()
    assert R.shape == (2, 9, 9)
    assert torch.equal(R, R.transpose(-1, -2))  # symmetric bit for bit
    block = R[1, 3:6, 3:6]
    b = body[1, 1]
    # radial: σ_r²; where an entry of b is small, the rounding of the terms of size σ_r² |b| = 1e-6 remains
    assert_within(block @ b, 1e-6 * b, relative_bound(1e-6 * b, 1e-12, 16 * EPS * 1e-6), "radial noise variance")
    # across: σ_s², along a unit t ⊥ b (from the axis least aligned with b, so that t is well defined); the
    # rounding of the σ_r² bbᵀ part (entries ~ σ_r², bᵀt ~ ε) is a few ε σ_r², whatever the draw
    axis = torch.zeros(3, dtype=torch.float64)
    axis[int(b.abs().argmin())] = 1.0
    t = torch.linalg.cross(b, axis)
    t = t / t.norm()
    assert_within(block @ t, 1e-10 * t, 16 * EPS * 1e-6, "cross-track noise variance")
    assert float(R[0, 0:3, 3:6].abs().max()) == 0.0
    with pytest.raises(ValueError, match="body"):
        StarVectorMeasurement(r, sigma=1e-5, noise_model="tangent")
    with pytest.raises(ValueError, match="noise_model"):
        StarVectorMeasurement(r, sigma=1e-5, noise_model="radial")


@pytest.mark.parametrize("scale, norm", [(2.0, "2"), (0.0, "0"), (1.0 + 2e-3, "1.002")])
def test_non_unit_star_vectors_are_refused_naming_vector_star_and_norm(gen, scale, norm):
    r = random_unit_vectors(gen, 2, 3)
    bad = r.clone()
    bad[1, 2] *= scale
    with pytest.raises(
        ValueError, match=rf"r_inertial: star 2 at batch index \(1,\) is not a unit vector \(norm {norm}\)"
    ):
        StarVectorMeasurement(bad, sigma=1e-5)
    with pytest.raises(ValueError, match=rf"body: star 2 at batch index \(1,\) is not a unit vector \(norm {norm}\)"):
        StarVectorMeasurement(r, sigma=1e-5, noise_model="tangent", body=bad)
    obs = {"star_body": bad, "star_inertial": r, "star_mask": torch.ones(2, 3, dtype=torch.bool)}
    with pytest.raises(
        ValueError, match=rf"star_body: star 2 at batch index \(1,\) is not a unit vector \(norm {norm}\)"
    ):
        StarVectorMeasurement.from_observation(obs, sigma=1e-5)
    with pytest.raises(
        ValueError, match=rf"y \(measured star vectors\): star 2 at batch index \(1,\) .*\(norm {norm}\)"
    ):
        StarVectorMeasurement(r, sigma=1e-5).check_measurement(bad.flatten(-2))
    # a masked-out star is ignored, whatever its vector (zeros by convention)
    mask = torch.tensor([[True] * 3, [True, True, False]])
    meas = StarVectorMeasurement(bad, mask, sigma=1e-5)
    assert torch.equal(meas.check_measurement(bad.flatten(-2)), bad.flatten(-2))


def test_star_vectors_within_tolerance_are_normalised_with_a_warning(gen):
    r = random_unit_vectors(gen, 2, 3)
    off = r.clone()
    off[0, 1] *= 1.0 + 1e-5
    with pytest.warns(UserWarning, match=r"r_inertial: star vectors off unit norm by up to 1\.00e-05"):
        meas = StarVectorMeasurement(off, sigma=1e-5)
    # v/‖v‖ of v = r(1 + 1e-5): the roundings of v, of its norm and of the division, and r's own norm (1 to a few
    # ε): a few ε relative to each entry
    assert_within(meas.r_inertial, r, relative_bound(r, 16 * EPS, 0.0), "renormalised catalogue vectors")
    with pytest.warns(UserWarning, match="star_body"):
        y, _ = StarVectorMeasurement.from_observation(
            {"star_body": off, "star_inertial": r, "star_mask": torch.ones(2, 3, dtype=torch.bool)}, 1e-5
        )
    assert_within(y, r.flatten(-2), relative_bound(r.flatten(-2), 16 * EPS, 0.0), "renormalised measured vectors")
    # unit to rounding: taken bit for bit, no warning (float32 vectors too, to float32's rounding)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        exact = StarVectorMeasurement(r, sigma=1e-5)
        r32 = r.to(torch.float32)
        assert torch.equal(
            StarVectorMeasurement(r32 / r32.norm(dim=-1, keepdim=True), sigma=1e-5).r_inertial.norm(dim=-1) > 0,
            torch.ones(r.shape[:-1], dtype=torch.bool),
        )
    assert torch.equal(exact.r_inertial, r) and exact.check_measurement(r.flatten(-2)) is not None


def test_filter_update_refuses_non_unit_measured_vectors_before_any_change(gen):
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import AdaptiveGaussianSumFilter
    from agsf_torch.models import AttitudeModel

    p = random_mrps(2, gen, max_norm=0.5)
    r = random_unit_vectors(gen, 2, 3)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    y = meas.predict(p)
    y_bad = y.clone()
    y_bad[0, 3:6] *= 1e5  # star 1 of trajectory 0: NIS 1e10 if it were used
    mix = GaussianMixture.from_gaussian(p, 1e-4 * torch.eye(3, dtype=torch.float64).expand(2, 3, 3), 3)
    filt = AdaptiveGaussianSumFilter(AttitudeModel())
    state = filt.state_dict()
    with pytest.raises(ValueError, match=r"star 1 at batch index \(0,\) is not a unit vector \(norm 100000\)"):
        filt.update(mix, y_bad, meas)
    with pytest.raises(ValueError, match=r"y has shape \(2, 6\): 6 entries but the measurement model predicts 9"):
        filt.update(mix, y[:, :6], meas)
    assert filt.state_dict() == state
    assert bool(torch.isfinite(filt.update(mix, y, meas).means).all())


def test_measured_vectors_are_unit_up_to_the_noise(gen):
    """y = C r + v is unit only up to the noise: used as it is within max(1e-3, 10σ), refused beyond."""
    r = random_unit_vectors(gen, 2, 3)
    y = r.clone()
    y[0, 1] *= 1.0 + 5e-3  # a 5σ radial draw for σ_s = 1e-3
    y = y.flatten(-2)
    out = StarVectorMeasurement(r, sigma=1e-3).check_measurement(y)
    assert out is y
    with pytest.raises(
        ValueError, match=r"star 1 at batch index \(0,\) is not a unit vector \(norm 1\.005\); .* within 0\.001"
    ):
        StarVectorMeasurement(r, sigma=1e-5).check_measurement(y)
    tangent = StarVectorMeasurement(r, sigma=1e-5, noise_model="tangent", body=r, radial_sigma=1e-3)
    assert tangent.check_measurement(y) is y
