"""The soak harness (short runs here; the one-hour soaks are marked slow)."""

from __future__ import annotations

import json

import pytest

from agsf_torch.experiments.cli.main import main
from agsf_torch.experiments.studies.soak import run_soak, soak_config, soak_verdict
from tests.helpers import assert_within, relative_bound


def _report_times(got: list, want: list) -> None:
    """The simulated times of the reports: steps × Δt, to pytest.approx's tolerance (1e-6 relative, 1e-12)."""
    assert len(got) == len(want)
    assert_within(got, want, relative_bound(want, 1e-6, 1e-12), "report times (s)")


def test_short_soak_rows_and_verdict(tmp_path):
    cfg = soak_config("GSF", runs=8, duration=30.0, components=2)
    rows = run_soak(cfg, tmp_path, report_every=10.0)
    _report_times([r["time_s"] for r in rows], [10.0, 20.0, 30.0])
    _report_times(
        [json.loads(line)["time_s"] for line in (tmp_path / "soak.jsonl").read_text().splitlines()], [10.0, 20.0, 30.0]
    )
    for r in rows:
        g = r["filters"]["GSF"]
        assert g["nonfinite"] == 0 and g["min_eig_ratio"] > 0 and len(g["inside_3sigma"]) == 6
        assert r["rss_mb"] > 0
    v = soak_verdict(rows, warmup=10.0)
    assert v["filters"]["GSF"]["nonfinite"] == 0 and v["memory_flat"]
    assert min(v["filters"]["GSF"]["inside_3sigma"]) > 0.9


def test_verdict_fails_an_overconfident_filter():
    # the filters assume a fifth of the star noise: errors leave their 3σ bounds
    rows = run_soak(
        soak_config("GSF", runs=8, duration=20.0, components=2, filter_sigma_s_scale=0.2), report_every=10.0
    )
    v = soak_verdict(rows, warmup=5.0)
    assert not v["passed"] and not v["filters"]["GSF"]["passed"]
    assert min(v["filters"]["GSF"]["inside_3sigma"]) < 0.9


def test_verdict_flags_memory_growth_and_bad_arguments():
    row = lambda t, mb: {
        "time_s": t,
        "rss_mb": mb,
        "filters": {
            "GSF": {  # noqa: E731
                "rms_arcsec": 1.0,
                "mean_nees": 6.0,
                "inside_3sigma": [1.0] * 6,
                "nonfinite": 0,
                "min_eig_ratio": 1e-3,
            }
        },
    }
    v = soak_verdict([row(60, 500), row(120, 500), row(180, 700)], warmup=60.0)
    assert v["rss_growth_mb"] == 200 and not v["memory_flat"] and not v["passed"]
    assert soak_verdict([row(60, 500), row(120, 500), row(180, 510)], warmup=60.0)["passed"]
    with pytest.raises(ValueError, match="no report after the warm-up"):
        soak_verdict([row(60, 500)], warmup=60.0)
    with pytest.raises(ValueError, match="report_every must be a positive multiple of dt"):
        run_soak(soak_config("GSF", runs=2, duration=1.0), report_every=0.05)


def test_cli_soak_writes_the_verdict(tmp_path, capsys):
    code = main(
        [
            "soak",
            "--runs",
            "4",
            "--duration",
            "4",
            "--report-every",
            "2",
            "--warmup",
            "2",
            "--set",
            "components=2",
            "--out",
            str(tmp_path),
            "--quiet",
        ]
    )
    verdict = json.loads((tmp_path / "verdict.json").read_text())
    assert code == (0 if verdict["passed"] else 1)
    assert verdict["filters"]["GSF"]["nonfinite"] == 0
    rows = [json.loads(line) for line in (tmp_path / "soak.jsonl").read_text().splitlines()]
    _report_times([r["time_s"] for r in rows], [2.0, 4.0])
    marker = json.loads((tmp_path / "experiment.json").read_text())
    assert marker["kind"] == "soak" and marker["config"]["runs"] == 4 and marker["config"]["components"] == 2


@pytest.mark.slow
def test_one_hour_soak_classic_6_state():
    """One simulated hour at 10 Hz, 256 runs, 6-state GSF with 5 components (15.5 min measured)."""
    v = soak_verdict(run_soak(soak_config("GSF")))
    assert v["passed"], v


@pytest.mark.slow
def test_soak_adaptive_6_state_ten_minutes():
    """256 runs, 6-state AGSF (5 components), weights adapted once per second, ten simulated
    minutes (69 min measured, sharing the machine).  The full hour with adaptation at every step (``agsf soak --filter AGSF``)
    costs ~2.6 s per step at B = 256 on 2 cores: ~26 h."""
    v = soak_verdict(run_soak(soak_config("AGSF", duration=600.0, cadence=10)))
    assert v["passed"], v
