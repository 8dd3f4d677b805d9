"""Small benchmark models (method.md §5)."""

from __future__ import annotations

import torch
from torch import Tensor

from .base import ContinuousModel, FokkerPlanckTerms, check_nonnegative

__all__ = ["SineDriftModel"]


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
