"""The physical floor (the DARE's steady state): Farrenkopf's closed form, the 3-state limit, the star count, the
Riccati equation itself, and the MEKF's own covariance recursion run to its steady state.

**Farrenkopf's single-axis result**, derived here independently (and evaluated at 50 digits with mpmath).  In
units of ``σ_n²`` (angle) and ``σ_n²/T²`` (bias), the single-axis model over one frame interval ``T`` is
``Φ = [[1, −1], [0, 1]]``, ``Q = [[S_v² + S_u²/3, −S_u²/2], [−S_u²/2, S_u²]]``, ``H = [1, 0]``, ``R = 1`` with
``S_u = σ_u T^{3/2}/σ_n``, ``S_v = σ_v T^{1/2}/σ_n``.  The second difference of the measurements is a moving
average of order 2 with autocovariances ``r₀ = 6 + 2S_v² + 2S_u²/3``, ``r₁ = −4 − S_v² + S_u²/6``, ``r₂ = 1``; its
minimum-phase factorisation ``r(z) = s |1 + c₁z⁻¹ + c₂z⁻²|²`` gives the steady innovation variance ``s = 1/c₂``.
Writing the two factors' outer roots ``x₁², x₂²`` with ``x_i − 1/x_i = t_i``, the factorisation gives
``t₁t₂ = S_u`` and ``t₁² + t₂² = S_v² − S_u²/6``, whence ``ξ = x₁x₂`` solves ``ξ + 1/ξ = γ``:

    γ = ½S_u + sqrt(4 + S_v² + S_u²/12),   ξ = ½(γ + sqrt(γ² − 4)),   s = ξ²,

so ``P⁻_θθ = s − 1 = ξ² − 1``, ``P⁺_θθ = P⁻/(1 + P⁻) = 1 − ξ⁻²``, and the steady-state equations of the bias
block give ``P⁻_θb = −S_u ξ``, ``P⁺_θb = −S_u/ξ``, ``P⁺_bb = S_u(ξ − ξ⁻¹) − S_u²/2``: Farrenkopf's result
(J. Guidance and Control 1(4), 1978; as presented in Crassidis & Junkins, *Optimal Estimation of Dynamic
Systems*, and Markley & Crassidis, *Fundamentals of Spacecraft Attitude Determination and Control*).
"""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.attitude.floor import ARCSEC_PER_RAD, Floor, frame_information, riccati_floor
from agsf_torch.filters.multiplicative import MultiplicativeEKF, mrp_to_error_state
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.rotations import quat_multiply, quat_to_dcm, rotvec_to_quat
from tests.helpers import F64, assert_within, random_unit_vectors

EPS = float(np.finfo(np.float64).eps)

#: The paper's case 1 (agsf_torch/experiments/config/presets/case1.toml): σ_v, σ_u, gyro step, frame interval,
#: stars per frame, camera noise.
CASE1 = dict(sigma_v=3.1622776601683795e-7, sigma_u=3.1622776601683794e-10, dt=0.1, T=1.0, m=5, sigma=10e-6)


def farrenkopf(S_u, S_v) -> dict[str, mpmath.mpf]:
    """Farrenkopf's steady state of the single-axis problem (module docstring), 50 digits, in units of ``σ_n²``
    (angle), ``σ_n²/T`` (cross) and ``σ_n²/T²`` (bias)."""
    with mpmath.workdps(50):
        S_u, S_v = mpmath.mpf(S_u), mpmath.mpf(S_v)
        g = S_u / 2 + mpmath.sqrt(4 + S_v**2 + S_u**2 / 12)
        xi = (g + mpmath.sqrt(g**2 - 4)) / 2
        return {
            "after": 1 - 1 / xi**2,
            "before": xi**2 - 1,
            "cross_after": -S_u / xi,
            "cross_before": -S_u * xi,
            "bias_after": S_u * (xi - 1 / xi) - S_u**2 / 2,
            "bias_before": S_u * (xi - 1 / xi) + S_u**2 / 2,
            "xi": xi,
            "gamma": g,
        }


def _sigma_n2(m: int, sigma: float):
    """The per-axis measurement variance of ``m`` isotropic stars of noise σ, ``3σ²/(2m)``, at 50 digits."""
    with mpmath.workdps(50):
        return 3 * mpmath.mpf(sigma) ** 2 / (2 * m)


def _rel(actual, expected) -> float:
    with mpmath.workdps(50):
        return float(abs((mpmath.mpf(float(actual)) - expected) / expected))


# --------------------------------------------------------------------------- Farrenkopf
FARRENKOPF_CASES = [(1.0, 1.0), (0.1, 0.5), (1e-3, 1e-2), (5.8e-5, 0.058), (10.0, 0.1), (1e-2, 10.0), (0.3, 3.0)]


@pytest.mark.parametrize(("S_u", "S_v"), FARRENKOPF_CASES)
@pytest.mark.parametrize("dt", [1.0, 0.1])
def test_each_axis_matches_farrenkopfs_closed_form(S_u, S_v, dt):
    """Isotropic information: every axis is Farrenkopf's single-axis problem with ``σ_n² = 3σ²/(2m)``; the
    steady state of the 6-state DARE (frames every 1 s, propagated in one step or composed from ten) matches the
    closed form to 1e-10 relative in every entry (the DARE of these well-scaled problems is solved to ~1e-13;
    measured ≤ 5e-13), and the axes are uncoupled."""
    m, sigma, T = 5, 10e-6, 1.0
    sn2 = _sigma_n2(m, sigma)
    sn = float(mpmath.sqrt(sn2))
    sigma_v, sigma_u = S_v * sn / math.sqrt(T), S_u * sn / T**1.5
    floor = riccati_floor(sigma_v, sigma_u, T, m, sigma, dt=dt)
    with mpmath.workdps(50):  # the S the floor saw (the rounded σ's), exactly
        s_v = mpmath.mpf(sigma_v) * mpmath.sqrt(T) / mpmath.sqrt(sn2)
        s_u = mpmath.mpf(sigma_u) * mpmath.mpf(T) ** 1.5 / mpmath.sqrt(sn2)
    ref = farrenkopf(s_u, s_v)
    for name, P in (("after", floor.P_after), ("before", floor.P_before)):
        for i in range(3):
            assert _rel(P[i, i], ref[name] * sn2) < 1e-10, (name, i)
            assert _rel(P[i, i + 3], ref[f"cross_{name}"] * sn2 / T) < 1e-10, (name, i)
            assert _rel(P[i + 3, i + 3], ref[f"bias_{name}"] * sn2 / T**2) < 1e-10, (name, i)
        scale = P.diagonal().sqrt()
        off = P.clone()
        idx = torch.arange(3)
        off[idx, idx] = off[idx, idx + 3] = off[idx + 3, idx] = off[idx + 3, idx + 3] = 0.0
        assert_within(off, 0.0, 1e-13 * scale[:, None] * scale[None, :], f"coupling between axes ({name})")
    assert_within(floor.arcsec_after, float(mpmath.sqrt(ref["after"] * sn2)) * ARCSEC_PER_RAD, 1e-10, "arcsec")


@pytest.mark.parametrize("S_v", [0.058, 0.5, 4.0])
def test_the_three_state_floor_is_farrenkopfs_without_a_bias_and_the_limit_of_the_six_state_one(S_v):
    """``sigma_u=None`` (the 3-state model): Farrenkopf's form at ``S_u = 0`` (``ξ = ½(S_v + sqrt(4 + S_v²))``)
    to 1e-10.  The 6-state floor tends to it as ``σ_u → 0`` at first order: ``(P⁺(S_u) − P⁺(0))/S_u`` tends to
    the closed form's derivative ``d = ξ⁻³(1 + γ/sqrt(γ² − 4))/2`` (units σ_n²) with an error that shrinks ten-fold
    per decade of ``S_u`` (Taylor's remainder), and the bias variance ``σ_n²(S_u(ξ − ξ⁻¹) − S_u²/2)/T²`` vanishes at
    least as fast as ``S_u``."""
    m, sigma, T = 5, 10e-6, 1.0
    sn2 = _sigma_n2(m, sigma)
    sn = float(mpmath.sqrt(sn2))
    three = riccati_floor(S_v * sn, None, T, m, sigma, dt=0.1)
    assert three.P_after.shape == (3, 3) and three.bias_after is None
    with mpmath.workdps(50):
        s_v = mpmath.mpf(S_v * sn) / mpmath.sqrt(sn2)
    ref = farrenkopf(0, s_v)
    with mpmath.workdps(50):
        # the oracle's own consistency at 50 digits: its ξ at S_u = 0 is the closed form's
        assert mpmath.almosteq(ref["xi"], (s_v + mpmath.sqrt(4 + s_v**2)) / 2, rel_eps=mpmath.mpf(10) ** -40)
    for i in range(3):
        assert _rel(three.P_after[i, i], ref["after"] * sn2) < 1e-10
        assert _rel(three.P_before[i, i], ref["before"] * sn2) < 1e-10
    g, xi = ref["gamma"], ref["xi"]
    d = float(xi**-3 * (1 + g / mpmath.sqrt(g**2 - 4)) / 2)
    deviations, bias = [], []
    for S_u in (c * min(1.0, S_v**2) for c in (1e-2, 1e-3, 1e-4)):  # S_u ≪ S_v²: the Taylor regime
        six = riccati_floor(S_v * sn, S_u * sn / T**1.5, T, m, sigma, dt=0.1)
        gap = float(six.P_after[0, 0] - three.P_after[0, 0]) / float(sn2)
        deviations.append(gap / S_u - d)
        assert 0.0 < gap < d * S_u  # the unknown bias costs accuracy, at most the tangent's worth (concave)
        bias.append(float(six.P_after[3, 3]))
    assert 9.0 < deviations[0] / deviations[1] < 11.0 and 9.0 < deviations[1] / deviations[2] < 11.0, deviations
    assert bias[1] < bias[0] / 10 and bias[2] < bias[1] / 10  # ξ falls with S_u too


# --------------------------------------------------------------------------- star count
def test_more_stars_lower_the_floor_with_the_scaling_the_closed_form_gives():
    """Strictly lower with every added star (both models, before and after a frame); exactly invariant under
    ``(m, σ) → (4m, 2σ)`` (the same information per frame: equal to rounding); and the exponent of the count
    lies between its two limits: ``σ⁺ ∝ m^{-1/2}`` when the gyro is poor (``S_v ≫ 1``, each frame on its own:
    ``P⁺ ≈ σ_n²(1 − S_v⁻²)``, ratio for 4× the stars ``½ + 3/(16S_v²)``) and ``m^{-1/4}`` when it is good
    (``S_v ≪ 1``: ``P⁺ ≈ σ_n² S_v = σ_n σ_v T^{½}``, ratio ``2^{-½}(1 − S_v/4)``), so ``1/√m`` is the
    gyro-poor limit only."""
    sigma, T, sv, su = 10e-6, 1.0, CASE1["sigma_v"], CASE1["sigma_u"]
    for sigma_u in (None, su):
        floors = [riccati_floor(sv, sigma_u, T, m, sigma, dt=0.1) for m in range(1, 31)]
        for a, b in zip(floors, floors[1:]):
            assert (b.arcsec_after < a.arcsec_after).all() and (b.arcsec_before < a.arcsec_before).all()
        one, four = riccati_floor(sv, sigma_u, T, 3, sigma), riccati_floor(sv, sigma_u, T, 12, 2 * sigma)
        for name in ("P_before", "P_after"):
            P = getattr(one, name)
            assert_within(getattr(four, name), P, 1e-13 * P.abs().max(), f"{name} of (4m, 2σ) against (m, σ)")
    m = 5
    sn = math.sqrt(3 * sigma**2 / (2 * m))
    for S_v in (1e2, 1e3):
        ratio = float(riccati_floor(S_v * sn, None, T, 4 * m, sigma).arcsec_after[0]) / float(
            riccati_floor(S_v * sn, None, T, m, sigma).arcsec_after[0]
        )
        assert_within(ratio, 0.5, 0.2 / S_v**2, f"σ⁺ ratio for 4× the stars at S_v = {S_v} (gyro poor)")
    for S_v in (1e-2, 1e-3, 1e-4):
        ratio = float(riccati_floor(S_v * sn, None, T, 4 * m, sigma).arcsec_after[0]) / float(
            riccati_floor(S_v * sn, None, T, m, sigma).arcsec_after[0]
        )
        assert_within(ratio, 2**-0.5, S_v / 4, f"σ⁺ ratio for 4× the stars at S_v = {S_v} (gyro good)")


# --------------------------------------------------------------------------- the Riccati equation
def _riccati_terms(floor: Floor, sigma_v: float, sigma_u: float | None):
    """``(Φ_T P Φ_Tᵀ, Φ_T P Hᵀ S⁻¹ H P Φ_Tᵀ, Q_T)`` of the floor's DARE, from the closed forms at ``ω̂ = 0``
    (module docstring of :mod:`agsf_torch.attitude.floor`), in numpy."""
    T = floor.frame_interval
    n = floor.P_before.shape[0]
    Phi, Q = np.eye(n), np.zeros((n, n))
    Q[:3, :3] = (sigma_v**2 * T + (0.0 if sigma_u is None else sigma_u**2 * T**3 / 3)) * np.eye(3)
    if n == 6:
        Phi[:3, 3:] = -T * np.eye(3)
        Q[:3, 3:] = Q[3:, :3] = -0.5 * sigma_u**2 * T**2 * np.eye(3)
        Q[3:, 3:] = sigma_u**2 * T * np.eye(3)
    P = floor.P_before.numpy()
    J = floor.information.numpy()
    H = np.zeros((3, n))
    H[:, :3] = np.eye(3)
    APA = Phi @ P @ Phi.T
    G = Phi @ P @ H.T
    # (H P Hᵀ + J⁻¹)⁻¹ = (J H P Hᵀ + I)⁻¹ J: J⁻¹ never formed
    gain = G @ np.linalg.solve(J @ H @ P @ H.T + np.eye(3), J) @ G.T
    return APA, gain, Q


@pytest.mark.parametrize("sigma_u", [None, CASE1["sigma_u"], 1e-7])
def test_the_solution_satisfies_the_riccati_equation(gen, sigma_u):
    """``P = Φ P Φᵀ − Φ P Hᵀ S⁻¹ H P Φᵀ + Q`` with anisotropic star directions.  A solution with the forward error
    ``δP`` leaves the residual ``δP − A_c δP A_cᵀ`` (``A_c = Φ(I − KH)``, the closed loop, spectral radius
    ``ρ < 1``), and the DARE's condition for that error is the closed-loop Lyapunov operator's, ``1/(1 − ρ²)``: the
    residual is bounded by ``4nε/(1 − ρ²)`` times the magnitude of the equation's terms (measured over 300 random
    geometries: at most 30 ε, against bounds of 100 ε to 10⁴ ε).  The iterated recursion from ``Q`` (the test's
    oracle, symmetrised; 3000 frames reach rounding where ``ρ`` ≤ 0.95) agrees to ``1e-11`` of ‖P‖ (measured
    ~6e-16)."""
    sigma_v, T, m, sigma = CASE1["sigma_v"], 1.0, 5, CASE1["sigma"]
    if sigma_u is not None and sigma_u > 1e-8:
        sigma_v = 1e-5  # a faster-converging scenario for the oracle
    directions = random_unit_vectors(gen, m)
    floor = riccati_floor(sigma_v, sigma_u, T, m, sigma, dt=0.1, directions=directions)
    APA, gain, Q = _riccati_terms(floor, sigma_v, sigma_u)
    P = floor.P_before.numpy()
    residual = APA - gain + Q - P
    scale = np.abs(APA) + np.abs(gain) + np.abs(Q) + np.abs(P)
    n = P.shape[0]
    H = np.zeros((3, n))
    H[:, :3] = np.eye(3)
    Phi = np.eye(n)
    if n == 6:
        Phi[:3, 3:] = -T * np.eye(3)
    J = floor.information.numpy()
    K = P @ H.T @ np.linalg.solve(J @ H @ P @ H.T + np.eye(3), J)  # P Hᵀ (H P Hᵀ + J⁻¹)⁻¹
    eig = np.linalg.eigvals(Phi @ (np.eye(n) - K @ H))
    rho = float(np.hypot(eig.real, eig.imag).max())  # the closed loop's spectral radius: a stable filter has < 1
    assert 0.0 < rho < 1.0
    bound = 4 * n * EPS / (1.0 - rho**2) * scale.max(axis=1, keepdims=True)
    assert_within(residual, 0.0, bound, f"DARE residual (closed-loop spectral radius {rho:.6f})")
    if sigma_u is None or sigma_u > 1e-8:
        it = Q.copy()
        for _ in range(3000):
            PH = it @ H.T
            post = it - PH @ np.linalg.solve(J @ H @ PH + np.eye(3), J) @ PH.T
            it = Phi @ post @ Phi.T + Q
            it = 0.5 * (it + it.T)  # unsymmetrised, the short-form recursion's rounding grows without bound
        assert_within(P, it, 1e-11 * np.abs(P).max(), "DARE solution against the iterated Riccati recursion")


# --------------------------------------------------------------------------- the MEKF's steady state
def _mekf_run(model, r, sigma, frames, steps, dt, P0, gen, rate=None):
    """The MEKF on ``B`` trajectories: ``steps`` gyro steps then one star frame (noisy vectors of the catalogue
    ``r [B, M, 3]`` seen from a truth turning at ``rate``), ``frames`` times.  With ``rate=None`` the gyro reads
    the current bias estimate (6-state) or the known bias (3-state), so ``ω̂ = 0`` exactly.  Returns the
    error-state covariances ``(P⁻, P⁺)`` of the last frame."""
    B = r.shape[0]
    n = model.state_dim
    mix = GaussianMixture.from_gaussian(torch.zeros(B, n, dtype=F64), P0.expand(B, n, n))
    mekf = MultiplicativeEKF(model)
    meas = StarVectorMeasurement(r, sigma=sigma)
    q_true = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64).expand(B, 4)
    for _ in range(frames):
        for _ in range(steps):
            if rate is None:
                u = mix.means[:, 0, 3:].clone() if n == 6 else torch.zeros(B, 3, dtype=F64)
            else:
                u = rate.expand(B, 3).clone()
                q_true = quat_multiply(rotvec_to_quat(rate * dt).expand(B, 4), q_true)
            mix = mekf.predict(mix, u, dt)
        before = mrp_to_error_state(mix.means[:, 0], mix.covs[:, 0])[2]
        b = (quat_to_dcm(q_true)[:, None] @ r[..., None]).squeeze(-1)
        y = (b + sigma * torch.randn(b.shape, generator=gen, dtype=F64)).flatten(-2)
        mix = mekf.update(mix, y, meas)
    return before, mrp_to_error_state(mix.means[:, 0], mix.covs[:, 0])[2]


def _axes_pairs() -> torch.Tensor:
    """Six stars along ±x, ±y, ±z: ``Σ(I − b bᵀ) = 4I`` in any attitude, the isotropic information of six stars."""
    eye = torch.eye(3, dtype=F64)
    return torch.cat((eye, -eye))


def test_the_mekf_covariance_converges_to_the_floor(gen):
    """The MEKF's covariance recursion is the Riccati recursion: from a wide prior, 80 frames (closed-loop
    contraction ≈ 0.4 per frame at S_u = 0.5, S_v = 1) of the 6-state MEKF on noisy frames of six stars at ±x,
    ±y, ±z (information ``4I/σ²``, the isotropic average of six stars, whatever the attitude) with ``ω̂ = 0``
    reach the floor before and after a frame to rounding (1e-13 of ‖P‖; measured ≤ 6e-15).  The 3-state MEKF on a
    body turning at a constant 0.05 rad/s does too: with isotropic ``P`` and information the rotation changes
    nothing."""
    sigma, T, dt, m = 1e-5, 1.0, 0.1, 6
    sn = math.sqrt(3 * sigma**2 / (2 * m))
    sigma_v, sigma_u = 1.0 * sn, 0.5 * sn
    floor = riccati_floor(sigma_v, sigma_u, T, m, sigma, dt=dt)
    r = _axes_pairs().expand(3, m, 3)
    P0 = torch.diag(torch.tensor([1e-6] * 3 + [1e-12] * 3, dtype=F64))
    model = AttitudeModel(estimate_bias=True, sigma_v=sigma_v, sigma_u=sigma_u)
    before, after = _mekf_run(model, r, sigma, 80, 10, dt, P0, gen)
    for got, want, what in ((before, floor.P_before, "before"), (after, floor.P_after, "after")):
        assert_within(got, want.expand_as(got), 1e-13 * float(want.abs().max()), f"6-state MEKF P {what} a frame")

    floor3 = riccati_floor(sigma_v, None, T, m, sigma, dt=dt)
    rate = torch.tensor([0.03, -0.04, 0.0], dtype=F64)
    model3 = AttitudeModel(estimate_bias=False, sigma_v=sigma_v)
    before, after = _mekf_run(model3, r, sigma, 60, 10, dt, P0[:3, :3], gen, rate=rate)
    for got, want, what in ((before, floor3.P_before, "before"), (after, floor3.P_after, "after")):
        assert_within(got, want.expand_as(got), 1e-13 * float(want.abs().max()), f"3-state MEKF P {what} a frame")


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_the_floor_of_case_1_is_a_fixed_point_of_the_mekf(gen, estimate_bias):
    """The paper's case 1 (σ_v, σ_u, 10 gyro steps per 1 s frame, 5 stars of 10 µrad): five stars in a tight
    frame (a pentagon at ``cos²α = 1/3`` from the boresight: ``Σ b bᵀ = (5/3)I``, so the information is exactly the
    isotropic average's) seen by the MEKF started at the floor: after 5 frames of noisy stars it is still there to
    rounding (1e-12 of ‖P‖; the case's slow bias mode, ρ ≈ 1 − 1e-3 per frame, makes a run from a wide prior
    too long for a unit test)."""
    c = CASE1
    alpha = math.acos(math.sqrt(1.0 / 3.0))
    phi = torch.arange(5, dtype=F64) * 2 * math.pi / 5
    r = torch.stack(
        (math.sin(alpha) * phi.cos(), math.sin(alpha) * phi.sin(), torch.full_like(phi, math.cos(alpha))), -1
    )
    assert_within(r.T @ r, (5.0 / 3.0) * torch.eye(3, dtype=F64), 1e-15, "Σ b bᵀ of the pentagon")
    sigma_u = c["sigma_u"] if estimate_bias else None
    floor = riccati_floor(c["sigma_v"], sigma_u, c["T"], c["m"], c["sigma"], dt=c["dt"])
    model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=c["sigma_v"], sigma_u=c["sigma_u"])
    # the prior at the floor just after a frame, in the MRP chart at p = 0 (T = blockdiag(¼I, I): exact)
    chart = torch.tensor([0.25] * 3 + [1.0] * 3, dtype=F64)[: model.state_dim]
    P0 = chart[:, None] * floor.P_after * chart[None, :]
    before, after = _mekf_run(model, r.expand(2, 5, 3), c["sigma"], 5, 10, c["dt"], P0, gen)
    for got, want, what in ((before, floor.P_before, "before"), (after, floor.P_after, "after")):
        assert_within(got, want.expand_as(got), 1e-12 * float(want.abs().max()), f"case-1 MEKF P {what} a frame")


# --------------------------------------------------------------------------- directions, between frames
def test_anisotropic_directions_decouple_along_the_informations_axes(gen):
    """Five stars in an 8° field (the camera of case 1): in the eigenbasis of the frame's information ``J`` the
    floor is three uncoupled Farrenkopf problems, axis ``i`` with ``σ_n,i² = 1/λ_i`` (1e-10 relative); the roll
    axis (the boresight, ``z``), seen only through the stars' small off-axis angles, is the worst."""
    half = math.radians(4.0)
    xy = (torch.rand(5, 2, generator=gen, dtype=F64) * 2 - 1) * math.tan(half)
    b = torch.cat((xy, torch.ones(5, 1, dtype=F64)), -1)
    b = b / b.norm(dim=-1, keepdim=True)
    sigma_v, sigma_u, T, sigma = CASE1["sigma_v"], CASE1["sigma_u"], 1.0, CASE1["sigma"]
    floor = riccati_floor(sigma_v, sigma_u, T, 5, sigma, dt=0.1, directions=b)
    J = floor.information
    assert_within(J, (torch.eye(3, dtype=F64) - b.T @ b / 5) * 5 / sigma**2, 1e-12 * float(J.abs().max()), "J")
    lam, V = torch.linalg.eigh(J)
    Vb = torch.block_diag(V, V)
    for name in ("after", "before"):
        P = Vb.T @ getattr(floor, f"P_{name}") @ Vb
        for i in range(3):
            with mpmath.workdps(50):
                sn2 = 1 / mpmath.mpf(float(lam[i]))
                s_v = mpmath.mpf(sigma_v) * mpmath.sqrt(T) / mpmath.sqrt(sn2)
                s_u = mpmath.mpf(sigma_u) * mpmath.mpf(T) ** 1.5 / mpmath.sqrt(sn2)
            ref = farrenkopf(s_u, s_v)
            assert _rel(P[i, i], ref[name] * sn2) < 1e-10, (name, i)
            assert _rel(P[i + 3, i + 3], ref[f"bias_{name}"] * sn2 / T**2) < 1e-10, (name, i)
            assert _rel(P[i, i + 3], ref[f"cross_{name}"] * sn2 / T) < 1e-10, (name, i)
    roll, pitch_yaw = float(floor.arcsec_after[2]), float(floor.arcsec_after[:2].max())
    assert roll > 3 * pitch_yaw, (roll, pitch_yaw)


def test_between_frames_the_covariance_grows_back_and_the_step_does_not_matter():
    """``k`` steps of the MEKF's transition carry ``P⁺`` back to ``P⁻`` (1e-13 of ‖P‖); the floor does not depend
    on the propagation step at ``ω̂ = 0`` (Farrenkopf's Q_d composes exactly: dt = T, T/10 and T/7 agree to
    1e-13), the time average lies between the two and, for one step per frame, is ``P⁺``."""
    sv, su, T, m, sigma = CASE1["sigma_v"], CASE1["sigma_u"], 1.4, 5, CASE1["sigma"]
    floors = [riccati_floor(sv, su, T, m, sigma, dt=T / k) for k in (1, 10, 7)]
    one, ten, seven = floors
    assert ten.steps_per_frame == 10 and seven.steps_per_frame == 7
    Phi, Q = MultiplicativeEKF(AttitudeModel(estimate_bias=True, sigma_v=sv, sigma_u=su)).transition(
        torch.zeros(3, dtype=F64), ten.dt
    )
    P = ten.P_after
    for _ in range(10):
        P = Phi @ P @ Phi.T + Q
    assert_within(P, ten.P_before, 1e-13 * float(ten.P_before.abs().max()), "P⁺ propagated over a frame interval")
    for f in (ten, seven):
        for name in ("P_before", "P_after"):
            want = getattr(one, name)
            assert_within(getattr(f, name), want, 1e-13 * float(want.abs().max()), f"{name} with dt = {f.dt}")
        assert (f.arcsec_after < f.arcsec_mean).all() and (f.arcsec_mean < f.arcsec_before).all()
    assert torch.equal(one.P_mean, one.P_after)
    # the mean over the grid from the closed form: P⁺_θθ − jΔt(P⁺_θb + P⁺_bθ) + (jΔt)²P⁺_bb + q(jΔt), j < k
    k, dt = 10, ten.dt
    Pa = ten.P_after
    t = torch.arange(k, dtype=F64) * dt
    mean = Pa[0, 0] - 2 * t.mean() * Pa[0, 3] + (t**2).mean() * Pa[3, 3] + sv**2 * t.mean() + su**2 * (t**3).mean() / 3
    assert_within(ten.P_mean[0, 0], mean, 1e-13 * float(Pa[0, 0]), "time-averaged attitude variance")


# --------------------------------------------------------------------------- bad input
def test_bad_input_is_refused_naming_the_argument():
    good = dict(sigma_v=1e-7, sigma_u=1e-10, frame_interval=1.0, stars_per_frame=5, sigma_star=1e-5)
    bad = {
        "sigma_v": [0.0, -1e-7, float("nan"), float("inf"), True, "1e-7", None],
        "sigma_u": [0.0, -1e-10, float("inf")],
        "frame_interval": [0.0, -1.0, float("nan")],
        "stars_per_frame": [0, -3, 1.5, True, None],
        "sigma_star": [0.0, -1e-5, float("nan")],
    }
    for name, values in bad.items():
        for value in values:
            with pytest.raises(ValueError, match=name):
                riccati_floor(**{**good, name: value})
    for dt in (0.0, -0.1, 0.3, 2.0):
        with pytest.raises(ValueError, match="dt"):
            riccati_floor(**good, dt=dt)
    with pytest.raises(ValueError, match="directions are all parallel"):
        riccati_floor(**good, directions=torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=F64))
    with pytest.raises(ValueError, match="directions must be unit vectors"):
        frame_information(5, 1e-5, torch.zeros(4, dtype=F64))
    with pytest.raises(ValueError, match="not a unit vector"):
        frame_information(5, 1e-5, torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0]], dtype=F64))
    iso = frame_information(6, 2.0)
    assert_within(frame_information(6, 2.0, _axes_pairs()), iso, 4 * EPS * iso, "± axes: the isotropic average")
    third = (2.0 / 3.0) * torch.eye(3, dtype=F64)
    assert_within(frame_information(1, 1.0, torch.eye(3, dtype=F64)), third, 4 * EPS, "three orthogonal directions")


def test_a_turning_body_with_a_narrow_field_reaches_the_floor_at_its_rate():
    """Five stars fixed in the body frame within 4° of the boresight (a narrow-field camera: the rotation about the
    boresight is observed ~300× less well than the others in one frame) on a body turning at a constant rate: the
    3-state MEKF's covariance converges to the floor computed with those directions *at that rate* (the turning
    body carries its error, fixed in inertial space, past the camera's directions), and that floor is below
    the one of a body at rest about the boresight axis."""
    sigma, T, dt = 1e-5, 1.0, 0.1
    sigma_v = 1e-6
    offsets = torch.tensor([[0.0, 0.0], [0.05, 0.02], [-0.04, 0.05], [0.03, -0.06], [-0.06, -0.03]], dtype=F64)
    body = torch.nn.functional.normalize(torch.cat((offsets, torch.ones(5, 1, dtype=F64)), -1), dim=-1)
    rate = torch.tensor([0.03, -0.04, 0.0], dtype=F64)
    floor = riccati_floor(sigma_v, None, T, 5, sigma, dt=dt, directions=body, rate=rate)
    resting = riccati_floor(sigma_v, None, T, 5, sigma, dt=dt, directions=body)
    assert float(floor.arcsec_mean[2]) < float(resting.arcsec_mean[2])  # 0.99″ against 1.84″

    B = 2
    model = AttitudeModel(estimate_bias=False, sigma_v=sigma_v)
    mekf = MultiplicativeEKF(model)
    mix = GaussianMixture.from_gaussian(torch.zeros(B, 3, dtype=F64), 1e-6 * torch.eye(3, dtype=F64).expand(B, 3, 3))
    q_true = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64).expand(B, 4)
    for _ in range(400):
        for _ in range(10):
            mix = mekf.predict(mix, rate.expand(B, 3).clone(), dt)
            q_true = quat_multiply(rotvec_to_quat(rate * dt).expand(B, 4), q_true)
        before = mrp_to_error_state(mix.means[:, 0], mix.covs[:, 0])[2]
        r = (quat_to_dcm(q_true).transpose(-1, -2)[:, None] @ body[None, :, :, None]).squeeze(-1)  # body-fixed stars
        # noise-free stars: the estimate stays on the truth, so the MEKF linearises where the floor does (with
        # noise its estimate, ~1e-6 rad off, would tilt an anisotropic H and P by that much relative)
        mix = mekf.update(mix, body.expand(B, 5, 3).flatten(-2), StarVectorMeasurement(r, sigma=sigma))
    after = mrp_to_error_state(mix.means[:, 0], mix.covs[:, 0])[2]
    # the MEKF's recursion is the DARE's at this rate: from the prior the gap contracts by ~1e-5 per 100 frames
    # (4e-5 of ‖P‖ at 100 frames, 4e-10 at 200), so after 400 it is rounding: 1e-12 of ‖P‖ (measured 8e-15)
    for got, want, what in ((before, floor.P_before, "before"), (after, floor.P_after, "after")):
        assert_within(got, want.expand_as(got), 1e-12 * float(want.abs().max()), f"turning MEKF P {what} a frame")
