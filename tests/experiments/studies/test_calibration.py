"""``agsf calibrate``: the study's rates, intervals and report, and its refusals."""

from __future__ import annotations

import json

import pytest

from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.studies.calibration import (
    MIS_SCALINGS,
    QUICK_STUDY,
    calibrate_setting,
    settings_named,
)
from agsf_torch.experiments.studies.calibration_report import calibration_markdown
from tests.experiments.cli.test_cli_failures import _agsf, _assert_refused


@pytest.fixture(scope="module")
def quick_result():
    """The quick study's σ_s, σ_v setting on 4 data sets."""
    return calibrate_setting(load_config("case1"), QUICK_STUDY[0], datasets=4, seed=3)


def test_a_setting_reports_every_rate_over_its_judged_data_sets(quick_result):
    r = quick_result
    assert r["datasets"] == 4 and r["learn"] == ["sigma_s", "sigma_v"] and r["converged"]["datasets"] == 4
    names = [c["name"] for c in r["coordinates"]]
    assert names == ["sigma_s", "sigma_v"]
    for c in r["coordinates"]:
        n = c["judged"]
        assert c["identified"]["datasets"] == 4 and 0 <= n <= c["identified"]["count"]
        assert c["coverage"]["datasets"] == n and c["false_alarm"]["datasets"] == n
        # for a scalar, a false alarm is a miss of the interval
        assert c["coverage"]["count"] + c["false_alarm"]["count"] == n
        assert set(c["detection"]) == {f"{f:.4g}" for s in MIS_SCALINGS for f in (s, 1 / s)}
        for rate in (c["coverage"], c["false_alarm"], *c["detection"].values()):
            if rate["datasets"]:
                assert rate["low"] <= rate["rate"] <= rate["high"]
    assert set(r["baseline"]) == {"sigma_s", "sigma_v"}
    json.dumps(r)  # plain JSON


def test_the_report_tabulates_each_setting(quick_result):
    text = calibration_markdown([quick_result])
    assert "| σ_s, σ_v · 10 s | log sigma_s |" in text and "| σ_s, σ_v · 10 s | sigma_v |" in text
    assert "autocovariance least squares" in text


def test_settings_are_named_by_their_labels():
    assert settings_named(["bias · 30 s"], QUICK_STUDY) == [QUICK_STUDY[1]]
    with pytest.raises(ValueError, match=r"unknown calibration setting\(s\) \['nope'\]"):
        settings_named(["nope"], QUICK_STUDY)


@pytest.mark.parametrize(
    "extra, names",
    [(["--datasets", "1"], "--datasets must be at least 2"), (["--setting", "nope"], "unknown calibration setting")],
)
def test_bad_requests_are_refused_before_anything_is_created(tmp_path, extra, names):
    _assert_refused(["calibrate", "case1", "--quick", *extra, "--out", str(tmp_path / "out")], tmp_path, names)


@pytest.mark.slow
def test_the_command_writes_its_tables_figure_and_data(tmp_path):
    out = tmp_path / "cal"
    code, err = _agsf(["calibrate", "--quick", "--datasets", "3", "--workers", "1", "--quiet", "--out", str(out)])
    assert code == 0, err
    data = json.loads((out / "calibration.json").read_text())
    assert [r["label"] for r in data["results"]] == [s.label for s in QUICK_STUDY]
    assert (out / "calibration.md").read_text().startswith("### Estimates")
    assert (out / "calibration.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
