"""Recorded-data format: round trip, replay equals the live environment, bad files named."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import envs
from agsf_torch.experiments.recorded import RecordingEnv, record_environment
from agsf_torch.experiments.runner import FilterSetup, run_monte_carlo
from agsf_torch.filters import GaussianSumFilter
from agsf_torch.models import AttitudeModel
from agsf_torch.recordings import Recording

F64 = torch.float64


@pytest.fixture(scope="module")
def recording():
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=4, max_steps=40)
    return record_environment(env, 30, seed=5)


def _run(env):
    model = AttitudeModel()
    return run_monte_carlo(
        env,
        {"gsf": FilterSetup(GaussianSumFilter(model, update_iterations=2), 3)},
        num_steps=30,
        prior_cov=1e-6 * torch.eye(3, dtype=F64),
        sigma_s=10e-6,
        seed=5,
    ).traces["gsf"]


def test_round_trip_is_bit_identical(recording, tmp_path):
    path = recording.save(tmp_path / "log.npz")
    back = Recording.load(path)
    for name in ("time", "gyro", "star_body", "star_inertial", "star_mask", "truth_mrp", "truth_bias"):
        assert np.array_equal(getattr(back, name), getattr(recording, name)), name
    a, b = _run(RecordingEnv(recording)), _run(RecordingEnv(back))
    assert np.array_equal(a.error, b.error) and np.array_equal(a.nees, b.nees) and np.array_equal(a.weights, b.weights)


def test_replay_equals_the_live_environment(recording):
    live = _run(envs.StarTrackerAttitudeVectorEnv(num_envs=4, max_steps=40))
    replay = _run(RecordingEnv(recording))
    assert np.array_equal(live.error, replay.error) and np.array_equal(live.weights, replay.weights)


def _arrays(rec):
    return {k: np.array(getattr(rec, k)) for k in ("time", "gyro", "star_body", "star_inertial", "star_mask")}


def test_bad_files_name_row_and_column(recording, tmp_path):
    a = _arrays(recording)
    a["gyro"][2, 7, 1] = np.nan
    with pytest.raises(ValueError, match=r"'gyro' is not finite at trajectory 2, row 7, entry \(1,\)"):
        Recording(**a)
    a = _arrays(recording)
    a["time"][12] = a["time"][11]
    with pytest.raises(ValueError, match="'time' is not strictly increasing at row 12"):
        Recording(**a)
    a = _arrays(recording)
    b, t, m = np.argwhere(a["star_mask"])[0]
    a["star_body"][b, t, m] *= 1.1
    with pytest.raises(ValueError, match=rf"'star_body' star {m} at trajectory {b}, row {t} is not a unit vector"):
        Recording(**a)
    a = _arrays(recording)
    a["star_inertial"][b, t, m] *= 1 + 1e-5
    with pytest.warns(UserWarning, match="normalised"):
        fixed = Recording(**a)
    assert abs(np.linalg.norm(fixed.star_inertial[b, t, m]) - 1) < 1e-15
    a = _arrays(recording)
    del a["star_mask"]
    np.savez(tmp_path / "missing.npz", **a)
    with pytest.raises(ValueError, match="missing column"):
        Recording.load(tmp_path / "missing.npz")


def test_replay_needs_truth(recording):
    a = _arrays(recording)
    with pytest.raises(ValueError, match="truth"):
        RecordingEnv(Recording(**a))


def test_cli_simulate_then_run_on_the_file(tmp_path):
    import json

    from agsf_torch.experiments import cli
    from agsf_torch.experiments.config import load_config
    from agsf_torch.experiments.experiment import make_env, run_experiment

    cfg = load_config("case1", ["runs=6", "duration=3.0", "compile=false", 'filters=["EKF", "GSF"]'])
    path = record_environment(make_env(cfg), cfg.num_steps, cfg.seed).save(tmp_path / "rec.npz")
    args = ["run", "case1", "--recording", str(path), "--quiet", "--out", str(tmp_path / "replay")]
    args += sum([["--set", s] for s in ("runs=6", "duration=3.0", "compile=false", 'filters=["EKF", "GSF"]')], [])
    assert cli.main(args) == 0
    live = run_experiment(cfg, tmp_path / "live", progress=False)
    replay = json.loads((tmp_path / "replay" / "summary.json").read_text())
    assert replay["filters"]["GSF"]["rms_deg"] == live["filters"]["GSF"]["rms_deg"]
    assert cli.main(["simulate", "--runs", "3", "--steps", "20", "--out", str(tmp_path / "sim")]) == 0
    assert Recording.load(tmp_path / "sim" / "recording.npz").num_samples == 21
    assert cli.main(args[:4] + ["--set", "runs=7", "--out", str(tmp_path / "x")]) == 2  # shape mismatch named


def test_gyro_valid_column_round_trips_replays_and_is_validated(tmp_path):
    faults = [{"kind": "gyro_dropout", "start": 1.0, "end": 1.5}]
    live_env = envs.StarTrackerAttitudeVectorEnv(num_envs=4, max_steps=40, faults=faults)
    rec = record_environment(envs.StarTrackerAttitudeVectorEnv(num_envs=4, max_steps=40, faults=faults), 30, seed=5)
    assert rec.gyro_valid.shape == (4, 31) and rec.gyro_valid.dtype == np.bool_
    assert (~rec.gyro_valid).any(0).tolist() == [10 <= k < 15 for k in range(31)]
    back = Recording.load(rec.save(tmp_path / "faulty.npz"))
    assert np.array_equal(back.gyro_valid, rec.gyro_valid)
    live, replay = _run(live_env), _run(RecordingEnv(back))
    assert np.array_equal(live.error, replay.error)
    assert replay.extra["gyro_held"].sum() == 4 * 5
    a = _arrays(rec)
    with pytest.raises(ValueError, match=r"column 'gyro_valid' must be boolean"):
        Recording(**a, gyro_valid=rec.gyro_valid.astype(np.int8))
    with pytest.raises(ValueError, match=r"column 'gyro_valid' must have shape \[4, 31\]"):
        Recording(**a, gyro_valid=rec.gyro_valid[:, :30])
    # without the column every sample counts as valid
    assert _run(RecordingEnv(Recording(**a, truth_mrp=rec.truth_mrp, truth_bias=rec.truth_bias))).extra["gyro_held"].sum() == 0
