"""The false-alarm and detection rates of ``agsf diagnose``'s verdicts (agsf_torch.experiments.studies.verdict_calibration):
its verdicts are diagnose's, data set by data set; at the truth each check fails at most at its level 5 %/3 and the
overall verdict at most 5 % (Bonferroni); the whiteness check, about the innovations' known mean, at its level for
white innovations whether a data set is one trajectory or 16; a threefold σ_s is caught in every data set; bad
requests are refused before anything runs; and the batched checks they rest on
(agsf_torch.consistency.consistency_check_arrays) are consistency_checks, data set by data set."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agsf_torch.consistency import consistency_check_arrays, consistency_checks
from agsf_torch.experiments.config.loader import MAX_SEED, load_config
from agsf_torch.experiments.report.statistics import clopper_pearson
from agsf_torch.experiments.studies import verdict_calibration
from agsf_torch.experiments.studies.diagnose import diagnose
from agsf_torch.experiments.studies.verdict_calibration import (
    CHECKS,
    LEVEL_SAMPLES,
    diagnose_verdict_rates,
)
from tests.helpers import EAGER, assert_statistic, assert_within, relative_bound

#: The EKF of case 1 with the iterated update (consistent, unlike the paper's single linearisation), 10 star frames.
CONSISTENT = [*EAGER, 'filters=["EKF"]', "update_iterations=3", "duration=10.0"]
#: Data sets of one trajectory each in the statistical tests.
DATASETS = 400
#: The chance that a correct implementation fails one statistical assertion below.
FALSE_FAILURE = 1e-3


@pytest.fixture(scope="module")
def verdicts():
    """The correctly configured EKF and one assuming 3 σ_s, on the same 400 data sets of one 10 s trajectory."""
    cfg = load_config("case1", CONSISTENT)
    return diagnose_verdict_rates(cfg, datasets=DATASETS, trajectories=1, scales=(1.0, 3.0), parameters=("sigma_s",))


def test_the_verdicts_are_those_agsf_diagnose_prints(tmp_path):
    """Each data set's verdicts (correctly configured, and with the filters assuming 2 σ_v) are what
    ``agsf diagnose`` of the same simulation gives that data set's trajectories: the run is diagnose's, the batched
    checks are its checks."""
    cfg = load_config("case1", [*EAGER, 'filters=["EKF", "GSF"]', "update_iterations=3", "duration=3.0"])
    D, B = 3, 2
    res = diagnose_verdict_rates(cfg, datasets=D, trajectories=B, scales=(2.0,), parameters=("sigma_v",))
    assert res.filters == ("EKF", "GSF") and res.checks == CHECKS and res.parameters == ("sigma_v",)
    assert res.scales.tolist() == [1.0, 2.0]  # the truth is always run, first when not asked for
    assert res.failed.shape == res.judged.shape == res.values.shape == (2, 1, 2, 4, D)
    for j, scale in enumerate(res.scales):
        out = tmp_path / f"scale{j}"
        diagnose(cfg.replace(runs=D * B, filter_sigma_v_scale=float(scale)), out, progress=False)
        data = np.load(out / "runs.npz")
        for f, name in enumerate(res.filters):
            for d in range(D):
                part = slice(d * B, (d + 1) * B)
                checks = {
                    c.name: c
                    for c in consistency_checks(
                        nees=data[f"{name}/nees"][part].T,
                        state_dim=3,
                        nis=data[f"{name}/nis"][part].T,
                        nis_dof=data[f"{name}/nis_dof"][part].T,
                    )
                }
                where = f"{name}, σ_v × {scale:g}, data set {d}"
                assert res.judged[f, 0, j, :3, d].tolist() == [c in checks for c in CHECKS[:3]], where
                assert res.failed[f, 0, j, :3, d].tolist() == [c in checks and not checks[c].passed for c in CHECKS[:3]]
                assert res.failed[f, 0, j, 3, d] == (not checks or not all(c.passed for c in checks.values()))
                made = [c for c in CHECKS[:3] if c in checks]
                got = res.values[f, 0, j, [CHECKS.index(c) for c in made], d]
                want = np.array([checks[c].value for c in made])
                # the same arithmetic on the same numbers, batched over other data sets: a few roundings of sums
                assert_within(got, want, relative_bound(want, 1e-13, 1e-300), f"{where}: the checks' statistics")
    assert np.array_equal(res.count, res.judged.sum(-1)) and np.array_equal(res.failures, res.failed.sum(-1))
    assert np.array_equal(res.rate, res.failures / res.count)


def se(p: float, datasets: int, extra: int = 0) -> float:
    """A binomial proportion's standard error over ``datasets`` (plus a reference's own, from ``extra`` samples)."""
    return math.sqrt(p * (1 - p) / datasets + (p * (1 - p) / extra if extra else 0.0))


def test_false_alarms_at_the_truth_are_each_checks_level(verdicts):
    """On the correctly configured filter each check fails at most at its level α/3 (the module docstring): the
    NIS at α/3 (χ² with the innovations' degrees of freedom), the NEES and the whiteness at most at it (the NEES
    band ignores the time average's smaller spread; the whiteness of 10 frames is flagged far less often, its
    rate is tested on longer runs below), and the overall verdict at most α = 5 % (Bonferroni)."""
    r, alpha = verdicts, 0.05
    level = alpha / 3
    fa = dict(zip(r.checks, r.false_alarm[0], strict=True))
    # 1 − 0.95 is 0.05 within a rounding, then divided by 3
    assert_within([r.level, r.familywise_level], [level, alpha], 1e-16, "each check's level and the family's")
    assert r.count[0, 0, 0].tolist() == [DATASETS] * 4  # every check made for every data set

    assert_statistic(fa["nis"], level, se(level, DATASETS), "NIS check's false-alarm rate", false_failure=FALSE_FAILURE)
    # one-sided: only a rate above the bound is evidence against it
    excess = [max(fa[c] - level, 0.0) for c in ("nees", "whiteness")] + [max(fa["any"] - alpha, 0.0)]
    assert_statistic(
        excess,
        0.0,
        [se(level, DATASETS)] * 2 + [se(alpha, DATASETS)],
        "NEES and whiteness false alarms above 5 %/3, overall above 5 %",
        false_failure=FALSE_FAILURE,
    )
    # the reported interval is Clopper–Pearson's at these counts
    assert np.array_equal(r.false_alarm_interval[0], clopper_pearson(r.failures[0, 0, 0], DATASETS))


#: Data sets at the truth for the whiteness check: one trajectory of 30 s (the preset's: 30 frames), and 16 of 20 s.
WHITE = {"1 trajectory": (1, 30.0, 1000), "16 trajectories": (16, 20.0, 400)}


@pytest.fixture(scope="module", params=list(WHITE))
def white(request):
    """The correctly configured EKF of case 1 alone on ``WHITE[param]``'s data sets."""
    trajectories, duration, datasets = WHITE[request.param]
    cfg = load_config("case1", [*CONSISTENT, f"duration={duration}"])
    return diagnose_verdict_rates(
        cfg, datasets=datasets, trajectories=trajectories, scales=(1.0,), parameters=("sigma_s",)
    )


def test_the_whiteness_check_fails_a_consistent_filter_at_its_level(white):
    """At the truth the whiteness check fails as often as it fails white χ² innovations with the same frames
    (:attr:`VerdictRates.whiteness_level`), whether a data set is one trajectory or 16, and that level is at most
    the nominal 5 %/3 (below it for runs of 20–30 frames: the module docstring); its statistic, the runs' lag-1
    autocorrelation about the innovations' known mean 0, has mean 0.  About each run's own mean its mean was about
    −1/frames (−0.033 for 30 frames, −0.05 for 20: 6 and 19 standard errors here), a bias no number of runs
    averages away while the band narrows: white innovations of 16 runs of 20 frames are flagged about 4.3 % of the
    time at this level that way, against 0.8 % about 0."""
    r = white
    D, level = r.datasets, r.level
    w = r.checks.index("whiteness")
    assert r.count[0, 0, 0, w] == D  # made for every data set
    fa, white_level = float(r.false_alarm[0, w]), float(r.whiteness_level[0])
    assert_statistic(
        fa,
        white_level,
        se(white_level, D, LEVEL_SAMPLES),
        f"whiteness false-alarm rate, {r.trajectories} trajectories per data set",
        false_failure=FALSE_FAILURE,
    )
    # one-sided: only a level above the nominal is evidence against the band
    excess = [max(white_level - level, 0.0), max(fa - level, 0.0), max(float(r.false_alarm[0, -1]) - 0.05, 0.0)]
    assert_statistic(
        excess,
        0.0,
        [se(level, LEVEL_SAMPLES), se(level, D), se(0.05, D)],
        "white-innovation and measured whiteness levels above 5 %/3, overall above 5 %",
        false_failure=FALSE_FAILURE,
    )
    # the statistic's mean over the data sets: a mean of D independent values, its standard error from their spread
    rho = r.values[0, 0, 0, w]
    assert_statistic(
        rho.mean(), 0.0, rho.std(ddof=1) / math.sqrt(D), "mean lag-1 autocorrelation", false_failure=FALSE_FAILURE
    )


def test_a_threefold_sigma_s_is_caught_in_every_data_set(verdicts):
    """Assuming 3 σ_s, the filter expects innovations 9 times too large after the first frame: the NIS sum over
    the 10 frames is about χ²(3) (the first frame's, the prior's) plus a ninth of a χ²(97), and passing needs it
    above 69 (the band's low end at level 5 %/3, χ²₀.₀₀₈₃(100)/100 = 0.693, times 100): with the χ²(3) below 20
    (probability 1 − 2e-4) a χ²(97) above 9 × 49 = 441, probability below 1e-45.  So every data set fails the NIS
    check and the overall verdict, far above their false-alarm rates (at most about 1.7 % and 5 %)."""
    r = verdicts
    j = int(np.flatnonzero(r.scales == 3.0)[0])
    detection = dict(zip(r.checks, r.rate[0, 0, j], strict=True))
    half_a_data_set = 0.5 / DATASETS
    assert_within(detection["nis"], 1.0, half_a_data_set, "NIS check's detection rate at 3 σ_s")
    assert_within(detection["any"], 1.0, half_a_data_set, "overall detection rate at 3 σ_s")
    rows = [row for row in r.rows() if row["scale"] == 3.0 and row["check"] == "nis"]
    assert len(rows) == 1 and rows[0]["kind"] == "detection" and rows[0]["failures"] == DATASETS


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"scales": ()}, "scales is empty"),
        ({"scales": (1.0, 0.0)}, "finite and > 0"),
        ({"scales": (-2.0,)}, "finite and > 0"),
        ({"scales": (float("nan"),)}, "finite and > 0"),
        ({"scales": (float("inf"),)}, "finite and > 0"),
        ({"scales": (True,)}, "must be numbers"),
        ({"scales": (2.0, 2.0)}, "distinct"),
        ({"scales": 2.0}, "a sequence of numbers"),
        ({"parameters": ("sigma_u",)}, r"unknown parameter\(s\) \['sigma_u'\]"),
        ({"parameters": ()}, "parameters is empty"),
        ({"datasets": 0}, "datasets must be an integer ≥ 1"),
        ({"datasets": 2.5}, "datasets must be an integer ≥ 1"),
        ({"trajectories": 0}, "trajectories must be an integer ≥ 1"),
        ({"seed": MAX_SEED}, "config key 'seed'"),
    ],
)
def test_bad_requests_are_refused_before_anything_runs(monkeypatch, kwargs, message):
    def ran(*_args, **_kwargs):
        raise AssertionError("something ran before the request was checked")

    for name in ("make_env", "record_environment", "run_monte_carlo", "check_memory"):
        monkeypatch.setattr(verdict_calibration, name, ran)
    cfg = load_config("case1", CONSISTENT)
    with pytest.raises(ValueError, match=message):
        diagnose_verdict_rates(cfg, **kwargs)


def test_a_mis_configured_base_is_refused(monkeypatch):
    monkeypatch.setattr(verdict_calibration, "record_environment", lambda *a, **k: pytest.fail("it ran"))
    cfg = load_config("case1", [*CONSISTENT, "filter_sigma_s_scale=2.0"])
    with pytest.raises(ValueError, match="correctly configured .*filter_sigma_s_scale = 1"):
        diagnose_verdict_rates(cfg, datasets=2)


def test_the_batched_checks_are_consistency_checks_data_set_by_data_set():
    """Many data sets judged at once give each the checks, verdicts and statistics of consistency_checks on it
    alone — with frames at which some runs have no update, data sets without any update, and a diverged NIS."""
    rng = np.random.default_rng(7)
    D, T, B = 40, 30, 3
    frame = np.arange(T) % 3 == 0
    dof = np.where(frame[:, None], rng.choice([0.0, 6.0, 15.0], size=(D, T, B), p=[0.2, 0.3, 0.5]), 0.0)
    dof[0] = 0.0  # no update at all: no NIS, no whiteness
    dof[1, :, 1:] = 0.0  # one run: whiteness from it alone
    nis = np.where(dof > 0, rng.chisquare(np.maximum(dof * 2 / 3, 1.0)), np.nan)
    nis[2, 0, 0], dof[2, 0, 0] = np.inf, 15.0  # a diverged filter: the NIS fails, no whiteness
    nis[3] = np.where(dof[3] > 0, 3.0 * nis[3], np.nan)  # innovations 3× too large
    nees = rng.chisquare(3.0, size=(D, T, B))
    batched = consistency_check_arrays(nees=nees, state_dim=3, nis=nis, nis_dof=dof)
    assert list(batched) == ["nees", "nis", "whiteness"]
    for d in range(D):
        single = {c.name: c for c in consistency_checks(nees=nees[d], state_dim=3, nis=nis[d], nis_dof=dof[d])}
        for name, c in batched.items():
            assert bool(c.made[d]) == (name in single), (d, name)
            if name not in single:
                assert not c.passed[d] and np.isnan(c.value[d])
                continue
            s = single[name]
            assert bool(c.passed[d]) == s.passed, (d, name)
            got = np.array([c.value[d], c.low[d], c.high[d]])
            want = np.array([s.value, *s.band])
            # the same arithmetic on the same numbers: sums rounded in another order at most
            assert_within(got, want, relative_bound(want, 1e-13, 1e-300), f"data set {d}, {name}")
    assert not batched["nis"].made[0] and not batched["whiteness"].made[0]
    assert batched["nis"].made[2] and not batched["nis"].passed[2] and not batched["whiteness"].made[2]
    assert not batched["nis"].passed[3]
