"""Autocovariance least squares (ALS), the baseline for learning σ_v and σ_s: the algebra exact on expected
autocovariances, the estimates unbiased on sampled model data and on the simulator's case 1, the frame errors'
conventions (inertial frame, a wrong start cancelling), and every refusal named."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy.stats import norm, t

import envs
from agsf_torch.attitude.autocovariance import (
    autocovariance_coefficients,
    autocovariance_least_squares,
    frame_errors,
    innovation_products,
    solve_autocovariance_ls,
)
from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.run.recorded import record_environment
from agsf_torch.rotations import mrp_compose
from tests.helpers import F64, assert_statistic, assert_within, random_unit_vectors

EPS = float(np.finfo(np.float64).eps)
FALSE_FAILURE = 1e-6


def _case1(gen, runs: int, duration: float, **overrides) -> tuple:
    """A case-1 recording (gyro at 10 Hz, stars at 1 Hz; ``overrides`` replace simulator settings) and the
    settings simulated; the seed is drawn by the test's generator."""
    cfg = load_config("case1", [f"runs={runs}", f"duration={duration}", "compile=false", "compile_fused=false"])
    settings = {**cfg.env_settings(), **overrides}
    seed = int(torch.randint(0, 2**31 - 1, (), generator=gen))
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=runs, **settings)
    return record_environment(env, cfg.num_steps, seed=seed), settings


def _mean_and_se(x, entries: int) -> tuple[np.ndarray, np.ndarray]:
    """The mean of ``x [D, …]`` over its first axis and its standard error from the sample spread, widened by
    ``t_{D−1}(p) / Φ⁻¹(p)`` at the quantile ``p`` that :func:`assert_statistic` uses for ``entries`` entries:
    the studentised mean is t-distributed, and the helper's normal limit is then the t limit."""
    x = np.asarray(x, dtype=np.float64)
    D = x.shape[0]
    p = 1.0 - FALSE_FAILURE / (2 * entries)
    return x.mean(0), x.std(0, ddof=1) / math.sqrt(D) * t.ppf(p, D - 1) / norm.ppf(p)


# --- the algebra ---------------------------------------------------------------------------------------------


def _information(gen, B: int, K: int, m: int, spread: float | None) -> torch.Tensor:
    """``M_k = Σ_j (I − r_j r_jᵀ)`` of ``m`` stars per frame ``[B, K, 3, 3]``: uniform over the sky, or within
    ``spread`` rad of a boresight that turns from frame to frame (a narrow camera: a poorly observed roll)."""
    if spread is None:
        r = random_unit_vectors(gen, B, K, m)
    else:
        axis = random_unit_vectors(gen, B, K, 1)
        r = axis + spread * torch.randn(B, K, m, 3, generator=gen, dtype=F64)
        r = r / r.norm(dim=-1, keepdim=True)
    return m * torch.eye(3, dtype=F64) - r.transpose(-1, -2) @ r


def _expected_products(q: torch.Tensor, r: torch.Tensor, information: torch.Tensor, p0: float, lags: int):
    """``E[e_{k+j} e_kᵀ]`` ``[B, lags, K−1, 3, 3]`` from the covariance of the whole sequence, built without the
    module's coefficients: ``Cov(z_k, z_l) = P₀ + q min(k, l) I + δ_kl r M_k⁻¹`` (``θ₀ ~ N(0, P₀ I)`` shared by
    every frame), differenced by the matrix ``Δ`` of ``e = Δ z``."""
    B, K = information.shape[:2]
    eye = torch.eye(3, dtype=F64)
    k = torch.arange(K, dtype=F64)
    walk = torch.minimum(k[:, None], k[None, :])  # [K, K]
    cov = (p0 + q[:, None, None, None, None] * walk[None, :, :, None, None]) * eye  # [B, K, K, 3, 3]
    idx = torch.arange(K)
    cov[:, idx, idx] += r[:, None, None, None] * torch.linalg.inv(information)
    cov = cov.transpose(2, 3).reshape(B, 3 * K, 3 * K)
    diff = torch.zeros(3 * (K - 1), 3 * K, dtype=F64)
    for i in range(K - 1):
        diff[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = -eye
        diff[3 * i : 3 * i + 3, 3 * i + 3 : 3 * i + 6] = eye
    cov_e = (diff @ cov @ diff.T).reshape(B, K - 1, 3, K - 1, 3).transpose(2, 3)  # [B, K−1, K−1, 3, 3]
    out = torch.zeros(B, lags, K - 1, 3, 3, dtype=F64)
    for j in range(lags):
        out[:, j, : K - 1 - j] = cov_e[:, idx[j : K - 1], idx[: K - 1 - j]]
    return out


@pytest.mark.parametrize(
    ("q", "r", "spread"),
    [(0.3, 0.7, None), (1e-13, 1e-10, 0.05)],
    ids=["comparable, stars over the sky", "case-1 magnitudes, a narrow camera"],
)
def test_expected_autocovariances_give_q_and_r_to_rounding(gen, q, r, spread):
    """Three data sets of two trajectories, each with its own ``(q, r)``, 14 frames, lags 0 … 3: the least-squares
    solution on the exact autocovariances is the truth up to rounding.  The system is consistent, so the
    perturbation bound of least squares is ``κ(A)(‖δA‖/‖A‖ + ‖δb‖/‖b‖)‖x‖`` (Golub & Van Loan, Thm. 5.3.1, the
    residual term vanishing): ``δA`` from the Cholesky solve for ``M_k⁻¹`` (``3κ(M_k)ε``), ``δb`` from the
    covariance's sums over ``K`` frames, where ``P₀`` and the walk's ``q·K`` cancel (``K(P₀ + qK + r λ_max)ε``
    against the products' scale), and the solver's backward error (``rows·ε``)."""
    D, per, K, lags, p0 = 3, 2, 14, 4, 1e-4
    scale = torch.tensor([1.0, 2.0, 0.5], dtype=F64)
    qs, rs = q * scale, r * scale.flip(0)
    information = _information(gen, D * per, K, 5, spread)
    q_b, r_b = qs.repeat_interleave(per), rs.repeat_interleave(per)
    expected = _expected_products(q_b, r_b, information, p0, lags)
    coefficients = autocovariance_coefficients(information, lags)
    q_hat, r_hat = solve_autocovariance_ls(expected, coefficients, datasets=D)

    A = coefficients.movedim(-3, -1).reshape(D, -1, 2)
    kappa_a = torch.linalg.cond(A)  # [D]
    ev = torch.linalg.eigvalsh(information)
    kappa_m = (ev[..., -1] / ev[..., 0]).reshape(D, -1).amax(-1)
    lam = (1.0 / ev[..., 0]).reshape(D, -1).amax(-1)
    b_scale = expected.reshape(D, -1).norm(dim=-1) / math.sqrt(A.shape[1])  # the rms product
    delta_b = K * (p0 + qs * K + rs * lam) * EPS / b_scale
    eta = 3 * kappa_m * EPS + delta_b + A.shape[1] * EPS
    bound = 4 * kappa_a * eta * torch.hypot(qs, rs)
    assert_within(q_hat, qs, bound, "q from the expected autocovariances")
    assert_within(r_hat, rs, bound, "r from the expected autocovariances")


def test_lags_beyond_one_do_not_move_the_solution(gen):
    """With the deadbeat gain the rows of lags ≥ 2 have zero coefficients: lags 0 … 5 give the lags-0-and-1
    solution, up to the solver's rounding (one orthogonal factorisation against another of the same rows)."""
    B, K = 4, 20
    z = 1e-5 * torch.randn(B, K, 3, generator=gen, dtype=F64)
    information = _information(gen, B, K, 5, None)
    two = solve_autocovariance_ls(innovation_products(z, 2), autocovariance_coefficients(information, 2), datasets=2)
    six = solve_autocovariance_ls(innovation_products(z, 6), autocovariance_coefficients(information, 6), datasets=2)
    coefficients = autocovariance_coefficients(information, 2).movedim(-3, -1).reshape(2, -1, 2)
    kappa = torch.linalg.cond(coefficients)
    products = innovation_products(z, 2).reshape(2, -1)
    rows = coefficients.shape[1]
    # forward error of a least-squares solution with a residual: κ² ε ‖b‖ / σ_min(A) per solve, twice
    bound = 2 * rows * EPS * kappa**2 * products.norm(dim=-1) / torch.linalg.svdvals(coefficients)[:, -1]
    for a, b, name in zip(two, six, ("q", "r"), strict=True):
        assert_within(b, a, bound, f"{name} with lags 0 … 5 against lags 0 and 1")


def test_sampled_model_data_give_unbiased_q_and_r(gen):
    """z drawn from the model itself (a random walk of variance q per frame plus star noise of covariance
    ``r M_k⁻¹``, stars over the sky), 400 data sets of 2 × 40 frames: the estimates are linear in the products,
    so their means are unbiased; q and r of one order, so both are tested."""
    D, per, K, q, r = 400, 2, 40, 2e-11, 5e-11
    B = D * per
    information = _information(gen, B, K, 5, None)
    walk = torch.cumsum(math.sqrt(q) * torch.randn(B, K, 3, generator=gen, dtype=F64), 1)
    chol = torch.linalg.cholesky(torch.linalg.inv(information))
    v = math.sqrt(r) * (chol @ torch.randn(B, K, 3, 1, generator=gen, dtype=F64)).squeeze(-1)
    z = walk + v
    q_hat, r_hat = solve_autocovariance_ls(
        innovation_products(z, 2), autocovariance_coefficients(information, 2), datasets=D
    )
    mean, se = _mean_and_se(torch.stack((q_hat / q, r_hat / r), -1), 2)
    assert_statistic(mean, 1.0, se, "mean of q̂/q and r̂/r over sampled model data", false_failure=FALSE_FAILURE)


# --- frame errors ----------------------------------------------------------------------------------------------


def _rounding(rec, fe) -> torch.Tensor:
    """A bound on the rounding of each frame error ``[B, K]`` (rad): a few ε per gyro step in the reference
    (``4ε`` per product and renormalisation, the simulator's truth as much again) and the star fix's rounding,
    amplified about the worst-determined axis by up to ``m λ_max(M_k⁻¹)`` (``m`` the frame's stars)."""
    m = torch.as_tensor(rec.star_mask[:, fe.rows].sum(-1), dtype=F64)
    lam = 1.0 / torch.linalg.eigvalsh(fe.information)[..., 0]
    return 8 * EPS * (torch.as_tensor(fe.rows, dtype=F64) + m * lam)


def test_noise_free_data_give_zero_frame_errors(gen):
    """Case 1 without any noise: the gyro reference and every star fix are the truth, z = 0 up to rounding."""
    rec, _ = _case1(gen, 4, 120.0, sigma_v=0.0, sigma_u=0.0, sigma_s=0.0)
    fe = frame_errors(rec)
    assert_within(fe.z.norm(dim=-1), 0.0, _rounding(rec, fe), "|z| of noise-free data")
    assert fe.frame_period == 1.0 and fe.z.shape == (4, 120, 3)


def test_a_wrong_start_cancels_in_the_innovations(gen):
    """A start 1.2e-4 rad off adds a constant to z (the gyro turns both attitudes alike), rotated into the wrong
    start's frame: the innovations change by no more than ``|θ₀|`` times the frame errors (the first-order
    rotation and the BCH term ``½ θ₀ × α``), plus the rounding of the noise-free case."""
    rec, _ = _case1(gen, 4, 30.0)
    truth0 = torch.as_tensor(rec.truth_mrp[:, 0])
    offset = torch.tensor([0.25e-4, -0.15e-4, 0.1e-4], dtype=F64)  # MRP: 4× is the angle
    theta0 = 4 * float(offset.norm())
    fe = frame_errors(rec)
    right = fe.z
    wrong = frame_errors(rec, initial_mrp=mrp_compose(truth0, offset.expand(4, 3))).z
    size, rounding = right.norm(dim=-1), _rounding(rec, fe)
    bound = (2 * theta0 * (size[:, 1:] + size[:, :-1]) + 2 * (rounding[:, 1:] + rounding[:, :-1]))[..., None]
    e_right, e_wrong = right.diff(dim=1), wrong.diff(dim=1)
    assert_within(e_wrong, e_right, bound, "innovations from a start 1.2e-4 rad off")


# --- the simulator ---------------------------------------------------------------------------------------------


def test_case1_estimates_are_unbiased(gen):
    """64 data sets of one 60 s case-1 trajectory: the mean of q̂ and r̂ is the truth within its standard error
    (σ's √ is biased and undefined for a negative solution; q̂ and r̂ are linear in the products, so unbiased).
    On these data the unweighted least squares hardly sees q (a standard error of about a thousand q per data set:
    the roll axis's star noise dominates the rows), so this checks mostly r; the next test gives q its teeth."""
    rec, s = _case1(gen, 64, 60.0)
    est = autocovariance_least_squares(rec, datasets=64)
    assert est.q.shape == est.r.shape == est.sigma_v.shape == est.sigma_s.shape == (64,)
    assert est.frames == 60 and est.frame_period == 1.0 and est.lags == 2
    q = s["sigma_v"] ** 2 * est.frame_period
    mean, se = _mean_and_se(torch.stack((est.q / q, est.r / s["sigma_s"] ** 2), -1), 2)
    assert_statistic(mean, 1.0, se, "case 1: mean of q̂/q and r̂/r", false_failure=FALSE_FAILURE)
    positive = torch.stack((est.q_positive, est.r_positive))
    sigma = torch.stack((est.sigma_v, est.sigma_s))
    assert bool((torch.isnan(sigma) == ~positive).all())


def test_the_gyro_alone_is_an_inertial_random_walk(gen):
    """Case 1 with noise-free stars: the innovations are the gyro reference's error increments alone, ``e_k = w_k``,
    white and isotropic with variance q per axis in the inertial frame while the body turns 5° per frame (in the
    body frame the accumulated error would turn with it: lag-1 correlations and lag-0 variances growing with time,
    to a few tenths of q here).  16 trajectories of 120 s, ``n = 16 × 119`` innovations: the sample autocovariances' entries have
    the standard errors of products of independent normals, ``√(2/n)`` on the lag-0 diagonal, ``√(1/n)``
    elsewhere.  ALS then finds q (16 data sets) and r = 0 within their errors."""
    rec, s = _case1(gen, 16, 120.0, sigma_s=0.0)
    q = s["sigma_v"] ** 2 * s["star_period"]
    e = frame_errors(rec).z.diff(dim=1) / math.sqrt(q)
    n = e.shape[0] * e.shape[1]
    lag0 = torch.einsum("bki,bkj->ij", e, e) / n
    lag1 = torch.einsum("bki,bkj->ij", e[:, 1:], e[:, :-1]) / (n - e.shape[0])
    iu = torch.triu_indices(3, 3)
    eye = torch.eye(3, dtype=F64)
    se0 = torch.sqrt((1.0 + eye) / n)[iu[0], iu[1]]
    assert_statistic(
        torch.cat((lag0[iu[0], iu[1]], lag1.reshape(-1))),
        torch.cat((eye[iu[0], iu[1]], torch.zeros(9, dtype=F64))),
        torch.cat((se0, torch.full((9,), math.sqrt(1.0 / (n - e.shape[0])), dtype=F64))),
        "noise-free stars: the innovations' autocovariances at lags 0 and 1 (in units of q)",
        false_failure=FALSE_FAILURE,
    )
    est = autocovariance_least_squares(rec, datasets=16)
    mean, se = _mean_and_se(torch.stack((est.q / q, est.r / q), -1), 2)
    assert_statistic(mean, [1.0, 0.0], se, "noise-free stars: mean of q̂/q and r̂/q", false_failure=FALSE_FAILURE)


# --- refusals --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small():
    """4 case-1 trajectories of 6 s: frames at rows 10, 20, … 60."""
    cfg = load_config("case1", ["runs=4", "duration=6", "compile=false", "compile_fused=false"])
    return record_environment(envs.StarTrackerAttitudeVectorEnv(num_envs=4, **cfg.env_settings()), 60, seed=3)


def _with_mask(rec, change):
    mask = rec.star_mask.copy()
    change(mask)
    return dataclasses.replace(rec, star_mask=mask)


def _drop_frame(mask):
    mask[:, 30] = False


def _drop_one(mask):
    mask[1, 30] = False


def _one_star(mask):
    mask[2, 40, 1:] = False


def _first_rows(rec, n):
    cut = {f.name: getattr(rec, f.name) for f in dataclasses.fields(rec)}
    return type(rec)(**{k: (v[:n] if k == "time" else v[:, :n]) if v is not None else None for k, v in cut.items()})


def test_a_good_small_recording_runs(small):
    est = autocovariance_least_squares(small, datasets=2, lags=5)
    assert est.frames == 6 and est.q.shape == (2,)


@pytest.mark.parametrize(
    ("make", "kwargs", "match"),
    [
        (lambda r: _first_rows(r, 25), {}, "at least 3 star frames per trajectory .* got 2"),
        (lambda r: _with_mask(r, _drop_one), {}, "differ between trajectories: trajectory 1 lacks a frame at row 30"),
        (lambda r: _with_mask(r, _drop_frame), {}, "not uniformly spaced: frames at rows 20 and 40 are 2 s apart"),
        (lambda r: _with_mask(r, _one_star), {}, "row 40 .* of trajectory 2 determines no attitude .1 valid star"),
        (lambda r: dataclasses.replace(r, truth_bias=None), {}, "no truth_bias column"),
        (lambda r: dataclasses.replace(r, truth_mrp=None, truth_bias=None), {"bias": torch.zeros(4, 3)}, "row 0"),
        (lambda r: r, {"bias": torch.zeros(4, 1)}, r"bias must have shape \[4, 3\]"),
        (lambda r: r, {"initial_mrp": torch.zeros(3)}, r"initial_mrp must have shape \[4, 3\]"),
        (lambda r: r, {"datasets": 3}, "4 trajectories do not split into 3 data sets"),
        (lambda r: r, {"datasets": 0}, "datasets must be a positive integer"),
        (lambda r: r, {"datasets": True}, "datasets must be a positive integer"),
        (lambda r: r, {"lags": 1}, "lags must be an integer ≥ 2"),
        (lambda r: r, {"lags": 6}, "lags must be at most K − 1 = 5"),
    ],
    ids=[
        "two frames",
        "frames differ",
        "irregular frames",
        "one star",
        "no bias",
        "no start",
        "bias shape",
        "start shape",
        "datasets not dividing",
        "datasets zero",
        "datasets bool",
        "one lag",
        "too many lags",
    ],
)
def test_refusals_name_what_is_wrong(small, make, kwargs, match):
    with pytest.raises(ValueError, match=match):
        autocovariance_least_squares(make(small), **kwargs)


def test_an_invalid_gyro_sample_is_refused(small):
    valid = np.ones_like(small.gyro_valid)
    valid[2, 17] = False
    with pytest.raises(ValueError, match="gyro sample invalid at trajectory 2, row 17"):
        autocovariance_least_squares(dataclasses.replace(small, gyro_valid=valid))


def test_a_start_from_the_recording_or_the_caller(small):
    """Without the truth the recording's initial_mrp (or the caller's) starts the reference: the same start gives
    the same frame errors (up to the rounding of :func:`_rounding`, as the order of a reduction may differ)."""
    start = small.truth_mrp[:, 0]
    no_truth = dataclasses.replace(small, truth_mrp=None, initial_mrp=start)
    truth = frame_errors(small)
    bound = _rounding(small, truth)[..., None]
    assert_within(frame_errors(no_truth).z, truth.z, bound, "z started from the initial_mrp column")
    assert_within(
        frame_errors(small, initial_mrp=torch.as_tensor(start)).z, truth.z, bound, "z from the caller's start"
    )
    assert autocovariance_least_squares(no_truth).r.shape == (1,)
