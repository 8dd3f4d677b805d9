"""GyroHold: the held input, the covariance inflation for the hold error, validation, state."""

from __future__ import annotations

import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.input_gaps import GyroHold

F64 = torch.float64


def test_holds_the_last_valid_reading_and_grows_the_variance_quadratically():
    hold = GyroHold(rate_sigma=2e-6)
    dt = 0.1
    readings = torch.arange(1, 8, dtype=F64)[:, None, None] * torch.ones(7, 2, 3, dtype=F64)
    valid = torch.tensor([[1, 1], [0, 1], [0, 1], [0, 0], [1, 0], [1, 0], [1, 1]], dtype=torch.bool)
    us, vars_ = [], []
    for k in range(7):
        u, v = hold.step(readings[k], valid[k], dt)
        us.append(u[:, 0])
        vars_.append(v)
    # trajectory 0 holds reading 1 over steps 1-3, trajectory 1 holds reading 3 over steps 3-5
    assert torch.stack(us)[:, 0].tolist() == [1, 1, 1, 1, 5, 6, 7]
    assert torch.stack(us)[:, 1].tolist() == [1, 2, 3, 3, 3, 3, 7]
    total = torch.stack(vars_).sum(0)
    # the angle error of a rate held for j steps is δω·jΔt: variance (σ_h·3Δt)² after 3 held steps
    assert total.tolist() == pytest.approx([(2e-6 * 3 * dt) ** 2] * 2, rel=1e-12)
    assert torch.stack(vars_)[:, 0].tolist() == pytest.approx([0, (2e-7) ** 2, 3 * (2e-7) ** 2, 5 * (2e-7) ** 2, 0, 0, 0])


def test_inflate_adds_to_the_attitude_block_of_every_component_in_mrp_units():
    covs = torch.eye(6, dtype=F64).expand(2, 3, 6, 6) * 1e-8
    mix = GaussianMixture(means=torch.zeros(2, 3, 6, dtype=F64), covs=covs.clone(), weights=torch.full((2, 3), 1 / 3, dtype=F64))
    out = GyroHold.inflate(mix, torch.tensor([16e-8, 0.0], dtype=F64))
    expected = covs.clone()
    expected[0, :, :3, :3] += 1e-8 * torch.eye(3, dtype=F64)
    assert torch.allclose(out.covs, expected, rtol=0, atol=1e-24)
    assert torch.equal(out.means, mix.means) and torch.equal(out.log_weights, mix.log_weights)


def test_bad_input_raises_and_state_round_trips():
    with pytest.raises(ValueError, match="rate_sigma must be finite and ≥ 0"):
        GyroHold(-1.0)
    hold = GyroHold(1e-6)
    with pytest.raises(ValueError, match=r"gyro must have shape \[B, 3\]"):
        hold.step(torch.zeros(4, dtype=F64), None, 0.1)
    with pytest.raises(ValueError, match=r"gyro_valid must have shape \[2\]"):
        hold.step(torch.zeros(2, 3, dtype=F64), torch.ones(3, dtype=torch.bool), 0.1)
    with pytest.raises(ValueError, match="valid gyro readings must be finite"):
        hold.step(torch.full((2, 3), float("nan"), dtype=F64), torch.tensor([True, False]), 0.1)
    assert hold.last is None  # nothing changed by the rejected calls
    hold.step(torch.ones(2, 3, dtype=F64), torch.tensor([True, False]), 0.1)
    other = GyroHold(0.0)
    other.load_state_dict(hold.state_dict())
    a = hold.step(torch.zeros(2, 3, dtype=F64), torch.tensor([False, False]), 0.1)
    b = other.step(torch.zeros(2, 3, dtype=F64), torch.tensor([False, False]), 0.1)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
