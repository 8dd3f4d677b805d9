"""`agsf diagnose` passes a matched filter and flags a mis-modelled one; `agsf learn` end to end."""

from __future__ import annotations

import json
import math

from agsf_torch.experiments import cli
from tests.helpers import EAGER, assert_statistic

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
    assert "larger than the filter expects" in capsys.readouterr().out


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
    import numpy as np

    from agsf_torch.consistency import consistency_checks

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
    from agsf_torch.experiments.config import load_config
    from agsf_torch.experiments.factories import make_env
    from agsf_torch.experiments.recorded import record_environment

    small = ["runs=8", "duration=6.0", "update_iterations=3", 'filters=["EKF"]', *EAGER]
    args = [*sum([["--set", s] for s in small], []), "--quiet"]
    cfg = load_config("case1", small)
    path = tmp_path / "logs.npz"
    record_environment(make_env(cfg), cfg.num_steps, seed=cfg.seed).save(path)
    live = cli.main(["diagnose", "case1", "--out", str(tmp_path / "live"), *args])
    replay = cli.main(["diagnose", "case1", "--recording", str(path), "--out", str(tmp_path / "replay"), *args])
    assert replay == live
    assert (tmp_path / "replay" / "diagnose.json").read_text() == (tmp_path / "live" / "diagnose.json").read_text()
