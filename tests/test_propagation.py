"""RK4 moment propagation against a tight adaptive reference integration."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from agsf_torch.models import AttitudeModel, ContinuousModel
from agsf_torch.propagation import moment_derivatives, propagate_moments
from tests.helpers import CubicDrift, assert_within, random_mrps, relative_bound


def _reference(model, mean, cov, u, dt):
    n = mean.shape[-1]

    def rhs(_, z):
        m = torch.tensor(z[:n])
        P = torch.tensor(z[n:]).reshape(n, n)
        r = moment_derivatives(model, m, P, torch.tensor(u))
        return np.concatenate((r.mean_rate.numpy(), r.cov_rate.numpy().ravel()))

    z0 = np.concatenate((mean.numpy(), cov.numpy().ravel()))
    sol = solve_ivp(rhs, (0.0, dt), z0, method="DOP853", rtol=1e-13, atol=1e-20)
    return sol.y[:n, -1], sol.y[n:, -1].reshape(n, n)


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_rk4_matches_fine_reference(gen, estimate_bias):
    model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=1e-5, sigma_u=1e-8)
    n = model.state_dim
    p = random_mrps(4, gen, max_norm=0.9)
    mean = torch.cat((p, 1e-4 * torch.ones(4, 3, dtype=torch.float64)), -1)[:, :n]
    cov = torch.diag(torch.tensor([1e-3] * 3 + [1e-10] * 3, dtype=torch.float64)[:n]).expand(4, n, n).clone()
    u = 2 * np.pi / 100 * np.array([1.0, 1.0, 0.0])
    m1, P1 = propagate_moments(model, mean, cov, torch.tensor(u).expand(4, 3), dt=0.1, substeps=1)
    for b in range(4):
        m_ref, P_ref = _reference(model, mean[b], cov[b], u, 0.1)
        assert_within(m1[b], m_ref, relative_bound(m_ref, 1e-9, 1e-9 * np.abs(m_ref).max()), "RK4 mean")
        assert_within(P1[b], P_ref, relative_bound(P_ref, 1e-9, 1e-9 * np.abs(P_ref).max()), "RK4 covariance")
    assert torch.equal(P1, P1.transpose(-1, -2))


class _Shear(ContinuousModel):
    """dx₀ = 100 x₁ dt, dx₁ = dβ: ‖A‖∞ = 100 but both eigenvalues are 0 (a nilpotent drift RK4 follows exactly)."""

    state_dim = 2

    def drift(self, x, u=None):
        return torch.stack((100.0 * x[..., 1], torch.zeros_like(x[..., 0])), -1)

    def noise_gain(self, x):
        return torch.tensor([[0.0], [1.0]], dtype=x.dtype).expand(*x.shape[:-1], 2, 1)

    def noise_psd(self):
        return torch.ones(1, 1, dtype=torch.float64)


def test_a_step_rk4_cannot_follow_is_refused_naming_the_component_and_the_substeps_that_can():
    """At x = 16.4 the drift's slope is 1 − 3·16.4² = −805.9 1/s: one RK4 step of 0.1 s (|λh| = 80.6) sent the
    moments to 1e45 and 1e95, finite and wrong.  It is refused, naming the component and the substeps needed by
    the covariance's mode 2λ = −1612 1/s (|2λ|·dt / 2 = 80.6 → 81); with them the step is stable, and more substeps
    converge on the exact mean at RK4's order."""
    model = CubicDrift()
    mean = torch.tensor([[[1.0], [16.4]], [[0.5], [-1.0]]], dtype=torch.float64)  # [B = 2, N = 2, 1]
    cov = torch.full((2, 2, 1, 1), 0.01, dtype=torch.float64)
    with pytest.raises(
        ValueError, match=r"at batch index \(0, 1\): the covariance's mode .* = -1612.*use at least substeps=81"
    ):
        propagate_moments(model, mean, cov, None, dt=0.1, substeps=1)
    # the mean's ODE ẋ = x − x³ (the moment equations' mean follows it) has the solution x² = 1 / (1 − c e^{−2t})
    x0, t = 16.4, 0.1
    exact = 1.0 / np.sqrt(1.0 - (1.0 - 1.0 / x0**2) * np.exp(-2.0 * t))
    errors = []
    for substeps in (81, 162, 324):
        m, P = propagate_moments(model, mean, cov, None, dt=0.1, substeps=substeps)
        assert torch.isfinite(m).all() and torch.isfinite(P).all() and bool((P > 0).all())
        errors.append(abs(float(m[0, 1, 0]) - exact) / exact)
    assert errors[0] < 1e-3  # stable, from x = 16.4 down to 2.33 in 0.1 s
    assert errors[1] < errors[0] / 16 and errors[2] < errors[1] / 16  # fourth order: halving h gains ≥ 2⁴


def test_the_step_check_reads_eigenvalues_not_the_norm():
    """A drift whose Jacobian has a large norm but no large eigenvalue (a shear) is not refused."""
    mean = torch.zeros(3, 2, dtype=torch.float64)
    cov = torch.eye(2, dtype=torch.float64).expand(3, 2, 2).clone()
    m, P = propagate_moments(_Shear(), mean, cov, None, dt=0.1, substeps=1)
    # exactly (RK4 integrates these polynomials of degree ≤ 3 without error): Φ = [[1, 10], [0, 1]] and
    # S = ∫ e^{As} B Bᵀ e^{Aᵀs} ds = [[1e4·h³/3, 100·h²/2], [100·h²/2, h]], so P = ΦΦᵀ + S
    h = 0.1
    expected = torch.tensor([[101 + 1e4 * h**3 / 3, 10 + 50 * h**2], [10 + 50 * h**2, 1 + h]], dtype=torch.float64)
    # the entries add terms of one sign (no cancellation): a few roundings of each entry's own size
    assert_within(P, expected, 1e-13 * expected, "covariance of the shear")


def test_the_step_check_names_the_component_in_chunked_batches(monkeypatch):
    """Batches propagated in chunks name the component's index in the whole batch, not in its chunk."""
    import agsf_torch.propagation as propagation

    monkeypatch.setattr(propagation, "PROPAGATION_CHUNK", 4)
    mean = torch.zeros(3, 5, 1, dtype=torch.float64)
    mean[2, 3, 0] = 16.4  # flat index 13: the fourth chunk of 4
    cov = torch.full((3, 5, 1, 1), 0.01, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"at batch index \(2, 3\)"):
        propagation.propagate_moments(CubicDrift(), mean, cov, None, dt=0.1, substeps=1)


def test_a_stiff_linear_model_is_refused_at_the_covariances_modes_and_converges_from_the_substeps_named():
    """A damped oscillator with eigenvalues −6.06 and −593.9 1/s, dt = 0.1 s: the covariance's noise integral has
    the mode 2λ = −1188 1/s, so 30 substeps (|λ|h = 1.98 but |2λ|h = 3.96) leave RK4's stability region; they had
    been suggested and then failed with a non-positive-definite covariance.  They are refused, naming 60; from 60
    substeps on the covariance converges on the exact one (the Lyapunov solution and the matrix exponential,
    scipy) at RK4's order."""
    import scipy.linalg

    from agsf_torch.models import LinearModel

    w, zeta, q = 60.0, 5.0, 0.5
    A = np.array([[0.0, 1.0], [-(w**2), -2 * zeta * w]])
    G = np.array([[0.0], [1.0]])
    model = LinearModel(torch.tensor(A), torch.tensor(G), torch.tensor([[q]]))
    mean = torch.zeros(1, 2, dtype=torch.float64)
    P0 = np.diag([1e-2, 1.0])
    cov = torch.tensor(P0)[None]
    with pytest.raises(ValueError, match=r"mode λᵢ \+ λⱼ = -1188.*use at least substeps=60 for dt=0\.1 s"):
        propagate_moments(model, mean, cov, None, dt=0.1, substeps=30)
    Phi = scipy.linalg.expm(A * 0.1)
    P_inf = scipy.linalg.solve_continuous_lyapunov(A, -G @ G.T * q)  # stationary: A P + P Aᵀ + G q Gᵀ = 0
    exact = Phi @ P0 @ Phi.T + P_inf - Phi @ P_inf @ Phi.T
    errors = []
    for substeps in (60, 120, 240):
        P = propagate_moments(model, mean, cov, None, dt=0.1, substeps=substeps)[1][0].numpy()
        errors.append(np.linalg.norm(P - exact) / np.linalg.norm(exact))
    assert errors[0] < 1e-2 and errors[1] < errors[0] / 8 and errors[2] < errors[1] / 8, errors
