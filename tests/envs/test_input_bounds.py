"""Bad inputs are refused with a clear error before anything happens: config field types,
physical ranges of the configuration, extreme actions and rate profiles."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

import envs
from envs import (
    AttitudeDynamics,
    Gyro,
    StarCamera,
    StarTrackerAttitudeEnv,
    StarTrackerAttitudeVectorEnv,
    StarTrackerConfig,
)

NUMBER_FIELDS = ("dt", "star_period", "sigma_v", "sigma_u", "sigma_s", "focal_length", "max_magnitude")
VECTOR_FIELDS = {"initial_bias": 3, "fov_deg": 2, "principal_point": 2, "rate": 3, "initial_attitude": 3}


# ------------------------------------------------------------------ field types
@pytest.mark.parametrize("field", NUMBER_FIELDS)
@pytest.mark.parametrize("value", [True, False, np.bool_(True), "1.0", b"1", 1j, np.complex128(1.0), None, [1.0]])
def test_number_fields_refuse_bools_strings_and_other_objects(field, value):
    with pytest.raises(ValueError, match=rf"StarTrackerConfig: {field} must be a number, got "):
        StarTrackerConfig(**{field: value})


@pytest.mark.parametrize("field", sorted(VECTOR_FIELDS))
@pytest.mark.parametrize("entry", [True, "0.01", 1j])
def test_vector_fields_refuse_bool_and_string_entries(field, entry):
    n = VECTOR_FIELDS[field]
    value = [0.01] * n
    value[1] = entry
    with pytest.raises(
        ValueError, match=rf"StarTrackerConfig: {field} must be {n} numbers.*, got .*: entry 1 is {entry!r}"
    ):
        StarTrackerConfig(**{field: value})


def test_whole_field_bool_and_string_vectors_are_refused():
    for field in ("initial_bias", "fov_deg"):  # scalars allowed, but not a bool or a string
        for value in (True, "8"):
            with pytest.raises(ValueError, match=rf"StarTrackerConfig: {field} must be \d numbers, got {value!r}"):
                StarTrackerConfig(**{field: value})


def test_ints_and_numpy_numbers_are_accepted_as_floats():
    cfg = StarTrackerConfig(
        dt=np.float64(0.1),
        star_period=1,
        sigma_v=0,
        sigma_u=np.int64(0),
        sigma_s=0,
        focal_length=np.float32(0.0625),
        max_magnitude=7,
        rate=np.array([0, 0, 1]),
        initial_bias=0,
        fov_deg=torch.tensor(8),
        initial_attitude=(0, 0, 0),
        max_stars=np.int64(4),
        max_steps=10.0,
    )
    assert (cfg.star_period, cfg.sigma_v, cfg.sigma_u, cfg.max_magnitude) == (1.0, 0.0, 0.0, 7.0)
    assert all(type(getattr(cfg, f)) is float for f in NUMBER_FIELDS)
    assert cfg.rate == (0.0, 0.0, 1.0) and cfg.fov_deg == (8.0, 8.0) and cfg.initial_attitude == (0.0, 0.0, 0.0)
    assert all(type(v) is float for v in cfg.rate + cfg.fov_deg + cfg.initial_bias + cfg.initial_attitude)
    assert (cfg.max_stars, cfg.max_steps) == (4, 10) and type(cfg.max_stars) is int


def test_component_classes_refuse_bools_and_strings():
    with pytest.raises(ValueError, match=r"Gyro: sigma_v must be a number, got True"):
        Gyro(sigma_v=True)
    with pytest.raises(ValueError, match=r"Gyro: initial_bias must be 3 numbers, got .*entry 0 is '1e-7'"):
        Gyro(initial_bias=("1e-7", 0.0, 0.0))
    with pytest.raises(ValueError, match=r"AttitudeDynamics: dt must be a number, got '0.1'"):
        AttitudeDynamics(dt="0.1")
    with pytest.raises(ValueError, match=r"AttitudeDynamics: rate must be 3 numbers \(rad/s\), got .*entry 2 is True"):
        AttitudeDynamics(rate=(0.0, 0.0, True))


def test_camera_refuses_bools_and_strings(default_catalog):
    with pytest.raises(ValueError, match=r"StarCamera: sigma must be a number, got '1e-5'"):
        StarCamera(default_catalog, sigma="1e-5")
    with pytest.raises(ValueError, match=r"StarCamera: max_stars must be an integer ≥ 1, got True"):
        StarCamera(default_catalog, max_stars=True)
    with pytest.raises(ValueError, match=r"StarCamera: principal_point must be 2 numbers \(m\), got .*entry 0 is '0'"):
        StarCamera(default_catalog, principal_point=("0", 0.0))


# ------------------------------------------------------------------ physical ranges of the configuration
@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (dict(rate=(1e300, 0.0, 0.0)), r"rate 1e\+300 rad/s turns 1e\+299 rad per step of dt=0.1 s; .*\|ω\|·dt < π"),
        (dict(rate=(40.0, 0.0, 0.0)), r"rate 40 rad/s turns 4 rad per step of dt=0.1 s"),
        (dict(dt=1e300, star_period=1e300), r"rate 0.0888577 rad/s turns 8.88577e\+298 rad per step of dt=1e\+300 s"),
        (dict(initial_bias=1e300), r"initial_bias 1.73205e\+300 rad/s turns .* rad per step of dt=0.1 s"),
        (dict(sigma_v=1e300), r"gyro noise \(1-σ reading\) .* rad/s turns .* rad per step of dt=0.1 s"),
        (dict(sigma_u=1e300), r"gyro noise \(1-σ reading\) .* rad/s turns .* rad per step"),
        (dict(sigma_v=1e150), r"gyro noise \(1-σ reading\) .* rad/s turns .* rad per step"),
        (dict(dt=1e-12, star_period=1e-12), r"dt must be ≥ 1e-09 s .*, got 1e-12"),
        (
            dict(dt=1e-9, star_period=1e308),
            r"star_period / dt must be a finite number of steps, got 1e\+308 / 1e-09 = inf",
        ),
        (dict(sigma_s=1e300), r"sigma_s must be ≤ 1 rad \(a small-angle noise model\), got 1e\+300"),
        (dict(sigma_s=2.0), r"sigma_s must be ≤ 1 rad"),
        (dict(focal_length=1e-160), r"focal_length must lie in \[1e-06, 1000\] m, got 1e-160"),
        (dict(focal_length=1e160), r"focal_length must lie in \[1e-06, 1000\] m, got 1e\+160"),
        (dict(principal_point=(1e300, 0.0)), r"principal_point x₀ = 1e\+300 m lies outside the imaged field"),
        (dict(principal_point=(0.0, -0.005)), r"principal_point y₀ = -0.005 m lies outside the imaged field .* 0.0045"),
        (
            dict(initial_attitude=(1e200, 0.0, 0.0)),
            r"initial_attitude must have every MRP component within ±1e\+150 .*got 1e\+200 at index \[0\]",
        ),
        (dict(max_stars=10**9), r"max_stars must be ≤ 117955 \(.*Hipparcos.*\), got 1000000000"),
        (dict(max_steps=2**53 + 1), r"max_steps must be ≤ 9007199254740992 .*, got 9007199254740993"),
        (
            dict(dt=1e295, star_period=1e295, rate=(0, 0, 0), initial_bias=0, sigma_v=0, sigma_u=0, max_steps=10**15),
            r"the episode duration max_steps·dt = inf s must be finite",
        ),
    ],
)
def test_extreme_finite_config_values_are_refused(overrides, message):
    with pytest.raises(ValueError, match=rf"StarTrackerConfig: {message}"):
        StarTrackerConfig(**overrides)


@pytest.mark.parametrize(
    "edge",
    [
        dict(rate=(0.999 * math.pi / 0.1, 0.0, 0.0), initial_bias=(0.0, 0.999 * math.pi / 0.1, 0.0)),
        dict(sigma_s=1.0, focal_length=1e-6, principal_point=(0.999e-6 * math.tan(math.radians(4.0)), 0.0)),
        dict(dt=1e-9, star_period=1e-9, max_stars=117_955, initial_attitude=(1e150, -1e150, 0.0)),
    ],
)
def test_values_at_the_edge_of_the_ranges_are_accepted_kept_and_simulated(edge):
    """Just inside every range: the configuration keeps the values as given, and an environment
    built from it steps to finite observations."""
    cfg = StarTrackerConfig(**edge)
    for key, value in edge.items():
        assert getattr(cfg, key) == value, key
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=2, max_steps=3, **edge)
    obs, _ = env.reset(seed=5)
    obs, *_ = env.step(torch.zeros(2, 3, dtype=torch.float64))
    for key in ("gyro", "star_body", "star_inertial", "time"):
        assert bool(torch.isfinite(torch.as_tensor(obs[key])).all()), key


def test_component_classes_apply_the_same_ranges(default_catalog):
    with pytest.raises(ValueError, match=r"Gyro: gyro noise \(1-σ reading\) .* rad per step"):
        Gyro(sigma_v=1e300)  # was an OverflowError
    with pytest.raises(ValueError, match=r"Gyro: initial_bias .* rad per step of dt=0.1 s"):
        Gyro(initial_bias=100.0)
    with pytest.raises(ValueError, match=r"AttitudeDynamics: rate 100 rad/s turns 10 rad per step of dt=0.1 s"):
        AttitudeDynamics(rate=(100.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"StarCamera: sigma must be ≤ 1 rad"):
        StarCamera(default_catalog, sigma=1e300)
    with pytest.raises(ValueError, match=r"StarCamera: max_stars must be ≤ 117955"):
        StarCamera(default_catalog, max_stars=10**9)
    with pytest.raises(ValueError, match=r"StarCamera: focal_length must lie in"):
        StarCamera(default_catalog, focal_length=1e160)


def test_a_rate_profile_turning_half_a_turn_per_step_is_refused_before_the_state_moves():
    def fast_after_one_second(t):
        w = torch.where(t > 1.0, 50.0, 0.01).to(t.dtype)
        return torch.stack((w, torch.zeros_like(w), torch.zeros_like(w)), -1)

    venv = StarTrackerAttitudeVectorEnv(2, max_steps=50, rate=fast_after_one_second)
    venv.reset(seed=0)
    for _ in range(10):
        venv.step(torch.zeros(2, 3))
    before = venv.sim.state_dict()
    with pytest.raises(
        ValueError, match=r"AttitudeDynamics: rate\(t\) returned 50 rad/s at t = 1.05 s, .*turns 5 rad per step"
    ):
        venv.step(torch.zeros(2, 3))
    after = venv.sim.state_dict()
    assert after["step_index"] == before["step_index"] == 10
    assert all(torch.equal(after[k], before[k]) for k in ("q", "bias", "rate", "seeds", "last_gyro"))
    # At reset, too: the previous episode's state is kept whole.
    speed = [0.01]
    venv = StarTrackerAttitudeVectorEnv(2, rate=lambda t: torch.full((*t.shape, 3), speed[0], dtype=t.dtype))
    venv.reset(seed=0)
    venv.step(torch.zeros(2, 3))
    before = venv.sim.state_dict()
    speed[0] = 50.0
    with pytest.raises(ValueError, match=r"rate\(t\) returned 86.6025 rad/s at t = 0 s"):  # |(50, 50, 50)|
        venv.reset(seed=7)
    after = venv.sim.state_dict()
    assert after["step_index"] == 1 and all(torch.equal(after[k], before[k]) for k in ("q", "seeds", "rate", "bias"))
    # a finished episode stays finished: the episode bookkeeping moves only after a successful reset
    speed[0] = 0.01
    venv = StarTrackerAttitudeVectorEnv(
        2, max_steps=2, rate=lambda t: torch.full((*t.shape, 3), speed[0], dtype=t.dtype)
    )
    venv.reset(seed=0)
    for _ in range(2):
        venv.step(torch.zeros(2, 3))
    flags = {k: v for k, v in venv.state_dict().items() if k != "sim"}
    speed[0] = 50.0
    with pytest.raises(ValueError, match=r"rate\(t\) returned"):
        venv.reset(seed=7)
    assert {k: v for k, v in venv.state_dict().items() if k != "sim"} == flags and flags["needs_reset"]


# ------------------------------------------------------------------ actions
@pytest.mark.parametrize("value", [1e300, 1e155, -1e151])
def test_extreme_actions_are_refused_before_the_state_moves(value):
    venv = StarTrackerAttitudeVectorEnv(3, max_steps=10)
    venv.reset(seed=0)
    before = venv.sim.state_dict()
    actions = torch.zeros(3, 3, dtype=torch.float64)
    actions[2, 1] = value
    with pytest.raises(
        ValueError,
        match=rf"actions must have every MRP component within ±1e\+150 .*got {re.escape(f'{value:g}')} at index \[2, 1\]",
    ):
        venv.step(actions)
    after = venv.sim.state_dict()
    assert after["step_index"] == 0 and torch.equal(after["q"], before["q"])
    env = StarTrackerAttitudeEnv(max_steps=10)
    env.reset(seed=0)
    with pytest.raises(
        ValueError,
        match=rf"action must have every MRP component within ±1e\+150 .*got {re.escape(f'{value:g}')} at index \[1\]",
    ):
        env.step(np.array([0.0, value, 0.0]))
    assert env.sim.step_index == 0


def test_large_but_valid_actions_give_finite_rewards():
    venv = StarTrackerAttitudeVectorEnv(2, max_steps=10)
    venv.reset(seed=0)
    _, reward, *_ = venv.step(torch.full((2, 3), 1e150, dtype=torch.float64))
    assert bool(torch.isfinite(reward).all())


@pytest.mark.parametrize(
    ("action", "kind"),
    [
        (np.array([True, False, True]), "bool"),
        (np.array([1j, 0, 0]), "complex128"),
        (np.array(["0.1", "0", "0"]), "<U3"),
        (np.array([0.1, None, 0.0], dtype=object), "object"),
    ],
)
def test_non_numeric_actions_are_refused(action, kind):
    env = StarTrackerAttitudeEnv(max_steps=10)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=rf"action must hold real numbers, got dtype {kind}"):
        env.step(action)
    venv = StarTrackerAttitudeVectorEnv(1, max_steps=10)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=rf"actions must hold real numbers, got dtype {kind}"):
        venv.step(action[None])
    with pytest.raises(ValueError, match=r"actions must hold real numbers, got dtype torch.bool"):
        venv.step(torch.ones(1, 3, dtype=torch.bool))
    assert env.sim.step_index == 0 and venv.sim.step_index == 0
