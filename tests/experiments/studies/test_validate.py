"""``agsf validate``: every scenario × filter against the Riccati floor, end to end on short runs, and its
measures on constructed data."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from agsf_torch.attitude.floor import ARCSEC_PER_RAD
from agsf_torch.consistency import chi2_band
from agsf_torch.experiments.cli.main import main
from agsf_torch.experiments.studies import validate
from agsf_torch.experiments.studies.validate import (
    SCENARIOS,
    VALIDATION_FILTERS,
    run_validation,
    scenario_config,
    scenario_measures,
)
from tests.helpers import EAGER, assert_within

#: The filters run end to end here (each scenario's own, less the adaptive ones, whose studies are elsewhere).
FILTERS = ["EKF", "GSF", "MEKF", "MEKF-fix", "USQUE", "PF"]
MEASURES = (
    "rms_steady_arcsec",
    "floor_arcsec",
    "anees",
    "anees_band",
    "nis_ratio",
    "diverged_fraction",
    "converge_time_s",
    "density_score",
    "cost_per_step_s",
)


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("validate") / "study"
    summaries = run_validation(
        ["case1", "single_vector-90deg"],
        out,
        runs=4,
        filters=FILTERS,
        density_samples=64,
        overrides=["duration=3.0", *EAGER],
        progress=False,
    )
    return out, summaries


def test_every_scenario_and_filter_has_every_measure_on_disk(study):
    out, summaries = study
    on_disk = json.loads((out / "validation.json").read_text())
    assert set(on_disk) == {"case1", "single_vector-90deg"}
    for name, s in on_disk.items():
        assert list(s["filters"]) == [f for f in SCENARIOS[name].filters if f in FILTERS]
        assert s["runs"] == 4 and len(s["floor_arcsec"]) == 3
        for f, m in s["filters"].items():
            assert set(MEASURES) <= set(m), (name, f)
            assert m["anees_band"] == list(chi2_band(3, 4))
            for axis, (lo, hi) in zip(m["rms_steady_arcsec"], m["rms_steady_arcsec_ci95"]):
                assert lo <= axis <= hi
            lo, hi = m["diverged_ci95"]
            assert 0.0 <= lo <= m["diverged_fraction"] <= hi <= 1.0
            assert m["cost_per_step_s"] > 0
            assert not any(k.endswith("_t_arcsec") for k in m)  # the figures' series stay out of the JSON
    for name in on_disk:  # the reference is run where the scenario asks for it
        assert (on_disk[name]["filters"]["GSF"]["density_score"] is not None) == SCENARIOS[name].density
    assert on_disk["single_vector-90deg"]["stars_per_frame_mean"] == 1.0


def test_the_star_fix_starts_the_mekf_at_the_first_frame_with_two_stars(study):
    """case 1 has five stars a frame: the star-fix MEKF's attitude is the fix's from the first frame (1 s) on, so
    after 3 s no run is off by more than a few arcseconds; with one star a frame no frame fixes an attitude and
    MEKF-fix is the MEKF, bit for bit."""
    _, summaries = study
    fixed = summaries["case1"]["filters"]["MEKF-fix"]
    assert fixed["diverged_fraction"] == 0.0 and max(fixed["rms_steady_arcsec"]) < 10.0
    single = summaries["single_vector-90deg"]["filters"]
    assert single["MEKF-fix"]["rms_t_arcsec"] == single["MEKF"]["rms_t_arcsec"]


def test_lost_in_space_the_star_fix_solves_a_uniform_start(tmp_path):
    """A uniformly random prior attitude (``prior_attitude = "uniform"``): the filters start tens of degrees off
    (the mean error of a uniform attitude is ~126°), and the star-fix MEKF is on the stars from its first frame."""
    summaries = run_validation(
        ["lost_in_space"],
        tmp_path / "lis",
        runs=8,
        filters=["MEKF-fix", "GSF"],
        overrides=["duration=3.0", *EAGER],
        progress=False,
    )
    m = summaries["lost_in_space"]["filters"]
    assert m["GSF"]["rms_t_arcsec"][0] > 20 * 3600  # > 20° RMS after the first step
    assert m["MEKF-fix"]["diverged_fraction"] == 0.0 and max(m["MEKF-fix"]["rms_steady_arcsec"]) < 10.0


def test_figures_and_the_table_in_words(study):
    out, summaries = study
    for name in summaries:
        assert (out / f"{name}.png").stat().st_size > 10_000
    assert (out / "summary.png").stat().st_size > 10_000
    text = (out / "results.md").read_text()
    assert "| case1 | MEKF-fix |" in text
    assert text.count("- **") == 2 and ("use " in text or "no filter is consistent" in text)


def _result(errors_rad: np.ndarray, t: np.ndarray, nees: np.ndarray) -> dict:
    T, B = errors_rad.shape[:2]
    return {
        "time": t,
        "frame": np.ones(T, dtype=bool),
        "stars": np.full((T, B), 5.0),
        "directions": None,
        "filters": {
            "EKF": {
                "error": errors_rad,
                "sigma3": np.full((T, B), 1e-5),
                "nees": nees,
                "nis": np.full((T, B), 15.0),
                "dof": np.full((T, B), 15.0),
                "score": np.full((T, B), np.nan),
                "seconds": 2.0,
                "steps": 100,
            }
        },
    }


def test_divergence_convergence_and_consistency_on_constructed_runs():
    """Four runs of 10 steps: run 0 settles at step 4, run 1 at step 7, run 2 never (ends 2° off), run 3 is
    below the threshold throughout."""
    cfg = scenario_config("case1", 4, overrides=EAGER)
    floor = validate.scenario_floor(cfg)
    threshold = validate.CONVERGED_FLOOR_MULTIPLE * math.sqrt(sum(float(v) ** 2 for v in floor.arcsec_mean))
    small, big = 0.5 * threshold / ARCSEC_PER_RAD, 2.0 * threshold / ARCSEC_PER_RAD
    t = np.arange(10) * 0.1
    angle = np.full((10, 4), small)
    angle[:4, 0] = big
    angle[:7, 1] = big
    angle[:, 2] = math.radians(2.0)
    errors = np.zeros((10, 4, 3))
    errors[..., 0] = 2.0 * np.sin(angle / 2.0)  # the error vector's magnitude is 2 sin(θ/2)
    m = scenario_measures(_result(errors, t, np.full((10, 4), 3.0)), cfg)["filters"]["EKF"]
    assert m["diverged_fraction"] == 0.25
    assert m["converged_fraction"] == 0.75
    assert m["converge_time_s"] == (t[4] + t[7]) / 2  # the median of 0, t₄, t₇ and ∞
    assert m["anees"]["run"]["mean"] == 3.0  # the mean of equal values, exactly
    assert m["nis_ratio"]["mean"] == 1.0  # Σ 15 / Σ 15 per run, exactly
    assert m["cost_per_step_s"] == 2.0 / 100


def test_bad_input_creates_nothing(tmp_path):
    for kwargs, match in (
        ({"runs": 1}, "runs must be"),
        ({"density_samples": 8}, "density_samples must be"),
        ({"filters": ["KF"]}, "unknown filter 'KF'"),
    ):
        with pytest.raises(ValueError, match=match):
            run_validation(["case1"], tmp_path / "x", **kwargs)
    with pytest.raises(ValueError, match="unknown scenario"):
        run_validation(["nope"], tmp_path / "x")
    with pytest.raises(ValueError, match="runs none of the filters"):
        scenario_config("case1-600s", 4, filters=["AGSF"])
    assert not (tmp_path / "x").exists()
    assert main(["validate", "--scenario", "case1", "--runs", "1", "--out", str(tmp_path / "y")]) == 2
    assert main(["validate", "--scenario", "case1", "--set", "runs=x", "--out", str(tmp_path / "y")]) == 2
    assert not (tmp_path / "y").exists()


def test_every_scenario_builds_and_names_only_registered_filters():
    for name, sc in SCENARIOS.items():
        cfg = scenario_config(name, 2)
        assert list(cfg.filters) == list(sc.filters) and set(sc.filters) <= set(VALIDATION_FILTERS)


def test_paired_divergence_is_mcnemars_exact_conditional_interval():
    from scipy.stats import binomtest

    from agsf_torch.experiments.studies.validate import paired_divergence

    baseline = np.array([1] * 9 + [0] * 23)
    managed = np.array([0] * 8 + [1] + [0] * 22 + [1])  # 8 runs only the baseline lost, 1 only the managed filter
    out = paired_divergence(baseline, managed)
    assert out["discordant"] == 9
    assert_within(out["difference"], 7 / 32, 1e-15, "difference of fractions")
    lo, hi = binomtest(8, 9).proportion_ci(0.95, method="exact")  # Clopper-Pearson of π = P(baseline | discordant)
    assert_within(out["ci95"], [9 / 32 * (2 * lo - 1), 9 / 32 * (2 * hi - 1)], 1e-12, "McNemar interval")
    assert out["ci95"][0] > 0  # McNemar's exact test: p = 0.039 < 0.05
    assert binomtest(8, 9).pvalue < 0.05
    same = paired_divergence(baseline, baseline)
    assert same == {"difference": 0.0, "ci95": [0.0, 0.0], "discordant": 0}


def test_the_median_interval_is_the_sign_tests_order_statistics():
    from scipy.stats import binom

    from agsf_torch.experiments.report.statistics import median_ci95

    rng = np.random.default_rng(3)
    values = rng.standard_cauchy(16)  # heavy tails: where the t interval says little
    med, lo, hi = median_ci95(values)
    x = np.sort(values)
    # n = 16: P(Bin(16, ½) ≤ 3) = 697/65536 ≤ 0.025 < P(Bin ≤ 4): the 4th and the 13th order statistics
    assert binom.cdf(3, 16, 0.5) <= 0.025 < binom.cdf(4, 16, 0.5)
    assert (lo, hi) == (x[3], x[12]) and med == np.median(x)
    assert 1 - 2 * binom.cdf(3, 16, 0.5) >= 0.95  # the interval's coverage
    assert median_ci95(values[:5])[1:] == (-math.inf, math.inf)  # 2·(½)⁵ > 0.05: no such interval
    assert median_ci95(values[:6])[1:] == (np.min(values[:6]), np.max(values[:6]))  # 2·(½)⁶ ≤ 0.05


def test_managed_comparisons_report_the_density_score_robustly():
    from agsf_torch.experiments.studies.validate import managed_comparisons

    runs = 8
    managed = {"diverged_runs": [0] * runs, "density_score_runs": [10.0] * runs}
    # the single Gaussian: one run far in its tail, the rest just below the managed filter
    baseline = {"diverged_runs": [0] * runs, "density_score_runs": [9.0] * (runs - 1) + [-1e9]}
    out = managed_comparisons({"GSF-managed": managed, "EKF": baseline})["GSF-managed vs EKF"]["density_score"]
    assert out["managed_better"] == runs and out["runs"] == runs
    assert out["median"] == 1.0 and out["median_ci95"][0] == 1.0  # every difference ≥ 1: the interval excludes 0
    assert out["ci95"][0] < 0  # the t interval, dominated by the one run, does not
