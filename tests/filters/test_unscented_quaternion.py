"""USQUE and its unscented core: the core against the Kalman filter on linear-Gaussian models, the attitude update
against the paper's formulas, USQUE against the MEKF as the covariance shrinks, the GRP chart, the paper's Q̄,
shapes, masks, gating, bad input, and convergence from a 30° per-axis error in the environment.

Every expected value comes from an independent source: a Kalman filter and the paper's unscented update written
here in numpy, scipy's rotations, the MEKF (held to Van Loan and a textbook update by its own tests), or the
environment's truth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from scipy.stats import multivariate_normal

import envs
from agsf_torch import GaussianMixture
from agsf_torch import rotations as rot
from agsf_torch.consistency import chi2_band
from agsf_torch.filters.error_state import error_state_to_mrp, mrp_to_error_state
from agsf_torch.filters.multiplicative import MultiplicativeEKF
from agsf_torch.filters.unscented_quaternion import (
    USQUE,
    grp_to_quat,
    quat_to_grp,
    sigma_points,
    unscented_moments,
    unscented_update,
    unscented_weights,
)
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from tests.filters.one_component_attitude import assert_bad_input_refused_before_anything_changes
from tests.helpers import F64, assert_within, random_mrps, random_spd, random_unit_vectors, relative_bound


def _belief(gen, B, estimate_bias, att_var=1e-4, bias_var=1e-10, max_norm=0.9):
    """A one-component MRP belief whose error-state covariance is ``scale · SPD · scale`` (rad², (rad/s)²)."""
    n = 6 if estimate_bias else 3
    q = rot.mrp_to_quat(random_mrps(B, gen, max_norm=max_norm))
    b = 1e-5 * torch.randn(B, 3, generator=gen, dtype=F64)[:, : n - 3]
    scale = torch.tensor([att_var] * 3 + [bias_var] * 3, dtype=F64)[:n].sqrt()
    P = scale[:, None] * random_spd(gen, B, n=n) * scale[None, :]
    mean, cov = error_state_to_mrp(q, b, P)
    return GaussianMixture(weights=torch.ones(B, 1, dtype=F64), means=mean[:, None], covs=cov[:, None])


def _trajectory(mix, i):
    """Trajectory ``i`` of a ``[B]`` mixture, as a batch of one."""
    return GaussianMixture(log_weights=mix.log_weights[i : i + 1], means=mix.means[i : i + 1], covs=mix.covs[i : i + 1])


# --------------------------------------------------------------------------- 1. the core on linear-Gaussian models
def _linear_system(gen, B, n, d):
    """Random stable ``A`` (spectral radius 0.9), ``H``, and SPD ``Q``, ``R``, ``P₀`` per trajectory."""
    M = torch.randn(B, n, n, generator=gen, dtype=F64)
    A = 0.9 * M / torch.linalg.eigvals(M).abs().amax(-1)[:, None, None]
    H = torch.randn(B, d, n, generator=gen, dtype=F64)
    Q = random_spd(gen, B, n=n, scale=0.1, floor=0.5)
    R = random_spd(gen, B, n=d, scale=0.2, floor=0.5)
    P0 = random_spd(gen, B, n=n, floor=0.5)
    return A, H, Q, R, P0


def _kalman_filter(m, P, A, H, Q, R, ys, masks):
    """The Kalman filter of one trajectory in numpy, the masked entries' rows removed; per step
    ``(mean, cov, log N(y; H m⁻, S), νᵀS⁻¹ν)`` (0, 0 without a valid entry)."""
    out = []
    for y, valid in zip(ys, masks, strict=True):
        m, P = A @ m, A @ P @ A.T + Q
        ll = nis = 0.0
        if valid.any():
            Hv, Rv, yv = H[valid], R[np.ix_(valid, valid)], y[valid]
            S = Hv @ P @ Hv.T + Rv
            K = np.linalg.solve(S, Hv @ P).T
            nu = yv - Hv @ m
            ll = multivariate_normal(mean=np.zeros(len(yv)), cov=S).logpdf(nu)
            nis = nu @ np.linalg.solve(S, nu)
            m = m + K @ nu
            P = P - K @ S @ K.T
            P = 0.5 * (P + P.T)
        out.append((m, P, ll, nis, np.linalg.cond(S) if valid.any() else 1.0, np.linalg.cond(P)))
    return out


@pytest.mark.parametrize("lam", [1.0, 0.5, 3.0])
@pytest.mark.parametrize("iterations", [1, 3])
def test_the_core_is_the_kalman_filter_on_a_linear_gaussian_model(gen, lam, iterations):
    """8 steps of sigma-point prediction (:func:`sigma_points`, :func:`unscented_moments`, + Q) and
    :func:`unscented_update` on 5 random linear-Gaussian systems at once (n = 4, d = 3, some entries masked,
    one trajectory without a valid entry at one step), against the Kalman filter in numpy.  On a linear model the
    unscented transformation is exact for any λ (the points reproduce the mean and covariance, the regression
    reproduces H with Ω = 0), and every iteration of the posterior linearisation is the same Kalman update.

    Tolerance 1e-10 relative (of each mean entry's scale |m| + √Pᵢᵢ, of each covariance's largest entry, of the
    log-likelihood's terms): both sides are backward-stable computations whose forward error per step is at most
    about ``c·n·ε·(κ(P) + κ(S))`` (sums of n outer products, Cholesky and triangular solves, with c ≲ 10), and the
    error is carried, not amplified, through steps of a stable filter; with n = 4, 8 steps and κ(P), κ(S) ≤ 10³
    (checked below) that is ≲ 8·10·4·2.2e-16·2e3 ≈ 1.4e-10 at worst, ≈ 1e-12 for the typical c ≈ 1."""
    B, n, d, T = 5, 4, 3, 8
    A, H, Q, R, P0 = _linear_system(gen, B, n, d)
    m0 = torch.randn(B, n, generator=gen, dtype=F64)

    def draw(cov):  # one N(0, cov) sample per trajectory
        return (torch.linalg.cholesky(cov) @ torch.randn(*cov.shape[:-1], 1, generator=gen, dtype=F64))[..., 0]

    x = m0 + draw(P0)
    ys, masks = [], []
    for k in range(T):
        x = (A @ x[..., None])[..., 0] + draw(Q)
        ys.append((H @ x[..., None])[..., 0] + draw(R))
        mask = torch.rand(B, d, generator=gen) > 0.25
        if k == 3:
            mask[2] = False  # no valid entry: the prediction is the posterior
        masks.append(mask)
    ref = []
    for i in range(B):
        system = [t[i].numpy() for t in (m0, P0, A, H, Q, R)]
        ref.append(_kalman_filter(*system, [y[i].numpy() for y in ys], [mk[i].numpy() for mk in masks]))
    assert max(max(step[4], step[5]) for traj in ref for step in traj) <= 1e3  # the conditioning the bound assumes

    def h(points):  # [S, B, n] → [S, B, d]
        return (H @ points[..., None])[..., 0]

    weights = unscented_weights(n, lam, like=m0)
    m, P = m0, P0
    for k in range(T):
        m, P = unscented_moments(sigma_points(m, P, lam) @ A.transpose(-1, -2), weights)
        P = P + Q
        res = unscented_update(m, P, ys[k], h, R, lam=lam, mask=masks[k], iterations=iterations)
        m, P = res.means[:, 0], res.covs[:, 0]
        for i in range(B):
            m_ref, P_ref, ll, nis = ref[i][k][:4]
            scale = np.abs(m_ref) + np.sqrt(np.diag(P_ref))
            assert_within(m[i], m_ref, 1e-10 * scale, f"mean at step {k}, trajectory {i}")
            assert_within(P[i], P_ref, 1e-10 * np.abs(P_ref).max(), f"covariance at step {k}, trajectory {i}")
            terms = abs(ll) + nis + d * math.log(2 * math.pi)
            assert_within(float(res.log_likelihood[i]), ll, 1e-10 * terms, f"log-likelihood at step {k}")
            assert_within(float(res.nis[i, 0]), nis, 1e-10 * terms, f"NIS at step {k}")
            assert int(res.dof[i]) == int(masks[k][i].sum())
    no_entry = unscented_update(m, P, ys[0], h, R, lam=lam, mask=torch.zeros(B, d, dtype=torch.bool))
    assert torch.equal(no_entry.means[:, 0], m) and torch.equal(no_entry.covs[:, 0], P)


def test_sigma_points_reproduce_the_mean_and_covariance(gen):
    """The 2n+1 points and weights of the paper reproduce N(mean, cov) exactly (rounding: n outer products of
    entries ~1, relative n·ε ≈ 1e-15; bound 1e-13), are symmetric about the mean, and lie √(n+λ) Cholesky columns
    out; the weights sum to 1 (each weight one division: bound 1e-14 relative)."""
    B, n, lam = 7, 6, 1.0
    mean = torch.randn(B, n, generator=gen, dtype=F64)
    cov = random_spd(gen, B, n=n)
    X = sigma_points(mean, cov, lam)
    assert X.shape == (B, 2 * n + 1, n)
    w = unscented_weights(n, lam, like=mean)
    assert_within(float(w.sum()), 1.0, 1e-14, "sum of the weights")
    expected_w = torch.tensor([lam / (n + lam)] + [0.5 / (n + lam)] * 2 * n, dtype=F64)
    assert_within(w, expected_w, relative_bound(expected_w, 1e-14, 0.0), "weights")
    m, P = unscented_moments(X, w)
    assert_within(m, mean, 1e-13 * (mean.abs() + 1.0), "mean of the sigma points")
    assert_within(P, cov, 1e-13 * cov.abs().amax((-1, -2), keepdim=True), "covariance of the sigma points")
    L = torch.linalg.cholesky(cov)
    columns = math.sqrt(n + lam) * L.transpose(-1, -2)
    assert_within(X[:, 1 : n + 1] - mean[:, None], columns, relative_bound(columns, 1e-14, 1e-14), "the columns")
    centre = 2 * X[:, :1].expand(B, n, n)
    assert_within(X[:, 1 : n + 1] + X[:, n + 1 :], centre, relative_bound(centre, 1e-14, 1e-14), "symmetry")


# --------------------------------------------------------------------------- the GRP chart
def test_grp_chart_is_the_papers_and_inverts():
    """δp = f δq_v/(a + δq_4): with a = 1, f = 4 it is 4 tan(θ/4) e; a = 0, f = 1 the Gibbs vector tan(θ/2) e;
    a = 1, f = 1 the MRP.  grp_to_quat inverts it (angles up to 179°), and δq and −δq give the same δp.
    Bounds: 1e-14 (≈ 50 ε) of the entries, closed forms of a few operations on O(1) numbers."""
    rng = np.random.default_rng(0)
    axis = rng.normal(size=(200, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    theta = np.concatenate([np.linspace(1e-9, 1e-3, 50), np.linspace(1e-3, np.radians(179.0), 150)])
    dq = torch.tensor(Rotation.from_rotvec(axis * theta[:, None]).as_quat())  # scalar-last, as the project's
    e, th = torch.tensor(axis), torch.tensor(theta)[:, None]
    assert_within(quat_to_grp(dq), 4 * torch.tan(th / 4) * e, 1e-14 * (1 + 4 * torch.tan(th / 4)), "default GRP")
    assert_within(quat_to_grp(-dq), quat_to_grp(dq), 1e-14, "δq and −δq")
    assert_within(quat_to_grp(dq, a=0.0, f=1.0), torch.tan(th / 2) * e, 1e-13 * (1 + torch.tan(th / 2)), "Gibbs")
    assert_within(quat_to_grp(dq, a=1.0, f=1.0), rot.quat_to_mrp(dq), 1e-14, "MRP")
    for a, f in ((1.0, None), (0.0, 1.0), (0.5, 0.7), (0.3, None)):
        back = grp_to_quat(quat_to_grp(dq, a, f), a, f)
        assert_within(back, dq, 1e-13, f"grp_to_quat ∘ quat_to_grp (a = {a}, f = {f})")
    with pytest.raises(ValueError, match="a must lie in"):
        quat_to_grp(dq, a=1.5)
    with pytest.raises(ValueError, match="f must be finite and > 0"):
        grp_to_quat(torch.zeros(3, dtype=F64), f=0.0)


# --------------------------------------------------------------------------- the update against the paper's formulas
def _np_grp_to_quat(dp, a=1.0, f=4.0):
    s = dp @ dp
    q4 = (-a * s + f * np.sqrt(f * f + (1 - a * a) * s)) / (f * f + s)
    return np.concatenate([(a + q4) * dp / f, [q4]])


def _paper_update(q, b, P, r, y, sigma, lam=1.0):
    """USQUE's measurement update for one trajectory in numpy, from the paper: sigma points
    ±columns of chol((n+λ)P), quaternions δq(δp_i) ⊗ q̂ (scipy, scalar-last: the project's product is scipy's
    with the attitude matrix transposed), γ_i = C(q_i) r_j, the weighted ȳ, P_yy, P_xy, Pνν = P_yy + R,
    K = P_xy Pνν⁻¹, δx̂ = K(ỹ − ȳ), P⁺ = P − K Pνν Kᵀ, and the reset."""
    n = P.shape[0]
    S = np.linalg.cholesky((n + lam) * P)
    dx = np.concatenate([np.zeros((1, n)), S.T, -S.T])
    w = np.array([lam / (n + lam)] + [0.5 / (n + lam)] * 2 * n)
    gammas = []
    for d in dx:
        # the project's δq ⊗ q̂ is scipy's R(q̂)·R(δq) (C = Rᵀ, C(a ⊗ b) = C(a) C(b))
        qi = (Rotation.from_quat(q) * Rotation.from_quat(_np_grp_to_quat(d[:3]))).as_quat()
        C = Rotation.from_quat(qi).as_matrix().T
        gammas.append((r @ C.T).reshape(-1))
    G = np.array(gammas)
    y_mean = w @ G
    Pyy = (w[:, None] * (G - y_mean)).T @ (G - y_mean)
    Pxy = (w[:, None] * dx).T @ (G - y_mean)
    Pvv = Pyy + sigma**2 * np.eye(len(y))
    K = np.linalg.solve(Pvv, Pxy.T).T
    d = K @ (y - y_mean)
    P_post = P - K @ Pvv @ K.T
    q_post = (Rotation.from_quat(q) * Rotation.from_quat(_np_grp_to_quat(d[:3]))).as_quat()
    return q_post, b + d[3:], 0.5 * (P_post + P_post.T), Pvv, y - y_mean


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_update_is_the_papers_unscented_update(gen, estimate_bias):
    """A star-vector update from a wide prior (0.3 rad per axis, where the unscented and the extended updates
    differ by degrees) against the paper's update written in numpy; also NIS and log-likelihood against
    Pνν.  The two sides differ only in rounding: the covariance form P − K Pνν Kᵀ here, the Joseph form on the
    regression there (with P H̃ᵀ = Pxy by triangular solves), each within about ε·(κ(Pνν) + κ(P)) of the exact
    update, κ(Pνν) ≲ (3·2·0.09 + 1e-4)/1e-4 ≈ 5e3 and κ(P) ≲ 2·0.09/(0.1·1e-4) ≈ 2e4 (attitude 0.09 rad², bias
    1e-4 (rad/s)², SPD factors in [0.1, 2]): ≈ 6e-12 relative; bound 1e-9 of each quantity's scale."""
    B, M, sigma = 4, 3, 1e-2
    model = AttitudeModel(estimate_bias=estimate_bias)
    mix = _belief(gen, B, estimate_bias, att_var=0.09, bias_var=1e-4)
    r = random_unit_vectors(gen, B, M)
    truth = rot.quat_multiply(
        rot.rotvec_to_quat(0.3 * torch.randn(B, 3, generator=gen, dtype=F64)), rot.mrp_to_quat(mix.means[:, 0, :3])
    )
    meas = StarVectorMeasurement(r, sigma=sigma)
    y = meas.predict(rot.quat_to_mrp(truth)) + sigma * torch.randn(B, 3 * M, generator=gen, dtype=F64)
    usque = USQUE(model)
    post = usque.update(mix, y, meas)
    q, b, P = mrp_to_error_state(mix.means[:, 0], mix.covs[:, 0])
    q_post, b_post, P_post = mrp_to_error_state(post.means[:, 0], post.covs[:, 0])
    for i in range(B):
        qe, be, Pe, Pvv, nu = _paper_update(q[i].numpy(), b[i].numpy(), P[i].numpy(), r[i].numpy(), y[i].numpy(), sigma)
        dq = Rotation.from_quat(q_post[i].numpy()) * Rotation.from_quat(qe).inv()
        assert_within(dq.magnitude(), 0.0, 1e-9 * 0.3, "angle between the posterior attitude and the paper's")
        assert_within(b_post[i], be, 1e-9 * np.sqrt(1e-4), "bias after the update")
        assert_within(P_post[i], Pe, 1e-9 * np.abs(Pe).max(), "covariance after the update")
        nis = nu @ np.linalg.solve(Pvv, nu)
        ll = multivariate_normal(mean=np.zeros(len(nu)), cov=Pvv).logpdf(nu)
        assert_within(float(usque.diagnostics["nis"][i, 0]), nis, 1e-9 * (nis + 1), "NIS")
        assert_within(float(usque.diagnostics["log_likelihood"][i]), ll, 1e-9 * (abs(ll) + nis), "log-likelihood")
    mekf_post = MultiplicativeEKF(model).update(mix, y, meas)
    gap = rot.attitude_error_angle(mekf_post.means[:, 0, :3], post.means[:, 0, :3])
    assert bool((gap > 1e-3).any())  # the comparison is not one between two equal linearisations


# --------------------------------------------------------------------------- 2. against the MEKF as P shrinks
@pytest.mark.parametrize(
    ("estimate_bias", "case"), [(False, "turning"), (True, "turning"), (True, "bias rate")], ids=str
)
def test_posterior_mean_approaches_the_mekfs_at_first_order(gen, estimate_bias, case):
    """One predict + update of USQUE and the MEKF from the same prior ``N(x̂, ε² P₀)`` and a measurement
    scaled with it (star noise ``0.5 ε``, innovation ``O(ε)``, process noise ``∝ ε``), for ε = 1e-3, 1e-4, 1e-5.

    Theory: both are the exact Bayes update for the linearised problem; USQUE adds the second-order terms
    of the dynamics and of the measurement (the mean of the propagated points, ``ȳ − h(x̂) = ½ tr(∇²h P)``),
    which shift the posterior mean by ``O(ε²)``, while its gain equals the MEKF's to relative ``O(ε²)`` (odd
    moments of the symmetric points vanish) and the GRP and rotation-vector charts agree to third order.  So the
    difference of the posterior means relative to the prior's standard deviation ``ε`` is ``c·ε + O(ε²)``: slope 1
    on log-log, and the covariances' relative difference ``O(ε²)``: slope 2.  The linear parts of the two must be
    identical for this, so the process noise is one both filters discretise alike: σ_u = 0 while turning
    (USQUE's Φ(P + Q̄)Φᵀ + Q̄ is then the MEKF's σ_v²Δt I), or σ_u > 0 with ω̂ = 0 (both the Farrenkopf Q_d).

    Band ±0.05 on the slopes: with ``d = cε(1 + kε)`` the fit over two decades moves by ≈ kε_max/ln 100, within
    0.05 for k up to ≈ 200, far above the O(1–10) ratio of third- to second-order terms of these O(1) matrices.
    The differences (≥ 1e-10 rad at ε = 1e-5) stand far above the rounding of the attitudes (≈ 1e-16)."""
    B, M, dt = 6, 3, 0.5
    n = 6 if estimate_bias else 3
    q = rot.mrp_to_quat(random_mrps(B, gen, max_norm=0.8))
    b = 1e-3 * torch.randn(B, 3, generator=gen, dtype=F64)[:, : n - 3]
    P0 = random_spd(gen, B, n=n, floor=0.2)
    z = torch.randn(B, 3, generator=gen, dtype=F64)
    w = torch.randn(B, 3 * M, generator=gen, dtype=F64)
    r = random_unit_vectors(gen, B, M)
    omega = 0.3 * torch.nn.functional.normalize(torch.randn(B, 3, generator=gen, dtype=F64), dim=-1)
    eps = np.array([1e-3, 1e-4, 1e-5])
    mean_gap, cov_gap = [], []
    for e in eps:
        if case == "turning":
            model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=0.3 * e, sigma_u=0.0)
            u = omega + torch.cat((b, torch.zeros(B, 3 - b.shape[-1], dtype=F64)), -1)
        else:
            model = AttitudeModel(estimate_bias=True, sigma_v=0.3 * e, sigma_u=0.2 * e)
            u = b.clone()  # ω̂ = ω̃ − b̂ = 0
        mean, cov = error_state_to_mrp(q, b, e**2 * P0)
        prior = GaussianMixture(weights=torch.ones(B, 1, dtype=F64), means=mean[:, None], covs=cov[:, None])
        mekf, usque = MultiplicativeEKF(model), USQUE(model)
        predicted = mekf.predict(prior, u, dt)
        truth = rot.quat_multiply(rot.rotvec_to_quat(e * z), rot.mrp_to_quat(predicted.means[:, 0, :3]))
        meas = StarVectorMeasurement(r, sigma=0.5 * e)
        y = meas.predict(rot.quat_to_mrp(truth)) + 0.5 * e * w
        ekf = mekf.update(predicted, y, meas)
        ukf = usque.update(usque.predict(prior, u, dt), y, meas)
        gap = rot.attitude_error_angle(ukf.means[:, 0, :3], ekf.means[:, 0, :3]) / e
        if estimate_bias:
            gap = torch.maximum(gap, torch.linalg.vector_norm(ukf.means[:, 0, 3:] - ekf.means[:, 0, 3:], dim=-1) / e)
        _, _, P_ukf = mrp_to_error_state(ukf.means[:, 0], ukf.covs[:, 0])
        _, _, P_ekf = mrp_to_error_state(ekf.means[:, 0], ekf.covs[:, 0])
        rel = torch.linalg.matrix_norm(P_ukf - P_ekf) / torch.linalg.matrix_norm(P_ekf)
        mean_gap.append(float(gap.max()))
        cov_gap.append(float(rel.max()))
    slope = np.polyfit(np.log(eps), np.log(mean_gap), 1)[0]
    cov_slope = np.polyfit(np.log(eps), np.log(cov_gap), 1)[0]
    print(f"{case}, n = {n}: mean gap / ε {mean_gap} (slope {slope:.4f}); covariance gap {cov_gap} ({cov_slope:.4f})")
    assert_within(slope, 1.0, 0.05, "fitted log-log slope of the mean difference / prior σ")
    assert_within(cov_slope, 2.0, 0.05, "fitted log-log slope of the covariances' relative difference")


# --------------------------------------------------------------------------- propagation and Q̄
@pytest.mark.parametrize("estimate_bias", [False, True])
def test_reference_follows_the_closed_form_rotation(gen, estimate_bias):
    """240 steps of 0.5 s at a constant ω (≈3.4 revolutions, through the MRP shadow switch) from a tight belief:
    the reference equals C(t) = exp(−[ω×]t) C(0) from scipy, the gyro's bias (the model's known one, or the
    belief's estimate) removed.  The sigma points' mean shift is O(P) ≈ 1e-12 rad per step here (P ≈ 1e-12, σ_v
    default), so 240 steps stay within 1e-9 of the rotation; rounding adds ≈ 240·ε."""
    B, steps, dt = 4, 240, 0.5
    bias = torch.tensor([1e-3, -2e-3, 5e-4], dtype=F64)
    model = AttitudeModel(estimate_bias=estimate_bias, bias=0.0 if estimate_bias else bias)
    mix = _belief(gen, B, estimate_bias, att_var=1e-12, bias_var=1e-20)
    if estimate_bias:
        mix = mix.replace(means=torch.cat((mix.means[..., :3], bias.expand(B, 1, 3)), -1))
    omega = 0.09 * torch.nn.functional.normalize(torch.randn(B, 3, generator=gen, dtype=F64), dim=-1)
    usque = USQUE(model)
    R0 = Rotation.from_mrp(mix.means[:, 0, :3].numpy())
    for k in range(1, steps + 1):
        mix = usque.predict(mix, omega + bias, dt)
        if k % 40 == 0:
            C = rot.mrp_to_dcm(mix.means[:, 0, :3]).numpy()
            C_ref = (R0 * Rotation.from_rotvec(omega.numpy() * k * dt)).as_matrix().transpose(0, 2, 1)
            assert_within(C, C_ref, 1e-9, f"attitude matrix after {k} steps")
    assert bool((mix.means[:, 0, :3].norm(dim=-1) <= 1.0).all())


@pytest.mark.parametrize("estimate_bias", [False, True])
@pytest.mark.parametrize("theta", [0.0, 0.3])
def test_process_noise_is_the_papers_q_bar_added_twice(estimate_bias, theta):
    """From a belief of covariance 1e-30 I the predicted covariance is the propagated Q̄ plus Q̄, i.e.
    ``Φ Q̄ Φᵀ + Q̄`` with the MEKF's exact Φ, and at ω̂ = 0 the MEKF's Farrenkopf Q_d (the paper's Q̄ is the half
    that makes the two agree).  σ_v = 1e-4, σ_u = 1e-4, Δt = 2 s so that every block shows.  The sigma points'
    nonlinearity adds O(|Q̄|) ≈ 1e-8 relative to the covariance; bound 1e-6 of its largest entry."""
    dt, sv, su = 2.0, 1e-4, 1e-4
    model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=sv, sigma_u=su)
    n = model.state_dim
    q = rot.mrp_to_quat(torch.tensor([[0.1, -0.2, 0.3]], dtype=F64))
    mean, cov = error_state_to_mrp(q, torch.zeros(1, n - 3, dtype=F64), 1e-30 * torch.eye(n, dtype=F64)[None])
    mix = GaussianMixture(weights=torch.ones(1, 1, dtype=F64), means=mean[:, None], covs=cov[:, None])
    omega = torch.tensor([[theta / dt, 0.0, 0.0]], dtype=F64)
    usque = USQUE(model)
    Qbar = usque.q_bar(dt, mean)
    attitude = 0.5 * dt * (sv**2 - su**2 * dt**2 / 6) if estimate_bias else 0.5 * dt * sv**2
    expected = torch.diag(torch.tensor([attitude] * 3 + [0.5 * dt * su**2] * 3, dtype=F64))[:n, :n]
    assert_within(Qbar, expected, relative_bound(expected, 1e-14, 0.0), "Q̄")
    pred = usque.predict(mix, omega, dt)
    _, _, P = mrp_to_error_state(pred.means[:, 0], pred.covs[:, 0])
    Phi, Q_mekf = MultiplicativeEKF(model).transition(omega, dt)
    bound = 1e-6 * float(P.abs().max())
    assert_within(P, Phi @ Qbar @ Phi.transpose(-1, -2) + Qbar, bound, "predicted covariance against Φ Q̄ Φᵀ + Q̄")
    if theta == 0.0:
        assert_within(P, Q_mekf, bound, "predicted covariance against the MEKF's Farrenkopf Q_d")


def test_noise_per_trajectory_is_each_trajectorys_own(gen):
    """A model with σ_v, σ_u [B, 1] (the models' per-trajectory form) gives each trajectory what a model with its
    own numbers gives it (the same arithmetic; bound 1e-13 relative for a possibly different order of sums)."""
    B = 3
    mix = _belief(gen, B, True, att_var=1e-6, bias_var=1e-12)
    sv, su = torch.tensor([[1e-6], [3e-6], [5e-7]], dtype=F64), torch.tensor([[1e-9], [2e-8], [5e-9]], dtype=F64)
    u = 0.05 * torch.randn(B, 3, generator=gen, dtype=F64)
    out = USQUE(AttitudeModel(estimate_bias=True, sigma_v=sv, sigma_u=su)).predict(mix, u, 1.0)
    for i in range(B):
        one = USQUE(AttitudeModel(estimate_bias=True, sigma_v=float(sv[i]), sigma_u=float(su[i])))
        ref = one.predict(_trajectory(mix, i), u[i : i + 1], 1.0)
        assert_within(out.means[i], ref.means[0], 1e-13 * ref.means[0].abs() + 1e-20, f"mean {i}")
        assert_within(out.covs[i], ref.covs[0], 1e-13 * float(ref.covs[0].abs().max()), f"covariance {i}")


# --------------------------------------------------------------------------- 3. shapes, masks, gate, bad input
def test_batch_dims_shapes_and_diagnostics(gen):
    """Trajectories in [2, 3]: the same numbers as flattened to [6] and as each trajectory alone (no
    trajectory sees another; bound 1e-12 relative for batched kernels that may sum in another order, cond(Pνν)
    ≲ 1e3 here), the shapes of every output and diagnostic, and the declared diagnostic keys."""
    model = AttitudeModel(estimate_bias=True)
    M = 4
    flat = _belief(gen, 6, True, att_var=1e-6, bias_var=1e-12)
    r = random_unit_vectors(gen, 6, M)
    meas = StarVectorMeasurement(r, sigma=1e-4)
    y = meas.predict(flat.means[:, 0]) + 1e-4 * torch.randn(6, 3 * M, generator=gen, dtype=F64)
    u = 0.02 * torch.randn(6, 3, generator=gen, dtype=F64)

    def run(mix, u, y, meas):
        usque = USQUE(model)
        pred = usque.predict(mix, u, 0.1)
        assert set(usque.diagnostics) == set(usque.diagnostic_keys("predict"))
        post = usque.update(pred, y, meas)
        assert set(usque.diagnostics) == set(usque.diagnostic_keys("update"))
        return post, usque.diagnostics, usque.estimate(post)

    grid = GaussianMixture(
        log_weights=flat.log_weights.reshape(2, 3, 1),
        means=flat.means.reshape(2, 3, 1, 6),
        covs=flat.covs.reshape(2, 3, 1, 6, 6),
    )
    grid_meas = StarVectorMeasurement(r.reshape(2, 3, M, 3), sigma=1e-4)
    post, diag, (mean, cov) = run(grid, u.reshape(2, 3, 3), y.reshape(2, 3, -1), grid_meas)
    assert post.means.shape == (2, 3, 1, 6) and post.covs.shape == (2, 3, 1, 6, 6)
    assert mean.shape == (2, 3, 6) and cov.shape == (2, 3, 6, 6)
    shapes = {
        "log_likelihood": (2, 3),
        "nis": (2, 3, 1),
        "nis_mixture": (2, 3),
        "dof": (2, 3),
        "weight_entropy": (2, 3),
    }
    for key, shape in shapes.items():
        assert diag[key].shape == shape, key
    post_flat, diag_flat, _ = run(flat, u, y, meas)
    assert_within(post.means.reshape(6, 1, 6), post_flat.means, 1e-12 * post_flat.means.abs() + 1e-24, "flattened")
    assert_within(diag["nis"].reshape(6, 1), diag_flat["nis"], 1e-12 * diag_flat["nis"] + 1e-12, "flattened NIS")
    for i in range(6):
        alone = StarVectorMeasurement(r[i : i + 1], sigma=1e-4)
        one, _, _ = run(_trajectory(flat, i), u[i : i + 1], y[i : i + 1], alone)
        assert_within(post_flat.means[i], one.means[0], 1e-12 * one.means[0].abs() + 1e-24, f"alone, {i}")
        assert_within(post_flat.covs[i], one.covs[0], 1e-12 * float(one.covs[0].abs().max()), f"alone, {i}")


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_missing_stars(gen, estimate_bias):
    """A trajectory whose stars are all missing keeps its predicted belief bit for bit (dof 0, likelihood 0); one
    with some missing equals the update with only its valid stars (the masked entries are removed exactly; bound
    1e-12 relative for the other order of the sums)."""
    B, M, sigma = 3, 4, 1e-4
    model = AttitudeModel(estimate_bias=estimate_bias)
    usque = USQUE(model)
    pred = usque.predict(
        _belief(gen, B, estimate_bias, att_var=1e-6, bias_var=1e-12), torch.zeros(B, 3, dtype=F64), 0.1
    )
    r = random_unit_vectors(gen, B, M)
    noise = sigma * torch.randn(B, 3 * M, generator=gen, dtype=F64)
    y = StarVectorMeasurement(r, sigma=sigma).predict(pred.means[:, 0]) + noise
    mask = torch.tensor([[True, False, True, False], [False] * 4, [True] * 4])
    post = usque.update(pred, y, StarVectorMeasurement(r, mask, sigma))
    diag = usque.diagnostics
    assert torch.equal(post.means[1], pred.means[1]) and torch.equal(post.covs[1], pred.covs[1])
    assert diag["dof"].tolist() == [6.0, 0.0, 12.0] and float(diag["log_likelihood"][1]) == 0.0
    keep = torch.tensor([0, 2])
    y_valid = y[:1].reshape(1, M, 3)[:, keep].reshape(1, 6)
    one = USQUE(model).update(_trajectory(pred, 0), y_valid, StarVectorMeasurement(r[:1, keep], sigma=sigma))
    assert_within(post.means[0], one.means[0], 1e-12 * one.means[0].abs() + 1e-24, "posterior mean, valid stars only")
    assert_within(post.covs[0], one.covs[0], 1e-12 * float(one.covs[0].abs().max()), "posterior covariance")
    assert float(post.means[0].sub(pred.means[0]).abs().max()) > 0.0  # the valid stars did update it


def test_gate_rejects_a_misidentified_star(gen):
    """With gate_probability a star 0.1° off its catalogue direction is rejected and the update equals the update
    with that star masked out, bit for bit (the gate only sets the mask)."""
    B, M, sigma = 3, 5, 1e-5
    model = AttitudeModel()
    mix = _belief(gen, B, False, att_var=1e-10)
    r = random_unit_vectors(gen, B, M)
    noise = sigma * torch.randn(B, 3 * M, generator=gen, dtype=F64)
    y = StarVectorMeasurement(r, sigma=sigma).predict(mix.means[:, 0]) + noise
    y[1, 6:9] = rot.mrp_to_dcm(torch.tensor([0.0, 4.4e-4, 0.0], dtype=F64)) @ y[1, 6:9]
    gated = USQUE(model, gate_probability=1 - 1e-4)
    post = gated.update(mix, y, StarVectorMeasurement(r, sigma=sigma))
    assert gated.diagnostics["gate_rejected"].tolist() == [0, 1, 0]
    mask = torch.ones(B, M, dtype=torch.bool)
    mask[1, 2] = False
    ref = USQUE(model).update(mix, y, StarVectorMeasurement(r, mask, sigma))
    assert torch.equal(post.means, ref.means) and torch.equal(post.covs, ref.covs)


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_a_float32_belief_stays_float32(gen, estimate_bias):
    model = AttitudeModel(estimate_bias=estimate_bias)
    mix = _belief(gen, 2, estimate_bias, att_var=1e-4, bias_var=1e-10)
    mix32 = GaussianMixture(weights=torch.ones(2, 1), means=mix.means.float(), covs=mix.covs.float())
    usque = USQUE(model, update_iterations=2)
    r = random_unit_vectors(gen, 2, 3).float()
    pred = usque.predict(mix32, torch.full((2, 3), 0.01), 0.1)
    post = usque.update(
        pred, StarVectorMeasurement(r, sigma=1e-3).predict(pred.means[:, 0]), StarVectorMeasurement(r, sigma=1e-3)
    )
    dtypes = {t.dtype for t in (pred.means, pred.covs, post.means, post.covs, post.log_weights)}
    dtypes |= {v.dtype for v in usque.diagnostics.values() if torch.is_tensor(v) and v.is_floating_point()}
    assert dtypes == {torch.float32}


def test_bad_inputs_raise_before_anything_changes(gen):
    model = AttitudeModel(estimate_bias=True)
    mix = _belief(gen, 4, True)
    usque = USQUE(model)
    meas = StarVectorMeasurement(random_unit_vectors(gen, 4, 5), sigma=1e-5)
    y = meas.predict(mix.means[:, 0])
    u = torch.zeros(4, 3, dtype=F64)
    usque.predict(mix, u, 0.1)
    assert_bad_input_refused_before_anything_changes(usque, mix, u, y, meas)

    with pytest.raises(TypeError, match="AttitudeModel"):
        USQUE(meas)  # type: ignore[arg-type]
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="GRP parameter a must lie in"):
            USQUE(model, a=bad)
    for bad in (0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="GRP scale f must be finite and > 0"):
            USQUE(model, f=bad)
    for bad in (-6.0, -7.0, float("nan")):
        with pytest.raises(ValueError, match=r"n \+ λ > 0 \(n = 6\)"):
            USQUE(model, lam=bad)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="update_iterations"):
            USQUE(model, update_iterations=bad)
    with pytest.raises(ValueError, match="gate probability"):
        USQUE(model, gate_probability=1.5)
    # the core names what it refuses
    with pytest.raises(ValueError, match=r"the covariance is not positive definite at trajectory index \(1,\)"):
        sigma_points(torch.zeros(2, 3, dtype=F64), torch.stack((torch.eye(3), -torch.eye(3))).to(F64))
    with pytest.raises(ValueError, match="iterations must be a positive integer"):
        eye = torch.eye(3, dtype=F64)
        unscented_update(torch.zeros(3, dtype=F64), eye, torch.zeros(3, dtype=F64), lambda x: x, eye, iterations=0)
    with pytest.raises(ValueError, match="per trajectory"):
        USQUE(AttitudeModel(sigma_v=torch.ones(4, 2, dtype=F64) * 1e-6)).predict(_belief(gen, 4, False), u, 0.1)


def test_run_state_and_checkpoint_options():
    """The base's run state (none) round-trips; the options a checkpoint records include the GRP and the spread."""
    usque = USQUE(AttitudeModel(estimate_bias=True), a=0.5, lam=2.0, update_iterations=2)
    state = usque.state_dict()
    assert state == {}
    usque.load_state_dict(state)
    with pytest.raises(ValueError, match="no run state"):
        usque.load_state_dict({"x": 1})
    opts = usque.checkpoint_options()
    assert (opts["a"], opts["f"], opts["lam"], opts["update_iterations"]) == (0.5, 3.0, 2.0, 2)


# --------------------------------------------------------------------------- 4. convergence in the environment
def _run_from_30_degrees(filters, *, B, steps, seed, **env_options):
    """Every filter over ``steps`` gyro periods of the environment, from an estimate 30° off per axis (random
    signs) with that prior σ, the bias estimate 0 with σ 0.2°/h; returns, per filter, the attitude errors after
    every step ``[steps, B]`` (rad) and the final NEES of the attitude ``[B]`` (3 dof, in the error chart)."""
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=B, max_steps=steps, **env_options)
    obs, info = env.reset(seed=seed)
    g = torch.Generator().manual_seed(seed)
    signs = torch.where(torch.rand(B, 3, generator=g) < 0.5, -1.0, 1.0).to(F64)
    q0 = rot.quat_multiply(rot.rotvec_to_quat(math.radians(30.0) * signs), rot.mrp_to_quat(info["truth_mrp"]))
    sigma_b = math.radians(0.2) / 3600
    P0 = torch.diag(torch.tensor([math.radians(30.0) ** 2] * 3 + [sigma_b**2] * 3, dtype=F64)).expand(B, 6, 6)
    mean, cov = error_state_to_mrp(q0, torch.zeros(B, 3, dtype=F64), P0)
    prior = GaussianMixture(weights=torch.ones(B, 1, dtype=F64), means=mean[:, None], covs=cov[:, None])
    beliefs = dict.fromkeys(filters, prior)
    sigma_s = env.config.sigma_s
    first = next(iter(filters))
    angles = {name: [] for name in filters}
    for _ in range(steps):
        obs, _, _, _, info = env.step(beliefs[first].means[:, 0, :3])
        frame = bool(obs["star_mask"].any())
        if frame:
            y, meas = StarVectorMeasurement.from_observation(obs, sigma_s)
        for name, filt in filters.items():
            beliefs[name] = filt.predict(beliefs[name], obs["gyro"], env.config.dt)
            if frame:
                beliefs[name] = filt.update(beliefs[name], y, meas)
            angles[name].append(rot.attitude_error_angle(beliefs[name].means[:, 0, :3], info["truth_mrp"]))
    out = {}
    for name, belief in beliefs.items():
        err = rot.attitude_error_vector(belief.means[:, 0, :3], info["truth_mrp"])
        _, _, P = mrp_to_error_state(belief.means[:, 0], belief.covs[:, 0])
        nees = (err[:, None] @ torch.linalg.solve(P[:, :3, :3], err[:, :, None]))[:, 0, 0]
        out[name] = (torch.stack(angles[name]), nees)
    return out


def test_converges_from_30_degrees_per_axis_with_a_coarse_vector_sensor():
    """32 runs × 60 s (600 gyro periods, 60 frames) of the 6-state problem from a 30° error per axis (52° in all)
    with a vector sensor of the paper's grade (σ_s = 2 mrad, up to 5 stars in a 20° field; the paper's
    magnetometer had about 1.7 mrad).  One frame fixes the attitude about the line of sight to
    σ_s/(√5·ρ) ≈ 0.36°, ρ = 10°·√(2/3) = 0.14 rad the RMS offset of stars spread over the field, and across it to
    σ_s/√5 ≈ 0.05°.

    USQUE with the update relinearised at its posterior (3 iterations) converges and is consistent: every final
    error below one frame's accuracy about the line of sight (a filter that has converged does at least as well
    as one frame), and the mean NEES of the 32 runs inside the 1 − 1e-4 χ²₃ band.  The paper's single update
    converges more slowly and overconfident (class docstring): every final error below 2° (5 frames' accuracy,
    25× under the start), and faster than the MEKF (the paper's finding): after 20 s its worst error is below
    the MEKF's.  Measured (seed 7): final iterated 0.032° (mean NEES 3.3), single 0.50°, MEKF 0.56°; after 20 s
    single 1.5°, MEKF 2.7°."""
    model = AttitudeModel(estimate_bias=True)
    filters = {"iterated": USQUE(model, update_iterations=3), "single": USQUE(model), "mekf": MultiplicativeEKF(model)}
    res = _run_from_30_degrees(filters, B=32, steps=600, seed=7, sigma_s=2e-3, fov_deg=(20.0, 20.0), max_stars=5)
    worst = {name: np.degrees(angles.amax(-1).numpy()) for name, (angles, _) in res.items()}
    for name, (_, nees) in res.items():
        at_20s, at_60s = worst[name][199], worst[name][-1]
        print(
            f"{name}: worst error after 20 s {at_20s:.4f}°, at 60 s {at_60s:.4f}°, mean NEES {float(nees.mean()):.3g}"
        )
    one_frame = 2e-3 / (math.sqrt(5.0) * math.radians(10.0) * math.sqrt(2.0 / 3.0))
    angles, nees = res["iterated"]
    assert_within(angles[-1], 0.0, one_frame, "final attitude error of the iterated USQUE")
    lo, hi = chi2_band(3, 32, confidence=1 - 1e-4)
    assert lo <= float(nees.mean()) <= hi
    assert_within(res["single"][0][-1], 0.0, math.radians(2.0), "final attitude error of the paper's USQUE")
    assert worst["single"][199] < worst["mekf"][199]


def test_converges_from_30_degrees_per_axis_with_the_star_camera():
    """16 runs × 30 s of the environment's own star camera (σ_s = 10 µrad, up to 5 stars in an 8° field) from
    the same 30° error: the iterated update (5 iterations) reaches the camera's accuracy, every final error below
    twice one frame's accuracy about the line of sight, 2·σ_s/(√5·ρ) ≈ 1.6e-4 rad (ρ = 4°·√(2/3) = 0.057 rad).
    (Its NEES is not asserted: like the iterated MEKF's in the same runs it is several times 3 after the first
    frame's linearisation.)  The single update does not converge here (class docstring).  Measured (seed 7): 17″
    (8.5e-5 rad)."""
    model = AttitudeModel(estimate_bias=True)
    res = _run_from_30_degrees({"iterated": USQUE(model, update_iterations=5)}, B=16, steps=300, seed=7)
    angles, nees = res["iterated"]
    print(f"final error max {float(angles[-1].max()):.3g} rad, mean NEES {float(nees.mean()):.3g}")
    one_frame = 10e-6 / (math.sqrt(5.0) * math.radians(4.0) * math.sqrt(2.0 / 3.0))
    assert_within(angles[-1], 0.0, 2.0 * one_frame, "final attitude error of the iterated USQUE")
