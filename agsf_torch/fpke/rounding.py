"""The rounding floor of the FPKE matrix ``L``: which components' residual is zero to rounding.

``ℓᵢ`` (:mod:`.residual`) is a sum of terms that cancel exactly where the component solves the Fokker–Planck
equation — everywhere for a linear model, whose Gaussians propagated by their moment equations are exact
solutions.  There ``L`` holds rounding alone: entries ~1e-31 of no sign, which the penalty update's trace scaling
(``L / (tr L / N)``) would turn into an O(1) matrix, moving the weights at random or making the QP's matrix
indefinite.  The size of the terms that cancel is measured by two of them: the component's own rate
``∂ₜ log pᵢ``, and the diffusion's ``tr(D Pᵢ⁻¹)``, which stays O(1) where the rate vanishes (a component at its
stationary covariance, where ``div f`` and ``tr(D Pᵢ⁻¹)`` cancel):

.. math:: S_i = \\dot μ_i^T P_i^{-1} \\dot μ_i + ½ \\operatorname{tr}\\left((P_i^{-1}\\dot P_i)^2\\right)
          + \\operatorname{tr}\\left(D(μ_i) P_i^{-1}\\right)^2

(the first two terms are ``E_{pᵢ}[(∂ₜ log pᵢ)²]``), and ``L_ii = z_ii E[ℓᵢ²]`` with
``z_ii = ∫pᵢ² dx = (4π)^{-n/2} |Pᵢ|^{-1/2}``.  A component with ``E[ℓᵢ²] ≤ (c ε)² Sᵢ`` (``c =``
:data:`ROUNDING_UNITS`, ``ε`` the dtype's) has a residual not resolved above rounding: its row and column of
``L`` (bounded by ``√(L_ii L_jj)``, Cauchy–Schwarz) are set to zero.

Measured (float64, the default rules): a linear model's components read ``E[ℓ²]/S`` 1e-33 to 2e-32 (rounding,
``ε² = 4.9e-32``), also at stationarity; the attitude models' ``E[ℓ²]/S`` falls with the MRP variance (1e-5 at
1e-3) until, below ~1e-12, their own route's rounding (~1e-25) takes over — a floor that no choice of ``c``
separates from the residual there.  The fused attitude route (:func:`~.matrices.fused_fpke_matrix`) does not form
the rates this check reads and does not apply it.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..models.base import ContinuousModel
from .matrices import FPKEMatrix
from .residual import ComponentRates

__all__ = ["ROUNDING_UNITS", "at_rounding_level", "without_rounding_rows"]

#: ``c``: a component's residual counts as zero where ``√E[ℓᵢ²]`` is within ``c`` rounding units of ``√Sᵢ``.
ROUNDING_UNITS = 100.0


def at_rounding_level(L: FPKEMatrix, rates: ComponentRates, model: ContinuousModel) -> Tensor:
    """``[..., N]`` bool: the components whose ``L_ii`` is at or below the rounding floor ``z_ii (c ε)² Sᵢ``
    (module docstring) of their own terms.

    Args:
        L: the mixture's :class:`~.matrices.FPKEMatrix` ``[..., N, N]``.
        rates: its components with their moment rates (:class:`~.residual.ComponentRates`).
        model: the model (its :meth:`~agsf_torch.models.base.ContinuousModel.diffusion` at the means).
    """
    Pi, mean_rate, cov_rate = rates.precision, rates.mean_rates, rates.cov_rates
    n = rates.means.shape[-1]
    PiPd = Pi @ cov_rate
    tr_DPi = (model.diffusion(rates.means).to(Pi) * Pi).sum((-2, -1))
    S = (
        torch.einsum("...i,...ij,...j->...", mean_rate, Pi, mean_rate)
        + 0.5 * (PiPd * PiPd.transpose(-1, -2)).sum((-2, -1))
        + tr_DPi.square()
    )
    log_z = -0.5 * n * math.log(4.0 * math.pi) - torch.log(rates.chol.diagonal(dim1=-2, dim2=-1)).sum(-1)
    eps = torch.finfo(L.scaled.dtype).eps
    floor = torch.exp(log_z - L.log_scale[..., None] + 2.0 * math.log(ROUNDING_UNITS * eps)) * S  # in L̃'s units
    return L.scaled.diagonal(dim1=-2, dim2=-1) <= floor


def without_rounding_rows(L: FPKEMatrix, rates: ComponentRates, model: ContinuousModel) -> FPKEMatrix:
    """``L`` with the rows and columns of the components :func:`at_rounding_level` set to zero (all of them: the
    zero matrix, whose penalty QP returns the reference weights)."""
    keep = (~at_rounding_level(L, rates, model)).to(L.scaled.dtype)
    return FPKEMatrix(L.scaled * keep[..., :, None] * keep[..., None, :], L.log_scale)
