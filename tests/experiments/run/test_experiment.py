"""An experiment end to end: outputs exist and agree; the summary equals an independent
recomputation from the saved per-run data; sweeps resume; folders are not overwritten."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import t as student_t

from agsf_torch.experiments.cli import main as cli
from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.run.experiment import OutputConflict, run_experiment
from agsf_torch.experiments.sweep import parse_grid, run_sweep
from tests.helpers import EAGER, assert_within, relative_bound

SMALL = ["runs=12", "duration=3.0", "star_period=1.0", *EAGER, "components=3"]


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    out = tmp_path_factory.mktemp("exp") / "case"
    cfg = load_config("case1", SMALL)
    summary = run_experiment(cfg, out, progress=False)
    return cfg, out, summary


def test_outputs_exist_and_agree(experiment):
    cfg, out, summary = experiment
    for name in ("summary.json", "runs.npz", "rms.png", "axes.png", "weights.png", "fpke.png", "experiment.json"):
        assert (out / name).stat().st_size > 0, name
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["filters"]["AGSF"]["rms_deg"] == summary["filters"]["AGSF"]["rms_deg"]
    from tests.experiments.report.test_tensorboard import assert_recorded, scalars_view

    view = scalars_view(out / "tensorboard")
    assert set(view) == set(cfg.filters)  # one run per filter
    for name in cfg.filters:
        events = view[name]["rms_deg"]
        assert len(events) == cfg.num_steps
        assert_recorded([e.value for e in events], summary["filters"][name]["rms_deg"], f"{name} RMS error (deg)")
    assert {"fpke/error_before", "fpke/error_after", "fpke/ratio"} <= set(view["AGSF"])
    assert list((out / "tensorboard" / "AGSF").glob("events.out.tfevents.*"))  # the weight histogram's run


def test_runs_file_is_batch_first_with_units_and_covariances(experiment):
    cfg, out, summary = experiment
    data = np.load(out / "runs.npz")
    B, T, n = cfg.runs, cfg.num_steps, 3
    units = json.loads(str(data["units"]))
    assert data["time"].shape == data["star_frame"].shape == (T,) and units["time"] == "s"
    for name in cfg.filters:
        assert data[f"{name}/error_angle"].shape == data[f"{name}/nees"].shape == (B, T)
        assert data[f"{name}/error"].shape == data[f"{name}/sigma"].shape == (B, T, n)
        cov = data[f"{name}/cov"]
        assert cov.shape == (B, T, n, n) and (np.linalg.eigvalsh(cov) > 0).all()
        # the attitude error is the rotation-error vector: its norm is 2 sin(θ/2) of the error angle (both from the
        # same δq, |δq_v| and 2·atan(|δq_v|/|δq_4|): relative, no terms cancel between them; they vanish together)
        chord = 2 * np.sin(data[f"{name}/error_angle"] / 2)
        assert_within(
            np.linalg.norm(data[f"{name}/error"], axis=-1), chord, relative_bound(chord, 1e-9, 0.0), "|error vector|"
        )
        assert np.isfinite(data[f"{name}/nees"]).all()
    assert "rad" in units["error"] and "MRP" in units["cov"] and units["weight_entropy"] == "nat"


def test_summary_matches_independent_recomputation(experiment):
    cfg, out, summary = experiment
    data = np.load(out / "runs.npz")
    frames = data["star_frame"]
    B = cfg.runs
    per_run = {}
    # RMS values, NEES and NIS means are sums of nonnegative terms in another order: a few ε relative (no terms
    # cancel; they vanish only where every term does, on both sides).  pytest.approx's absolute 1e-12 beside
    # rel=1e-12 was up to 3e5 times the relative bound at these magnitudes (σ ~3e-6 rad): not kept.

    def same(got, want, what):
        assert_within(got, want, relative_bound(want, 1e-12, 0.0), f"{name} {what}")

    for name in cfg.filters:
        theta = data[f"{name}/error_angle"]
        # RMS over runs at each time, by explicit loops
        for k in (0, len(frames) // 2, len(frames) - 1):
            expect = np.degrees(np.sqrt(sum(theta[b, k] ** 2 for b in range(B)) / B))
            same(summary["filters"][name]["rms_deg"][k], expect, f"RMS error (deg) at step {k}")
        # between frames: after the first star frame, off frames; before the first frame: the prior's stretch
        first = next(k for k in range(len(frames)) if frames[k])
        r, r_prior = [], []
        for b in range(B):
            vals = [theta[b, k] ** 2 for k in range(first + 1, len(frames)) if not frames[k]]
            r.append(np.degrees(np.sqrt(np.mean(vals))))
            r_prior.append(np.degrees(np.sqrt(np.mean([theta[b, k] ** 2 for k in range(first)]))))
        per_run[name] = np.array(r)
        same(summary["filters"][name]["between_frames"]["mean_rms_deg"], np.mean(r), "mean RMS between frames")
        got_prior = summary["filters"][name]["before_first_frame"]["mean_rms_deg"]
        same(got_prior, np.mean(r_prior), "mean RMS before the first frame")
        err, sig = data[f"{name}/error"], data[f"{name}/sigma"]  # [B, T, n]
        for k in (0, len(frames) - 1):
            for a in range(err.shape[-1]):
                want_err = np.sqrt(sum(err[b, k, a] ** 2 for b in range(B)) / B)
                want_sig = np.sqrt(sum(sig[b, k, a] ** 2 for b in range(B)) / B)
                same(summary["filters"][name]["rms_error_axes_rad"][k][a], want_err, f"RMS error {k}, {a}")
                same(summary["filters"][name]["rms_sigma_axes_rad"][k][a], want_sig, f"RMS σ {k}, {a}")
        same(summary["filters"][name]["time_averaged_nees"], float(np.mean(data[f"{name}/nees"])), "mean NEES")
        # NIS over expectation, pooled over every update with a valid NIS: 2 per star, ⅔ of the valid entries
        nis, dof = data[f"{name}/nis"], data[f"{name}/nis_dof"]
        updates = [(b, k) for b in range(B) for k in range(len(frames)) if np.isfinite(nis[b, k]) and dof[b, k] > 0]
        assert updates and all(frames[k] for _, k in updates)
        ratio = sum(nis[b, k] for b, k in updates) / sum(2.0 * dof[b, k] / 3.0 for b, k in updates)
        same(summary["filters"][name]["nis_per_expected"], ratio, "NIS / expected")
    d = per_run["AGSF"] - per_run["GSF"]
    half = student_t.ppf(0.975, B - 1) * np.std(d, ddof=1) / np.sqrt(B)
    got = summary["agsf_minus_gsf"]["between_frames"]
    # the per-run RMS values (~0.5 deg) cancel in the differences: the absolute 1e-15 (~9 ε of them) is the floor
    want = np.array([d.mean(), d.mean() - half, d.mean() + half])
    assert_within(
        [got["mean_deg"], *got["ci95_deg"]], want, relative_bound(want, 1e-9, 1e-15), "AGSF − GSF mean and 95 % CI"
    )


def test_same_seed_same_numbers(experiment, tmp_path):
    cfg, out, summary = experiment
    again = run_experiment(cfg, tmp_path / "again", progress=False)
    assert again["filters"]["GSF"]["rms_deg"] == summary["filters"]["GSF"]["rms_deg"]


def test_output_folder_is_not_overwritten(experiment, tmp_path):
    cfg, out, summary = experiment
    with pytest.raises(OutputConflict, match="different experiment"):
        run_experiment(cfg.replace(seed=cfg.seed + 1), out, progress=False)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(OutputConflict, match="not an agsf experiment"):
        run_experiment(cfg, tmp_path / "other", progress=False)
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


def test_sweep_resumes_after_interruption(tmp_path):
    base = load_config(
        "case1",
        ["runs=4", "duration=1.0", *EAGER, "components=2", 'filters=["GSF", "AGSF"]'],
    )
    grid = parse_grid(["reg=0.1,1.0", "scaling=trace,none"])
    calls = []

    def interrupted(cfg, out, **kw):
        if len(calls) == 2:
            raise KeyboardInterrupt
        calls.append(cfg.digest())
        return run_experiment(cfg, out, **kw)

    with pytest.raises(KeyboardInterrupt):
        run_sweep(base, grid, tmp_path / "sweep", progress=False, runner=interrupted)
    lines = (tmp_path / "sweep" / "results.jsonl").read_text().splitlines()
    assert len(lines) == 2
    resumed = []

    def counting(cfg, out, **kw):
        resumed.append(cfg.digest())
        return run_experiment(cfg, out, **kw)

    rows = run_sweep(base, grid, tmp_path / "sweep", progress=False, runner=counting)
    assert len(rows) == 4 and len(resumed) == 2 and not set(resumed) & set(calls)
    assert {tuple(sorted(r["params"].items())) for r in rows} == {
        (("reg", r), ("scaling", s)) for r in (0.1, 1.0) for s in ("trace", "none")
    }
    # a different grid may not reuse the folder
    with pytest.raises(OutputConflict):
        run_sweep(base, parse_grid(["reg=0.5"]), tmp_path / "sweep", progress=False)


def test_cli_rejects_bad_config_before_work(tmp_path, capsys):
    assert cli.main(["run", "case1", "--set", "runs=-3", "--out", str(tmp_path / "x")]) == 2
    assert "'runs'" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert cli.main(["sweep", "case1", "--grid", "bogus=1,2", "--out", str(tmp_path / "y")]) == 2
    assert "bogus" in capsys.readouterr().err


def test_the_prior_error_at_t0_is_the_prior_means_against_the_truth(experiment):
    """``prior_error_angle`` is the error of every filter's estimate before its first step (the prior mean drawn
    around the truth at t = 0); the summary's ``prior_rms_deg`` is its RMS over the runs, where rms.png starts."""
    cfg, out, summary = experiment
    data = np.load(out / "runs.npz")
    prior = data["prior_error_angle"]
    assert prior.shape == (cfg.runs,) and np.isfinite(prior).all() and (prior > 0).all()
    want = np.degrees(np.sqrt(np.mean(prior**2)))  # a sum of squares: relative
    assert_within(summary["prior_rms_deg"], want, relative_bound(want, 1e-12, 0.0), "prior RMS error (deg)")
    assert json.loads(str(data["units"]))["prior_error_angle"] == "rad"
