"""Monte Carlo consistency on the paper's case 1 (method.md §4): 1 Hz star frames,
σ_s = 10 µrad, 5 stars, P₀ = 1e-3·I (≈7° per axis), ω = 2π/100·[1, 1, 0] rad/s."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import envs
from agsf_torch.consistency import chi2_band
from agsf_torch.experiments.run.runner import FilterSetup, run_monte_carlo
from agsf_torch.filters import ExtendedKalmanFilter, GaussianSumFilter
from agsf_torch.models import AttitudeModel
from tests.helpers import F64, assert_within, relative_bound

SIGMA_B0 = 0.2 * np.pi / 180 / 3600  # prior bias σ, rad/s


def _run(estimate_bias, iterations, B=200, T=300, rate=None, seed=1, callback=None):
    kwargs = {} if rate is None else {"rate": rate}
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=B, max_steps=T, **kwargs)
    model = AttitudeModel(estimate_bias=estimate_bias)
    n = model.state_dim
    P0 = torch.diag(torch.tensor([1e-3] * 3 + [SIGMA_B0**2] * 3, dtype=F64)[:n])
    filters = {
        "ekf": FilterSetup(ExtendedKalmanFilter(model, update_iterations=iterations), 1),
        "gsf": FilterSetup(GaussianSumFilter(model, update_iterations=iterations), 5),
    }
    res = run_monte_carlo(
        env,
        filters,
        num_steps=T,
        prior_cov=P0,
        sigma_s=10e-6,
        seed=seed,
        estimate_bias=estimate_bias,
        callback=callback,
    )
    return res, n


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_case1_nees_inside_chi2_band(estimate_bias):
    """200 runs × 30 s.  The measurement update is the iterated EKF update (3 linearisations):
    with one linearisation the 7° prior leaves the first star frame's estimate ~100 µrad off
    while its covariance says ~60 µrad, and NEES stays far above the band (next test)."""
    res, n = _run(estimate_bias, iterations=3)
    lo, hi = chi2_band(n, 200)
    for name, tr in res.traces.items():
        avg = tr.nees.mean(0).mean()
        print(
            f"{name} {n}-state: time-averaged NEES {avg:.3f}, band [{lo:.3f}, {hi:.3f}], final RMS {tr.rms_error()[-1] * 1e6:.2f} µrad"
        )
        assert lo <= avg <= hi
        if estimate_bias:
            err, sig = tr.error[:, -1, 3:], tr.sigma[:, -1, 3:]
            inside = (np.abs(err) <= 3 * sig).mean()
            assert inside >= 0.97
            assert sig.mean() < 0.5 * SIGMA_B0  # the bias is being learned


def test_case1_single_linearisation_is_inconsistent():
    """The method's plain EKF update (one linearisation) on the same case: documented limitation."""
    res, n = _run(False, iterations=1, T=100)
    for tr in res.traces.values():
        assert tr.nees.mean(0)[10:].mean() > 100.0


def test_longer_than_one_revolution_stays_inside_3_sigma():
    """|ω| = 0.0889 rad/s: one revolution in 70.7 s; 90 s crosses the MRP shadow switch."""
    near_switch = []

    def watch(k, name, filt, mix):
        near_switch.append(float(mix.means[..., :3].norm(dim=-1).max()) > 0.99)

    res, n = _run(False, iterations=3, B=48, T=900, seed=3, callback=watch)
    assert sum(near_switch) > 10  # components reach |p| → 1 and are switched to the shadow set
    tr = res.traces["gsf"]
    inside = (np.abs(tr.error[:, 100:]) <= 3 * tr.sigma[:, 100:]).mean()
    assert inside >= 0.97
    assert np.isfinite(tr.nees).all() and tr.nees.mean(0)[100:].mean() < 4.0


def test_refuses_a_model_that_does_not_match_estimate_bias():
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=2, max_steps=3)
    filters = {"ekf": FilterSetup(ExtendedKalmanFilter(AttitudeModel(estimate_bias=False)), 1)}
    with pytest.raises(ValueError, match="the filters' model has 3 states, but estimate_bias=True"):
        run_monte_carlo(env, filters, num_steps=3, prior_cov=torch.eye(6, dtype=F64), sigma_s=1e-5, estimate_bias=True)


@pytest.mark.parametrize("n", [3, 6])
def test_the_scores_over_every_step_at_once_equal_those_of_each_step(gen, n):
    """The runner scores a run once, over ``[B, T]``: the same numbers as step by step over ``[B]`` (to rounding:
    a batched 3×3 product may take another kernel at another batch size)."""
    from agsf_torch.consistency import nees
    from agsf_torch.experiments.run.runner import rotation_error
    from agsf_torch.rotations import attitude_error_angle
    from tests.helpers import random_mrps, random_spd

    B, T = 7, 5
    mean = torch.cat((random_mrps(B * T, gen), 1e-5 * torch.randn(B * T, n - 3, generator=gen, dtype=F64)), -1)
    truth = torch.cat((random_mrps(B * T, gen), 1e-5 * torch.randn(B * T, n - 3, generator=gen, dtype=F64)), -1)
    cov = random_spd(gen, B * T, n=n, scale=1e-3)
    mean, truth, cov = mean.reshape(B, T, n), truth.reshape(B, T, n), cov.reshape(B, T, n, n)
    # another summation order of a quadratic form moves it by ~n·κ(P)·ε relative (κ ≤ ~40 here)
    rtol = 10 * n * float(torch.linalg.cond(cov).max()) * torch.finfo(F64).eps
    error, sigma = rotation_error(mean, cov, truth)
    # the error's terms cancel where it is small: 2·δq_v of unit quaternions (scale 2), b̂ − b (scale |b̂| + |b|)
    scale = torch.cat((torch.full((B, T, 3), 2.0, dtype=F64), mean[..., 3:].abs() + truth[..., 3:].abs()), -1)
    for t in range(T):
        e, s = rotation_error(mean[:, t], cov[:, t], truth[:, t])
        assert_within(error[:, t], e, relative_bound(e, rtol, rtol * scale[:, t]), "rotation error")
        # σ and the NEES are positive (P is SPD): relative, as the summation-order argument above gives
        assert_within(sigma[:, t], s, relative_bound(s, rtol, 0.0), "rotation σ")
        want = nees(error[:, t], cov[:, t])
        assert_within(nees(error, cov)[:, t], want, relative_bound(want, rtol, 0.0), "NEES")
        # written to be the same bits at any batch size (its docstring)
        assert torch.equal(
            attitude_error_angle(mean[..., :3], truth[..., :3])[:, t],
            attitude_error_angle(mean[:, t, :3], truth[:, t, :3]),
        )


def test_a_managed_filters_counts_of_a_step_cover_its_predict_and_its_update():
    """``splits``, ``merges`` and ``prunes`` of a step are its predict's plus its update's (as each call reported
    them, recorded here as it happens), ``active_components`` the update's at a star frame: then the count at
    each step's end follows from the counts alone, ``K_t = K_{t−1} + 2·splits − merges − prunes`` (a split makes one
    component three), from the prior's ``K = 5``."""
    from agsf_torch.filters.management import MANAGEMENT_DIAGNOSTICS, MixtureManagement

    B, T, N = 3, 25, 5  # star frames at 1 s and 2 s (dt = 0.1 s)
    filt = GaussianSumFilter(AttitudeModel(estimate_bias=False), management=MixtureManagement())
    calls: list[tuple[str, dict[str, np.ndarray]]] = []

    def recording(step):
        inner = getattr(filt, step)

        def call(*args, **kwargs):
            out = inner(*args, **kwargs)
            calls.append((step, {k: filt.diagnostics[k].numpy().copy() for k in MANAGEMENT_DIAGNOSTICS}))
            return out

        return call

    filt.predict, filt.update = recording("predict"), recording("update")
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=B, max_steps=T)
    res = run_monte_carlo(
        env, {"gsf": FilterSetup(filt, N)}, num_steps=T, prior_cov=1e-3 * torch.eye(3, dtype=F64), sigma_s=10e-6
    )
    extra = res.traces["gsf"].extra
    steps: list[list[dict[str, np.ndarray]]] = []  # each step's calls: its predict, then its update if any
    for kind, counts in calls:
        if kind == "predict":
            steps.append([])
        steps[-1].append(counts)
    assert len(steps) == T
    assert [len(s) == 2 for s in steps] == res.star_frame.tolist() and res.star_frame.sum() == 2
    for key in ("splits", "merges", "prunes"):
        want = np.stack([sum(c[key] for c in s) for s in steps], 1)
        assert extra[key].dtype == np.int64 and extra[key].shape == (B, T)
        np.testing.assert_array_equal(extra[key], want, err_msg=key)
    np.testing.assert_array_equal(extra["active_components"], np.stack([s[-1]["active_components"] for s in steps], 1))
    # the updates do split here (what a predict-only record would lose), and the bookkeeping closes
    assert sum(int(s[1]["splits"].sum()) for s in steps if len(s) == 2) > 0
    change = 2 * extra["splits"] - extra["merges"] - extra["prunes"]
    np.testing.assert_array_equal(extra["active_components"], N + np.cumsum(change, 1))
