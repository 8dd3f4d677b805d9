"""The exact-density reference sampler (agsf_torch.density.reference).

Expected values are computed independently of the code under test: the Kalman
filter with numpy/scipy (matrix exponential and Van Loan's integral), the
Fokker–Planck density with the Crank–Nicolson grid solver.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg as sla
import torch

from agsf_torch.density import PosteriorReference, density_score
from agsf_torch.density.grid import FokkerPlanckGrid
from agsf_torch.mixture import GaussianMixture
from agsf_torch.models import FunctionMeasurement, LinearModel
from agsf_torch.models.benchmarks import SineDriftModel
from tests.density.conftest import f64, gaussian
from tests.helpers import assert_statistic, assert_within, relative_bound


def expected_log_gaussian(mu_p, Sig_p, mu_q, Sig_q) -> float:
    """E_{N(μp, Σp)}[log N(x; μq, Σq)] in closed form."""
    d = mu_p - mu_q
    c = sla.cho_factor(Sig_q)
    return -0.5 * (
        np.trace(sla.cho_solve(c, Sig_p)) + d @ sla.cho_solve(c, d) + np.linalg.slogdet(2 * np.pi * Sig_q)[1]
    )


# ------------------------------------------------------------------ (a) linear-Gaussian
A_LIN = np.array([[0.0, 1.0], [-1.0, -0.3]])
G_LIN = np.array([[0.0], [1.0]])
Q_LIN = np.array([[0.005]])
DT_LIN = 0.1


def kalman_predict(m, P):
    """Exact discretisation of dx = Ax dt + G dβ over DT_LIN (Van Loan)."""
    n = A_LIN.shape[0]
    M = sla.expm(np.block([[-A_LIN, G_LIN @ Q_LIN @ G_LIN.T], [np.zeros((n, n)), A_LIN.T]]) * DT_LIN)
    F = M[n:, n:].T
    return F @ m, F @ P @ F.T + F @ M[:n, n:]


def kalman_update(m, P, H, R, y):
    S = H @ P @ H.T + R
    K = sla.cho_solve(sla.cho_factor(S), H @ P).T
    I_KH = np.eye(len(m)) - K @ H
    return m + K @ (y - H @ m), I_KH @ P @ I_KH.T + K @ R @ K.T


def test_linear_gaussian_score_matches_kalman_before_and_after_sharp_frames():
    """E_p[log q] from the reference equals the closed form under the Kalman posterior,
    for the posterior itself and for a displaced, widened Gaussian, before the frames,
    right after a frame that collapses a bootstrap filter (R = 1e-4 against P₀ ~ 1),
    after a second sharp frame and after further propagation."""
    model = LinearModel(torch.tensor(A_LIN), torch.tensor(G_LIN), torch.tensor(Q_LIN))
    B, K = 2, 4000
    m0 = np.array([[0.5, -0.3], [-0.2, 0.4]])
    P0 = np.array([[1.0, 0.2], [0.2, 0.5]])
    frames = {
        3: (np.array([[1.0, 0.0]]), np.array([[1e-4]]), np.array([[0.62], [-0.05]])),
        6: (np.eye(2), 1e-3 * np.eye(2), np.array([[0.55, -0.4], [0.1, 0.3]])),
    }
    ref = PosteriorReference(
        model,
        torch.tensor(m0),
        torch.tensor(P0),
        num_samples=K,
        generator=torch.Generator().manual_seed(3),
        substeps=20,
    )
    m, P = m0.copy(), np.stack([P0] * B)
    checked = 0
    for k in range(1, 11):
        ref.predict(None, DT_LIN)
        for b in range(B):
            m[b], P[b] = kalman_predict(m[b], P[b])
        if k in frames:
            H, R, y = frames[k]
            meas = FunctionMeasurement(lambda x, H=torch.tensor(H): x @ H.T, torch.tensor(R))
            ref.update(torch.tensor(y), meas)
            for b in range(B):
                m[b], P[b] = kalman_update(m[b], P[b], H, R, y[b])
            rec = ref.history[-1]
            assert bool((rec.bootstrap_ess < 0.1 * K).all())  # a bootstrap filter collapses here
            assert bool(rec.redrawn.all())
            assert bool((rec.ess > 0.05 * K).all())
        if k in (2, 3, 6, 10):
            shift = 0.5 * np.sqrt(np.diagonal(P, axis1=1, axis2=2))
            for mq, Pq in ((m, P), (m + shift, 2.0 * P)):
                score, se = ref.score(gaussian(mq, Pq))
                exact = np.array([expected_log_gaussian(m[b], P[b], mq[b], Pq[b]) for b in range(B)])
                # 1e-4 per check (the 4σ limit per entry it replaces had 6.3e-5 per entry)
                assert_statistic(
                    score, exact, se, f"score at step {k} against the Kalman closed form", false_failure=1e-4
                )
                assert np.all(se.numpy() < 0.1)
                checked += 1
    assert checked == 8
    hist = ref.stacked_history()
    assert hist["ess"].shape == (12, B) and hist["lineages"].shape == (12, B)  # 10 predicts, 2 updates
    assert hist["frame"].tolist() == [False] * 3 + [True] + [False] * 3 + [True] + [False] * 4


# ------------------------------------------------------------------ (b) scalar sine SDE
def test_sine_forecast_score_matches_fokker_planck_grid():
    """Without measurements the reference is the forecast of ẋ = sin x + Γ (q = 1):
    its score of three Gaussians at t = 2 s equals ∫ p log q dx with p the
    Crank–Nicolson solution of the FPKE from the benchmark's mixture prior."""
    grid = np.linspace(-15.0, 15.0, 3001)
    solver = FokkerPlanckGrid(grid, np.sin, lambda x: 0.5 * np.ones_like(x), dt=0.002)
    w, mu = np.array([0.1, 0.9]), np.array([-0.2, 0.2])
    p = (w[:, None] * np.exp(-0.5 * (grid[None] - mu[:, None]) ** 2) / np.sqrt(2 * np.pi)).sum(0)
    p = solver.normalise(solver.step(p, 2.0))
    mean = np.trapezoid(grid * p, grid)
    var = np.trapezoid((grid - mean) ** 2 * p, grid)
    cases = [(mean, var), (0.0, 2.0), (1.5, 1.0)]

    B, K = 2, 20000
    prior = GaussianMixture(
        weights=torch.tensor([[0.1, 0.9]] * B, dtype=f64),
        means=torch.tensor([[[-0.2], [0.2]]] * B, dtype=f64),
        covs=torch.ones(B, 2, 1, 1, dtype=f64),
    )
    ref = PosteriorReference(
        SineDriftModel(), prior=prior, num_samples=K, generator=torch.Generator().manual_seed(7), substeps=10
    )
    for _ in range(20):
        ref.predict(None, 0.1)
    assert_within(ref.time, 2.0, relative_bound(2.0, 1e-6, 1e-12), "time after 20 steps of 0.1 s")
    for mq, vq in cases:
        expected = np.trapezoid(p * (-0.5 * ((grid - mq) ** 2 / vq + np.log(2 * np.pi * vq))), grid)
        mix = GaussianMixture(
            weights=torch.ones(B, 1, dtype=f64),
            means=torch.full((B, 1, 1), mq, dtype=f64),
            covs=torch.full((B, 1, 1, 1), vq, dtype=f64),
        )
        score, se = ref.score(mix)
        # the grid's error (Δx = 0.01, Δt = 2 ms) is taken as negligible against se (< 0.05), as always: the
        # sampling spread sets the limit; 1e-4 per case (the 4σ limit per entry it replaces had 6.3e-5 per entry)
        assert_statistic(
            score, expected, se, f"score of N({mq:.3g}, {vq:.3g}) against the FPKE grid", false_failure=1e-4
        )
        assert np.all(se.numpy() < 0.05)
    # no measurement: equal weights, independent samples
    full = torch.full((B,), float(K), dtype=f64)
    assert_within(ref.ess, full, relative_bound(full, 1e-5, 1e-8), "ESS of equal weights")  # allclose's defaults


def test_forecast_is_reproducible_from_the_generator():
    model = SineDriftModel()
    runs = []
    for _ in range(2):
        ref = PosteriorReference(
            model,
            torch.zeros(3, 1, dtype=f64),
            torch.eye(1, dtype=f64),
            num_samples=50,
            generator=torch.Generator().manual_seed(11),
            substeps=2,
        )
        ref.predict(None, 0.1)
        runs.append(ref.samples)
    assert torch.equal(runs[0], runs[1])


# ------------------------------------------------------------------ (d) bad inputs
def test_bad_inputs_raise_clear_errors():
    model = LinearModel(torch.tensor(A_LIN), torch.tensor(G_LIN), torch.tensor(Q_LIN))
    gen = torch.Generator().manual_seed(0)
    m0, P0 = torch.zeros(2, 2, dtype=f64), torch.eye(2, dtype=f64)

    def make(**kw):
        args = dict(num_samples=10, generator=gen)
        args.update(kw)
        return PosteriorReference(model, args.pop("m0", m0), args.pop("P0", P0), **args)

    with pytest.raises(ValueError, match="prior_mean"):
        make(m0=torch.zeros(2, dtype=f64))
    with pytest.raises(ValueError, match="prior_cov"):
        make(P0=torch.eye(3, dtype=f64))
    with pytest.raises(ValueError, match="positive definite"):
        make(P0=torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=f64))
    with pytest.raises(ValueError, match="state_dim"):
        make(m0=torch.zeros(2, 3, dtype=f64), P0=torch.eye(3, dtype=f64))
    with pytest.raises(ValueError, match="num_samples"):
        make(num_samples=1)
    with pytest.raises(ValueError, match="generator"):
        make(generator=0)
    with pytest.raises(ValueError, match="chart"):
        make(chart="quaternion")
    with pytest.raises(ValueError, match="MRP"):
        make(chart="mrp")
    with pytest.raises(ValueError, match="redraw_threshold"):
        make(redraw_threshold=1.5)
    with pytest.raises(ValueError, match="lineage_threshold"):
        make(lineage_threshold=-0.1)
    assert make().lineage_threshold == 0.1 and make(lineage_threshold=0.02).lineage_threshold == 0.02
    with pytest.raises(ValueError, match="substeps"):
        make(substeps=0)
    with pytest.raises(ValueError, match="not both"):
        make(prior=gaussian(np.zeros((2, 2)), np.stack([np.eye(2)] * 2)))
    with pytest.raises(ValueError, match="prior_mean and prior_cov"):
        PosteriorReference(model, m0, num_samples=10, generator=gen)
    ref = make()
    for dt in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="dt"):
            ref.predict(None, dt)
    with pytest.raises(ValueError, match="u must"):
        ref.predict(torch.zeros(3, 1, dtype=f64), 0.1)
    meas = FunctionMeasurement(lambda x: x[..., :1], torch.eye(1, dtype=f64))
    with pytest.raises(ValueError, match="y must have shape"):
        ref.update(torch.zeros(2, dtype=f64), meas)
    with pytest.raises(ValueError, match="finite"):
        ref.update(torch.tensor([[math.nan], [0.0]], dtype=f64), meas)
    with pytest.raises(ValueError, match="entries"):
        ref.update(torch.zeros(2, 3, dtype=f64), meas)
    with pytest.raises(ValueError, match="hints"):
        ref.update(torch.zeros(2, 1, dtype=f64), meas, hints=torch.zeros(2, 2, dtype=f64))

    mix = gaussian(np.zeros((2, 2)), np.stack([np.eye(2)] * 2))
    x, lw = torch.zeros(2, 5, 2, dtype=f64), torch.zeros(2, 5, dtype=f64)
    with pytest.raises(ValueError, match="samples"):
        density_score(x[0], lw, mix)
    with pytest.raises(ValueError, match="log_weights"):
        density_score(x, lw[:, :4], mix)
    with pytest.raises(ValueError, match="at least one"):
        density_score(x, torch.full((2, 5), -math.inf, dtype=f64), mix)
    with pytest.raises(ValueError, match="state dimension"):
        density_score(torch.zeros(2, 5, 3, dtype=f64), lw, mix)
    with pytest.raises(ValueError, match="batch shape"):
        density_score(torch.zeros(3, 5, 2, dtype=f64), torch.zeros(3, 5, dtype=f64), mix)
    with pytest.raises(ValueError, match="finite"):
        density_score(torch.full((2, 5, 2), math.nan, dtype=f64), lw, mix)
    with pytest.raises(ValueError, match="lineage"):
        density_score(x, lw, mix, lineage=torch.full((2, 5), 5))
    with pytest.raises(ValueError, match="chart"):
        density_score(x, lw, mix, chart="mrp")
