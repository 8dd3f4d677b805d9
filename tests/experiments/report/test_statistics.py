"""The time windows of the error statistics and the sentences that say what they are."""

from __future__ import annotations

import numpy as np

from agsf_torch.experiments.report.statistics import WINDOW_TEXT, clopper_pearson, error_windows, mixture_life
from agsf_torch.experiments.studies.reproduce import results_table
from tests.helpers import assert_within, relative_bound


def test_windows_split_the_prior_stretch_the_frames_and_the_steps_between():
    frames = np.array([False, False, False, True, False, False, True, False])
    w = error_windows(frames)
    assert w["before_first_frame"].tolist() == [True, True, True, False, False, False, False, False]
    assert w["between_frames"].tolist() == [False, False, False, False, True, True, False, True]
    assert w["all"].all()
    # every step is in exactly one of: the prior's stretch, a frame, between frames
    assert (w["before_first_frame"].astype(int) + frames + w["between_frames"]).tolist() == [1] * len(frames)


def test_a_run_without_frames_is_all_prior_and_a_frame_at_t0_has_no_prior_stretch():
    none = error_windows(np.zeros(5, dtype=bool))
    assert none["before_first_frame"].all() and not none["between_frames"].any()
    at_start = error_windows(np.array([True, False, False, True, False]))
    assert not at_start["before_first_frame"].any()
    assert at_start["between_frames"].tolist() == [False, True, True, False, True]


def test_reproduce_tables_say_what_their_windows_are():
    filters = {
        f: {
            "between_frames_mean_rms_deg": 0.5,
            "before_first_frame_mean_rms_deg": 8.0,
            "final_rms_deg": 0.01,
            "time_averaged_nees": 3.0,
        }
        for f in ("GSF", "AGSF")
    }
    diff = {
        w: {"mean_deg": -0.01, "ci95_deg": [-0.02, 0.0], "relative": -0.02}
        for w in ("between_frames", "before_first_frame")
    }
    text = results_table({"case1": {"star_period_s": 1.0, "filters": filters, "agsf_minus_gsf": diff}})
    blocks = text.split("\n\n")
    assert len(blocks) == 4  # the table, its sentence, the differences, their sentence
    for table, note in ((blocks[0], blocks[1]), (blocks[2], blocks[3])):
        assert table.startswith("| case |") and not note.startswith("|")
        assert WINDOW_TEXT["between_frames"] in note and WINDOW_TEXT["before_first_frame"] in note
    assert "| case1 | between frames | -0.01 |" in blocks[2]
    assert "NIS / expected" in blocks[0] and "NIS / expected" in blocks[1]
    assert blocks[0].splitlines()[2].endswith("| 3 | — |")  # a summary without star frames has no NIS ratio
    filters["GSF"]["nis_per_expected"] = 1.02345
    rows = results_table({"case1": {"star_period_s": 1.0, "filters": filters}}).splitlines()
    assert rows[2] == "| case1 | 1 Hz | GSF | 0.5 | 8 | 0.01 | 3 | 1.023 |"


def test_nis_per_expected_pools_every_valid_update_and_gives_the_chi2_band():
    """``Σ NIS / Σ ⅔·dof`` over the finite NIS with ``dof > 0``; the band of a consistent filter's ratio is
    that of the average of ``count`` χ²(k) values divided by ``k``, ``k`` the mean expectation."""
    from scipy.stats import chi2

    from agsf_torch.consistency import nis_per_expected

    nis = np.array([[2.0, np.nan, 5.0], [4.0, 6.0, 1.0]])
    dof = np.array([[3, 0, 0], [6, 3, 3]])  # the 5.0 has no valid entry: not counted
    ratio, (lo, hi) = nis_per_expected(nis, dof)
    assert ratio == (2.0 + 4.0 + 6.0 + 1.0) / (2.0 + 4.0 + 2.0 + 2.0)
    # 4 updates, mean expectation k = 2.5: the sum of 4 χ²(2.5) values is χ²(10)
    band = np.array([chi2.ppf(0.025, 10), chi2.ppf(0.975, 10)]) / 4 / 2.5
    assert_within([lo, hi], band, relative_bound(band, 1e-9, 1e-12), "χ² band of the NIS ratio")
    assert nis_per_expected(np.full((2, 3), np.nan), np.zeros((2, 3))) is None


def test_a_non_finite_nis_at_an_update_makes_the_ratio_non_finite_and_fails_the_check():
    """A diverged filter's NIS (inf or NaN where an update had valid entries) is counted, not left out: left
    out, the other updates made such a filter look consistent."""
    from agsf_torch.consistency import consistency_checks, nis_per_expected

    dof = np.array([[3, 3, 0], [3, 3, 3]])
    for bad, want in ((np.inf, np.isposinf), (np.nan, np.isnan)):
        nis = np.array([[2.0, 2.0, np.nan], [2.0, bad, 2.0]])
        ratio, _ = nis_per_expected(nis, dof)
        assert want(ratio)
        check = next(c for c in consistency_checks(nees=None, state_dim=3, nis=nis.T, nis_dof=dof.T) if c.name == "nis")
        assert not check.passed and "not finite — the filter diverged" in check.text


def test_fpke_ratio_is_per_run_and_skips_steps_without_a_residual():
    """``after / before`` per run, then the mean and the 10–90 % range over the runs; a zero or non-finite
    ``before`` gives no ratio for that run (a step without any gives NaN, not a warning)."""
    from agsf_torch.experiments.report.statistics import fpke_ratio

    before = np.array([[1.0, 2.0, 0.0], [4.0, 1.0, np.inf]])
    after = np.array([[0.5, 2.0, 1.0], [1.0, 0.1, 1.0]])
    out = fpke_ratio(before, after)
    # a mean and linear interpolations of two ratios each: a few roundings; numpy's default rtol 1e-7
    mean = np.array([(0.5 + 0.25) / 2, (1.0 + 0.1) / 2])
    assert_within(out["fpke_ratio_mean"][:2], mean, relative_bound(mean, 1e-7, 0.0), "mean FPKE ratio")
    assert np.isnan(out["fpke_ratio_mean"][2])
    lo, hi = out["fpke_ratio_p10_p90"]
    p10, p90 = np.array([0.25 + 0.1 * 0.25, 0.1 + 0.1 * 0.9]), np.array([0.25 + 0.9 * 0.25, 0.1 + 0.9 * 0.9])
    assert_within(lo[:2], p10, relative_bound(p10, 1e-7, 0.0), "10th percentile of the FPKE ratio")
    assert_within(hi[:2], p90, relative_bound(p90, 1e-7, 0.0), "90th percentile of the FPKE ratio")


def test_clopper_pearson_is_the_exact_binomial_interval():
    """The ends solve ``P(X ≥ k | p_low) = P(X ≤ k | p_high) = 2.5 %`` (the regularised incomplete beta function
    in 40-digit arithmetic, mpmath); 0 and 1 at ``k = 0`` and ``k = n``; no trials gives NaN."""
    import mpmath as mp

    mp.mp.dps = 40
    n, k = 100, np.array([0, 1, 7, 50, 99, 100])
    got = clopper_pearson(k, n)

    def solve(a, b, p, start):
        return float(mp.findroot(lambda x: mp.betainc(a, b, 0, x, regularized=True) - mp.mpf(p), mp.mpf(start)))

    want = np.array(
        [
            (0.0 if x == 0 else solve(x, n - x + 1, "0.025", lo), 1.0 if x == n else solve(x + 1, n - x, "0.975", hi))
            for x, (lo, hi) in zip(k.tolist(), got.tolist(), strict=True)
        ]
    )
    # the inverse incomplete beta function is accurate to a few ulps here (p away from 0 and 1); 1e-12 relative
    assert_within(got, want, relative_bound(want, 1e-12, 0.0), "Clopper–Pearson interval")
    assert np.isnan(clopper_pearson(0, 0)).all()


def test_mixture_life_is_the_mean_and_range_of_the_count_and_the_mean_of_the_events_so_far():
    """Two runs of three steps: run 0 splits five components into fifteen, then prunes fourteen; run 1 merges two."""
    life = mixture_life(
        active=np.array([[5, 15, 1], [5, 5, 3]]),
        splits=np.array([[0, 5, 0], [0, 0, 0]]),
        merges=np.array([[0, 0, 0], [0, 0, 2]]),
        prunes=np.array([[0, 0, 14], [0, 0, 0]]),
    )
    assert life == {
        "active_components_mean": [5.0, 10.0, 2.0],
        "active_components_min_max": [[5.0, 5.0, 1.0], [5.0, 15.0, 3.0]],
        "splits_cumulative_mean": [0.0, 2.5, 2.5],
        "merges_cumulative_mean": [0.0, 0.0, 1.0],
        "prunes_cumulative_mean": [0.0, 0.0, 7.0],
    }
