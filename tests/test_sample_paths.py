"""Sample paths (:mod:`agsf_torch.sample_paths`): the chain's drift is RK4's, its noise ``g Q^{1/2} ξ √τ``, its
chart switch after every step, and the PSD square root squares to ``Q``."""

from __future__ import annotations

import math

import numpy as np
import torch

from agsf_torch.models import LinearModel
from agsf_torch.sample_paths import em_rk4_interval, sqrt_psd
from tests.helpers import F64, assert_within

EPS = float(np.finfo(np.float64).eps)


def _model() -> LinearModel:
    A = torch.tensor([[-0.5, 1.0, 0.0], [-1.0, -0.2, 0.3], [0.0, 0.1, -1.5]], dtype=F64)
    G = torch.tensor([[1.0, 0.0], [0.5, 2.0], [0.0, 1.0]], dtype=F64)
    Q = torch.tensor([[0.4, 0.1], [0.1, 0.2]], dtype=F64)
    return LinearModel(A, G, Q)


def test_the_noise_free_chain_is_rk4(gen):
    """``ẋ = Ax`` with zero noise: ``substeps`` RK4 steps, ``x ← (I + τA + (τA)²/2 + (τA)³/6 + (τA)⁴/24) x`` each
    (the same polynomial, evaluated in numpy; the two round differently, a few ε of the terms per step)."""
    model = _model()
    x = torch.randn(4, 5, 3, generator=gen, dtype=F64)
    dt, substeps = 0.7, 6
    out = em_rk4_interval(model, x, None, dt, substeps, torch.zeros(2, 2, dtype=F64), lambda z: z, torch.zeros)
    T = (dt / substeps) * model.A.numpy()
    step = np.eye(3) + T + T @ T / 2 + T @ T @ T / 6 + T @ T @ T @ T / 24
    want = x.numpy() @ np.linalg.matrix_power(step, substeps).T
    bound = 64 * substeps * EPS * float(np.abs(x.numpy()).max()) * float(np.abs(step).sum(-1).max()) ** substeps
    assert_within(out, want, bound, "RK4 steps of a linear drift")


def test_the_noise_is_g_q_half_xi_root_tau_and_the_chart_switches_after_every_step():
    """``f = 0``: each step adds ``G Q^{1/2} ξⱼ √τ`` with the ``ξⱼ`` the caller's draws (``[..., K, q]`` each), and
    the chart switch (here: a halving) follows every step, so ``x ← (x + G Q^{1/2} ξⱼ √τ)/2``."""
    model = _model()
    model.A.zero_()
    Q_sqrt = sqrt_psd(model.Q)
    draws = [torch.full((2, 3, 2), float(j + 1), dtype=F64) * torch.tensor([1.0, -0.5], dtype=F64) for j in range(3)]
    it = iter(draws)
    shapes = []

    def randn(shape):
        shapes.append(shape)
        return next(it)

    x = torch.ones(2, 3, 3, dtype=F64)
    dt = 0.3
    out = em_rk4_interval(model, x, None, dt, 3, Q_sqrt, lambda z: 0.5 * z, randn)
    assert shapes == [(2, 3, 2)] * 3
    want = x.numpy()
    GQ = model.G.numpy() @ Q_sqrt.numpy()
    for xi in draws:
        want = 0.5 * (want + math.sqrt(dt / 3) * xi.numpy() @ GQ.T)
    assert_within(out, want, 64 * EPS * (1 + float(np.abs(want).max())), "three noisy steps with a chart switch")


def test_the_psd_square_root_squares_to_q_and_clips_negative_eigenvalues(gen):
    """``S = S^T``, ``S² = Q`` for a positive semidefinite ``Q`` (rank 2 of 3 here); an eigenvalue ``−δ`` of rounding
    size is clipped to 0."""
    V = torch.randn(3, 2, generator=gen, dtype=F64)
    Q = V @ V.T
    S = sqrt_psd(Q)
    assert_within(S, S.T, 8 * EPS * float(S.abs().max()), "symmetric")
    assert_within(S @ S, Q, 64 * EPS * float(Q.abs().max()), "S² of a rank-2 Q")
    bent = torch.diag(torch.tensor([1.0, 0.5, -1e-12], dtype=F64))
    S = sqrt_psd(bent)
    assert_within(
        S @ S, torch.diag(torch.tensor([1.0, 0.5, 0.0], dtype=F64)), 16 * EPS, "the negative eigenvalue clipped"
    )
