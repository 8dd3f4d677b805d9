"""Model protocol: torch.func defaults, FunctionMeasurement, LinearModel."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.models import ContinuousModel, FunctionMeasurement, LinearModel, batched_jacobian


class Pendulum(ContinuousModel):
    """A user model with no closed forms: θ̈ = −sin θ − c θ̇ + u."""

    state_dim = 2

    def drift(self, x, u):
        return torch.stack((x[..., 1], -torch.sin(x[..., 0]) - 0.3 * x[..., 1] + u[..., 0]), -1)

    def noise_gain(self, x):
        return torch.stack((torch.zeros_like(x[..., 0]), 1.0 + 0.1 * x[..., 0] ** 2), -1)[..., None]

    def noise_psd(self):
        return torch.tensor([[0.5]], dtype=torch.float64)


def test_generic_jacobian_of_user_model(gen):
    model = Pendulum()
    x = torch.randn(7, 5, 2, generator=gen, dtype=torch.float64)
    u = torch.randn(5, 1, generator=gen, dtype=torch.float64)
    A = model.drift_jacobian(x, u)
    assert A.shape == (7, 5, 2, 2)
    ref = torch.zeros(7, 5, 2, 2, dtype=torch.float64)
    ref[..., 0, 1] = 1.0
    ref[..., 1, 0] = -torch.cos(x[..., 0])
    ref[..., 1, 1] = -0.3
    torch.testing.assert_close(A, ref, rtol=0, atol=1e-15)
    g = model.noise_gain(x)
    torch.testing.assert_close(model.diffusion(x), 0.5 * 0.5 * g @ g.transpose(-1, -2))


def test_batched_jacobian_broadcasts_parameters(gen):
    W = torch.randn(4, 3, 2, generator=gen, dtype=torch.float64)  # parameters with their own batch dim
    x = torch.randn(6, 1, 2, generator=gen, dtype=torch.float64)
    J = batched_jacobian(lambda z: torch.tanh((W @ z[..., None]).squeeze(-1)), x)
    assert J.shape == (6, 4, 3, 2)
    y = (W @ x[..., None]).squeeze(-1)
    torch.testing.assert_close(J, (1 - torch.tanh(y) ** 2)[..., None] * W, rtol=0, atol=1e-14)


def test_function_measurement(gen):
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, torch.eye(1, dtype=torch.float64))
    x = torch.randn(10, 1, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(meas.jacobian(x), 2 * x[..., None])
    assert meas.mask() is None
    closed = FunctionMeasurement(lambda x: x**2, torch.eye(1, dtype=torch.float64), jacobian=lambda x: 2 * x[..., None])
    torch.testing.assert_close(closed.jacobian(x), meas.jacobian(x))


@pytest.mark.parametrize(
    "R, match",
    [
        (torch.ones(3), "square"),
        (torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=torch.float64), "symmetric"),
        (torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64), "positive definite"),
        (torch.tensor([[float("nan")]], dtype=torch.float64), "finite"),
    ],
)
def test_function_measurement_rejects_bad_noise(R, match):
    with pytest.raises(ValueError, match=match):
        FunctionMeasurement(lambda x: x, R)


def test_linear_model(gen):
    A = torch.tensor([[0.0, 1.0], [-2.0, -0.5]], dtype=torch.float64)
    G = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    model = LinearModel(A, G, torch.tensor([[0.3]], dtype=torch.float64), B=G)
    x = torch.randn(8, 2, generator=gen, dtype=torch.float64)
    u = torch.randn(8, 1, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(model.drift(x, u), x @ A.T + u @ G.T)
    torch.testing.assert_close(model.drift_jacobian(x, u), ContinuousModel.drift_jacobian(model, x, u))
    with pytest.raises(ValueError, match="A must be square"):
        LinearModel(torch.ones(2, 3), G, torch.eye(1))
    with pytest.raises(ValueError, match="Q must be"):
        LinearModel(A, G, torch.eye(2))
