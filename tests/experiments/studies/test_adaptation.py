"""``agsf adaptation``: the study of where adapting the weights pays, end to end on a small case."""

from __future__ import annotations

import json

import pytest

from agsf_torch.experiments.cli.main import main
from agsf_torch.experiments.studies.adaptation import STUDY_FILTERS, run_adaptation_study, scenario_config
from tests.helpers import EAGER


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("adaptation") / "study"
    summaries = run_adaptation_study(
        ["case1", "ambiguous"],
        out,
        runs=4,
        samples=128,
        overrides=["duration=2.5", *EAGER],
        progress=False,
    )
    return out, summaries


def test_every_filter_window_and_interval_is_reported(study):
    out, summaries = study
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summaries))
    for name, s in summaries.items():
        assert list(s["filters"]) == list(STUDY_FILTERS)
        assert s["reference"]["samples"] == 128 and s["reference"]["ess_min"] > 0
        for f in STUDY_FILTERS:
            for window in ("before_first_frame", "between_frames", "all"):
                w = s["filters"][f][window]
                for key in ("rms_deg", "nees", "density_score"):
                    lo, hi = w[f"{key}_ci95"]
                    assert lo <= w[key] <= hi, (name, f, window, key)
            assert len(s["filters"][f]["density_score_t"]) == len(s["time_s"]) == 25
        assert set(s["minus_gsf"]) == set(STUDY_FILTERS) - {"GSF"}


def test_before_the_first_frame_the_galerkin_filter_equals_the_gsf_in_density(study):
    """With a 7° prior the exact forecast is nearly Gaussian over one second: the Galerkin weights
    barely move (score difference ≪ the penalised filter's, which re-spreads the weights)."""
    _, summaries = study
    d = summaries["case1"]["minus_gsf"]
    gal = abs(d["AGSF-galerkin"]["before_first_frame"]["score"]["mean"])
    pen = abs(d["AGSF"]["before_first_frame"]["score"]["mean"])
    assert gal < 1e-4 and gal < 0.01 * pen


def test_files_figures_and_tensorboard(study):
    """One run per (scenario, filter) with a tag per metric, read back by TensorBoard's data provider."""
    from tests.experiments.report.test_tensorboard import assert_recorded, scalars_view

    out, summaries = study
    view = scalars_view(out / "tensorboard")
    for name in summaries:
        assert (out / f"{name}.png").stat().st_size > 10_000
        assert {f"{name}/{f}" for f in STUDY_FILTERS} | {f"{name}/reference"} == {
            r for r in view if r.startswith(f"{name}/")
        }
        assert all(set(view[f"{name}/{f}"]) == {"rms_deg", "nees", "density_score"} for f in STUDY_FILTERS)
        events = view[f"{name}/GSF"]["density_score"]
        assert [e.step for e in events][:3] == [100, 200, 300]  # time in ms
        assert_recorded(
            [e.value for e in events], summaries[name]["filters"]["GSF"]["density_score_t"], f"{name} GSF score"
        )
        assert set(view[f"{name}/reference"]) == {"ess_median"}
    assert (out / "scores.png").exists()
    assert "| ambiguous | MEKF |" in (out / "results.md").read_text()


def test_bad_input_creates_nothing(tmp_path):
    for kwargs, match in (
        ({"runs": 1}, "runs must be"),
        ({"samples": 8}, "samples must be"),
    ):
        with pytest.raises(ValueError, match=match):
            run_adaptation_study(["case1"], tmp_path / "x", **kwargs)
    with pytest.raises(ValueError, match="unknown scenario"):
        run_adaptation_study(["nope"], tmp_path / "x")
    with pytest.raises(ValueError, match="unknown scenario"):
        scenario_config("nope", 4)
    assert not (tmp_path / "x").exists()
    assert (
        main(["adaptation", "--scenario", "case1", "--runs", "4", "--set", "runs=x", "--out", str(tmp_path / "y")]) == 2
    )
    assert not (tmp_path / "y").exists()
