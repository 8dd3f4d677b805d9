"""Truth dynamics: exactness of the quaternion step, rate profiles, bad settings."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.rotations import attitude_error_angle, cross_matrix, mrp_to_quat, quat_to_dcm, quat_to_mrp
from envs.dynamics import DEFAULT_RATE, AttitudeDynamics, propagate_quat
from tests.helpers import assert_within


def _mrp_rate(p: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """ṗ = ¼ B(p) ω, B(p) = (1 − s)I + 2[p×] + 2ppᵀ."""
    s = (p * p).sum(-1, keepdim=True)
    return 0.25 * ((1.0 - s) * w + 2.0 * torch.linalg.cross(p, w, dim=-1) + 2.0 * p * (p * w).sum(-1, keepdim=True))


def _rk4(p: torch.Tensor, rate, t0: float, t1: float, steps: int) -> torch.Tensor:
    h = (t1 - t0) / steps
    t = t0
    for _ in range(steps):
        k1 = _mrp_rate(p, rate(t))
        k2 = _mrp_rate(p + 0.5 * h * k1, rate(t + 0.5 * h))
        k3 = _mrp_rate(p + 0.5 * h * k2, rate(t + 0.5 * h))
        k4 = _mrp_rate(p + h * k3, rate(t + h))
        p = p + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        t += h
    return p


def _random_state(num: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    p0 = torch.randn(num, 3, generator=g, dtype=torch.float64)
    p0 = 0.5 * p0 / p0.norm(dim=-1, keepdim=True) * torch.rand(num, 1, generator=g, dtype=torch.float64)
    w = torch.randn(num, 3, generator=g, dtype=torch.float64)  # up to a few rad/s
    return p0, w


def test_one_step_equals_rk4_on_mrp_kinematics():
    p0, w = _random_state(32, 0)
    dt = 0.1
    q1 = propagate_quat(mrp_to_quat(p0), w, dt)
    p_ref = _rk4(p0, lambda t: w, 0.0, dt, 2000)
    assert float(p_ref.norm(dim=-1).max()) < 1.0  # no shadow switch inside the step
    assert_within(quat_to_mrp(q1), p_ref, 1e-12, "MRP after one step against RK4")
    assert_within(attitude_error_angle(quat_to_mrp(q1), p_ref), 0.0, 1e-12, "angle to the RK4 attitude")


def test_many_steps_equal_the_matrix_exponential():
    p0, w = _random_state(16, 1)
    w = 0.2 * w
    dyn = AttitudeDynamics(dt=0.1)
    q = mrp_to_quat(p0)
    steps = 1000
    for _ in range(steps):
        q = dyn.step(q, w)
    C_ref = torch.linalg.matrix_exp(-cross_matrix(w) * (steps * 0.1)) @ quat_to_dcm(mrp_to_quat(p0))
    assert_within(quat_to_dcm(q), C_ref, 1e-12, "attitude matrix after 1000 steps against the matrix exponential")
    assert_within(q.norm(dim=-1), 1.0, 1e-15, "quaternion norm after 1000 steps")


def test_default_rate_profile():
    dyn = AttitudeDynamics()
    t = torch.tensor([0.0, 3.0, 50.0], dtype=torch.float64)
    assert dyn.rate(t).tolist() == [list(DEFAULT_RATE)] * 3
    w = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    assert torch.equal(AttitudeDynamics(w).rate(t[:1]), w[None])


def _profile(t: torch.Tensor) -> torch.Tensor:
    return torch.stack((0.3 * torch.sin(t), 0.2 * torch.cos(0.5 * t), 0.1 + 0.05 * t), -1)


def test_callable_rate_is_held_at_the_midpoint_and_second_order():
    dyn = AttitudeDynamics(_profile, dt=0.1)
    t = torch.tensor([0.0, 1.0], dtype=torch.float64)
    assert torch.equal(dyn.held_rate(t), _profile(t + 0.05))
    p0, _ = _random_state(4, 2)
    t_end = 2.0
    ref = _rk4(p0, lambda s: _profile(torch.full((4,), s, dtype=torch.float64)), 0.0, t_end, 4000)
    errors = []
    for dt in (0.1, 0.05):
        dyn = AttitudeDynamics(_profile, dt=dt)
        q = mrp_to_quat(p0)
        n = round(t_end / dt)
        for k in range(n):
            q = dyn.step(q, dyn.held_rate(torch.full((4,), k * dt, dtype=torch.float64)))
        errors.append(float(attitude_error_angle(quat_to_mrp(q), ref).max()))
    # Zero-order hold at the midpoint: global error O(Δt²), so halving Δt quarters it.
    assert errors[0] < 1e-3
    assert 3.5 < errors[0] / errors[1] < 4.5, errors


def test_callable_rate_returning_bad_values_raises():
    t = torch.zeros(5, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"rate\(t\) must return a tensor of shape \(5, 3\), got \(5,\)"):
        AttitudeDynamics(lambda t: t).rate(t)
    with pytest.raises(ValueError, match=r"rate\(t\) returned non-finite values"):
        AttitudeDynamics(lambda t: torch.full((5, 3), float("nan"), dtype=torch.float64)).rate(t)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(rate=(float("nan"), 0.0, 0.0)), r"rate must be 3 finite numbers \(rad/s\), got \(nan, 0.0, 0.0\)"),
        (dict(rate=(0.1, 0.2)), r"rate must be 3 finite numbers \(rad/s\), got \(0.1, 0.2\)"),
        (dict(rate="fast"), r"rate must be 3 numbers \(rad/s\), got 'fast'"),
        (dict(dt=0.0), r"dt must be finite and > 0, got 0.0"),
        (dict(dt=-0.1), r"dt must be finite and > 0, got -0.1"),
        (dict(dt=float("inf")), r"dt must be finite and > 0, got inf"),
    ],
)
def test_bad_dynamics_settings_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        AttitudeDynamics(**kwargs)
