"""Small benchmark models: the scalar sine SDE (method.md §5) and the stochastic Lorenz system."""

from __future__ import annotations

import torch
from torch import Tensor

from .base import ContinuousModel, FokkerPlanckTerms, check_nonnegative

__all__ = ["SineDriftModel", "LorenzModel"]


class SineDriftModel(ContinuousModel):
    """Scalar SDE ``dx = sin(x) dt + dβ``, ``E[dβ²] = q dt`` (the authors' benchmark, ``q = 1``).

    Unstable equilibrium at 0, stable ones at ±π: a prior near 0 splits into
    two modes, which the weights of a Gaussian sum must follow.
    """

    state_dim = 1

    def __init__(self, q: float = 1.0) -> None:
        super().__init__()
        self.register_buffer("q", check_nonnegative("q", q))

    def drift(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        """``sin(x)`` ``[..., 1]``."""
        return torch.sin(x)

    def drift_jacobian(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        """``cos(x)`` ``[..., 1, 1]``."""
        return torch.cos(x).unsqueeze(-1)

    def noise_gain(self, x: Tensor) -> Tensor:
        return torch.ones_like(x).unsqueeze(-1)

    def noise_psd(self) -> Tensor:
        return self.q.reshape(1, 1)

    def fokker_planck_terms(self, x: Tensor, u: Tensor | None = None) -> FokkerPlanckTerms:
        """``div f = cos x``, ``D = q/2`` constant (its derivatives vanish)."""
        return FokkerPlanckTerms(
            drift=torch.sin(x),
            drift_divergence=torch.cos(x[..., 0]),
            diffusion=(0.5 * self.q.to(x)).expand(*x.shape[:-1], 1, 1),
            diffusion_divergence=torch.zeros_like(x),
            diffusion_second_divergence=torch.zeros_like(x[..., 0]),
        )


class LorenzModel(ContinuousModel):
    r"""Stochastic Lorenz system ``dx = f(x) dt + dβ``, ``E[dβ dβᵀ] = Q dt`` (the authors' 3-D example).

    .. math:: f(x) = [σ(x_2 − x_1),\; x_1(ρ − x_3) − x_2,\; x_1x_2 − βx_3]

    Defaults: ``σ = 10``, ``ρ = 28``, ``β = 8/3``, ``Q = diag(1, 1, 2)``.  The drift
    is quadratic and ``g = I``, so the FPKE residual factor ``ℓ`` is a cubic:
    ``ℓⱼ`` is integrated exactly by 2 Gauss–Hermite points per axis, ``ℓᵢℓⱼ`` by 4.
    """

    state_dim = 3

    def __init__(self, sigma: float = 10.0, rho: float = 28.0, beta: float = 8.0 / 3.0, Q=(1.0, 1.0, 2.0)) -> None:
        super().__init__()
        for name, v in (("sigma", sigma), ("rho", rho), ("beta", beta)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not torch.isfinite(torch.tensor(float(v))):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        self.sigma, self.rho, self.beta = float(sigma), float(rho), float(beta)
        q = check_nonnegative("Q", torch.as_tensor(Q, dtype=torch.float64))
        if q.shape != (3,):
            raise ValueError(f"Q must be the 3 diagonal entries, got shape {tuple(q.shape)}")
        self.register_buffer("q_diag", q)

    def drift(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        """``f(x)`` ``[..., 3]``."""
        x1, x2, x3 = x.unbind(-1)
        return torch.stack((self.sigma * (x2 - x1), x1 * (self.rho - x3) - x2, x1 * x2 - self.beta * x3), -1)

    def drift_jacobian(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        """``∂f/∂x`` ``[..., 3, 3]``."""
        x1, x2, x3 = x.unbind(-1)
        s, one, zero = torch.full_like(x1, self.sigma), torch.ones_like(x1), torch.zeros_like(x1)
        rows = (
            torch.stack((-s, s, zero), -1),
            torch.stack((self.rho - x3, -one, -x1), -1),
            torch.stack((x2, x1, torch.full_like(x1, -self.beta)), -1),
        )
        return torch.stack(rows, -2)

    def noise_gain(self, x: Tensor) -> Tensor:
        return torch.eye(3, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], 3, 3)

    def noise_psd(self) -> Tensor:
        return torch.diag(self.q_diag)

    def fokker_planck_terms(self, x: Tensor, u: Tensor | None = None) -> FokkerPlanckTerms:
        """``div f = −(σ + 1 + β)``, ``D = Q/2`` constant (its derivatives vanish), given as its diagonal."""
        return FokkerPlanckTerms(
            drift=self.drift(x),
            drift_divergence=torch.full_like(x[..., 0], -(self.sigma + 1.0 + self.beta)),
            diffusion=(0.5 * self.q_diag.to(x)).expand(*x.shape[:-1], 3),
            diffusion_divergence=torch.zeros_like(x),
            diffusion_second_divergence=torch.zeros_like(x[..., 0]),
        )

    def fpke_polynomial_space(self) -> tuple[tuple[tuple[int, ...], int], ...]:
        """``ℓ`` is a cubic in ``(x, y, z)``: ``P₃``, 20 interpolation nodes."""
        return (((0, 1, 2), 3),)

    def fpke_quadrature_points(self, factors: int = 2) -> tuple[int, ...]:
        """``ℓ`` is cubic: ``⌈(3·factors + 1)/2⌉`` points per axis (2 for ``ℓⱼ``, 4 for ``ℓᵢℓⱼ``)."""
        if factors not in (1, 2):
            raise ValueError(f"factors must be 1 or 2, got {factors}")
        return (2, 2, 2) if factors == 1 else (4, 4, 4)
