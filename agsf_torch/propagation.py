"""Moment propagation of Gaussian components between measurements (method.md §2).

Every component follows the extended-Kalman moment equations

.. math::

    \\dot μ = f(μ, u),\\qquad \\dot P = A P + P A^T + g(μ) Q g(μ)^T,\\quad A = ∂f/∂x|_μ,

integrated jointly with classic fourth-order Runge–Kutta over the interval
``dt``, the input ``u`` held constant (zero-order hold).  All trajectories and
components advance in one batched call.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .models.base import ContinuousModel

__all__ = ["moment_derivatives", "propagate_moments", "MomentRates"]


@dataclass(frozen=True)
class MomentRates:
    """Time derivatives of the moments at a point of the trajectory.

    Attributes:
        mean_rate: ``μ̇`` ``[..., n]``.
        cov_rate: ``Ṗ`` ``[..., n, n]``.
    """

    mean_rate: Tensor
    cov_rate: Tensor


def moment_derivatives(model: ContinuousModel, mean: Tensor, cov: Tensor, u: Tensor | None) -> MomentRates:
    """Right-hand side of the moment ODE: ``μ̇ = f(μ, u)``, ``Ṗ = AP + PAᵀ + gQgᵀ``.

    Args:
        model: the continuous-time model.
        mean: ``[..., n]``; cov: ``[..., n, n]``; u: input broadcastable to ``[..., m]``.
    """
    A = model.drift_jacobian(mean, u)
    AP = A @ cov
    Pdot = AP + AP.transpose(-1, -2) + model.process_noise(mean)
    return MomentRates(model.drift(mean, u), Pdot)


def propagate_moments(
    model: ContinuousModel, mean: Tensor, cov: Tensor, u: Tensor | None, dt: float, substeps: int = 1
) -> tuple[Tensor, Tensor]:
    """Advance ``(μ, P)`` by ``dt`` with ``substeps`` RK4 steps.

    Args:
        model: the continuous-time model.
        mean: ``[..., n]``.
        cov: ``[..., n, n]`` symmetric.
        u: input ``[..., m]`` (broadcast against ``mean``'s leading dims) or ``None``.
        dt: interval (s), > 0.
        substeps: RK4 steps in the interval (≥ 1).

    Returns:
        ``(mean [..., n], cov [..., n, n])`` at ``t + dt``, covariance symmetrised.
    """
    h = dt / substeps
    for _ in range(substeps):
        k1 = moment_derivatives(model, mean, cov, u)
        k2 = moment_derivatives(model, mean + 0.5 * h * k1.mean_rate, cov + 0.5 * h * k1.cov_rate, u)
        k3 = moment_derivatives(model, mean + 0.5 * h * k2.mean_rate, cov + 0.5 * h * k2.cov_rate, u)
        k4 = moment_derivatives(model, mean + h * k3.mean_rate, cov + h * k3.cov_rate, u)
        mean = mean + (h / 6.0) * (k1.mean_rate + 2.0 * (k2.mean_rate + k3.mean_rate) + k4.mean_rate)
        cov = cov + (h / 6.0) * (k1.cov_rate + 2.0 * (k2.cov_rate + k3.cov_rate) + k4.cov_rate)
        cov = 0.5 * (cov + cov.transpose(-1, -2))
    return mean, cov
