"""`agsf diagnose` passes a matched filter and flags a mis-modelled one, its checks' bands simultaneous (a
consistent filter fails some check at most 5 % of the time); `agsf learn` end to end."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.special import ndtri

from agsf_torch.consistency import (
    chi2_band,
    consistency_check_arrays,
    consistency_checks,
    format_report,
    nis_per_expected,
)
from agsf_torch.experiments.cli import main as cli
from tests.helpers import EAGER, assert_statistic, assert_within, relative_bound

SMALL = ["runs=48", "duration=20.0", "update_iterations=3", 'filters=["EKF"]', *EAGER]


def test_diagnose_passes_the_matched_and_flags_the_mis_modelled(tmp_path, capsys):
    assert (
        cli.main(
            ["diagnose", "case1", "--quiet", "--out", str(tmp_path / "ok"), *sum([["--set", s] for s in SMALL], [])]
        )
        == 0
    )
    ok = json.loads((tmp_path / "ok" / "diagnose.json").read_text())
    assert ok["passed"]
    # star noise twice what the filter assumes
    bad_args = [*sum([["--set", s] for s in SMALL], []), "--set", "filter_sigma_s_scale=0.5"]
    assert cli.main(["diagnose", "case1", "--quiet", "--out", str(tmp_path / "bad"), *bad_args]) == 1
    bad = json.loads((tmp_path / "bad" / "diagnose.json").read_text())
    failed = {c["name"] for c in bad["filters"]["EKF"] if not c["passed"]}
    assert "nis" in failed
    out = capsys.readouterr().out
    assert "larger than the filter expects" in out
    assert "the 3 bands are simultaneous, each at level 1.67 % (Bonferroni)" in out
    assert "a consistent filter fails some check at most 5 % of the time" in out
    levels = [c["level"] for c in ok["filters"]["EKF"] + bad["filters"]["EKF"]]
    assert_within(levels, 0.05 / 3, 1e-16, "each check's level: 5 %/3 (1 − 0.95 rounded, divided)")


def test_learn_command_flags_the_configured_gyro_noise(tmp_path, capsys):
    args = [
        "--set",
        "runs=16",
        "--set",
        "duration=15.0",
        "--set",
        "star_period=5.0",
        "--set",
        "sigma_v=2e-5",
        "--set",
        "filter_sigma_v_scale=0.5",
        "--set",
        "update_iterations=3",
    ]
    assert cli.main(["learn", "case1", "--learn", "sigma_v", "--out", str(tmp_path / "l"), *args]) == 0
    res = json.loads((tmp_path / "l" / "learn.json").read_text())
    # the maximum-likelihood log σ_v is asymptotically normal about the truth, its standard error the inverse
    # Fisher information's, which the 95 % interval exp(log σ̂ ± 1.96 se) reports (the curvature of −ℓ)
    lo, hi = res["interval"]["sigma_v"]
    se = math.log(hi / lo) / (2 * 1.959963984540054)
    learned = math.log(res["learned"]["sigma_v"])
    assert_statistic(learned, math.log(2e-5), se, "learned log σ_v", false_failure=1e-6)
    assert res["inside"]["sigma_v"] is False
    out = capsys.readouterr().out
    assert "mis-modelled" in out
    # the report shows 5 significant digits of the exact values learn.json keeps
    line = f"sigma_v: learned {res['learned']['sigma_v']:.5g}, 95 % interval ({lo:.5g}, {hi:.5g}), configured 1e-05 — "
    assert line in out


def test_whiteness_check_on_synthetic_innovations():
    rng = np.random.default_rng(0)
    T, B, dof = 200, 20, 15
    k = 10.0  # expected NIS = 2/3 · 15
    white = rng.chisquare(k, size=(T, B))
    e = np.zeros((T, B))
    for t in range(1, T):  # AR(1), φ = 0.8, on the standardised scale
        e[t] = 0.8 * e[t - 1] + 0.6 * rng.normal(size=B)
    correlated = k + np.sqrt(2 * k) * e
    dofs = np.full((T, B), float(dof))
    by_name = lambda cs: {c.name: c for c in cs}  # noqa: E731
    w = by_name(consistency_checks(nees=None, state_dim=3, nis=white, nis_dof=dofs))
    c = by_name(consistency_checks(nees=None, state_dim=3, nis=correlated, nis_dof=dofs))
    assert w["whiteness"].passed and w["nis"].passed
    assert not c["whiteness"].passed and c["whiteness"].value > 0.5


def test_diagnose_judges_a_recording_as_the_live_run_it_records(tmp_path, capsys):
    """``agsf diagnose --recording`` replays the file as ``agsf run --recording`` does: a recording of the
    configuration's own simulation gets the live run's verdict, number for number."""
    from agsf_torch.experiments.config.factories import make_env
    from agsf_torch.experiments.config.loader import load_config
    from agsf_torch.experiments.run.recorded import record_environment

    small = ["runs=8", "duration=6.0", "update_iterations=3", 'filters=["EKF"]', *EAGER]
    args = [*sum([["--set", s] for s in small], []), "--quiet"]
    cfg = load_config("case1", small)
    path = tmp_path / "logs.npz"
    record_environment(make_env(cfg), cfg.num_steps, seed=cfg.seed).save(path)
    live = cli.main(["diagnose", "case1", "--out", str(tmp_path / "live"), *args])
    replay = cli.main(["diagnose", "case1", "--recording", str(path), "--out", str(tmp_path / "replay"), *args])
    assert replay == live
    assert (tmp_path / "replay" / "diagnose.json").read_text() == (tmp_path / "live" / "diagnose.json").read_text()


@pytest.mark.parametrize("truth", [True, False], ids=["with the truth", "without"])
def test_each_band_is_at_the_familys_level_over_the_checks_made(truth):
    """Bonferroni: with the truth the 3 checks are each at level 5 %/3, without it the 2 at 5 %/2 — the NEES and NIS
    χ² bands at that confidence, the whiteness bound the normal quantile Φ⁻¹(1 − level/2)/√pairs; not familywise,
    each at 5 % (the whiteness bound 1.96/√pairs)."""
    rng = np.random.default_rng(3)
    T, B = 12, 5
    dof = np.full((T, B), 15.0)
    nis = rng.chisquare(10.0, size=(T, B))
    nees = rng.chisquare(3.0, size=(T, B)) if truth else None
    pairs = (T - 1) * B
    for familywise, level in ((True, 0.05 / (3 if truth else 2)), (False, 0.05)):
        checks = {
            c.name: c for c in consistency_checks(nees=nees, state_dim=3, nis=nis, nis_dof=dof, familywise=familywise)
        }
        assert list(checks) == (["nees"] if truth else []) + ["nis", "whiteness"]
        assert_within([c.level for c in checks.values()], level, 1e-16, "each check's level (1 − 0.95 rounded)")
        want = {
            "nis": nis_per_expected(nis, dof, confidence=1.0 - level)[1],
            "whiteness": (-ndtri(1.0 - level / 2) / math.sqrt(pairs), ndtri(1.0 - level / 2) / math.sqrt(pairs)),
        }
        if truth:
            want["nees"] = chi2_band(3, B, confidence=1.0 - level)
        for name, band in want.items():
            band = np.array(band)
            # the same quantile functions at the same probability: a rounding of the level at most
            assert_within(checks[name].band, band, relative_bound(band, 1e-12, 0.0), f"{name} band at {level:.4g}")
    report = format_report("EKF", consistency_checks(nees=nees, state_dim=3, nis=nis, nis_dof=dof))
    assert f"the {3 if truth else 2} bands are simultaneous" in report and "at most 5 % of the time" in report


def test_a_consistent_filter_fails_some_check_at_most_five_percent_of_the_time():
    """Synthetic consistent data sets (NEES χ²(3) at one step, white χ²(10) NIS at 20 frames of 4 runs): the NEES
    and NIS checks, exact χ² bands, each fail at their level 5 %/3; the whiteness check at most at it (the
    self-normalised autocorrelation of 20 frames has lighter tails than the normal); so the overall verdict fails
    at most 5 % — where with each check at 5 % it fails far more often (about 1 − 0.95² plus the whiteness')."""
    rng = np.random.default_rng(11)
    D, T, B = 20000, 20, 4
    nees = rng.chisquare(3.0, size=(D, 1, B))
    dof = np.full((D, T, B), 15.0)
    nis = rng.chisquare(10.0, size=(D, T, B))

    def rates(familywise):
        checks = consistency_check_arrays(nees=nees, state_dim=3, nis=nis, nis_dof=dof, familywise=familywise)
        assert all(c.made.all() for c in checks.values())
        failed = {name: ~c.passed for name, c in checks.items()}
        return {name: f.mean() for name, f in failed.items()} | {"any": np.any(list(failed.values()), 0).mean()}

    def se(p):  # a binomial proportion's standard error over the D data sets
        return math.sqrt(p * (1 - p) / D)

    level, alpha = 0.05 / 3, 0.05
    r = rates(True)
    for name in ("nees", "nis"):
        assert_statistic(r[name], level, se(level), f"{name} check's false-alarm rate", false_failure=1e-6)
    # one-sided: only rates above the bound are evidence against it
    excess = [max(r["whiteness"] - level, 0.0), max(r["any"] - alpha, 0.0)]
    assert_statistic(excess, 0.0, [se(level), se(alpha)], "whiteness, overall above their bounds", false_failure=1e-6)
    # each at 5 %: the NEES and NIS alone, independent here, fail 1 − 0.95² = 9.75 % of the data sets
    apart = rates(False)["any"]
    shortfall = max(1 - 0.95**2 - apart, 0.0)
    assert_statistic(shortfall, 0.0, se(0.0975), "overall rate of 5 % checks below 9.75 %", false_failure=1e-6)
