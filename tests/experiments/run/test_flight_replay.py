"""A recording without the truth (flight data): the filters start at its initial estimate and nothing is scored."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from agsf_torch.attitude.recordings import Recording
from agsf_torch.experiments.cli import main as cli
from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.run.experiment import make_env, prior_covariance
from agsf_torch.experiments.run.recorded import record_environment
from agsf_torch.filter_loop import PRIOR_SEED_OFFSET, sample_prior
from tests.helpers import EAGER, assert_within, relative_bound

KEYS = ["runs=3", "duration=3.0", "update_iterations=2", "sigma_u=0.0", *EAGER]  # sigma_u = 0: a constant bias
SENSORS = ("time", "gyro", "star_body", "star_inertial", "star_mask")


@pytest.fixture(scope="module", params=["6 states", "3 states"])
def recorded(request, tmp_path_factory):
    """The configuration's keys, a simulated recording with its truth and the same without it, starting where
    the simulated run's prior draw starts (with 3 states, the bias known: the truth's, constant)."""
    keys = KEYS + [f"estimate_bias={'true' if request.param == '6 states' else 'false'}"]
    cfg = load_config("case1", keys)
    rec = record_environment(make_env(cfg), cfg.num_steps, cfg.seed)
    truth0 = torch.cat((torch.as_tensor(rec.truth_mrp[:, 0]), torch.as_tensor(rec.truth_bias[:, 0])), -1)
    gen = torch.Generator().manual_seed(cfg.seed + PRIOR_SEED_OFFSET)  # the runner's draw of the prior mean
    n = 6 if cfg.estimate_bias else 3
    mean0 = sample_prior(truth0[:, :n], prior_covariance(cfg), gen).numpy()
    bias0 = mean0[:, 3:] if cfg.estimate_bias else rec.truth_bias[:, 0]
    assert np.array_equal(rec.truth_bias, np.broadcast_to(rec.truth_bias[:, :1], rec.truth_bias.shape))
    folder = tmp_path_factory.mktemp("flight")
    with_truth = rec.save(folder / "sim.npz")
    flight = Recording(**{k: getattr(rec, k) for k in SENSORS}, initial_mrp=mean0[:, :3], initial_bias=bias0).save(
        folder / "flight.npz"
    )
    return keys, with_truth, flight


def _run(tmp_path, name, path, keys, command="run"):
    argv = [command, "case1", *sum((["--set", k] for k in keys), []), "--recording", str(path)]
    code = cli.main([*argv, "--out", str(tmp_path / name), "--quiet"])
    return code, np.load(tmp_path / name / "runs.npz"), json.loads((tmp_path / name / "summary.json").read_text())


def test_a_replay_without_truth_gives_the_estimates_of_the_one_with_it(recorded, tmp_path, capsys):
    """Started at the same prior mean, the filters see the same data: every array they produce is equal bit for
    bit; what needs the truth (errors, NEES, the RMS and its figures) is absent, and the summary says so."""
    keys, with_truth, flight = recorded
    code_t, data_t, _ = _run(tmp_path, "truth", with_truth, keys)
    code_f, data_f, summary = _run(tmp_path, "flight", flight, keys)
    assert code_t == code_f == 0
    scored = {"prior_error_angle"} | {k for k in data_t.files if k.split("/")[-1] in ("error_angle", "error", "nees")}
    assert scored and set(data_f.files) == set(data_t.files) - scored
    for key in set(data_f.files) - {"units"}:
        assert np.array_equal(data_f[key], data_t[key], equal_nan=True), key
    assert summary["scored_against_truth"] is False and "nees_band_95" not in summary
    for name, f in summary["filters"].items():
        assert "rms_deg" not in f and "time_averaged_nees" not in f and "between_frames" not in f
        assert f["nis_per_expected"] > 0 and f["estimate_run0"] == data_f[f"{name}/estimate"][0].tolist()
    assert not (tmp_path / "flight" / "rms.png").exists() and not (tmp_path / "flight" / "axes.png").exists()
    assert (tmp_path / "flight" / "weights.png").exists() and (tmp_path / "truth" / "rms.png").exists()
    assert "no truth in the recording, so no errors or NEES" in capsys.readouterr().out


def test_diagnose_without_truth_judges_the_innovations_alone(recorded, tmp_path):
    keys, with_truth, flight = recorded
    _run(tmp_path, "truth", with_truth, keys, "diagnose")
    _run(tmp_path, "flight", flight, keys, "diagnose")
    judged = {
        which: json.loads((tmp_path / which / "diagnose.json").read_text())["filters"] for which in ("truth", "flight")
    }
    for name, checks in judged["flight"].items():
        with_truth = [c for c in judged["truth"][name] if c["name"] != "nees"]
        assert [c["name"] for c in checks] == [c["name"] for c in with_truth]
        assert [c["value"] for c in checks] == [c["value"] for c in with_truth]  # the same innovations
        # Bonferroni over the checks made: 2 without the truth at 5 %/2 each, 3 with it at 5 %/3 (wider bands)
        assert_within([c["level"] for c in checks], 0.05 / 2, 1e-16, "each check's level without the truth")
        assert_within([c["level"] for c in with_truth], 0.05 / 3, 1e-16, "each check's level with the truth")
        for c, t in zip(checks, with_truth, strict=True):
            assert t["band"][0] < c["band"][0] and c["band"][1] < t["band"][1], c["name"]


def test_initial_estimate_columns_are_validated_naming_them(recorded):
    _, _, flight = recorded
    rec = Recording.load(flight)
    base = {k: getattr(rec, k) for k in SENSORS}
    with pytest.raises(ValueError, match=r"column 'initial_mrp' must have shape \[3, 3\], got \(2, 3\)"):
        Recording(**base, initial_mrp=rec.initial_mrp[:2])
    bad = rec.initial_mrp.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="column 'initial_mrp' is not finite at trajectory 1"):
        Recording(**base, initial_mrp=bad)
    with pytest.raises(ValueError, match="'initial_bias' needs 'initial_mrp'"):
        Recording(**base, initial_bias=rec.initial_bias)
    assert Recording.load(flight).content_digest() == rec.content_digest()  # the columns round-trip
    assert Recording(**base, initial_mrp=rec.initial_mrp).content_digest() != rec.content_digest()


def test_a_log_that_starts_at_a_star_frame_needs_no_initial_estimate(tmp_path):
    """Without the truth and ``initial_mrp`` the filters start at row 0's star fix (here: scipy's solution of the
    same frame, an independent one) with a zero bias; a row 0 without a determining frame is refused, naming it."""
    from scipy.spatial.transform import Rotation

    from agsf_torch.experiments.run.recorded import RecordingEnv
    from agsf_torch.rotations import mrp_to_dcm

    keys = KEYS + ["estimate_bias=true"]
    cfg = load_config("case1", keys)
    longer = load_config("case1", keys + ["duration=4.0"])  # 10 steps more: the log is cut at the first frame
    rec = record_environment(make_env(longer), longer.num_steps, cfg.seed)
    first = int(np.argmax(rec.star_frames()))  # the first star frame (t = 1 s)
    cut = Recording(**{k: getattr(rec, k)[first:] if k == "time" else getattr(rec, k)[:, first:] for k in SENSORS})
    _, info = RecordingEnv(cut).reset()
    assert np.array_equal(info["initial_bias"].numpy(), np.zeros((cfg.runs, 3)))
    C = mrp_to_dcm(info["initial_mrp"]).numpy()
    for b in range(cfg.runs):
        m = cut.star_mask[b, 0]
        theirs = Rotation.align_vectors(cut.star_body[b, 0][m], cut.star_inertial[b, 0][m])[0].as_matrix()
        # assert_allclose's rtol=1e-7 (numpy's default) beside atol=1e-12, as before
        assert_within(C[b], theirs, relative_bound(theirs, 1e-7, 1e-12), "initial attitude matrix against scipy's")
    code, _, summary = _run(tmp_path, "cut", cut.save(tmp_path / "cut.npz"), keys)
    assert code == 0 and summary["scored_against_truth"] is False
    uncut = Recording(**{k: getattr(rec, k) for k in SENSORS}).save(tmp_path / "uncut.npz")  # row 0: no frame
    with pytest.raises(ValueError, match="row 0 of trajectory 0 holds no star frame that determines an attitude"):
        RecordingEnv(Recording.load(uncut))


def test_diagnose_with_nothing_to_judge_does_not_pass(recorded, tmp_path):
    """Without the truth and without a star frame in the run there is no NEES and no NIS: the verdict is a
    failure that says so, not a pass of zero checks."""
    keys, _, flight = recorded
    short = [k for k in keys if not k.startswith("duration")] + ["duration=0.5"]  # the first frame is at 1 s
    code, _, _ = _run(tmp_path, "short", flight, short, "diagnose")
    verdict = json.loads((tmp_path / "short" / "diagnose.json").read_text())
    assert code == 1 and verdict["passed"] is False
    for checks in verdict["filters"].values():
        assert [c["name"] for c in checks] == ["nothing"] and "nothing to judge" in checks[0]["text"]
