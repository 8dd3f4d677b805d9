"""The filters are differentiable end to end: gradcheck of the measurement log-likelihood
Σ log Σᵢ wᵢβᵢ with respect to the noise model, the gyro bias, the prior scale and λ
(through the adaptive weight QP: the KKT solve on the optimal support is the implicit
derivative at the solution)."""

from __future__ import annotations

import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.filters import AdaptiveGaussianSumFilter, ExtendedKalmanFilter, GaussianSumFilter, PenaltyWeightUpdate
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from tests.helpers import F64


def _nll(cls, estimate_bias, log_sv, log_su, log_ss, log_scale, bias, reg):
    g = torch.Generator().manual_seed(0)
    B, N = 2, 1 if cls is ExtendedKalmanFilter else 3
    p = 0.3 * torch.randn(B, 3, generator=g, dtype=F64)
    r = torch.randn(B, 4, 3, generator=g, dtype=F64)
    r = r / r.norm(dim=-1, keepdim=True)
    u = 0.05 * torch.randn(B, 3, generator=g, dtype=F64)
    model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=log_sv.exp(), sigma_u=log_su.exp(), bias=bias)
    n = model.state_dim
    mean = torch.cat((p, torch.zeros(B, 3, dtype=F64)), -1)[:, :n]
    P0 = torch.diag(torch.tensor([1e-4] * 3 + [1e-8] * 3, dtype=F64)[:n]) * log_scale.exp()
    mix = GaussianMixture.from_gaussian(mean, P0.expand(B, n, n), N)
    filt = cls(model, weight_update=PenaltyWeightUpdate(reg=reg)) if cls is AdaptiveGaussianSumFilter else cls(model)
    meas = StarVectorMeasurement(r, sigma=log_ss.exp())
    y = StarVectorMeasurement(r, sigma=1e-3).predict(p + 1e-3)
    total = 0.0
    for _ in range(3):
        mix = filt.predict(mix, u, 0.1)
        mix = filt.update(mix, y, meas)
        total = total + filt.diagnostics["log_likelihood"].sum()
    return -total


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, GaussianSumFilter, AdaptiveGaussianSumFilter])
@pytest.mark.parametrize("estimate_bias", [False, True])
def test_gradcheck_log_likelihood(cls, estimate_bias):
    def t(v):
        return torch.tensor(v, dtype=F64, requires_grad=True)

    args = (t(-5.0), t(-8.0), t(-6.0), t(0.0), t([1e-4, -2e-4, 3e-4]), t(1.0))
    assert torch.autograd.gradcheck(lambda *a: _nll(cls, estimate_bias, *a), args, eps=1e-6, atol=1e-5, rtol=1e-4)
