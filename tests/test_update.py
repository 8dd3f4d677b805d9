"""The measurement update: a precise sensor after a wide prior, the covariance form kept where it is
accurate, and bad input named before anything changes.

Expected values come from an independent computation: the same linearised update (the ``h``, ``H``,
``R`` and ``P`` the update sees) in 50-digit arithmetic (mpmath), with the textbook formulas
``K = P Hᵀ S⁻¹``, ``P⁺ = P − K S Kᵀ``, ``νᵀS⁻¹ν`` and ``log det S``.
"""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest
import torch
from scipy import stats
from scipy.stats import chi2

from agsf_torch import update as update_module
from agsf_torch.consistency import chi2_band
from agsf_torch.experiments.config.factories import make_env, make_filters, prior_covariance
from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.run.runner import run_monte_carlo
from agsf_torch.filters import ExtendedKalmanFilter, MultiplicativeEKF
from agsf_torch.gating import innovation_gate
from agsf_torch.mixture import GaussianMixture
from agsf_torch.models import AttitudeModel, FunctionMeasurement, StarVectorMeasurement
from agsf_torch.models.star_vectors import tangent_basis
from agsf_torch.update import evaluate_measurement, kalman_update
from tests.helpers import EAGER, F64, assert_within, random_mrps

EPS = float(np.finfo(np.float64).eps)
PRIOR_VAR = 1e-3  # MRP² per axis: ≈ 7° per axis, the paper's prior


def _frame(gen, B, N, sigma, M=5, fov_deg=8.0, noise_model="isotropic", mean_error=PRIOR_VAR**0.5):
    """``B`` trajectories, ``N`` components with the 1e-3 prior covariance whose means lie ``mean_error``
    (per axis, MRP) around the truth (default: drawn from the prior), ``M`` stars in one camera field of
    view (the geometry of the paper's star tracker)."""
    truth = random_mrps(B, gen, max_norm=0.5)
    bore = torch.randn(B, 1, 3, generator=gen, dtype=F64)
    r = bore / bore.norm(dim=-1, keepdim=True) + math.radians(fov_deg / 4) * torch.randn(
        B, M, 3, generator=gen, dtype=F64
    )
    r = r / r.norm(dim=-1, keepdim=True)
    means = truth[:, None] + mean_error * torch.randn(B, N, 3, generator=gen, dtype=F64)
    covs = PRIOR_VAR * torch.eye(3, dtype=F64).expand(B, N, 3, 3)
    body = StarVectorMeasurement(r, sigma=sigma).predict(truth).reshape(B, M, 3)
    body = body + sigma * torch.randn(B, M, 3, generator=gen, dtype=F64)
    body = body / body.norm(dim=-1, keepdim=True)
    meas = StarVectorMeasurement(r, sigma=sigma, noise_model=noise_model, body=body)
    log_w = torch.log(torch.rand(B, N, generator=gen, dtype=F64) + 0.5)
    return truth, means, covs, log_w - torch.logsumexp(log_w, -1, keepdim=True), body.flatten(-2), meas


def _mp(t: torch.Tensor) -> mpmath.matrix:
    return mpmath.matrix(t.tolist())


def _exact(P, H, R, nu, T=None):
    """50-digit textbook update of one component: ``(δx, P⁺, νᵀS⁻¹ν, log det S, rounding)`` as float64 tensors,
    and with ``T`` (the tangent bases of the measured star vectors, ``[d, 2m]``) the data's log-density
    ``log N(Tᵀν; 0, TᵀST)``."""
    mpmath.mp.dps = 50
    P, H, R, nu = _mp(P), _mp(H), _mp(R), _mp(nu)
    S = H * P * H.T + R
    data = None
    if T is not None:
        T = _mp(T)
        S_t, v = T.T * S * T, T.T * nu
        data = -0.5 * (
            (v.T * mpmath.lu_solve(S_t, v))[0] + mpmath.log(mpmath.det(S_t)) + S_t.rows * mpmath.log(2 * mpmath.pi)
        )
        # its rounding in float64: backward-stable steps, κ(S_t)ε of the terms (bounded by the Frobenius form)
        data = (data, float(mpmath.mnorm(S_t, "F") * mpmath.mnorm(mpmath.inverse(S_t), "F")))
    S_inv_nu = mpmath.lu_solve(S, nu)
    K = P * H.T * mpmath.inverse(S)
    dx, P_post = K * nu, P - K * S * K.T
    to = lambda m: torch.tensor([[float(m[i, j]) for j in range(m.cols)] for i in range(m.rows)], dtype=F64)
    # the rounding any float64 update makes in δx = (PHᵀ)(S⁻¹ν): the solve to κ(S)ε of ‖S⁻¹ν‖, then PHᵀ
    condition = float(mpmath.mnorm(S, "F") * mpmath.mnorm(mpmath.inverse(S), "F"))  # ≥ κ₂(S)
    rounding = torch.finfo(F64).eps * float(mpmath.mnorm(P * H.T, "F")) * condition * float(mpmath.norm(S_inv_nu))
    log_det = float(mpmath.log(mpmath.det(S)))
    return to(dx)[:, 0], to(P_post), float((nu.T * S_inv_nu)[0]), log_det, rounding, data


def _check_against_exact(
    res, log_w, means, covs, y, meas, *, mean_tol, cov_tol, nis_tol, data_tol=0.0, solve_rounding=False
):
    """``res`` against the 50-digit update: the mean to ``mean_tol`` posterior σ, plus ``data_tol(1 + √NIS)`` σ
    for data known only to ``data_tol`` (relative) and, for the covariance form (``solve_rounding``), the
    rounding of its solve with ``S``, ``16 κ(S) ε ‖PHᵀ‖ ‖S⁻¹ν‖``."""
    h, H = evaluate_measurement(meas, means)
    R = meas.noise_cov().expand(*means.shape[:-2], y.shape[-1], y.shape[-1])
    B, N = log_w.shape
    log_beta = torch.empty(B, N, dtype=F64)
    log_data = torch.empty(B, N, dtype=F64)  # the data's: two degrees of freedom per star vector
    data_condition = 1.0
    for b in range(B):
        v = y[b].unflatten(-1, (-1, 3))
        T = torch.block_diag(*tangent_basis(v / v.norm(dim=-1, keepdim=True)))
        for i in range(N):
            dx, P_post, nis, log_det, rounding, data = _exact(covs[b, i], H[b, i], R[b], y[b] - h[b, i], T)
            log_data[b, i] = float(data[0])
            data_condition = max(data_condition, data[1])
            sd = torch.linalg.eigvalsh(P_post)[0].sqrt()  # smallest posterior standard deviation
            bound = (mean_tol + data_tol * (1.0 + math.sqrt(nis))) * float(sd) + (
                16 * rounding if solve_rounding else 0.0
            )
            assert_within(res.means[b, i] - means[b, i], dx, bound, "mean correction")
            # a relative error of cov_tol in the norm: each entry to cov_tol of ‖P⁺‖ (entries near 0 included)
            assert_within(res.covs[b, i], P_post, cov_tol * float(P_post.norm()), "posterior covariance")
            assert_within(res.nis[b, i], nis, nis_tol * nis, "NIS")
            log_beta[b, i] = -0.5 * (nis + log_det + y.shape[-1] * math.log(2 * math.pi))
    joint = log_w + log_beta  # log-likelihood and weights: the NIS's accuracy on its scale
    scale = nis_tol * float(log_beta.abs().max()) + 1e-9
    data_scale = max(nis_tol, 64 * torch.finfo(F64).eps * data_condition) * float(log_data.abs().max()) + 1e-9
    assert_within(res.log_likelihood, torch.logsumexp(log_w + log_data, -1), data_scale, "the data's log-likelihood")
    assert_within(res.log_weights, joint - torch.logsumexp(joint, -1, keepdim=True), 2 * scale, "log-weights")
    # the posterior covariances are symmetric positive definite
    assert torch.equal(res.covs, res.covs.transpose(-1, -2))
    assert bool((torch.linalg.cholesky_ex(res.covs).info == 0).all())


# --------------------------------------------------------------------------- A. precise sensor
def test_precise_sensor_after_wide_prior_matches_the_exact_update(gen):
    # σ_s = 1 nrad after the 1e-3 prior, means drawn from it: cond(S) ≈ 4e16, beyond float64 for a
    # Cholesky factor of S (it failed: "innovation covariance is not positive definite")
    _, means, covs, log_w, y, meas = _frame(gen, B=3, N=2, sigma=1e-9)
    res = kalman_update(log_w, means, covs, y, meas)
    _check_against_exact(res, log_w, means, covs, y, meas, mean_tol=1e-3, cov_tol=1e-9, nis_tol=1e-9)


def test_precise_sensor_with_tangent_noise_matches_the_exact_update(gen):
    # the camera noise model, R_j = σ_s²(I − b̃b̃ᵀ) + σ_r²b̃b̃ᵀ (σ_r = 1e-3): its float64 entries carry σ_s²
    # to ε·σ_r²/σ_s² ≈ 2e-4 only, so the update is well posed only where the linearised equations are
    # consistent to σ_s (means within a few σ_s of the truth; far off, rounding R moves the exact answer
    # by ~100 σ).  The covariance is still the wide prior's.
    _, means, covs, log_w, y, meas = _frame(gen, B=3, N=2, sigma=1e-9, noise_model="tangent", mean_error=1e-9)
    res = kalman_update(log_w, means, covs, y, meas)
    cov_tol = torch.finfo(F64).eps * (meas.radial_sigma / 1e-9) ** 2  # ≈ 2e-4, the data's own precision
    _check_against_exact(
        res, log_w, means, covs, y, meas, mean_tol=1e-6, cov_tol=cov_tol, nis_tol=cov_tol, data_tol=16 * cov_tol
    )


def test_covariance_form_is_kept_where_accurate_and_the_information_form_agrees(gen, monkeypatch):
    # σ_s = 10 µrad (the paper's): cond(S) ≈ 4e8, the covariance form; forcing the information
    # form everywhere (threshold 1: every S counts as ill-conditioned) gives the same update
    _, means, covs, log_w, y, meas = _frame(gen, B=3, N=2, sigma=1e-5)
    default = kalman_update(log_w, means, covs, y, meas)
    _check_against_exact(
        default, log_w, means, covs, y, meas, mean_tol=1e-6, cov_tol=1e-9, nis_tol=1e-7, solve_rounding=True
    )
    monkeypatch.setattr(update_module, "COVARIANCE_FORM_MAX_CONDITION", math.inf)  # covariance form only
    plain = kalman_update(log_w, means, covs, y, meas)
    for field in ("means", "covs", "log_weights", "nis", "nis_mixture"):
        assert torch.equal(getattr(default, field), getattr(plain, field)), field
    monkeypatch.setattr(update_module, "COVARIANCE_FORM_MAX_CONDITION", 1.0)
    forced = kalman_update(log_w, means, covs, y, meas)
    _check_against_exact(forced, log_w, means, covs, y, meas, mean_tol=1e-6, cov_tol=1e-12, nis_tol=1e-12)


def test_mixture_and_gate_nis_for_a_precise_sensor(gen):
    # the moment-matched NIS of the whole measurement (update diagnostic) and of each star (gate)
    _, means, covs, log_w, y, meas = _frame(gen, B=2, N=3, sigma=1e-9)
    res = kalman_update(log_w, means, covs, y, meas)
    _, gate_nis, _, _ = innovation_gate(log_w, means, covs, y, meas, 21.1)
    h, H = evaluate_measurement(meas, means)
    mpmath.mp.dps = 50
    for b in range(2):
        w = [mpmath.exp(mpmath.mpf(float(v))) for v in log_w[b]]
        nus = [_mp(y[b] - h[b, i]) for i in range(3)]
        Ss = [_mp(H[b, i]) * _mp(covs[b, i]) * _mp(H[b, i]).T + _mp(meas.noise_cov()) for i in range(3)]
        for rows, got in [(slice(0, 15), res.nis_mixture[b])] + [
            (slice(3 * j, 3 * j + 3), gate_nis[b, j]) for j in range(5)
        ]:
            idx = list(range(15))[rows]
            Ssub = [mpmath.matrix([[S[i, k] for k in idx] for i in idx]) for S in Ss]
            nv = [mpmath.matrix([v[i] for i in idx]) for v in nus]
            nu_bar = sum((wi * v for wi, v in zip(w, nv)), mpmath.zeros(len(idx), 1))
            S_bar = sum(
                (wi * (S + (v - nu_bar) * (v - nu_bar).T) for wi, S, v in zip(w, Ssub, nv)), mpmath.zeros(len(idx))
            )
            expect = float((nu_bar.T * mpmath.lu_solve(S_bar, nu_bar))[0])
            assert_within(got, expect, 1e-8 * expect, "moment-matched NIS")


def test_iterated_update_is_consistent_for_a_precise_sensor(gen):
    # truths drawn from the 1e-3 prior, σ_s = 1 nrad: after Gauss–Newton the error is at the level of the
    # posterior covariance (a few nrad) and the NEES is χ²₃: its average over 200 trajectories inside the
    # band, and every trajectory's below the χ²₃ quantile, each at a false-alarm probability of 5e-7
    B = 200
    truth, means, covs, log_w, y, meas = _frame(gen, B=B, N=1, sigma=1e-9)
    res = kalman_update(log_w, means, covs, y, meas, iterations=8)
    err = (res.means[:, 0] - truth).unsqueeze(-1)
    L = torch.linalg.cholesky(res.covs[:, 0])
    nees = torch.linalg.solve_triangular(L, err, upper=False).square().sum((-2, -1))
    lo, hi = chi2_band(3, B, confidence=1.0 - 5e-7)
    assert lo <= float(nees.mean()) <= hi
    assert float(nees.max()) <= stats.chi2.isf(5e-7 / B, 3)
    # converged: more iterations move the mean by rounding only (far below the posterior's nrad)
    more = kalman_update(log_w, means, covs, y, meas, iterations=16)
    sd = float(res.covs.diagonal(dim1=-2, dim2=-1).sqrt().min())
    assert_within(more.means, res.means, 1e-3 * sd, "mean after 16 Gauss–Newton iterations against 8")


def test_filters_update_a_precise_sensor_after_a_wide_prior(gen):
    # every filter sharing the update takes the first frame of σ_s = 1 nrad after the 1e-3 prior.  The
    # correction is large (|δθ| up to ~0.5 rad), so the MEKF carries its covariance to the new reference
    # (covariance_reset=True); the classic reset leaves it, an O(|δθ|) error that makes its NEES reach ~60
    truth, means, covs, log_w, y, meas = _frame(gen, B=3, N=1, sigma=1e-9)
    model = AttitudeModel(estimate_bias=False)
    mix = GaussianMixture(log_weights=log_w, means=means, covs=covs)
    mekf = MultiplicativeEKF(model, update_iterations=8, covariance_reset=True)
    for filt in (ExtendedKalmanFilter(model, update_iterations=8), mekf):
        post = filt.update(mix, y, meas)
        mean, cov = filt.estimate(post)
        err = (mean - truth).unsqueeze(-1)
        nees = torch.linalg.solve_triangular(torch.linalg.cholesky(cov), err, upper=False).square().sum((-2, -1))
        assert bool((nees < stats.chi2.isf(1e-6 / 6, 3)).all()), (type(filt).__name__, nees)  # 6 draws, 1e-6
        assert bool(torch.isfinite(filt.diagnostics["nis_mixture"]).all())


# --------------------------------------------------------------------------- B. bad input, named
def test_non_finite_mean_and_measurement_are_named(gen):
    _, means, covs, log_w, y, meas = _frame(gen, B=4, N=2, sigma=1e-5)
    bad = means.clone()
    bad[2, 1, 0] = float("nan")
    with pytest.raises(ValueError, match=r"state mean is not finite at trajectory index \(2,\), component 1"):
        kalman_update(log_w, bad, covs, y, meas)
    y_bad = y.clone()
    y_bad[3, 7] = float("inf")
    with pytest.raises(ValueError, match=r"measurement y is not finite at trajectory index \(3,\), entry 7"):
        kalman_update(log_w, means, covs, y_bad, meas)
    cov_bad = covs.clone()
    cov_bad[1, 0, 2, 2] = float("nan")
    with pytest.raises(ValueError, match=r"innovation variance .* trajectory index \(1,\), component 0"):
        kalman_update(log_w, means, cov_bad, y, meas)
    with pytest.raises(ValueError, match=r"state mean is not finite at trajectory index \(2,\), component 1"):
        innovation_gate(log_w, bad, covs, y, meas, 21.1)


@pytest.mark.parametrize("gate", [None, 0.9999])
def test_absurd_measurement_is_named_before_anything_changes(gen, gate):
    # y = 1e100 in a valid entry: 1e105 standard deviations off.  It was "covariance lost positive
    # definiteness" (EKF, after the MRP shadow switch of a 1e100 mean) or a silent garbage posterior
    # (MEKF).  A model without checks of its own (a plain function) shows the update's message.
    _, means, covs, log_w, y, meas = _frame(gen, B=4, N=1, sigma=1e-5)
    plain = FunctionMeasurement(meas.predict, 1e-10 * torch.eye(15, dtype=F64), jacobian=meas.jacobian)
    model = AttitudeModel(estimate_bias=False)
    mix = GaussianMixture(log_weights=log_w, means=means, covs=covs)
    y_bad = y.clone()
    y_bad[2, 4] = 1e100
    for filt in (ExtendedKalmanFilter(model, gate_probability=gate), MultiplicativeEKF(model, gate_probability=gate)):
        filt.diagnostics = {"before": 1}
        with pytest.raises(ValueError, match=r"measurement entry 4 at trajectory index \(2,\), component 0 is absurd"):
            filt.update(mix, y_bad, plain)
        assert filt.diagnostics == {"before": 1}
    assert torch.equal(mix.means, means) and torch.equal(mix.covs, covs)


def test_absurd_value_in_a_masked_entry_is_ignored(gen):
    _, means, covs, log_w, y, meas = _frame(gen, B=3, N=2, sigma=1e-5)
    mask = torch.ones(3, 5, dtype=torch.bool)
    mask[1, 2] = False
    masked = StarVectorMeasurement(meas.r_inertial, mask, 1e-5)
    y_placeholder = y.clone()
    y_placeholder[1, 6:9] = 1e100
    ref = kalman_update(log_w, means, covs, y, masked)
    res = kalman_update(log_w, means, covs, y_placeholder, masked)
    assert torch.equal(res.means, ref.means) and torch.equal(res.covs, ref.covs)
    assert torch.equal(res.log_weights, ref.log_weights)


@pytest.mark.parametrize(("iterations", "noise_model"), [(1, "isotropic"), (6, "tangent")])
def test_case1_runs_with_a_precise_sensor(iterations, noise_model):
    """The paper's case 1 at σ_s = 1 nrad (prior 1e-3), EKF, GSF and AGSF, 3 runs × 2 s (frames at 1 s
    and 2 s).  It stopped at the first frame ("innovation covariance is not positive definite").

    The one-linearisation update (the paper's) completes with finite estimates; its first-frame error
    is its linearisation error, |δθ|²-sized (measured 0.04°–0.26° from prior errors of several degrees:
    the EKF's own limit, not a numerical one — test_precise_sensor_after_wide_prior_matches_the_exact_update),
    and the second frame shrinks it in every run.  With 6 linearisations (Gauss–Newton from ≈ 7° to σ_s) the errors at
    both frames are σ-level: NEES below the χ²₃ 1 − 1e-6 quantile (30.7) for every run and filter."""
    cfg = load_config(
        "case1",
        [
            "runs=3",
            "duration=2.0",
            "sigma_s=1e-9",
            *EAGER,
            "components=3",
            f"update_iterations={iterations}",
            f"star_noise_model={noise_model!r}".replace("'", '"'),
            'filters=["EKF", "GSF", "AGSF"]',
        ],
    )
    res = run_monte_carlo(
        make_env(cfg),
        make_filters(cfg),
        num_steps=cfg.num_steps,
        prior_cov=prior_covariance(cfg),
        sigma_s=cfg.sigma_s,
        seed=cfg.seed,
        estimate_bias=cfg.estimate_bias,
        noise_model=cfg.star_noise_model,
    )
    frames = np.flatnonzero(res.star_frame)
    assert len(frames) == 2
    for name, trace in res.traces.items():
        assert np.isfinite(trace.error).all() and np.isfinite(trace.sigma).all() and np.isfinite(trace.nees).all(), name
        assert np.isfinite(trace.nis[:, frames]).all(), name
        err_deg = np.degrees(trace.error_angle[:, frames].T)  # [frame, run]
        if iterations == 1:
            assert err_deg[0].max() < 1.0 and (err_deg[1] < 0.1 * err_deg[0]).all(), (name, err_deg)
        else:
            assert trace.nees[:, frames].max() < 30.7, (name, trace.nees[:, frames])
            assert err_deg.max() < 1e-6, (name, err_deg)  # < 20 nrad: σ_s-level for 5 stars in 8°


def test_the_covariance_form_test_ignores_units_and_follows_the_dtype():
    """Entries in different units (S = diag(2e6, 2e-6)) are not ill-conditioning; a correlation
    condition of 1e3 is fine in float64 but beyond float32's error bound."""
    from agsf_torch.update import covariance_form_usable

    S = torch.diag(torch.tensor([2e6, 2e-6], dtype=torch.float64))
    L, info = torch.linalg.cholesky_ex(S)
    assert bool(covariance_form_usable(L, info, torch.ones(2), S))
    rho = 1 - 1e-3  # correlation condition ≈ 2e3
    C = torch.tensor([[1.0, rho], [rho, 1.0]], dtype=torch.float64)
    for dtype, usable in ((torch.float64, True), (torch.float32, False)):
        L, info = torch.linalg.cholesky_ex(C.to(dtype))
        assert bool(covariance_form_usable(L, info, torch.ones(2), C.to(dtype))) is usable


def test_the_covariance_form_test_without_a_mask_counts_every_entry():
    from agsf_torch.update import covariance_form_usable

    gen = torch.Generator().manual_seed(5)
    v = torch.randn(4, 3, 1, generator=gen, dtype=torch.float64)
    floor = torch.tensor([1.0, 1.0, 1e-15, 1e-15], dtype=torch.float64)[:, None, None]
    S = v @ v.mT + floor * torch.eye(3, dtype=torch.float64)  # the last two near rank one: not usable
    L, info = torch.linalg.cholesky_ex(S)
    every = covariance_form_usable(L, info, torch.ones(4, 3), S)
    assert torch.equal(covariance_form_usable(L, info, None, S), every)
    assert every.tolist() == [True, True, False, False]


def test_the_second_order_update_of_a_quadratic_measurement_is_its_closed_form():
    # h(x) = x² on N(μ, P): E[h] = μ² + P, Var[h] = 4μ²P + 2P² (Gaussian moments), and the divided differences
    # along s = √P give c = 2P exactly: the update predicts μ² + P with S = 4μ²P + 2P² + R and gain K = 2μP/S
    mu, P, R, y = 0.7, 0.3, 0.04, 0.9
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, torch.tensor([[R]], dtype=F64))
    means = torch.tensor([[[mu]]], dtype=F64)
    covs = torch.tensor([[[[P]]]], dtype=F64)
    c = update_module.measurement_curvature(means, covs, meas)
    assert_within(c[0, 0, 0, 0], 2 * P, 16 * EPS * (mu * mu + P), "c of x² along √P")
    out = kalman_update(
        torch.zeros(1, 1, dtype=F64), means, covs, torch.tensor([[y]], dtype=F64), meas, second_order=True
    )
    H = 2 * mu
    S = H * H * P + 2 * P * P + R
    K = P * H / S
    mean = mu + K * (y - mu * mu - P)
    cov = (1 - K * H) ** 2 * P + K * K * (R + 2 * P * P)  # Joseph form with the second-order noise
    nis = (y - mu * mu - P) ** 2 / S
    scale = 16 * EPS * (1 + mu * mu + P + abs(y)) / R  # the gain divides by S ≥ R
    assert_within(out.innovation_cov[0, 0, 0, 0], S, 16 * EPS * S, "S with the second-order terms")
    assert_within(out.means[0, 0, 0], mean, scale, "second-order mean")
    assert_within(out.covs[0, 0, 0, 0], cov, scale * P, "second-order covariance")
    assert_within(out.nis[0, 0], nis, scale * (1 + nis), "second-order NIS")


def test_the_second_order_update_of_a_product_takes_the_mixed_terms():
    # h(x) = x₁x₂ on N(μ, P): E[h] = μ₁μ₂ + P₁₂ and Var[h] = HPHᵀ + P₁₁P₂₂ + P₁₂² with H = (μ₂, μ₁) (Gaussian
    # moments: ½tr(∇²h P ∇²h P)); the axes' second differences alone (c_k) would miss P₁₁P₂₂ − P₁₂² of it
    mu = torch.tensor([0.7, -0.4], dtype=F64)
    P = torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=F64)
    R, y = 0.04, 0.5
    meas = FunctionMeasurement(lambda x: x[..., :1] * x[..., 1:2], torch.tensor([[R]], dtype=F64))
    means, covs = mu[None, None], P[None, None]
    c, M = update_module.measurement_second_differences(means, covs, meas)
    assert c.shape == (1, 1, 2, 1) and M.shape == (1, 1, 1, 1)
    L = torch.linalg.cholesky(P)
    A = torch.tensor([[0.0, 1.0], [1.0, 0.0]], dtype=F64)
    LAL = L.T @ A @ L  # entry (k, l): s_kᵀ∇²h s_l
    bound = 32 * EPS * float((mu.abs().max() + L.abs().sum(0).max()) ** 2)
    assert_within(c[0, 0, :, 0], LAL.diagonal(), bound, "c_k of x₁x₂")
    assert_within(M[0, 0, 0, 0], LAL[0, 1], bound, "M_12 of x₁x₂")
    out = kalman_update(
        torch.zeros(1, 1, dtype=F64), means, covs, torch.tensor([[y]], dtype=F64), meas, second_order=True
    )
    H = torch.stack((mu[1], mu[0]))
    S = float(H @ P @ H) + R + float(P[0, 0] * P[1, 1] + P[0, 1] ** 2)
    pred = float(mu[0] * mu[1] + P[0, 1])
    K = P @ H / S
    mean = mu + K * (y - pred)
    IKH = torch.eye(2, dtype=F64) - K[:, None] * H[None, :]
    cov = IKH @ P @ IKH.T + (S - float(H @ P @ H)) * K[:, None] * K[None, :]  # Joseph form, R + the second order
    scale = 64 * EPS * (1 + float(mu.abs().max()) ** 2 + float(P.abs().max()) + abs(y)) / R
    assert_within(out.innovation_cov[0, 0, 0, 0], S, scale * S, "S of x₁x₂ with the mixed terms")
    assert_within(out.means[0, 0], mean, scale, "second-order mean of x₁x₂")
    assert_within(out.covs[0, 0], cov, scale * float(P.abs().max()), "second-order covariance of x₁x₂")


def test_the_second_order_terms_over_the_read_entries_are_those_over_every_axis(gen):
    # the star measurement reads the MRP only (state_entries 0–2): its second differences over the MRP's marginal
    # (3 axes, 3 pairs) give the update that every axis of the 6-state covariance gives (6 axes, 15 pairs), whose
    # bias axes add exact zeros (the Cholesky factor is lower triangular, the MRP first)
    from agsf_torch.models import StarVectorMeasurement

    class EveryEntry(StarVectorMeasurement):
        def state_entries(self):
            return None

    B, N, M = 4, 3, 2
    r = torch.nn.functional.normalize(torch.randn(B, M, 3, generator=gen, dtype=F64), dim=-1)
    means = torch.cat((0.2 * torch.randn(B, N, 3, generator=gen, dtype=F64), torch.zeros(B, N, 3, dtype=F64)), -1)
    G = torch.randn(B, N, 6, 6, generator=gen, dtype=F64)
    covs = 1e-3 * G @ G.transpose(-1, -2) + 1e-6 * torch.eye(6, dtype=F64)
    y = torch.nn.functional.normalize(torch.randn(B, M, 3, generator=gen, dtype=F64), dim=-1).flatten(-2)
    log_w = torch.log_softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    star, every = StarVectorMeasurement(r, sigma=1e-2), EveryEntry(r, sigma=1e-2)
    c3, M3 = update_module.measurement_second_differences(means, covs, star)
    c6, M6 = update_module.measurement_second_differences(means, covs, every)
    assert c3.shape[-2] == 3 and M3.shape[-2] == 3 and c6.shape[-2] == 6 and M6.shape[-2] == 15
    bound = 16 * EPS  # second differences of unit vectors: entries of |h| ≤ 1, four of them
    assert_within(c3, c6[..., :3, :], bound, "c along the MRP axes")
    assert_within(c6[..., 3:, :], torch.zeros_like(c6[..., 3:, :]), bound, "c along the bias axes")
    pairs = [(k, l) for k in range(6) for l in range(k + 1, 6)]
    mrp_pairs = [i for i, (k, l) in enumerate(pairs) if l < 3]
    assert_within(M3, M6[..., mrp_pairs, :], bound, "M across MRP axes")
    a = kalman_update(log_w, means, covs, y, star, second_order=True)
    b = kalman_update(log_w, means, covs, y, every, second_order=True)
    # the same prediction shift and noise to the rounding of the sums over axes, scaled by the gains (S ≥ σ²)
    scale = 64 * EPS * (1 + 1 / 1e-2**2 * float(covs.diagonal(dim1=-2, dim2=-1).max()))
    assert_within(a.means, b.means, scale, "means")
    assert_within(a.covs, b.covs, scale * float(covs.abs().max()), "covariances")
    assert_within(a.log_weights, b.log_weights, scale * (1 + b.nis.abs().max()), "log-weights")


def _iterated_plain_posterior_variance(mu, P, R, y):
    """The plain two-linearisation update of h(x) = x² by hand: its posterior variance."""
    H0 = 2 * mu
    x1 = mu + P * H0 / (H0 * H0 * P + R) * (y - mu * mu)
    H1 = 2 * x1
    K = P * H1 / (H1 * H1 * P + R)
    return (1 - K * H1) ** 2 * P + K * K * R


def test_the_iterated_second_order_update_keeps_the_priors_terms():
    # h(x) = x² again, two linearisations: the second at the first's mean x₁ (H = 2x₁), with the prior's
    # second-order terms (c = 2P: the prediction x₁² + P + H(μ − x₁), the noise R + 2P²), applied to the prior,
    # where h is not linear over the plain iterated posterior: its second-order size 3P₊²/R (c = 2P₊: the bias
    # P₊ and the variance 2P₊²) is above LINEAR_POSTERIOR
    mu, P, R, y = 0.3, 1.0, 1.0, 0.9
    P_plus = _iterated_plain_posterior_variance(mu, P, R, y)
    assert 3 * P_plus**2 / R > 2 * update_module.LINEAR_POSTERIOR
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, torch.tensor([[R]], dtype=F64))
    means = torch.tensor([[[mu]]], dtype=F64)
    covs = torch.tensor([[[[P]]]], dtype=F64)
    Y = torch.tensor([[y]], dtype=F64)
    out = kalman_update(torch.zeros(1, 1, dtype=F64), means, covs, Y, meas, iterations=2, second_order=True)
    H0 = 2 * mu
    x1 = mu + P * H0 / (H0 * H0 * P + 2 * P * P + R) * (y - mu * mu - P)
    H1 = 2 * x1
    S = H1 * H1 * P + R + 2 * P * P
    K = P * H1 / S
    nu = y - x1 * x1 - P - H1 * (mu - x1)
    mean = mu + K * nu
    cov = (1 - K * H1) ** 2 * P + K * K * (R + 2 * P * P)
    scale = 64 * EPS * (1 + mu * mu + P + abs(y)) / R  # two gains, each dividing by S ≥ R
    assert_within(out.innovation_cov[0, 0, 0, 0], S, scale * S, "S at the iterate with the prior's terms")
    assert_within(out.means[0, 0, 0], mean, scale, "iterated second-order mean")
    assert_within(out.covs[0, 0, 0, 0], cov, scale * P, "iterated second-order covariance")
    assert_within(out.nis[0, 0], nu * nu / S, scale * (1 + nu * nu / S), "iterated second-order NIS")


def test_the_iterated_second_order_update_keeps_the_plain_posterior_where_h_is_linear_over_it():
    # h(x) = x² from a prior the sensor narrows: over the plain iterated posterior the second-order size 3P₊²/R is
    # below LINEAR_POSTERIOR, so the second-order update returns the plain iterated update: the same computation
    mu, P, R, y = 0.7, 0.3, 0.04, 0.9
    P_plus = _iterated_plain_posterior_variance(mu, P, R, y)
    assert 3 * P_plus**2 / R < 0.5 * update_module.LINEAR_POSTERIOR
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, torch.tensor([[R]], dtype=F64))
    args = (torch.zeros(1, 1, dtype=F64), torch.tensor([[[mu]]], dtype=F64), torch.tensor([[[[P]]]], dtype=F64))
    Y = torch.tensor([[y]], dtype=F64)
    plain = kalman_update(*args, Y, meas, iterations=2)
    second = kalman_update(*args, Y, meas, iterations=2, second_order=True)
    for name in (
        "means",
        "covs",
        "log_weights",
        "log_likelihood",
        "nis",
        "innovation",
        "innovation_cov",
        "nis_mixture",
    ):
        assert torch.equal(getattr(second, name), getattr(plain, name)), name
    # one linearisation is not the mode: the second-order terms stay
    once = kalman_update(*args, Y, meas, iterations=1, second_order=True)
    assert not torch.equal(once.means, kalman_update(*args, Y, meas, iterations=1).means)


def test_the_iterated_second_order_update_chooses_per_mixture():
    # two trajectories of two components of h(x) = x²: in the first both are narrowed by the sensor (h linear over
    # their plain posteriors), and the mixture keeps its plain update; in the second one is (0.7, 0.3) and one sits
    # near h's stationary point, where the sensor hardly narrows it (not), and the whole mixture takes the prior's
    # terms, so that both components' likelihoods βᵢ, which set the weights, come from one approximation
    R, y = 0.04, 0.9
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, torch.tensor([[R]], dtype=F64))
    means = torch.tensor([[[0.7], [0.8]], [[0.7], [0.01]]], dtype=F64)
    covs = torch.tensor([[[[0.3]], [[0.3]]], [[[0.3]], [[0.1]]]], dtype=F64)
    log_w = torch.log(torch.tensor([[0.25, 0.75], [0.25, 0.75]], dtype=F64))
    Y = torch.tensor([[y], [y]], dtype=F64)
    sizes = [3 * _iterated_plain_posterior_variance(m, P, R, y) ** 2 / R for m, P in ((0.7, 0.3), (0.8, 0.3))]
    assert max(sizes) < 0.5 * update_module.LINEAR_POSTERIOR
    curved = 3 * _iterated_plain_posterior_variance(0.01, 0.1, R, y) ** 2 / R
    assert curved > 2 * update_module.LINEAR_POSTERIOR
    plain = kalman_update(log_w, means, covs, Y, meas, iterations=2)
    chosen = kalman_update(log_w, means, covs, Y, meas, iterations=2, second_order=True)
    with_terms = update_module._component_updates(
        means, covs, Y.unsqueeze(-2), meas, torch.tensor([[R]], dtype=F64), None, 2, prior_terms=True
    )
    for name, field in (
        ("means", "means"),
        ("covs", "covs"),
        ("nis", "nis"),
        ("innovation", "nu"),
        ("innovation_cov", "S"),
    ):
        got = getattr(chosen, name)
        assert torch.equal(got[0], getattr(plain, name)[0]), f"{name}: the linear mixture's plain update"
        assert torch.equal(got[1], getattr(with_terms, field)[1]), f"{name}: the curved mixture's, with the terms"
    assert torch.equal(chosen.log_weights[0], plain.log_weights[0])
    log_beta = -0.5 * (chosen.nis + torch.logdet(chosen.innovation_cov) + math.log(2 * math.pi))
    expected = torch.log_softmax(log_w + log_beta, -1)
    assert_within(chosen.log_weights, expected, 16 * EPS * (1 + log_beta.abs().max()), "Bayes' rule")
    # an inactive slot (weight 0) has no say: the second trajectory's curved slot switched off, it keeps its plain
    # update too
    off = log_w.clone()
    off[1] = torch.tensor([0.0, -math.inf], dtype=F64)
    plain_off = kalman_update(off, means, covs, Y, meas, iterations=2)
    chosen_off = kalman_update(off, means, covs, Y, meas, iterations=2, second_order=True)
    assert torch.equal(chosen_off.means, plain_off.means) and torch.equal(chosen_off.covs, plain_off.covs)


def test_a_frame_that_contradicts_the_prediction_takes_the_priors_terms():
    # h(x) = x² from (0.7, 0.3) with R = 0.04: y = 10 moves the iterates to x ≈ 4.2, where h is linear over the
    # narrow posterior (3P₊²/R ≈ 3e-6), but the NIS at the last linearisation, ν²/S ≈ 42, is far beyond the
    # χ²₁ quantile at PLAIN_POSTERIOR_PROBABILITY (10.8 at 0.999): the data contradict the component, and the
    # update keeps the prior's terms; y = 3 (NIS ≈ 4.2) keeps the plain posterior
    R = torch.tensor([[0.04]], dtype=F64)
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, R)
    log_w, means, covs = torch.zeros(1, 1, dtype=F64), torch.tensor([[[0.7]]], dtype=F64), torch.full((1, 1, 1, 1), 0.3)
    covs = covs.to(F64)
    bound = float(chi2.ppf(update_module.PLAIN_POSTERIOR_PROBABILITY, 1))
    for y, plain_kept in ((10.0, False), (3.0, True)):
        Y = torch.tensor([[y]], dtype=F64)
        parts = {
            terms: update_module._component_updates(means, covs, Y.unsqueeze(-2), meas, R, None, 2, prior_terms=terms)
            for terms in (False, True)
        }
        plain = parts[False]
        assert float(update_module.second_order_size(plain.means, plain.covs, meas, plain.R_eff, plain.valid)) < 1e-3
        assert (float(plain.nis[0, 0]) <= bound) == plain_kept
        assert not torch.equal(parts[True].means, plain.means)
        out = kalman_update(log_w, means, covs, Y, meas, iterations=2, second_order=True)
        chosen = parts[not plain_kept]
        assert torch.equal(out.means, chosen.means) and torch.equal(out.covs, chosen.covs), y


def test_a_plain_posterior_without_a_cholesky_factor_takes_the_priors_terms(monkeypatch):
    # the linear component of the test above, its plain posterior covariance replaced by an indefinite one (what
    # rounding could leave): the choice does not factor it, and the component takes the prior's terms
    R, y = 0.04, 0.9
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, torch.tensor([[R]], dtype=F64))
    args = (torch.zeros(1, 1, dtype=F64), torch.tensor([[[0.7]]], dtype=F64), torch.tensor([[[[0.3]]]], dtype=F64))
    Y = torch.tensor([[y]], dtype=F64)
    honest = kalman_update(*args, Y, meas, iterations=2, second_order=True)
    original = update_module._component_updates

    def indefinite(*a, prior_terms, **k):
        part = original(*a, prior_terms=prior_terms, **k)
        return part if prior_terms else part._replace(covs=-part.covs)

    monkeypatch.setattr(update_module, "_component_updates", indefinite)
    out = kalman_update(*args, Y, meas, iterations=2, second_order=True)
    with_terms = original(
        args[1], args[2], Y.unsqueeze(-2), meas, torch.tensor([[R]], dtype=F64), None, 2, prior_terms=True
    )
    assert torch.equal(out.means, with_terms.means) and torch.equal(out.covs, with_terms.covs)
    assert not torch.equal(out.means, honest.means)


def test_second_order_size_is_the_gaussian_moment_of_the_quadratic_part():
    # h = (x₁², x₁x₂) on N(μ, P) with entry noise R = diag(r₁, r₂): the quadratic parts δ₁² and δ₁δ₂ have means
    # (P₁₁, P₁₂) and variances (2P₁₁², P₁₁P₂₂ + P₁₂²), so E‖R^{-½}h₂‖² = (3P₁₁²)/r₁ + (P₁₁P₂₂ + 2P₁₂²)/r₂; a
    # masked entry takes no part
    mu = torch.tensor([0.4, -0.2], dtype=F64)
    P = torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=F64)
    r = torch.tensor([0.05, 0.02], dtype=F64)
    meas = FunctionMeasurement(lambda x: torch.cat((x[..., :1] ** 2, x[..., :1] * x[..., 1:2]), -1), torch.diag(r))
    size = update_module.second_order_size(mu[None, None], P[None, None], meas, torch.diag(r), torch.ones(1, 1, 2))
    first, second = 3 * P[0, 0] ** 2 / r[0], (P[0, 0] * P[1, 1] + 2 * P[0, 1] ** 2) / r[1]
    bound = 64 * EPS * float(1 + mu.abs().max()) ** 2 / float(r.min())
    assert_within(size[0, 0], first + second, bound, "both entries")
    masked = torch.tensor([[[1.0, 0.0]]], dtype=F64)
    R_eff = torch.diag(torch.stack((r[0], torch.ones((), dtype=F64))))  # kalman_update's: the identity block
    size = update_module.second_order_size(mu[None, None], P[None, None], meas, R_eff, masked)
    assert_within(size[0, 0], first, bound, "the first entry only")


def test_the_second_order_update_of_a_linear_measurement_is_the_ekf_update(gen):
    # h = Ax: every second difference is zero but for rounding, ≤ 4ε(|A||m| + |A||s|) per entry, which moves the
    # prediction by half the sum over the n axes and the mean by the gain times that
    B, N, n = 4, 3, 2
    A = torch.tensor([[1.5, -0.5], [0.25, 2.0]], dtype=F64)
    meas = FunctionMeasurement(lambda x: x @ A.T, 0.01 * torch.eye(n, dtype=F64))
    means = torch.randn(B, N, n, generator=gen, dtype=F64)
    G = torch.randn(B, N, n, n, generator=gen, dtype=F64)
    covs = 0.1 * G @ G.transpose(-1, -2) + 0.01 * torch.eye(n, dtype=F64)
    log_w = torch.log_softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    y = torch.randn(B, n, generator=gen, dtype=F64)
    for iterations in (1, 3):
        plain = kalman_update(log_w, means, covs, y, meas, iterations)
        second = kalman_update(log_w, means, covs, y, meas, iterations, second_order=True)
        spread = means.abs().amax((-2, -1)) + covs.diagonal(dim1=-2, dim2=-1).amax(-1).sqrt().amax(-1)  # [B]
        c_max = 4 * EPS * A.abs().sum(-1).max() * spread  # [B] bound on |c_k| entries
        shift = 0.5 * n * c_max  # [B] bound on the prediction's shift
        K_t = torch.linalg.solve(plain.innovation_cov, A @ covs)  # Kᵀ = S⁻¹HP, the EKF's gain
        gain = K_t.abs().sum(-2).amax((-2, -1))  # [B] the largest row sum of |K|
        m_max, y_max = means.abs().amax((-2, -1)), y.abs().amax(-1)
        tol = 64 * EPS * (1 + m_max * (1 + gain * A.abs().sum(-1).max()) + gain * y_max) + gain * shift
        assert_within(second.means, plain.means, tol[:, None, None], f"means, {iterations} linearisations")
        cov_scale = covs.diagonal(dim1=-2, dim2=-1).amax((-2, -1))
        assert_within(second.covs, plain.covs, 64 * EPS * cov_scale[:, None, None, None], "covariances")


def test_moment_matched_innovation_is_the_mixtures_mean_and_covariance_in_closed_form():
    # two components in two entries, exact binary fractions: ν̄ = Σ wᵢνᵢ, S̄ = Σ wᵢ(Sᵢ + (νᵢ − ν̄)(νᵢ − ν̄)ᵀ)
    w = torch.tensor([[0.25, 0.75]], dtype=F64)
    nu = torch.tensor([[[1.0, 0.0], [-1.0, 2.0]]], dtype=F64)
    S = torch.tensor([[[[2.0, 0.5], [0.5, 1.0]], [[1.0, -0.25], [-0.25, 4.0]]]], dtype=F64)
    nu_bar, S_bar = update_module.moment_matched_innovation(w.log(), nu, S)
    # ν̄ = (−0.5, 1.5); deviations (1.5, −1.5) and (−0.5, 0.5):
    # S̄ = 0.25·[[2 + 2.25, 0.5 − 2.25], [., 1 + 2.25]] + 0.75·[[1 + 0.25, −0.25 − 0.25], [., 4 + 0.25]]
    want_S = torch.tensor([[[2.0, -0.8125], [-0.8125, 4.0]]], dtype=F64)
    assert_within(nu_bar, torch.tensor([[-0.5, 1.5]], dtype=F64), 4 * float(np.finfo(np.float64).eps), "ν̄")
    assert_within(S_bar, want_S, 16 * float(np.finfo(np.float64).eps), "S̄")
    assert torch.equal(S_bar, S_bar.transpose(-1, -2))
