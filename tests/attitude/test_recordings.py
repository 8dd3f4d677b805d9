"""Recorded-data format: round trip, replay equals the live environment, bad files named."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import torch

import envs
from agsf_torch.attitude.recordings import Recording
from agsf_torch.experiments.run.recorded import RecordingEnv, record_environment
from agsf_torch.experiments.run.runner import FilterSetup, run_monte_carlo
from agsf_torch.filters import GaussianSumFilter
from agsf_torch.models import AttitudeModel
from tests.helpers import EAGER, F64, assert_within


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
    assert_within(np.linalg.norm(fixed.star_inertial[b, t, m]), 1.0, 1e-15, "norm of the normalised star vector")
    np.savez(tmp_path / "off.npz", **a)  # read from a file, the warning names it
    with pytest.warns(
        UserWarning, match=r"^recording .*off\.npz: column 'star_inertial' has star vectors off unit norm"
    ):
        Recording.load(tmp_path / "off.npz")
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

    from agsf_torch.experiments.cli import main as cli
    from agsf_torch.experiments.config.loader import load_config
    from agsf_torch.experiments.run.experiment import make_env, run_experiment

    cfg = load_config("case1", ["runs=6", "duration=3.0", *EAGER, 'filters=["EKF", "GSF"]'])
    path = record_environment(make_env(cfg), cfg.num_steps, cfg.seed).save(tmp_path / "rec.npz")
    args = ["run", "case1", "--recording", str(path), "--quiet", "--out", str(tmp_path / "replay")]
    args += sum(
        [["--set", s] for s in ("runs=6", "duration=3.0", *EAGER, 'filters=["EKF", "GSF"]')],
        [],
    )
    assert cli.main(args) == 0
    live = run_experiment(cfg, tmp_path / "live", progress=False)
    replay = json.loads((tmp_path / "replay" / "summary.json").read_text())
    assert replay["filters"]["GSF"]["rms_deg"] == live["filters"]["GSF"]["rms_deg"]
    assert cli.main(["simulate", "--runs", "3", "--steps", "20", "--out", str(tmp_path / "sim")]) == 0
    assert Recording.load(tmp_path / "sim" / "recording.npz").num_samples == 21
    assert cli.main(args[:4] + ["--set", "runs=7", "--out", str(tmp_path / "x")]) == 2  # shape mismatch named


def test_a_replay_is_identified_by_the_keys_it_reads(tmp_path):
    """Keys a replay does not read (the simulation's) leave it the same experiment: a rerun into its folder
    with them changed is accepted and gives the same numbers; a key the filters read makes another experiment."""
    import json

    from agsf_torch.experiments.config.loader import REPLAY_IGNORED, load_config
    from agsf_torch.experiments.run.experiment import make_env, run_experiment
    from agsf_torch.experiments.run.outputs import OutputConflict, release_outputs

    keys = ["runs=3", "duration=2.0", *EAGER, 'filters=["GSF"]']
    cfg = load_config("case1", keys)
    ignored = ["star_period=2.0", "max_stars=3", "omega0=0.002", "fov_deg=12.0"]
    other = load_config("case1", keys + ignored)
    assert {k.split("=")[0] for k in ignored} <= set(REPLAY_IGNORED)
    assert other.digest() != cfg.digest() and other.digest(replay=True) == cfg.digest(replay=True)
    for read in ("sigma_s=2e-5", "gyro_bias_deg_per_hr=5.0"):  # the filters' noise; agsf learn's starting bias
        assert load_config("case1", keys + [read]).digest(replay=True) != cfg.digest(replay=True)
    path = record_environment(make_env(cfg), cfg.num_steps, cfg.seed).save(tmp_path / "rec.npz")
    out = tmp_path / "replay"
    first = run_experiment(cfg, out, progress=False, recording=path)
    release_outputs()
    again = run_experiment(other, out, progress=False, recording=path)  # the same experiment: accepted
    release_outputs()
    assert again["filters"]["GSF"]["rms_deg"] == first["filters"]["GSF"]["rms_deg"]
    assert json.loads((out / "experiment.json").read_text())["config"]["star_period"] == 2.0
    with pytest.raises(OutputConflict, match=r"different experiment .*differs in sigma_s: 1e-05 there, 2e-05 here;"):
        run_experiment(load_config("case1", keys + ["sigma_s=2e-5"]), out, progress=False, recording=path)


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
    assert (
        _run(RecordingEnv(Recording(**a, truth_mrp=rec.truth_mrp, truth_bias=rec.truth_bias))).extra["gyro_held"].sum()
        == 0
    )


# ------------------------------------------------------------------ column dtypes, file errors, atomic save, digest
def _small(seed: int = 0, **extra) -> dict:
    """A valid two-trajectory recording's columns (5 samples, 3 stars), built directly."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(2, 5, 3, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    cols = dict(time=np.arange(5) * 0.1, gyro=rng.normal(size=(2, 5, 3)) * 1e-3, star_body=v, star_inertial=v.copy())
    return {**cols, "star_mask": rng.random((2, 5, 3)) < 0.7, **extra}


@pytest.mark.parametrize("column", ["time", "gyro", "star_body", "star_inertial", "truth_mrp", "truth_bias"])
@pytest.mark.parametrize("dtype", [np.complex128, np.complex64, object, str, bool])
def test_non_real_columns_are_refused_naming_column_and_dtype(column, dtype):
    a = _small(truth_mrp=np.zeros((2, 5, 3)), truth_bias=np.zeros((2, 5, 3)))
    a[column] = a[column].astype(dtype)
    kind = r"<U\d+" if dtype is str else str(np.dtype(dtype))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning on the way to the error
        with pytest.raises(ValueError, match=rf"recording: column '{column}' must hold real numbers, got dtype {kind}"):
            Recording(**a)


def test_integer_columns_are_accepted_as_float64():
    a = _small()
    a["time"] = np.arange(5)
    rec = Recording(**a)
    assert rec.time.dtype == np.float64 and rec.time.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]


def _write_bytes(path, data: bytes):
    path.write_bytes(data)
    return path


def test_load_names_the_file_for_every_kind_of_bad_file(tmp_path):
    good = Recording(**_small()).save(tmp_path / "good.npz")
    raw = good.read_bytes()
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "nope.npz"))):
        Recording.load(tmp_path / "nope.npz")
    (tmp_path / "folder.npz").mkdir()
    np.save(tmp_path / "array.npy", np.zeros(3))
    cases = {
        "folder.npz": "is a directory, not an .npz archive",
        "text.npz": r"not an \.npz archive",
        "empty.npz": r"empty file, not an \.npz archive",
        "truncated.npz": r"not an \.npz archive",
        "array.npy": r"not an \.npz archive",
    }
    _write_bytes(tmp_path / "text.npz", b"time,gyro\n0.0,1.0\n")
    _write_bytes(tmp_path / "empty.npz", b"")
    _write_bytes(tmp_path / "truncated.npz", raw[: len(raw) // 2])
    for name, message in cases.items():
        with pytest.raises(ValueError, match=rf"^recording {re.escape(str(tmp_path / name))}: {message}"):
            Recording.load(tmp_path / name)


def test_load_turns_a_corrupt_archive_into_a_value_error_naming_the_file(tmp_path):
    raw = bytearray(Recording(**_small()).save(tmp_path / "good.npz").read_bytes())
    seen = set()
    for offset in range(30, len(raw) - 22, 7):  # every 7th byte of the members and the directory
        flipped = bytearray(raw)
        flipped[offset] ^= 0xFF
        path = _write_bytes(tmp_path / "flipped.npz", bytes(flipped))
        try:
            Recording.load(path)
        except ValueError as exc:
            assert str(exc).startswith(f"recording {path}: "), str(exc)
            seen.add(type(exc.__cause__).__name__ if exc.__cause__ else "ValueError")
    assert {"BadZipFile", "error"} <= seen  # CRC / header errors and zlib errors were among them


def test_load_refuses_pickled_object_columns_naming_them(tmp_path):
    a = _small()
    a["gyro"] = a["gyro"].astype(object)
    np.savez(tmp_path / "objects.npz", **a)
    with pytest.raises(
        ValueError, match=rf"^recording {re.escape(str(tmp_path / 'objects.npz'))}: column 'gyro' cannot be read"
    ):
        Recording.load(tmp_path / "objects.npz")


def test_save_is_atomic_and_returns_the_written_path(tmp_path, monkeypatch):
    rec = Recording(**_small())
    assert rec.save(tmp_path / "a.npz") == tmp_path / "a.npz"
    assert rec.save(tmp_path / "b") == tmp_path / "b.npz" and (tmp_path / "b.npz").is_file()
    before = (tmp_path / "a.npz").read_bytes()

    def interrupted(file, *args, **kwargs):
        file.write(b"PK\x03\x04 half an archive")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez_compressed", interrupted)
    with pytest.raises(KeyboardInterrupt):
        Recording(**_small(seed=1)).save(tmp_path / "a.npz")
    with pytest.raises(KeyboardInterrupt):
        Recording(**_small(seed=1)).save(tmp_path / "new.npz")
    assert (tmp_path / "a.npz").read_bytes() == before  # the old file is intact
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz"]  # no torn file, no temporary left


def test_content_digest_depends_on_the_contents_only(tmp_path):
    rec = Recording(**_small(truth_mrp=np.zeros((2, 5, 3))))
    d = rec.content_digest()
    assert isinstance(d, str) and len(d) == 16 and int(d, 16) >= 0
    one = Recording.load(rec.save(tmp_path / "one.npz"))
    (tmp_path / "sub").mkdir()
    two = Recording.load(rec.save(tmp_path / "sub" / "two.npz"))
    assert one.content_digest() == two.content_digest() == d
    assert Recording(**_small(truth_mrp=np.zeros((2, 5, 3)))).content_digest() == d  # rebuilt from equal arrays
    changed = _small(truth_mrp=np.zeros((2, 5, 3)))
    changed["gyro"][1, 3, 2] = np.nextafter(changed["gyro"][1, 3, 2], 1.0)  # one value, by one ulp
    assert Recording(**changed).content_digest() != d
    flipped = _small(truth_mrp=np.zeros((2, 5, 3)))
    flipped["star_mask"][0, 0, 0] = ~flipped["star_mask"][0, 0, 0]
    assert Recording(**flipped).content_digest() != d
    assert Recording(**_small()).content_digest() != d  # without the optional column
    moved = _small(truth_bias=np.zeros((2, 5, 3)))  # the same zeros under another column
    assert Recording(**moved).content_digest() != d
