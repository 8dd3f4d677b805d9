"""StarVectorMeasurement: prediction, closed-form Jacobian, masks, validation."""

from __future__ import annotations

import pytest
import torch

from agsf_torch import rotations as rot
from agsf_torch.models import MeasurementModel, StarVectorMeasurement
from tests.conftest import random_mrps


def _unit(gen, *shape):
    r = torch.randn(*shape, 3, generator=gen, dtype=torch.float64)
    return r / r.norm(dim=-1, keepdim=True)


def test_predict_is_C_r(gen):
    p = random_mrps(50, gen)
    r = _unit(gen, 50, 5)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    y = meas.predict(p).reshape(50, 5, 3)
    ref = torch.einsum("bij,bmj->bmi", rot.mrp_to_dcm(p), r)
    torch.testing.assert_close(y, ref, rtol=0, atol=1e-15)


@pytest.mark.parametrize("n", [3, 6])
def test_jacobian_matches_autograd(gen, n):
    x = random_mrps(1000, gen, max_norm=1.5)
    if n == 6:
        x = torch.cat((x, torch.randn(1000, 3, generator=gen, dtype=torch.float64)), -1)
    r = _unit(gen, 1000, 4)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    H = meas.jacobian(x)
    H_ad = MeasurementModel.jacobian(meas, x)
    assert H.shape == (1000, 12, n)
    torch.testing.assert_close(H, H_ad, rtol=0, atol=1e-10)


def test_component_first_broadcast(gen):
    """States [N, B, n] broadcast against stars [B, M, 3] (the filters' layout)."""
    x = random_mrps(12, gen).reshape(4, 3, 3)
    r = _unit(gen, 3, 5)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    assert meas.predict(x).shape == (4, 3, 15)
    assert meas.jacobian(x).shape == (4, 3, 15, 3)
    torch.testing.assert_close(meas.predict(x)[2, 1], StarVectorMeasurement(r[1], sigma=1e-5).predict(x[2, 1]))


def test_mask_and_noise(gen):
    r = _unit(gen, 2, 3)
    mask = torch.tensor([[True, False, True], [False, False, False]])
    meas = StarVectorMeasurement(r, mask, sigma=2e-5)
    assert meas.mask().tolist() == [[True] * 3 + [False] * 3 + [True] * 3, [False] * 9]
    torch.testing.assert_close(meas.noise_cov(), 4e-10 * torch.eye(9, dtype=torch.float64))


def test_from_observation(gen):
    r = _unit(gen, 2, 3)
    obs = {"star_body": r.flip(-1), "star_inertial": r, "star_mask": torch.ones(2, 3, dtype=torch.bool)}
    y, meas = StarVectorMeasurement.from_observation(obs, sigma=1e-5)
    assert y.shape == (2, 9)
    torch.testing.assert_close(y.reshape(2, 3, 3), r.flip(-1))


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
    r = _unit(gen, 2, 3)
    body = _unit(gen, 2, 3)
    meas = StarVectorMeasurement(r, sigma=1e-5, noise_model="tangent", body=body, radial_sigma=1e-3)
    R = meas.noise_cov()
    assert R.shape == (2, 9, 9)
    torch.testing.assert_close(R, R.transpose(-1, -2), rtol=0, atol=0)
    block = R[1, 3:6, 3:6]
    b = body[1, 1]
    torch.testing.assert_close(block @ b, 1e-6 * b, rtol=1e-12, atol=0)  # radial: σ_r²
    t = torch.linalg.cross(b, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(block @ t, 1e-10 * t, rtol=1e-9, atol=1e-25)  # across: σ_s²
    assert float(R[0, 0:3, 3:6].abs().max()) == 0.0
    with pytest.raises(ValueError, match="body"):
        StarVectorMeasurement(r, sigma=1e-5, noise_model="tangent")
    with pytest.raises(ValueError, match="noise_model"):
        StarVectorMeasurement(r, sigma=1e-5, noise_model="radial")
