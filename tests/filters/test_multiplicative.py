"""Multiplicative EKF: belief conversion, exact propagation, Φ and Q_d, the update, Monte Carlo, bad input.

Every expected value comes from an independent source: scipy's Rotation, a matrix
exponential (Van Loan), a Monte Carlo of the environment's gyro, a hand-written
textbook MEKF update in numpy, or the project's EKF on the MRP model.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.linalg import expm
from scipy.spatial.transform import Rotation
from scipy.stats import multivariate_normal

import envs
from agsf_torch import GaussianMixture
from agsf_torch import rotations as rot
from agsf_torch.consistency import chi2_band
from agsf_torch.experiments.run.runner import FilterSetup, run_monte_carlo
from agsf_torch.filters import ExtendedKalmanFilter
from agsf_torch.filters.multiplicative import MultiplicativeEKF, error_state_to_mrp, mrp_to_error_state
from agsf_torch.models import AttitudeModel, FunctionMeasurement, StarVectorMeasurement
from envs.gyro import Gyro
from tests.filters.one_component_attitude import assert_bad_input_refused_before_anything_changes
from tests.helpers import (
    F64,
    assert_statistic,
    assert_within,
    random_mrps,
    random_spd,
    random_unit_vectors,
    relative_bound,
)


def _belief(gen, B, estimate_bias, att_var=1e-4, bias_var=1e-10, max_norm=0.9):
    n = 6 if estimate_bias else 3
    p = random_mrps(B, gen, max_norm=max_norm)
    b = 1e-5 * torch.randn(B, 3, generator=gen, dtype=F64)
    mean = torch.cat((p, b), -1)[:, :n]
    scale = torch.tensor([att_var] * 3 + [bias_var] * 3, dtype=F64)[:n].sqrt()
    P = scale[:, None] * random_spd(gen, B, n=n) * scale[None, :]
    return GaussianMixture(weights=torch.ones(B, 1, dtype=F64), means=mean[:, None], covs=P[:, None])


# --------------------------------------------------------------------------- 1. belief conversion
@pytest.mark.parametrize("estimate_bias", [False, True])
def test_belief_round_trip_reproduces_mean_and_cov(gen, estimate_bias):
    mix = _belief(gen, 50, estimate_bias)
    mean, cov = mix.means[:, 0], mix.covs[:, 0]
    q, b, P = mrp_to_error_state(mean, cov)
    mean2, cov2 = error_state_to_mrp(q, b, P)
    assert_within(mean2, mean, 1e-12, "mean after the round trip")
    assert_within(
        cov2, cov, relative_bound(cov, 1e-12, 1e-12 * float(cov.abs().max())), "covariance after the round trip"
    )
    # the quaternion is the attitude of p (scipy: its matrix is Cᵀ, quaternions share [x, y, z, w])
    q_ref = Rotation.from_mrp(mean[:, :3].numpy()).as_quat()
    assert_within(np.abs((q.numpy() * q_ref).sum(-1)), 1.0, 1e-12, "|q · q_scipy|")


def test_mrp_map_is_the_jacobian_of_body_frame_composition(gen):
    """The belief map is T = ∂p(δq(δθ) ⊗ q̂)/∂δθ at 0: central differences of the composition done
    by scipy (C_true = exp(−[δθ×]) C(q̂), i.e. scipy's active rotation R(q̂)·R(δθ)).  A rank-one
    error covariance v vᵀ must map to (J v)(J v)ᵀ, which pins T (up to sign per v), so a wrong
    composition order or sign fails here."""
    B = 20
    p = random_mrps(B, gen, max_norm=0.8)
    base = Rotation.from_mrp(p.numpy())
    h = 1e-6
    cols = []
    for k in range(3):
        e = np.zeros((B, 3))
        e[:, k] = h
        cols.append(((base * Rotation.from_rotvec(e)).as_mrp() - (base * Rotation.from_rotvec(-e)).as_mrp()) / (2 * h))
    J_fd = torch.tensor(np.stack(cols, -1))
    for _ in range(3):
        v = torch.randn(B, 3, generator=gen, dtype=F64)
        _, cov = error_state_to_mrp(rot.mrp_to_quat(p), p[:, 3:], v[:, :, None] * v[:, None, :])
        Jv = (J_fd @ v[..., None]).squeeze(-1)
        # J by central differences of step 1e-6: O(h²) truncation and O(ε/h) ≈ 1e-10 rounding, on entries ~1
        assert_within(cov, Jv[:, :, None] * Jv[:, None, :], 1e-9, "mapped rank-one covariance (J v)(J v)ᵀ")


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_shadow_set_input_comes_back_on_the_short_set(gen, estimate_bias):
    """A belief given on the shadow set (|p| > 1; mean −p/|p|², covariance mapped with the shadow
    Jacobian of rotations.mrp_shadow_jacobian) goes through the quaternion and comes back as the
    original short-set belief."""
    mix = _belief(gen, 30, estimate_bias, max_norm=0.8)
    mean, cov = mix.means[:, 0], mix.covs[:, 0]
    n = mean.shape[-1]
    Tsh = torch.eye(n, dtype=F64).repeat(30, 1, 1)
    Tsh[:, :3, :3] = rot.mrp_shadow_jacobian(mean[:, :3])
    shadow_mean = torch.cat((rot.mrp_shadow(mean[:, :3]), mean[:, 3:]), -1)
    shadow_cov = Tsh @ cov @ Tsh.transpose(-1, -2)
    mean2, cov2 = error_state_to_mrp(*mrp_to_error_state(shadow_mean, shadow_cov))
    assert_within(mean2, mean, 1e-12, "mean back from the shadow set")
    assert_within(
        cov2, cov, relative_bound(cov, 1e-10, 1e-10 * float(cov.abs().max())), "covariance back from the shadow set"
    )


# --------------------------------------------------------------------------- 2. reference propagation
@pytest.mark.parametrize("estimate_bias", [False, True])
def test_reference_follows_the_closed_form_rotation(gen, estimate_bias):
    """240 steps of 0.5 s at a constant ω (≈3.4 revolutions, through the MRP shadow switch): the
    reference equals C(t) = exp(−[ω×]t) C(0), from scipy.  The gyro reads ω + b, with b the
    model's known bias (3-state) or the belief's bias estimate (6-state), which must be removed."""
    B, steps, dt = 4, 240, 0.5
    bias = torch.tensor([1e-3, -2e-3, 5e-4], dtype=F64)
    model = AttitudeModel(estimate_bias=estimate_bias, bias=0.0 if estimate_bias else bias)
    mix = _belief(gen, B, estimate_bias, att_var=1e-6)
    if estimate_bias:
        mix = mix.replace(means=torch.cat((mix.means[..., :3], bias.expand(B, 1, 3)), -1))
    omega = torch.randn(B, 3, generator=gen, dtype=F64)
    omega = 0.09 * omega / omega.norm(dim=-1, keepdim=True)
    mekf = MultiplicativeEKF(model)
    R0 = Rotation.from_mrp(mix.means[:, 0, :3].numpy())
    for k in range(1, steps + 1):
        mix = mekf.predict(mix, omega + bias, dt)
        if k % 20 == 0:
            C = rot.mrp_to_dcm(mix.means[:, 0, :3]).numpy()
            C_ref = (R0 * Rotation.from_rotvec(omega.numpy() * k * dt)).as_matrix().transpose(0, 2, 1)
            assert_within(C, C_ref, 1e-11, f"attitude matrix after {k} steps")
    assert bool((mix.means[:, 0, :3].norm(dim=-1) <= 1.0).all())


# --------------------------------------------------------------------------- 3. covariance propagation
@pytest.mark.parametrize("estimate_bias", [False, True])
def test_covariance_propagation_matches_the_mrp_ekf(gen, estimate_bias):
    """The MEKF (closed-form Φ, exact Q_d) and the project's EKF on the MRP model (RK4 on the Riccati
    equation) propagate linearisations of the same SDE in two charts along the same reference, and
    the linearisation commutes with the chart change ``p(δq(δθ) ⊗ q̂)``, so ``P_MRP = T P_δ Tᵀ``
    holds exactly for the continuous-time equations: they agree far beyond first order, up to the
    EKF's RK4 truncation error, which is global order 4 in its step.  Checked: 50 steps of 0.1 s
    at |ω| = 0.2 rad/s with inflated noise (σ_v = 1e-4, σ_u = 1e-5 so that every block matters):
    relative difference < 1e-11 with 8 RK4 substeps (measured ≈ 4e-14), and halving the EKF's step
    shrinks the difference by ≈ 2⁴ = 16 (the residual is the EKF's integration error, not the MEKF's).
    The Farrenkopf Q_d (default) differs by its documented O(|ω|Δt) error in the σ_u terms only."""
    model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=1e-4, sigma_u=1e-5)
    mix0 = _belief(gen, 8, estimate_bias, att_var=1e-6, bias_var=1e-12, max_norm=0.5)
    u = torch.randn(8, 3, generator=gen, dtype=F64)
    u = 0.2 * u / u.norm(dim=-1, keepdim=True)

    def run(filt):
        mix = mix0
        for _ in range(50):
            mix = filt.predict(mix, u, 0.1)
        return mix

    def rel(a, b):
        return float(((a.covs - b.covs).norm(dim=(-1, -2)) / b.covs.norm(dim=(-1, -2))).max())

    exact = run(MultiplicativeEKF(model, discrete_noise="exact"))
    ekfs = {s: run(ExtendedKalmanFilter(model, substeps=s)) for s in (1, 2, 8)}
    assert_within(exact.means, ekfs[8].means, 1e-12, "MEKF means against the MRP EKF's")
    # within 1e-11 of ‖P‖ normwise, so each entry within 1e-11 of its matrix's Frobenius norm
    frobenius = ekfs[8].covs.norm(dim=(-1, -2))[..., None, None]
    assert_within(exact.covs, ekfs[8].covs, 1e-11 * frobenius, "MEKF covariances against the 8-substep EKF's")
    ratio = rel(exact, ekfs[1]) / rel(exact, ekfs[2])
    assert 14.0 < ratio < 18.0, ratio
    farrenkopf = run(MultiplicativeEKF(model))
    if estimate_bias:
        assert 1e-10 < rel(farrenkopf, exact) < 1e-5  # σ_u terms only (θ = |ω|Δt = 0.02); measured 8e-8
    else:
        assert torch.equal(farrenkopf.covs, exact.covs)  # without a bias the two Q_d are one computation


def _van_loan(omega: np.ndarray, dt: float, sv: float, su: float, n: int):
    """Φ and Q_d of the error dynamics δθ̇ = −[ω×]δθ − δb − η_v, δḃ = η_u by Van Loan's matrix
    exponential (scipy.linalg.expm; torch.linalg.matrix_exp is only good to ~1e-12 here)."""
    w = torch.tensor(omega, dtype=F64)
    A = torch.zeros(6, 6, dtype=F64)
    A[:3, :3] = -rot.cross_matrix(w)
    A[:3, 3:] = -torch.eye(3, dtype=F64)
    GQG = torch.diag(torch.tensor([sv**2] * 3 + [su**2] * 3, dtype=F64))
    A, GQG = A[:n, :n], GQG[:n, :n]
    M = torch.zeros(2 * n, 2 * n, dtype=F64)
    M[:n, :n], M[:n, n:], M[n:, n:] = -A, GQG, A.T
    E = torch.tensor(expm((M * dt).numpy()))
    Phi = E[n:, n:].T
    return Phi, Phi @ E[:n, n:]


@pytest.mark.parametrize("theta", [0.0, 1e-6, 0.02, 0.5, 0.999, 1.001, 2.5])
def test_transition_and_discrete_noise_match_van_loan(gen, theta):
    """Φ and the exact Q_d against the matrix exponential for rotation angles |ω|Δt on both sides
    of the series/closed-form switch (θ = 1); the Farrenkopf Q_d against the same reference
    within its documented error: Q₁₂ off by ≈ σ_u²Δt²θ/6, Q₁₁ by ≈ σ_u²Δt³θ²/60."""
    dt, sv, su = 0.5, 3e-4, 2e-4
    axis = random_unit_vectors(gen, 1)[0].numpy()
    omega = axis * theta / dt
    for estimate_bias in (False, True):
        n = 6 if estimate_bias else 3
        model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=sv, sigma_u=su)
        Phi_ref, Q_ref = _van_loan(omega, dt, sv, su, n)
        Phi, Q = MultiplicativeEKF(model, discrete_noise="exact").transition(torch.tensor(omega, dtype=F64), dt)
        tiny = 1e-13 * float(Q_ref.abs().max())
        assert_within(Phi, Phi_ref, 1e-13, f"Φ at θ = {theta}")
        assert_within(Q, Q_ref, tiny, f"exact Q_d at θ = {theta}")
        _, Qf = MultiplicativeEKF(model).transition(torch.tensor(omega, dtype=F64), dt)
        # the Farrenkopf Q_d within its documented error (and the rounding of the exact one)
        bound = su**2 * dt**3 * theta**2 / 30 + tiny
        assert_within(Qf[:3, :3], Q_ref[:3, :3], bound, f"Farrenkopf Q₁₁ at θ = {theta}")
        if estimate_bias:
            bound = su**2 * dt**2 * theta / 5 + tiny
            assert_within(Qf[:3, 3:], Q_ref[:3, 3:], bound, f"Farrenkopf Q₁₂ at θ = {theta}")
            assert_within(Qf[3:, 3:], Q_ref[3:, 3:], tiny, f"Farrenkopf Q₂₂ at θ = {theta}")


def test_farrenkopf_noise_matches_a_monte_carlo_of_the_gyro():
    """One gyro period of the environment's gyro model (envs.gyro.Gyro, ω = 0, noise inflated so
    every block is visible) from a perfectly known bias: the attitude error the integrated rate
    makes, δθ = −Δt(ω̃ − b₀), and δb = b₁ − b₀ have the covariance Q_d.  200 000 samples; each
    entry within 5 standard errors, ``sqrt((QᵢᵢQⱼⱼ + Qᵢⱼ²)/N)``."""
    dt, sv, su, N = 1.0, 1e-3, 1e-3, 200_000
    gyro = Gyro(sigma_v=sv, sigma_u=su, dt=dt, initial_bias=0.0)
    g = torch.Generator().manual_seed(42)
    n_v = torch.randn(N, 3, generator=g, dtype=F64)
    n_u = torch.randn(N, 3, generator=g, dtype=F64)
    b0 = torch.zeros(N, 3, dtype=F64)
    measured, b1 = gyro.step(torch.zeros(N, 3, dtype=F64), b0, n_v, n_u)
    samples = torch.cat((-dt * (measured - b0), b1 - b0), -1)
    S = samples.T @ samples / N
    model = AttitudeModel(estimate_bias=True, sigma_v=sv, sigma_u=su)
    _, Q = MultiplicativeEKF(model).transition(torch.zeros(3, dtype=F64), dt)
    se = torch.sqrt((Q.diagonal()[:, None] * Q.diagonal()[None, :] + Q**2) / N)
    assert_statistic(S, Q, se, "sample covariance of the gyro's errors", false_failure=1e-6)
    # a few roundings of the closed form (the 1e-12 absolute default of pytest.approx had made these void)
    q11 = sv**2 * dt + su**2 * dt**3 / 3
    assert_within(float(Q[0, 0]), q11, relative_bound(q11, 1e-14, 0.0), "Q₁₁ at ω = 0")
    q12 = -0.5 * su**2 * dt**2
    assert_within(float(Q[0, 3]), q12, relative_bound(q12, 1e-14, 0.0), "Q₁₂ at ω = 0")


# --------------------------------------------------------------------------- the update
def _textbook_update(q, b, P, r, y, mask, sigma):
    """One MEKF update written from Crassidis & Junkins in numpy, one trajectory:
    H = [[(A r_j)×], 0], K = P Hᵀ (H P Hᵀ + R)⁻¹, δx = K (y − A r), q⁺ = δq(δθ) ⊗ q, Joseph P⁺."""
    n = P.shape[0]
    A = rot.quat_to_dcm(torch.tensor(q)).numpy()
    rows, res = [], []
    for j in np.flatnonzero(mask):
        bj = A @ r[j]
        Hj = np.zeros((3, n))
        Hj[:, :3] = np.array([[0, -bj[2], bj[1]], [bj[2], 0, -bj[0]], [-bj[1], bj[0], 0]])
        rows.append(Hj)
        res.append(y[3 * j : 3 * j + 3] - bj)
    H, nu = np.concatenate(rows), np.concatenate(res)
    R = sigma**2 * np.eye(len(nu))
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    dx = K @ nu
    I_KH = np.eye(n) - K @ H
    P_post = I_KH @ P @ I_KH.T + K @ R @ K.T
    # scipy: the attitude C = Rᵀ, so C⁺ = exp(−[δθ×]) C ⇔ R⁺ = R · R(δθ)
    q_post = (Rotation.from_quat(q) * Rotation.from_rotvec(dx[:3])).as_quat()
    loglik = multivariate_normal(mean=np.zeros(len(nu)), cov=S).logpdf(nu)
    return q_post, b + dx[3:], P_post, loglik, float(nu @ np.linalg.solve(S, nu)), len(nu)


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_update_matches_a_textbook_mekf(gen, estimate_bias):
    """Masked star-vector update against the numpy textbook MEKF (with the MRP-belief maps of the
    module), plus the likelihood against scipy; a trajectory with no valid star is returned
    bit-identical; a FunctionMeasurement (autograd Jacobian) gives the same posterior."""
    B, M, sigma = 5, 4, 1e-4
    model = AttitudeModel(estimate_bias=estimate_bias)
    mix = _belief(gen, B, estimate_bias, att_var=1e-6, bias_var=1e-12)
    r = random_unit_vectors(gen, B, M)
    truth = mix.means[:, 0, :3] + 1e-3 * torch.randn(B, 3, generator=gen, dtype=F64)
    y = StarVectorMeasurement(r, sigma=sigma).predict(truth) + sigma * torch.randn(B, 3 * M, generator=gen, dtype=F64)
    mask = torch.tensor([[True, True, False, True], [True] * 4, [False] * 4, [False, True, True, False], [True] * 4])
    mekf = MultiplicativeEKF(model)
    post = mekf.update(mix, y, StarVectorMeasurement(r, mask, sigma))
    diag = mekf.diagnostics
    q, b, P = mrp_to_error_state(mix.means[:, 0], mix.covs[:, 0])
    q_post, b_post, P_post = mrp_to_error_state(post.means[:, 0], post.covs[:, 0])
    for i in range(B):
        if not bool(mask[i].any()):
            assert torch.equal(post.means[i], mix.means[i]) and torch.equal(post.covs[i], mix.covs[i])
            assert float(diag["dof"][i]) == 0.0 and float(diag["log_likelihood"][i]) == 0.0
            continue
        qe, be, Pe, ll, nis, dof = _textbook_update(
            q[i].numpy(), b[i].numpy(), P[i].numpy(), r[i].numpy(), y[i].numpy(), mask[i].numpy(), sigma
        )
        assert_within(abs(float((q_post[i].numpy() * qe).sum())), 1.0, 1e-14, "|q⁺ · q⁺_textbook|")
        dq = Rotation.from_quat(q_post[i].numpy()) * Rotation.from_quat(qe).inv()
        assert_within(dq.magnitude(), 0.0, 1e-13, "angle between the posterior attitude and the textbook one")
        # 1e-8 of the bias correction's size (the bias itself is 1e-5, its correction far smaller)
        b_bound = 1e-8 * np.abs(be - b[i].numpy()).max(initial=0.0) + 1e-22
        assert_within(b_post[i], be, b_bound, "bias after the update")
        assert_within(P_post[i], Pe, relative_bound(Pe, 1e-8, 1e-9 * np.abs(Pe).max()), "covariance after the update")
        # pytest.approx(x, rel=r): max(r·|x|, 1e-12)
        assert_within(float(diag["log_likelihood"][i]), ll, max(1e-10 * abs(ll), 1e-12), "log-likelihood")
        assert_within(float(diag["nis"][i, 0]), nis, max(1e-8 * abs(nis), 1e-12), "NIS")
        assert_within(float(diag["nis_mixture"][i]), nis, max(1e-8 * abs(nis), 1e-12), "NIS of the mixture")
        assert float(diag["dof"][i]) == dof
    # generic measurement models: h through FunctionMeasurement, Jacobian by torch.func
    svm = StarVectorMeasurement(r, mask, sigma)
    fm = FunctionMeasurement(svm.predict, svm.noise_cov(), mask=svm.mask())
    post_f = MultiplicativeEKF(model).update(mix, y, fm)
    assert_within(post_f.means, post.means, 1e-15, "means with a FunctionMeasurement")
    covs_bound = relative_bound(post.covs, 1e-9, 1e-9 * float(post.covs.abs().max()))
    assert_within(post_f.covs, post.covs, covs_bound, "covariances with a FunctionMeasurement")


def test_gate_rejects_a_misidentified_star(gen):
    """With gate_probability a star 0.1° off the catalogue is rejected (agsf_torch.gating), and the
    update equals the update with that star masked out."""
    B, M, sigma = 3, 5, 1e-5
    model = AttitudeModel()
    mix = _belief(gen, B, False, att_var=1e-10)
    r = random_unit_vectors(gen, B, M)
    noise = sigma * torch.randn(B, 3 * M, generator=gen, dtype=F64)
    y = StarVectorMeasurement(r, sigma=sigma).predict(mix.means[:, 0]) + noise
    y_bad = y.clone()
    y_bad[1, 6:9] = rot.mrp_to_dcm(torch.tensor([0.0, 4.4e-4, 0.0], dtype=F64)) @ y[1, 6:9]  # star 2 turned 0.1°
    gated = MultiplicativeEKF(model, gate_probability=1 - 1e-4)
    post = gated.update(mix, y_bad, StarVectorMeasurement(r, sigma=sigma))
    assert gated.diagnostics["gate_rejected"].tolist() == [0, 1, 0]
    mask = torch.ones(B, M, dtype=torch.bool)
    mask[1, 2] = False
    ref = MultiplicativeEKF(model).update(mix, y_bad, StarVectorMeasurement(r, mask, sigma))
    assert torch.equal(post.means, ref.means) and torch.equal(post.covs, ref.covs)  # bit for bit


# --------------------------------------------------------------------------- 4. Monte Carlo
@pytest.mark.parametrize("estimate_bias", [False, True])
def test_monte_carlo_next_to_the_iterated_ekf(estimate_bias):
    """64 runs × 10 s of the paper's case 1 (1 Hz frames, σ_s = 10 µrad, 5 stars) through the
    project's runner, prior P₀ = 1e-7·I MRP² (≈ 0.07° per axis, first-frame linearisation error
    ≈ |δθ|²/2 ≈ 2 µrad < σ_s).  The classic MEKF: final RMS within 3 % of the iterated MRP EKF
    (3 linearisations) and time-averaged NEES inside the 95 % χ² band; the iterated MEKF (3
    linearisations, covariance reset) reproduces the iterated EKF to 0.1 %.

    Measured (seed 2): 3-state final RMS 6.30 µrad (MEKF) / 6.22 (IEKF) / 6.22 (IMEKF), NEES 2.857 /
    2.835 / 2.835, band [2.43, 3.63]; 6-state 12.32 / 12.31 / 12.31 µrad, NEES 5.74 / 5.71 / 5.71,
    band [5.18, 6.88].  At P₀ = 1e-6 (4 mrad, first-frame linearisation error ≈ σ_s) the classic
    MEKF's 3-state final RMS is 20 % above the IEKF's (7.48 µrad) and its NEES (3.81) leaves the
    band, like the one-linearisation MRP EKF (7.69 µrad, NEES 4.28; tests/experiments/test_runner.py)."""
    B, T = 64, 100
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=B, max_steps=T)
    model = AttitudeModel(estimate_bias=estimate_bias)
    n = model.state_dim
    sigma_b0 = 0.2 * math.pi / 180 / 3600
    P0 = torch.diag(torch.tensor([1e-7] * 3 + [sigma_b0**2] * 3, dtype=F64)[:n])
    filters = {
        "mekf": FilterSetup(MultiplicativeEKF(model), 1),
        "imekf": FilterSetup(MultiplicativeEKF(model, update_iterations=3, covariance_reset=True), 1),
        "iekf": FilterSetup(ExtendedKalmanFilter(model, update_iterations=3), 1),
    }
    res = run_monte_carlo(env, filters, num_steps=T, prior_cov=P0, sigma_s=10e-6, seed=2, estimate_bias=estimate_bias)
    lo, hi = chi2_band(n, B)
    rms = {k: float(tr.rms_error()[-1]) for k, tr in res.traces.items()}
    nees = {k: float(tr.nees.mean(1).mean()) for k, tr in res.traces.items()}
    print(
        f"{n}-state: final RMS (µrad) { {k: round(v * 1e6, 3) for k, v in rms.items()} }, "
        f"NEES { {k: round(v, 3) for k, v in nees.items()} }, band [{lo:.3f}, {hi:.3f}]"
    )
    # the same 64 runs through each filter: the allowances are the docstring's, relative to the iterated EKF's
    assert_within(rms["mekf"], rms["iekf"], 0.03 * rms["iekf"], "final RMS of the MEKF against the iterated EKF")
    assert lo <= nees["mekf"] <= hi
    assert_within(rms["imekf"], rms["iekf"], 1e-3 * rms["iekf"], "final RMS of the iterated MEKF against the IEKF")
    assert_within(nees["imekf"], nees["iekf"], 1e-2 * nees["iekf"], "NEES of the iterated MEKF against the IEKF")
    assert np.isfinite(res.traces["mekf"].nis[:, res.star_frame]).all()


# --------------------------------------------------------------------------- 5. bad input
def test_bad_inputs_raise_before_anything_changes(gen):
    model = AttitudeModel(estimate_bias=True)
    mix = _belief(gen, 4, True)
    mekf = MultiplicativeEKF(model)
    r = random_unit_vectors(gen, 4, 5)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    y = meas.predict(mix.means[:, 0])
    u = torch.zeros(4, 3, dtype=F64)
    mekf.predict(mix, u, 0.1)
    assert_bad_input_refused_before_anything_changes(mekf, mix, u, y, meas)

    with pytest.raises(TypeError, match="AttitudeModel"):
        MultiplicativeEKF(StarVectorMeasurement(r))  # type: ignore[arg-type]
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="update_iterations"):
            MultiplicativeEKF(model, update_iterations=bad)
    with pytest.raises(ValueError, match="gate probability"):
        MultiplicativeEKF(model, gate_probability=1.5)
    with pytest.raises(ValueError, match="discrete_noise"):
        MultiplicativeEKF(model, discrete_noise="van-loan")
    with pytest.raises(ValueError, match="no run state"):
        mekf.load_state_dict({"x": 1})


# --------------------------------------------------------------------------- 6. the star-fix start
def _wrong_prior(gen, truth, angle, estimate_bias, att_var=1e-3):
    """A belief ``angle`` rad off the truth (about a random axis; ``angle=None``: uniformly random attitudes),
    covariance ``att_var·I`` on the attitude (MRP²) and 1e-12 on the bias."""
    B = truth.shape[0]
    if angle is None:
        p = random_mrps(B, gen)
    else:
        axis = random_unit_vectors(gen, B)
        p = rot.quat_to_mrp(rot.quat_multiply(rot.rotvec_to_quat(angle * axis), rot.mrp_to_quat(truth)))
    n = 6 if estimate_bias else 3
    mean = torch.cat((p, 1e-6 * torch.randn(B, 3, generator=gen, dtype=F64)), -1)[:, :n]
    P0 = torch.diag(torch.tensor([att_var] * 3 + [1e-12] * 3, dtype=F64)[:n])
    return GaussianMixture.from_gaussian(mean, P0.expand(B, n, n))


def _frame(gen, truth, r, sigma):
    """Noisy star vectors ``C(truth) r_j + σ n`` ``[B, 3M]`` (the measurement model's isotropic noise)."""
    y = StarVectorMeasurement(r, sigma=sigma).predict(truth)
    return y + sigma * torch.randn(y.shape, generator=gen, dtype=F64)


@pytest.mark.parametrize("estimate_bias", [False, True])
@pytest.mark.parametrize("angle", [math.pi / 2, None])
def test_star_fix_start_converges_in_one_frame_from_a_wrong_prior(gen, estimate_bias, angle):
    """From a prior 90° off (or uniformly random) that believes itself within 2° (P₀ = 1e-3 MRP²), one frame of 5
    stars of 10 µrad: the star-fix start lands on the truth with an error its covariance accounts for (each
    trajectory's ``δθᵀ P_θθ⁻¹ δθ`` below the χ²(3) quantile of a 1e-6 false-failure rate, Bonferroni over the
    trajectories), while the prior-start MEKF linearised 90° away is still far off (measured: ~0.6 rad).  The
    next frames are ordinary Kalman updates and the filter stays consistent."""
    from scipy.stats import chi2

    B, M, sigma = 32, 5, 1e-5
    truth = random_mrps(B, gen)
    mix = _wrong_prior(gen, truth, angle, estimate_bias)
    model = AttitudeModel(estimate_bias=estimate_bias)
    r = random_unit_vectors(gen, B, M)
    meas = StarVectorMeasurement(r, sigma=sigma)
    y = _frame(gen, truth, r, sigma)
    limit = chi2.ppf(1.0 - 1e-6 / B, 3)

    fixed = MultiplicativeEKF(model, start="star_fix")
    post = fixed.update(mix, y, meas)
    assert fixed.initialised.tolist() == [True] * B
    assert fixed.diagnostics["dof"].tolist() == [0.0] * B  # the fixing frame is not used again
    e = rot.attitude_error_vector(post.means[:, 0, :3], truth)
    P = mrp_to_error_state(post.means[:, 0], post.covs[:, 0])[2][:, :3, :3]
    nees = (e[:, None, :] @ torch.linalg.solve(P, e[:, :, None])).reshape(-1)
    assert float(nees.max()) < limit, float(nees.max())

    prior = MultiplicativeEKF(model).update(mix, y, meas)
    err_prior = rot.attitude_error_angle(prior.means[:, 0, :3], truth)
    err_fixed = rot.attitude_error_angle(post.means[:, 0, :3], truth)
    if angle is not None:
        assert float(err_prior.min()) > 0.1 and float(err_fixed.max()) < 1e-3 * float(err_prior.min())

    for _ in range(3):  # one gyro second, then a frame: ordinary updates from the fix
        u = torch.zeros(B, 3, dtype=F64) + (post.means[:, 0, 3:] if estimate_bias else 0.0)
        post = fixed.predict(post, u, 1.0)
        y = _frame(gen, truth, r, sigma)
        post = fixed.update(post, y, meas)
        assert fixed.diagnostics["dof"].tolist() == [3.0 * M] * B
    e = rot.attitude_error_vector(post.means[:, 0, :3], truth)
    P = mrp_to_error_state(post.means[:, 0], post.covs[:, 0])[2][:, :3, :3]
    nees = (e[:, None, :] @ torch.linalg.solve(P, e[:, :, None])).reshape(-1)
    assert float(nees.max()) < limit, float(nees.max())


@pytest.mark.parametrize("noise_model", ["isotropic", "tangent"])
def test_star_fix_is_the_wahba_solution_with_the_quest_covariance(gen, noise_model):
    """The fix, against independent computations, one trajectory at a time: the attitude is scipy's
    ``Rotation.align_vectors`` of the valid stars' measured directions (1e-12 rad), the attitude covariance is
    ``(Σ_j (I − b̃_j b̃_jᵀ)/σ²)⁻¹`` (numpy's inverse of the information, 1e-10 relative: the MRP chart's round trip),
    the bias estimate, its covariance and the attitude–bias covariance are the prior's, its and zero.  Masked
    stars, one σ per trajectory, both noise models."""
    from scipy.spatial.transform import Rotation

    B, M = 6, 6
    truth = random_mrps(B, gen)
    mix = _wrong_prior(gen, truth, 0.3, True, att_var=1e-2)
    mix = mix.replace(covs=mix.covs + 1e-9 * torch.eye(6, dtype=F64).roll(3, -1))  # a prior cross-covariance
    sigma = torch.tensor([1e-5, 2e-5, 5e-6, 1e-5, 3e-5, 1e-4], dtype=F64)
    r = random_unit_vectors(gen, B, M)
    mask = torch.ones(B, M, dtype=torch.bool)
    mask[0, 3:] = False
    mask[1, :2] = False
    mask[4, 1:4] = False
    y = StarVectorMeasurement(r, sigma=1.0).predict(truth)
    y = y + sigma[:, None] * torch.randn(B, 3 * M, generator=gen, dtype=F64)
    body = y.unflatten(-1, (M, 3))
    extra = {"body": body / body.norm(dim=-1, keepdim=True)} if noise_model == "tangent" else {}
    meas = StarVectorMeasurement(r, mask, sigma, noise_model=noise_model, **extra)
    mekf = MultiplicativeEKF(AttitudeModel(estimate_bias=True), start="star_fix")
    post = mekf.update(mix, y, meas)
    _, b_post, P_post = mrp_to_error_state(post.means[:, 0], post.covs[:, 0])
    _, b_prior, P_prior = mrp_to_error_state(mix.means[:, 0], mix.covs[:, 0])
    for i in range(B):
        bj = body[i][mask[i]].numpy()
        bj = bj / np.linalg.norm(bj, axis=-1, keepdims=True)
        rj = r[i][mask[i]].numpy()
        C = Rotation.align_vectors(bj, rj)[0].as_matrix()
        dC = rot.mrp_to_dcm(post.means[i, 0, :3]).numpy() @ C.T
        angle = Rotation.from_matrix(dC).magnitude()
        assert_within(angle, 0.0, 1e-12, f"attitude of the fix against scipy's (trajectory {i})")
        info = sum(np.eye(3) - np.outer(b, b) for b in bj) / float(sigma[i]) ** 2
        quest = np.linalg.inv(info)
        assert_within(P_post[i, :3, :3], quest, relative_bound(quest, 1e-10, 1e-10 * np.abs(quest).max()), "QUEST")
    assert torch.equal(b_post, b_prior) and torch.equal(post.means[:, 0, 3:], mix.means[:, 0, 3:])
    assert_within(P_post[:, 3:, 3:], P_prior[:, 3:, 3:], 1e-15 * P_prior[:, 3:, 3:].abs().max(), "bias covariance")
    assert_within(P_post[:, :3, 3:], 0.0, 1e-30, "attitude–bias covariance after the fix")


def test_star_fix_flag_survives_state_dict_and_trajectories_without_a_fix_stay_on_the_prior(gen, tmp_path):
    """Frames of 5, 1, 0 and 2 parallel stars: the first trajectory is fixed, the others run from their prior
    exactly as the prior-start MEKF (bit for bit, their one star used by the Kalman update) and stay
    unflagged; the flag survives ``state_dict``/``load_state_dict`` and a checkpoint (which a prior-start MEKF
    refuses, naming the option), and the next frame, which
    fixes the others, gives the same result bit for bit in the restored filter.  ``reset`` forgets it; a state of
    another batch shape or kind is refused."""
    from agsf_torch.storage.checkpoint import load_checkpoint, save_checkpoint

    B, M, sigma = 4, 5, 1e-5
    truth = random_mrps(B, gen)
    mix = _wrong_prior(gen, truth, 0.01, True, att_var=1e-4)
    model = AttitudeModel(estimate_bias=True)
    r = random_unit_vectors(gen, B, M)
    r[3, 1] = r[3, 0]  # two parallel stars: no attitude
    mask = torch.tensor([[True] * 5, [True] + [False] * 4, [False] * 5, [True, True, False, False, False]])
    meas = StarVectorMeasurement(r, mask, sigma)
    y = _frame(gen, truth, r, sigma)
    fixed = MultiplicativeEKF(model, start="star_fix")
    assert fixed.state_dict() == {"initialised": None} and fixed.initialised is None
    post = fixed.update(mix, y, meas)
    assert fixed.initialised.tolist() == [True, False, False, False]
    ref = MultiplicativeEKF(model).update(mix, y, meas)
    assert torch.equal(post.means[1:], ref.means[1:]) and torch.equal(post.covs[1:], ref.covs[1:])
    assert not torch.equal(post.means[0], ref.means[0])

    restored = MultiplicativeEKF(model, start="star_fix")
    restored.load_state_dict(fixed.state_dict())
    assert torch.equal(restored.initialised, fixed.initialised)
    path = save_checkpoint(tmp_path / "ck.pt", {"f": post}, {"f": fixed})
    from_disk = MultiplicativeEKF(model, start="star_fix")
    mixtures, _ = load_checkpoint(path, {"f": from_disk})
    assert torch.equal(from_disk.initialised, fixed.initialised)
    with pytest.raises(ValueError, match="start is 'star_fix' in the checkpoint, absent in this filter"):
        load_checkpoint(path, {"f": MultiplicativeEKF(model)})  # a prior-start MEKF records no start: as before

    full = StarVectorMeasurement(random_unit_vectors(gen, B, M), sigma=sigma)
    y2 = _frame(gen, truth, full.r_inertial, sigma)
    outs = [f.update(m, y2, full) for f, m in ((fixed, post), (restored, post), (from_disk, mixtures["f"]))]
    for out in outs[1:]:
        assert torch.equal(out.means, outs[0].means) and torch.equal(out.covs, outs[0].covs)
    assert fixed.initialised.tolist() == [True] * B
    assert fixed.diagnostics["dof"].tolist() == [15.0, 0.0, 0.0, 0.0]  # the newly fixed take no Kalman update

    fixed.reset()
    assert fixed.initialised is None and fixed.state_dict() == {"initialised": None}
    restored.update(outs[1], y2, full)
    with pytest.raises(ValueError, match=r"covers trajectories of shape \(4,\), the belief has batch shape \(2,\)"):
        two = StarVectorMeasurement(full.r_inertial[:2], sigma=sigma)
        restored.update(GaussianMixture.from_gaussian(mix.means[:2, 0], mix.covs[:2, 0]), y2[:2], two)
    for bad in ({}, {"initialised": [True]}, {"initialised": torch.ones(4)}, {"x": None, "initialised": None}):
        with pytest.raises(ValueError, match="initialised"):
            restored.load_state_dict(bad)
    assert restored.initialised.tolist() == [True] * B  # refused states change nothing


def test_start_prior_is_todays_mekf_and_star_fix_after_the_fix_runs_it_bit_for_bit(gen):
    """``start="prior"`` (default) keeps no run state and gives the same bits as before the option (the same code
    path: its state is ``{}``, its steps the base class's); a star-fix MEKF once every trajectory is fixed makes
    exactly the prior-start MEKF's updates, gated or not.  Bad starts are refused: other filters take
    ``"prior"`` only, unknown names none, and ``start="star_fix"`` with a measurement that is not a star-vector one
    is refused at the update, before anything changes."""
    from agsf_torch.filters.registry import make_filter

    B, M, sigma = 5, 4, 1e-5
    truth = random_mrps(B, gen)
    model = AttitudeModel(estimate_bias=True)
    mix = _wrong_prior(gen, truth, 1e-3, True, att_var=1e-6)
    r = random_unit_vectors(gen, B, M)
    meas = StarVectorMeasurement(r, sigma=sigma)
    for gate in (None, 1 - 1e-4):
        default = MultiplicativeEKF(model, gate_probability=gate)
        prior = MultiplicativeEKF(model, start="prior", gate_probability=gate)
        fixed = MultiplicativeEKF(model, start="star_fix", gate_probability=gate)
        assert default.start == "prior" and default.state_dict() == {} and prior.state_dict() == {}
        fixed.load_state_dict({"initialised": torch.ones(B, dtype=torch.bool)})
        a = b = c = mix
        for _ in range(3):
            u = 1e-3 * torch.randn(B, 3, generator=gen, dtype=F64)
            a, b, c = (f.predict(m, u, 0.5) for f, m in ((default, a), (prior, b), (fixed, c)))
            y = _frame(gen, truth, r, sigma)
            a, b, c = (f.update(m, y, meas) for f, m in ((default, a), (prior, b), (fixed, c)))
            for m in (b, c):
                assert torch.equal(m.means, a.means) and torch.equal(m.covs, a.covs)
            for key in ("log_likelihood", "nis", "dof"):
                assert torch.equal(fixed.diagnostics[key], default.diagnostics[key])
    assert make_filter("MEKF-fix", model).start == "star_fix" and make_filter("MEKF", model).start == "prior"
    with pytest.raises(TypeError, match="start"):
        ExtendedKalmanFilter(model, start="star_fix")  # a start of the MEKF's only
    with pytest.raises(ValueError, match="start must be one of 'prior', 'star_fix', got 'quest'"):
        MultiplicativeEKF(model, start="quest")
    fixed = MultiplicativeEKF(model, start="star_fix")
    fm = FunctionMeasurement(meas.predict, meas.noise_cov())
    y = _frame(gen, truth, r, sigma)
    with pytest.raises(ValueError, match="must be a StarVectorMeasurement, got FunctionMeasurement"):
        fixed.update(mix, y, fm)
    assert fixed.initialised is None
