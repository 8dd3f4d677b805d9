"""The rounding floor of the FPKE matrix: a linear model's residual is zero to rounding, and the penalty update
leaves its weights alone; the attitude models' and a nonlinear model's residuals are resolved above it."""

from __future__ import annotations

import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.filters import AdaptiveGaussianSumFilter, GaussianSumFilter, PenaltyWeightUpdate
from agsf_torch.filters.weight_updates.base import component_rates
from agsf_torch.fpke import fpke_matrix, residual_rule
from agsf_torch.fpke.rounding import at_rounding_level
from agsf_torch.models import AttitudeModel, ContinuousModel, LinearModel
from tests.helpers import F64, CubicDrift, assert_within


class _Oscillator(ContinuousModel):
    """A user's linear model with an input, differentiated by torch.func (no closed forms)."""

    state_dim = 2
    input_dim = 1

    def drift(self, x, u=None):
        force = 0.0 if u is None else u[..., 0]
        return torch.stack((x[..., 1], -4.0 * x[..., 0] - 0.4 * x[..., 1] + force), -1)

    def noise_gain(self, x):
        return torch.tensor([[0.0], [1.0]], dtype=x.dtype).expand(*x.shape[:-1], 2, 1)

    def noise_psd(self):
        return torch.full((1, 1), 0.5, dtype=F64)


def _split_prior(B: int = 6, N: int = 4, seed: int = 0) -> GaussianMixture:
    gen = torch.Generator().manual_seed(seed)
    mean = torch.randn(B, 2, generator=gen, dtype=F64)
    return GaussianMixture.from_gaussian(mean, torch.tensor([[1.0, 0.3], [0.3, 0.5]], dtype=F64).expand(B, 2, 2), N)


def _flags(model, mixture, u=None):
    comp = component_rates(model, mixture, u).with_precision()
    nodes, weights = residual_rule(model, None, 2)
    return at_rounding_level(fpke_matrix(model, u, comp, nodes, weights), comp, model)


@pytest.mark.parametrize("scaling", ["trace", "none"])
@pytest.mark.parametrize("driven", [False, True])
def test_on_a_linear_model_the_penalty_update_leaves_the_weights_alone(scaling, driven):
    """Every Gaussian propagated by a linear model's moment equations solves the FPKE exactly, so ``L = 0`` and the
    penalty QP returns the reference weights.  ``L`` held rounding (entries ~1e-31 of no sign), which the trace
    scaling made an O(1) matrix: the weights moved by up to 0.17 over 20 steps, or, with an input, the QP refused
    its matrix as indefinite.  Now they stay at the prior's to rounding, and the residual reads 0."""
    model = _Oscillator() if driven else LinearModel(A=[[0.0, 1.0], [-4.0, -0.4]], G=[[0.0], [1.0]], Q=[[0.5]])
    prior = _split_prior()
    filt = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(scaling=scaling))
    gen = torch.Generator().manual_seed(1)
    mixture = prior
    for _ in range(20):
        u = torch.randn(6, 1, generator=gen, dtype=F64) if driven else None
        mixture = filt.predict(mixture, u, 0.1)
        assert bool(_flags(model, mixture, u).all())
        assert float(filt.diagnostics["fpke_error_before"].abs().max()) == 0.0
    assert_within(mixture.weights, prior.weights, 1e-15, "weights after 20 steps on a linear model")


@pytest.mark.parametrize("estimate_bias", [False, True])
@pytest.mark.parametrize("variance", [1e-3, 1e-8, 1e-11])
def test_the_attitude_residual_lies_above_the_floor_where_it_is_resolved(estimate_bias, variance):
    """The attitude models' ``E[ℓ²]/S`` falls as the MRP variance squared (5e-6 at 1e-3, 6e-22 at 1e-11) until their
    route's own rounding (~3e-25) takes over below ~1e-12; where it is resolved it lies far above the floor's 4.9e-28
    and no component is dropped."""
    gen = torch.Generator().manual_seed(2)
    B, n = 6, 6 if estimate_bias else 3
    model = AttitudeModel(estimate_bias=estimate_bias, bias=1e-7)
    u = torch.tensor([0.0628, 0.0628, 0.0], dtype=F64).expand(B, 3)  # case 1's rate (rad/s)
    mean = torch.cat(
        (0.3 * torch.randn(B, 3, generator=gen, dtype=F64), 1e-7 * torch.randn(B, n - 3, generator=gen, dtype=F64)), -1
    )
    cov = torch.diag(torch.tensor([variance] * 3 + [1e-14] * (n - 3), dtype=F64)).expand(B, n, n)
    mixture = GaussianSumFilter(model).predict(GaussianMixture.from_gaussian(mean, cov, 5), u, 0.1)
    u = torch.tensor([0.0628, 0.0628, 0.0], dtype=F64).expand(B, 3)
    assert not bool(_flags(model, mixture, u).any())


def test_a_nonlinear_models_residual_is_not_taken_for_rounding():
    """The double well ``dx = (x − x³)dt + dβ``: a residual of the order of its terms, never dropped."""
    prior = GaussianMixture.from_gaussian(
        torch.tensor([[0.2], [-1.5], [3.0]], dtype=F64), torch.full((3, 1, 1), 0.05, dtype=F64), 3
    )
    mixture = GaussianSumFilter(CubicDrift(), substeps=4).predict(prior, None, 0.05)
    assert not bool(_flags(CubicDrift(), mixture).any())


def test_a_linear_model_at_its_stationary_covariance_is_at_the_floor_too():
    """An Ornstein–Uhlenbeck model whose components have reached their stationary covariance: the rate ``∂ₜ log p``
    vanishes while ``div f = −2`` and ``tr(D P⁻¹) = 2`` stay O(1) and cancel in ``ℓ``; judged against the rate alone
    its rounding was taken for a residual and the penalty update failed at step 44 on an indefinite matrix.  The
    floor counts ``tr(D P⁻¹)²``: every component is at it, and the weights stay put over 150 steps."""
    ou = LinearModel(A=[[-1.0, 0.0], [0.0, -1.0]], G=[[1.0, 0.0], [0.0, 1.0]], Q=[[2.0, 0.0], [0.0, 2.0]])
    gen = torch.Generator().manual_seed(0)
    prior = GaussianMixture.from_gaussian(
        1e-3 * torch.randn(6, 2, generator=gen, dtype=F64), torch.eye(2, dtype=F64), 4
    )
    filt = AdaptiveGaussianSumFilter(ou, weight_update=PenaltyWeightUpdate())
    mixture = prior
    for _ in range(150):
        mixture = filt.predict(mixture, None, 0.1)
    assert bool(_flags(ou, mixture).all())
    assert_within(mixture.weights, prior.weights, 1e-15, "weights after 150 steps at the stationary covariance")
