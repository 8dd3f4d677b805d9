"""RK4 moment propagation against a tight adaptive reference integration."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from agsf_torch.models import AttitudeModel
from agsf_torch.propagation import moment_derivatives, propagate_moments
from tests.helpers import random_mrps


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
        np.testing.assert_allclose(m1[b].numpy(), m_ref, rtol=1e-9, atol=1e-9 * np.abs(m_ref).max())
        np.testing.assert_allclose(P1[b].numpy(), P_ref, rtol=1e-9, atol=1e-9 * np.abs(P_ref).max())
    torch.testing.assert_close(P1, P1.transpose(-1, -2), rtol=0, atol=0)
