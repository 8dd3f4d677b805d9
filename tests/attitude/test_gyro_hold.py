"""GyroHold: the held input, the covariance inflation for the hold error, validation, state."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.attitude.gyro_hold import GyroHold
from tests.helpers import F64, assert_statistic, assert_within, relative_bound


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
    # the angle error of a rate held for j steps is δω·jΔt: variance (σ_h·3Δt)² after 3 held steps (a sum of
    # nonnegative terms of a few roundings each: relative; the values, ~1e-13, are far below an absolute 1e-12)
    held = (2e-6 * 3 * dt) ** 2
    assert_within(total, torch.full((2,), held, dtype=F64), 1e-12 * held, "variance after 3 held steps")
    # (σ_h·Δt)²·(2j − 1) per held step, relative; an exact 0 (torch.where) at each valid sample
    per_step = torch.tensor([0, (2e-7) ** 2, 3 * (2e-7) ** 2, 5 * (2e-7) ** 2, 0, 0, 0], dtype=F64)
    assert_within(torch.stack(vars_)[:, 0], per_step, relative_bound(per_step, 1e-6, 0.0), "variance of each step")


def _B(p: torch.Tensor) -> torch.Tensor:
    """``B(p) = (1 − pᵀp) I + 2[p×] + 2ppᵀ`` written out (``ṗ = ¼ B(p) ω``), ``[..., 3, 3]``."""
    x, y, z = p.unbind(-1)
    zero = torch.zeros_like(x)
    cross = torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), -1).reshape(*p.shape, 3)
    s = (p * p).sum(-1)[..., None, None]
    return (1 - s) * torch.eye(3, dtype=p.dtype) + 2 * cross + 2 * p[..., :, None] * p[..., None, :]


def test_inflate_adds_the_mrp_covariance_of_the_angle_variance_to_every_component():
    """``T P_δ Tᵀ`` with ``T = ¼ B(p)`` of each component's mean and ``P_δ = v I₃``: ``v/16 · B Bᵀ`` (written out,
    not through the ``(1 + |p|²)²`` identity the implementation uses); zero for ``v = 0``, the bias block untouched."""
    gen = torch.Generator().manual_seed(5)
    means = torch.randn(2, 3, 6, generator=gen, dtype=F64)
    means[..., :3] *= 0.9 / means[..., :3].norm(dim=-1, keepdim=True)  # |p| = 0.9: near the short set's edge
    covs = torch.eye(6, dtype=F64).expand(2, 3, 6, 6) * 1e-8
    mix = GaussianMixture(means=means, covs=covs.clone(), weights=torch.full((2, 3), 1 / 3, dtype=F64))
    v = 16e-8
    out = GyroHold.inflate(mix, torch.tensor([v, 0.0], dtype=F64))
    B = _B(means[0, :, :3])
    expected = covs.clone()
    expected[0, :, :3, :3] += v / 16 * B @ B.transpose(-1, -2)
    # B Bᵀ's off-diagonal entries vanish to rounding of its O(1) terms: an absolute tolerance of v/16 · 1e-14
    assert_within(out.covs, expected, relative_bound(expected, 1e-14, v / 16 * 1e-14), "inflated covariances")
    assert torch.equal(out.means, mix.means) and torch.equal(out.log_weights, mix.log_weights)
    # at |p| = 0.9 that is (1 + 0.81)² = 3.28 times the p = 0 value v/16; the prior variance 1e-8 cancels in the
    # difference: its scale is the floor (an absolute 1e-12 would be 3e-5 of the value)
    added = v / 16 * 1.81**2
    assert_within(out.covs[0, 0, 0, 0] - covs[0, 0, 0, 0], added, 1e-12 * (added + 1e-8), "variance added at |p| = 0.9")


@pytest.mark.parametrize("norm", [0.0, 0.5, 0.95])
def test_the_inflation_is_the_covariance_of_the_mrp_error_a_held_rate_makes(norm):
    """Monte Carlo, independent of the filters: a reading off the true rate by ``δω ~ N(0, σ_h² I)`` (body
    frame), held over ``j`` steps, turns the attitude by ``δθ = δω jΔt`` (``C = exp(−[δθ×]) C(q̂)``, scipy's
    rotations); the covariance of the resulting MRP error equals what :meth:`GyroHold.step` accumulates and
    :meth:`GyroHold.inflate` adds, each entry within 5 standard errors ``sqrt((PᵢᵢPⱼⱼ + Pᵢⱼ²)/N)``.  The
    angles (~1e-3 rad) keep the linearisation's error (~1e-3 relative, second order in the angle) below the
    standard error (~0.5 %)."""
    from scipy.spatial.transform import Rotation

    sigma_h, dt, held, N = 1e-3, 0.1, 10, 100_000
    gen = torch.Generator().manual_seed(11)
    direction = torch.randn(3, generator=gen, dtype=F64)
    p_hat = norm * direction / direction.norm()
    hold = GyroHold(sigma_h)
    hold.step(torch.zeros(1, 3, dtype=F64), None, dt)
    total = sum(float(hold.step(torch.zeros(1, 3, dtype=F64), torch.tensor([False]), dt)[1]) for _ in range(held))
    floor = 1e-30 * torch.eye(3, dtype=F64)  # a covariance to add to, negligible against the inflation (~1e-8)
    mix = GaussianMixture.from_gaussian(p_hat[None], floor[None], 1)
    predicted = (GyroHold.inflate(mix, torch.tensor([total], dtype=F64)).covs[0, 0] - floor).numpy()

    rng = np.random.default_rng(12)
    dtheta = rng.standard_normal((N, 3)) * sigma_h * held * dt
    # C(q) = exp(−[δθ×]) C(q̂) with C = R.as_matrix().T: R(q) = R(q̂) · exp(δθ)
    p = (Rotation.from_mrp(p_hat.numpy()) * Rotation.from_rotvec(dtheta)).as_mrp()
    err = p - p_hat.numpy()
    empirical = err.T @ err / N
    se = np.sqrt((np.outer(np.diag(predicted), np.diag(predicted)) + predicted**2) / N)
    assert_statistic(empirical, predicted, se, "empirical MRP error covariance", false_failure=1e-6)
    # a sum of nonnegative terms: relative (an absolute 1e-12 would be 1e4 times the value, 1e-8)
    assert_within(total, (sigma_h * held * dt) ** 2, 1e-12 * (sigma_h * held * dt) ** 2, "variance after 10 held steps")


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


def _obs(gyro, valid):
    B = gyro.shape[0]
    return {
        "gyro": gyro,
        "gyro_valid": valid,
        "star_mask": torch.zeros(B, 2, dtype=torch.bool),
        "star_body": torch.zeros(B, 2, 3, dtype=F64),
        "star_inertial": torch.zeros(B, 2, 3, dtype=F64),
    }


def test_known_bias_must_have_three_axes():
    """A true bias [B, 1] would be subtracted from all three axes: refused, before the hold moves."""
    from agsf_torch.attitude.inputs import AttitudeInputs

    adapter = AttitudeInputs(sigma_s=1e-5, gyro_hold_sigma=1e-6, known_bias=True)
    gyro = torch.ones(2, 3, dtype=F64)
    with pytest.raises(
        ValueError, match=r"truth_bias must have the gyro's shape \(2, 3\) \(\[B, 3\], rad/s\), got \(2, 1\)"
    ):
        adapter.start(_obs(gyro, torch.ones(2, dtype=torch.bool)), 0.1, torch.zeros(2, 1, dtype=F64))
    adapter.start(_obs(gyro, torch.ones(2, dtype=torch.bool)), 0.1, torch.zeros(2, 3, dtype=F64))
    last = adapter.hold.last.clone()
    with pytest.raises(ValueError, match=r"truth_bias must have the gyro's shape \(2, 3\)"):
        adapter(_obs(2 * gyro, torch.ones(2, dtype=torch.bool)), 0.1, torch.zeros(2, 1, dtype=F64))
    assert torch.equal(adapter.hold.last, last)
    step = adapter(_obs(2 * gyro, torch.ones(2, dtype=torch.bool)), 0.1, torch.full((2, 3), 0.5, dtype=F64))
    assert torch.equal(step.u, torch.full((2, 3), 1.75, dtype=F64))  # 2 − ½(0 + 0.5)


def test_start_begins_a_new_run():
    """The first held sample of a new run is not the previous run's last reading."""
    from agsf_torch.attitude.inputs import AttitudeInputs

    adapter = AttitudeInputs(sigma_s=1e-5, gyro_hold_sigma=1e-6)
    valid, held = torch.ones(2, dtype=torch.bool), torch.zeros(2, dtype=torch.bool)
    adapter.start(_obs(torch.full((2, 3), 7.0, dtype=F64), valid), 0.1)
    adapter(_obs(torch.full((2, 3), 8.0, dtype=F64), valid), 0.1)
    adapter.start(_obs(torch.full((2, 3), 9.0, dtype=F64), held), 0.1)
    step = adapter(_obs(torch.full((2, 3), 9.0, dtype=F64), held), 0.1)
    assert torch.equal(step.u, torch.zeros(2, 3, dtype=F64))


def test_hold_refuses_another_batch_and_bad_variances_and_states():
    hold = GyroHold(1e-6)
    hold.step(torch.ones(2, 3, dtype=F64), None, 0.1)
    with pytest.raises(
        ValueError, match=r"gyro has shape \(3, 3\) but this hold follows a run of shape \(2, 3\); call reset\(\)"
    ):
        hold.step(torch.ones(3, 3, dtype=F64), torch.zeros(3, dtype=torch.bool), 0.1)
    assert hold.last.shape == (2, 3)
    hold.reset()
    assert hold.step(torch.ones(3, 3, dtype=F64), None, 0.1)[0].shape == (3, 3)

    mix = GaussianMixture(
        means=torch.zeros(2, 1, 3, dtype=F64),
        covs=1e-8 * torch.eye(3, dtype=F64).expand(2, 1, 3, 3),
        weights=torch.ones(2, 1, dtype=F64),
    )
    for bad, match in (
        (
            torch.tensor([0.0, float("nan")], dtype=F64),
            r"angle_variance must be finite and ≥ 0 \(rad²\), got nan at trajectory 1",
        ),
        (
            torch.tensor([-1e-6, 0.0], dtype=F64),
            r"angle_variance must be finite and ≥ 0 \(rad²\), got -1e-06 at trajectory 0",
        ),
        (
            torch.zeros(2, 1, dtype=F64),
            r"angle_variance must have the mixture's batch shape \[B\] = \(2,\), got \(2, 1\)",
        ),
    ):
        with pytest.raises(ValueError, match=match):
            GyroHold.inflate(mix, bad)

    good = hold.state_dict()
    for change, match in (
        ({"last": torch.ones(3, 1, dtype=F64)}, r"'last' must be a floating tensor \[B, 3\], got \(3, 1\)"),
        ({"last": torch.full((3, 3), float("nan"), dtype=F64)}, r"'last' must be finite"),
        ({"held_steps": torch.zeros(2, dtype=torch.int64)}, r"'held_steps' must be an integer tensor \[3\]"),
        ({"held_steps": -torch.ones(3, dtype=torch.int64)}, r"'held_steps' must be ≥ 0"),
        ({"held_steps": None}, r"'last' and 'held_steps' must both be None"),
        ({"rate_sigma": -1.0}, r"'rate_sigma' must be a finite number ≥ 0"),
        ({"extra": 1}, r"GyroHold state must have the keys"),
    ):
        other = GyroHold(2e-6)
        with pytest.raises(ValueError, match=match):
            other.load_state_dict({**good, **change})
        assert other.last is None and other.rate_sigma == 2e-6


def test_a_refused_star_frame_leaves_the_hold_and_bias_as_they_were():
    """A frame with a non-unit catalogue vector is refused before the gyro hold counts the interval."""
    from agsf_torch.attitude.inputs import AttitudeInputs

    adapter = AttitudeInputs(sigma_s=1e-5, gyro_hold_sigma=1e-6, known_bias=True)
    bias = torch.full((2, 3), 1e-6, dtype=F64)
    adapter.start(_obs(torch.ones(2, 3, dtype=F64), torch.ones(2, dtype=torch.bool)), 0.1, bias)
    held = torch.tensor([True, False])
    adapter(_obs(torch.ones(2, 3, dtype=F64), held), 0.1, bias)
    before = adapter.hold.state_dict()
    obs = _obs(torch.ones(2, 3, dtype=F64), held)
    obs["star_mask"][:, 0] = True
    obs["star_body"][:, 0] = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    obs["star_inertial"][:, 0] = torch.tensor([0.0, 0.0, 2.0], dtype=F64)
    with pytest.raises(ValueError, match="unit"):
        adapter(obs, 0.1, 2 * bias)
    after = adapter.hold.state_dict()
    assert torch.equal(after["held_steps"], before["held_steps"]) and torch.equal(adapter._bias, bias)
