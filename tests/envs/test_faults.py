"""Sensor-fault injection: validation, each fault kind, and equality of stepping and simulate()."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs import StarTrackerAttitudeVectorEnv, StarTrackerConfig
from envs.faults import SensorFault, apply_gyro_faults, apply_star_faults, nearest_other_star, parse_faults
from tests.helpers import assert_within

FAULTS = [
    {"kind": "gyro_dropout", "start": 0.5, "end": 0.8},
    {"kind": "gyro_saturation", "start": 1.0, "end": 1.5, "limit": 5e-4},
    {"kind": "misidentified_star", "start": 2.0, "end": 4.0, "slot": 1},
    {"kind": "star_outage", "start": 5.0, "end": 7.0},
]


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ({"kind": "sun_blind", "start": 0, "end": 1}, r"kind must be one of"),
        ({"kind": "star_outage", "start": 2, "end": 1}, r"end \(1.0\) must be after start \(2.0\)"),
        ({"kind": "star_outage", "start": -1, "end": 1}, r"start must be finite and ≥ 0"),
        ({"kind": "star_outage", "start": 0, "end": float("inf")}, r"end must be finite and ≥ 0"),
        ({"kind": "gyro_saturation", "start": 0, "end": 1}, r"gyro_saturation needs limit > 0"),
        ({"kind": "gyro_saturation", "start": 0, "end": 1, "limit": -1.0}, r"gyro_saturation needs limit > 0"),
        ({"kind": "gyro_dropout", "start": 0, "end": 1, "limit": 1.0}, r"limit applies to gyro_saturation only"),
        ({"kind": "misidentified_star", "start": 0, "end": 1, "slot": -1}, r"slot must be an integer ≥ 0"),
        ({"kind": "star_outage", "start": 0, "end": 1, "duration": 3}, r"unknown key\(s\) \['duration'\]"),
        ({"kind": "star_outage", "start": 0}, r"no end given; every fault needs kind, start and end"),
        ({"start": 0}, r"no kind, end given; every fault needs kind, start and end"),
    ],
)
def test_bad_faults_raise_naming_the_entry(fault, message):
    with pytest.raises(ValueError, match=rf"StarTrackerConfig: faults\[0\]: .*{message}"):
        StarTrackerConfig(faults=[fault])


def test_faults_must_be_a_list_and_round_trip_through_dicts():
    with pytest.raises(ValueError, match="faults must be a list"):
        StarTrackerConfig(faults={"kind": "star_outage", "start": 0, "end": 1})
    parsed = parse_faults(FAULTS)
    assert all(isinstance(f, SensorFault) for f in parsed)
    assert parse_faults([f.to_dict() for f in parsed]) == parsed
    assert StarTrackerConfig(faults=parsed).faults == parsed


def test_windows_are_half_open():
    f = SensorFault("gyro_dropout", 1.0, 2.0)
    t = torch.tensor([0.9, 1.0, 1.5, 1.9, 2.0, 3 * 0.1 * 10 / 3], dtype=torch.float64)
    assert f.active(t).tolist() == [False, True, True, True, False, True]


def test_gyro_dropout_and_saturation():
    gyro = torch.tensor([[1e-3, -2e-4, 3e-4], [1e-4, 1e-4, -1e-4]], dtype=torch.float64)
    t = torch.tensor(1.2, dtype=torch.float64)
    out, valid = apply_gyro_faults(parse_faults([FAULTS[1]]), gyro, t)
    assert out.tolist() == [[5e-4, -2e-4, 3e-4], gyro[1].tolist()]  # clipped per axis
    assert valid.tolist() == [False, True]  # only the sample beyond the range is flagged
    out, valid = apply_gyro_faults(parse_faults([FAULTS[0]]), gyro, torch.tensor(0.6, dtype=torch.float64))
    assert torch.equal(out, torch.zeros_like(gyro)) and not valid.any()
    out, valid = apply_gyro_faults(parse_faults(FAULTS), gyro, torch.tensor(0.4, dtype=torch.float64))
    assert torch.equal(out, gyro) and valid.all()


def test_nearest_other_star_is_the_brute_force_neighbour(default_catalog):
    cat = default_catalog.r
    idx = torch.tensor([0, 17, 500, 9000, len(cat) - 1])
    got = nearest_other_star(cat, cat[idx])
    c = cat.numpy()
    for i, k in enumerate(idx.tolist()):
        sep = np.degrees(np.arccos(np.clip(c @ c[k], -1, 1)))
        sep[k] = np.inf
        j = int(np.argmin(sep))
        assert np.array_equal(got[i].numpy(), c[j])
        assert 0.0 < sep[j] < 5.0


def test_env_injects_each_fault_and_simulate_equals_stepping(default_catalog):
    b, n = 4, 100
    clean = StarTrackerAttitudeVectorEnv(b, max_steps=n).simulate(n, seed=3)
    venv = StarTrackerAttitudeVectorEnv(b, max_steps=n, faults=FAULTS)
    out = venv.simulate(n, seed=3)
    stepper = StarTrackerAttitudeVectorEnv(b, max_steps=n, faults=FAULTS)
    obs, _ = stepper.reset(seed=3)
    hist = [obs]
    for _ in range(n):
        obs, *_ = stepper.step(torch.zeros(b, 3))
        hist.append(obs)
    for k in range(n + 1):
        assert torch.equal(out["gyro"][:, k], hist[k]["gyro"]), k
        assert torch.equal(out["gyro_valid"][:, k], hist[k]["gyro_valid"][:, 0]), k
    for f, k in enumerate(out["star_steps"].tolist()):
        for key in ("star_body", "star_inertial", "star_mask"):
            assert torch.equal(out[key][:, f], hist[k][key]), (k, key)

    t = out["time"]
    drop = (t >= 0.5 - 1e-9) & (t < 0.8 - 1e-9)
    sat = (t >= 1.0 - 1e-9) & (t < 1.5 - 1e-9)
    assert (~out["gyro_valid"]).any(0).tolist() == (drop | sat).tolist()  # the truth rate (0.063 rad/s) saturates
    assert torch.equal(out["gyro"][:, drop], torch.zeros_like(out["gyro"][:, drop]))
    assert out["gyro"][:, sat, :2].abs().max() == 5e-4
    untouched = ~(drop | sat)
    assert torch.equal(out["gyro"][:, untouched], clean["gyro"][:, untouched])

    ft = out["star_time"].tolist()
    for f, tf in enumerate(ft):
        if 5.0 <= tf < 7.0:  # outage
            assert not out["star_mask"][:, f].any()
            continue
        assert torch.equal(out["star_body"][:, f], clean["star_body"][:, f])  # body vectors never change
        assert torch.equal(out["star_mask"][:, f], clean["star_mask"][:, f])
        wrong = out["star_inertial"][:, f] != clean["star_inertial"][:, f]
        if 2.0 <= tf < 4.0:  # slot 1 carries the nearest other catalogue star
            assert wrong[:, 1].all() and not wrong[:, [0, 2, 3, 4]].any()
            r = out["star_inertial"][:, f, 1]
            assert torch.equal(r, nearest_other_star(default_catalog.r, clean["star_inertial"][:, f, 1]))
            sep = torch.rad2deg(torch.acos((r * clean["star_inertial"][:, f, 1]).sum(-1)))
            assert (sep > 0.0).all() and (sep < 5.0).all()
        else:
            assert not wrong.any()


def test_faults_live_in_the_config_and_the_single_env_reports_gyro_valid():
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environment)

    env = gym.make("agsf/StarTrackerAttitude-v0", max_steps=20, faults=[FAULTS[0]])
    obs, _ = env.reset(seed=0)
    assert obs["gyro_valid"].tolist() == [True]
    flags = []
    for _ in range(10):
        obs, *_ = env.step(np.zeros(3))
        flags.append(bool(obs["gyro_valid"][0]))
    assert flags == [True, True, True, True, False, False, False, True, True, True]  # t = 0.5, 0.6, 0.7
    assert_within(float(obs["time"][0]), 1.0, 1e-9, "time after 10 steps of 0.1 s")


def test_a_misidentified_star_slot_beyond_max_stars_is_refused():
    fault = {"kind": "misidentified_star", "start": 2.0, "end": 4.0, "slot": 5}
    message = r"faults\[1\]: misidentified_star slot 5 does not exist: a frame reports max_stars=3 stars \(slots 0…2\)"
    with pytest.raises(ValueError, match=rf"StarTrackerConfig: {message}"):
        StarTrackerConfig(max_stars=3, faults=[FAULTS[0], fault])
    with pytest.raises(ValueError, match=rf"StarTrackerConfig: {message}"):  # a SensorFault object, too
        StarTrackerConfig(max_stars=3, faults=[FAULTS[0], SensorFault(**fault)])
    with pytest.raises(ValueError, match=rf"^{message}$"):  # what a configuration that knows max_stars calls
        parse_faults([FAULTS[0], fault], max_stars=3)
    assert parse_faults([fault]) == (SensorFault(**fault),)  # without max_stars the slot is not checked
    assert StarTrackerConfig(max_stars=6, faults=[fault]).faults == (SensorFault(**fault),)
    body = torch.zeros(2, 3, 3, dtype=torch.float64)
    with pytest.raises(
        ValueError, match=r"faults\[0\]: misidentified_star slot 5 does not exist: a frame reports max_stars=3"
    ):
        apply_star_faults(
            parse_faults([fault]),
            torch.eye(3, dtype=torch.float64),
            body,
            body,
            torch.ones(2, 3, dtype=torch.bool),
            torch.tensor(3.0),
        )


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ({"kind": "star_outage", "start": True, "end": 1.0}, r"start must be a number, got True"),
        ({"kind": "star_outage", "start": 0.0, "end": "1.0"}, r"end must be a number, got '1.0'"),
        ({"kind": "gyro_saturation", "start": 0, "end": 1, "limit": "1e-3"}, r"limit must be a number, got '1e-3'"),
        ({"kind": "misidentified_star", "start": 0, "end": 1, "slot": "1"}, r"slot must be an integer ≥ 0, got '1'"),
    ],
)
def test_fault_numbers_refuse_bools_and_strings(fault, message):
    with pytest.raises(ValueError, match=rf"StarTrackerConfig: faults\[0\]: SensorFault: .*{message}"):
        StarTrackerConfig(faults=[fault])
