"""The fused star-vector update (information form on lanes) against a 50-digit reference and the generic update."""

from __future__ import annotations

import math

import mpmath as mp
import pytest
import torch

import agsf_torch.update as generic
from agsf_torch import GaussianMixture
from agsf_torch.filters import ExtendedKalmanFilter, GaussianSumFilter
from agsf_torch.fused.star_update import fused_star_update
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.rotations import mrp_to_dcm
from tests.helpers import F64, assert_within, random_mrps, random_spd, random_unit_vectors

EPS = torch.finfo(F64).eps


def _problem(gen, B, N, n, sigma, prior_var, M=5, masked=True, condition=10.0):
    truth = random_mrps(B, gen, max_norm=0.8)
    means = truth[:, None, :] + math.sqrt(prior_var) * torch.randn(B, N, 3, generator=gen, dtype=F64)
    if n == 6:
        means = torch.cat((means, 1e-6 * torch.randn(B, N, 3, generator=gen, dtype=F64)), -1)
    scale = torch.tensor([prior_var] * 3 + [1e-12] * 3, dtype=F64)[:n].sqrt()
    covs = scale[:, None] * random_spd(gen, B, N, n=n, floor=1.0 / condition) * scale[None, :]
    r = random_unit_vectors(gen, B, M)
    mask = torch.rand(B, M, generator=gen) > 0.3 if masked else None
    y = (mrp_to_dcm(truth)[:, None] @ r.unsqueeze(-1)).squeeze(-1) + sigma * torch.randn(
        B, M, 3, generator=gen, dtype=F64
    )
    y = y / y.norm(dim=-1, keepdim=True)
    log_w = torch.log_softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    return log_w, means, covs, y.reshape(B, 3 * M), StarVectorMeasurement(r, mask, sigma)


def _reference(mean, P, y, meas, b):
    """The exact EKF update of one component in 50-digit arithmetic, ``h`` and ``H`` as float64 computes
    them (their rounding is the problem's data): ``(P⁺, μ⁺, NIS, κ(I + A))``."""
    mp.mp.dps = 50
    B = meas.r_inertial.shape[0]
    h = meas.predict(mean.expand(B, -1))[b]
    H = meas.jacobian(mean.expand(B, -1))[b]
    valid = meas.mask()[b] if meas.mask() is not None else torch.ones(h.shape[0], dtype=torch.bool)
    idx = [k for k in range(h.shape[0]) if bool(valid[k])]
    n = P.shape[-1]
    Hm = mp.matrix([[mp.mpf(float(H[k, j])) for j in range(n)] for k in idx])
    Pm = mp.matrix([[mp.mpf(float(P[i, j])) for j in range(n)] for i in range(n)])
    nu = mp.matrix([mp.mpf(float(y[b, k])) - mp.mpf(float(h[k])) for k in idx])
    s2 = mp.mpf(float(meas.sigma)) ** 2
    S = Hm * Pm * Hm.T + s2 * mp.eye(len(idx))
    K = Pm * Hm.T * mp.inverse(S)
    Pp = Pm - K * Hm * Pm
    x = [mp.mpf(float(mean[j])) + (K * nu)[j] for j in range(n)]
    nis = (nu.T * mp.inverse(S) * nu)[0]
    L = mp.cholesky(Pm)
    A = L.T * Hm.T * Hm * L / s2
    eig = mp.eigsy(A + mp.eye(n))[0]
    kappa = float(max(eig) / min(eig))
    to = lambda v: torch.tensor([[float(v[i, j]) for j in range(n)] for i in range(n)], dtype=F64)  # noqa: E731
    return to(Pp), torch.tensor([float(v) for v in x], dtype=F64), float(nis), kappa


@pytest.mark.parametrize("n", [3, 6])
@pytest.mark.parametrize(
    ("sigma", "prior_var", "condition"), [(1e-3, 1e-4, 1e3), (1e-5, 1e-3, 1e6), (1e-9, 1e-3, 1e12)]
)
def test_fused_update_matches_a_50_digit_reference(gen, n, sigma, prior_var, condition):
    """The information form is backward stable: its error in ``z = (I + A)⁻¹g`` is bounded by
    ``κ(I + A)·ε`` relative, which bounds the mean's and the NIS's; ``P⁺ = YYᵀ + L_bb L_bbᵀ`` is a sum of
    outer products of such solutions.  The kernel evaluates ``h = R(p)r`` on lanes, in another order than
    the reference's float64 ``h``: the innovation differs by up to ``8ε`` per entry (``|h| = 1``), which
    moves the NIS by up to ``2√NIS·√(3M)·8ε/σ`` (``λ_min(S) ≥ σ²``) — the dominant term for a precise
    camera, whose NIS is mostly the innovation's part along the star vectors, ``O(|ν|²/σ²)``."""
    log_w, means, covs, y, meas = _problem(gen, 4, 2, n, sigma, prior_var, condition=condition)
    out = fused_star_update(log_w, means, covs, y, meas)
    for b in range(4):
        for i in range(2):
            P_ref, x_ref, nis_ref, kappa = _reference(means[b, i], covs[b, i], y, meas, b)
            tol = 64 * n * EPS * kappa
            assert_within(out.covs[b, i], P_ref, tol * P_ref.abs().max(), "posterior covariance (50 digits)")
            step = (x_ref - means[b, i]).abs().max()
            # the step to κ(I + A)ε of itself, and the sum μ + Δ and the reference's float64 an ulp each of x
            bound = tol * step + 2 * EPS * x_ref.abs()
            assert_within(out.means[b, i], x_ref, bound, "posterior mean (50 digits)")
            h_rounding = 2 * math.sqrt(nis_ref) * math.sqrt(3 * 5) * 8 * EPS / sigma
            assert_within(out.nis[b, i], nis_ref, tol * nis_ref + h_rounding, "component NIS (50 digits)")


@pytest.mark.parametrize("n", [3, 6])
@pytest.mark.parametrize("iterations", [1, 3])
@pytest.mark.parametrize(("B", "N"), [(1, 1), (3, 64), (2001, 5)])
def test_fused_update_equals_the_generic_information_form(gen, monkeypatch, n, iterations, B, N):
    """Against the generic update in its information form (the covariance form's own rounding grows
    like ε·cond(S)), with masked stars, in a conditioning where ``κ(I + A) ≤ 1 + 5‖P‖/σ² ≈ 500``.  Each
    path's rounding is bounded by ``γ_k κ`` with ``k = 3n + 1`` (a Cholesky solve of order ``n``) plus
    ``3M`` (the information ``HᵀR⁻¹H`` summed over ``M = 5`` stars, every entry of either order):
    agreement to ``2(3n + 1 + 3M)·κ·ε`` of each quantity's scale."""
    log_w, means, covs, y, meas = _problem(gen, B, N, n, 1e-3, 1e-4)
    got = fused_star_update(log_w, means, covs, y, meas, iterations)
    monkeypatch.setattr(generic, "COVARIANCE_FORM_MAX_CONDITION", 0.0)  # the information form everywhere
    want = generic.kalman_update(log_w, means, covs, y, meas, iterations)
    tol = 2 * (3 * n + 1 + 3 * 5) * 500 * EPS

    def close(name, scale):
        assert_within(getattr(got, name), getattr(want, name), tol * scale, f"{name} of the information forms")

    close("means", want.means.abs().amax(-1, keepdim=True))
    close("covs", want.covs.abs().amax((-1, -2), keepdim=True))
    close("nis", want.nis.abs() + 1.0)
    close("log_weights", want.log_weights.abs() + 1.0)
    close("log_likelihood", want.log_likelihood.abs() + 1.0)
    # the mixture NIS solves with the moment-matched S̄ (the components' spread included): to 10 κ(S̄) ε
    h, H = generic.evaluate_measurement(meas, means)
    nu = y.unsqueeze(-2) - h
    S = H @ covs @ H.transpose(-1, -2) + meas.noise_cov().unsqueeze(-3)
    _, S_bar = generic.moment_matched_innovation(log_w, nu, S)
    valid = meas.star_mask.repeat_interleave(3, dim=-1).to(F64)  # masked entries out of the conditioning
    S_bar = S_bar * valid.unsqueeze(-1) * valid.unsqueeze(-2) + torch.diag_embed((1.0 - valid) * meas.sigma**2)
    kappa = torch.linalg.cond(S_bar)
    bound = 10 * kappa * EPS * (want.nis_mixture.abs() + 1.0)
    assert_within(got.nis_mixture, want.nis_mixture, bound, "mixture NIS of the information forms")
    assert torch.equal(got.dof, want.dof)


def test_trajectories_without_a_valid_star_are_left_exactly_as_they_were(gen):
    log_w, means, covs, y, meas = _problem(gen, 6, 3, 6, 1e-5, 1e-3)
    mask = meas.star_mask.clone()
    mask[2] = False
    meas = StarVectorMeasurement(meas.r_inertial, mask, 1e-5)
    out = fused_star_update(log_w, means, covs, y, meas)
    assert torch.equal(out.means[2], means[2]) and torch.equal(out.covs[2], covs[2])
    assert torch.equal(out.log_weights[2], log_w[2]) and float(out.log_likelihood[2]) == 0.0 and int(out.dof[2]) == 0


def test_the_fused_update_refuses_what_the_generic_one_refuses(gen):
    log_w, means, covs, y, meas = _problem(gen, 3, 2, 3, 1e-5, 1e-3, masked=False)
    bad = y.clone()
    bad[1, 4] = 1e20
    for update in (fused_star_update, generic.kalman_update):
        with pytest.raises(ValueError, match=r"measurement entry 4 at trajectory index \(1,\), component 0 is absurd"):
            update(log_w, means, covs, bad, meas)
    nan_means = means.clone()
    nan_means[0, 1, 2] = float("nan")
    for update in (fused_star_update, generic.kalman_update):
        with pytest.raises(ValueError, match=r"state mean is not finite at trajectory index \(0,\), component 1"):
            update(log_w, nan_means, covs, y, meas)


@pytest.mark.parametrize("gate", [None, 0.9999])
@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, GaussianSumFilter])
def test_filters_give_the_same_posterior_with_and_without_the_fused_path(gen, cls, gate):
    """2000 trajectories (past the eager crossover, so the fused path is taken), in a conditioning where both
    forms are accurate (``cond(S) ≤ 1 + 5‖P‖/σ² ≈ 500``): agreement to ``10·500·ε``.  The tangent model has no
    fused path and goes the generic way with ``fused=True``."""
    N = 1 if cls is ExtendedKalmanFilter else 3
    log_w, means, covs, y, meas = _problem(gen, 2000, N, 6, 1e-3, 1e-4)
    mix = GaussianMixture(log_weights=log_w, means=means, covs=covs)
    model = AttitudeModel(estimate_bias=True)
    fused, plain = cls(model, gate_probability=gate), cls(model, gate_probability=gate, fused=False)
    a, b = fused.update(mix, y, meas), plain.update(mix, y, meas)
    tol = 10 * 500 * EPS
    assert_within(a.means, b.means, tol * b.means.abs().amax(-1, keepdim=True), "posterior means, fused and not")
    assert_within(
        a.covs, b.covs, tol * b.covs.abs().amax((-1, -2), keepdim=True), "posterior covariances, fused and not"
    )
    assert set(fused.diagnostics) == set(plain.diagnostics)
    tangent = StarVectorMeasurement(
        meas.r_inertial, meas.star_mask, 1e-3, noise_model="tangent", body=y.reshape(2000, 5, 3)
    )
    assert tangent.fused_update(log_w, means, covs, y) is None


@pytest.mark.slow
@pytest.mark.parametrize("n", [3, 6])
def test_the_compiled_update_equals_the_eager_one(gen, n):
    log_w, means, covs, y, meas = _problem(gen, 70, 5, n, 1e-5, 1e-3)
    eager = fused_star_update(log_w, means, covs, y, meas, 2)
    compiled = fused_star_update(log_w, means, covs, y, meas, 2, compile=True)
    # κ(I + A) ≤ 1 + 5‖P‖/σ² ≈ 5e7 bounds both routes' rounding (the same analysis as the information forms'
    # above), relative to each quantity's scale; not the 1e6 at which the two happened to round alike
    tol = 64 * n * EPS * (1 + 5 * 1e-3 / 1e-5**2)
    for name in ("means", "covs", "log_weights", "nis", "log_likelihood", "nis_mixture"):
        a, b = getattr(compiled, name), getattr(eager, name)
        if name == "means":
            scale = b.abs().amax(-1, keepdim=True)
        elif name == "covs":
            scale = b.abs().amax((-1, -2), keepdim=True)
        else:
            scale = b.abs() + 1.0
        assert_within(a, b, tol * scale, f"compiled update's {name}")


def test_a_kernel_result_that_is_not_finite_falls_back_to_the_generic_update(gen, monkeypatch):
    """Never a wrong number: where the kernel's arithmetic leaves its range (a NaN covariance was returned for
    σ = 1 nrad after a 1e-3 prior of condition 1e12), the call returns the generic update."""
    import agsf_torch.fused.star_update as fused

    log_w, means, covs, y, meas = _problem(gen, 5, 3, 6, 1e-5, 1e-3)
    real = fused.star_kernel

    def broken(*args):
        out = list(real(*args))
        out[1] = out[1].clone()
        out[1][7, 0, 0] = float("nan")
        return tuple(out)

    monkeypatch.setattr(fused, "star_kernel", broken)
    got = fused_star_update(log_w, means, covs, y, meas)
    want = generic.kalman_update(log_w, means, covs, y, meas)
    for field in ("means", "covs", "log_weights", "nis", "log_likelihood", "nis_mixture"):
        assert torch.equal(getattr(got, field), getattr(want, field)), field
