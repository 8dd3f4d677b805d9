"""Measurement update of every mixture component (method.md §2).

For each component, with ``H = ∂h/∂x`` at the predicted mean:

.. math::

    S = H P H^T + R,\\quad K = P H^T S^{-1},\\quad μ^+ = μ + K(\\tilde y - h(μ)),

    P^+ = (I - KH) P (I - KH)^T + K R K^T \\quad\\text{(Joseph form)},

    \\log w^+ = \\log w + \\log N(\\tilde y; h(μ), S) - \\operatorname{logsumexp}(\\cdot).

Solves go through Cholesky factors of ``S``; no inverse is formed.  Invalid
measurement entries (a mask) are removed exactly: their rows of ``H`` and of the
innovation are zeroed and their block of ``R`` is replaced by the identity, so
they change neither the state nor the likelihood; a trajectory with no valid
entry is returned unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .models.base import MeasurementModel

__all__ = ["ComponentUpdate", "kalman_update", "evaluate_measurement", "moment_matched_innovation"]


@dataclass(frozen=True)
class ComponentUpdate:
    """Result of :func:`kalman_update`.

    Attributes:
        means: ``[..., N, n]``; covs: ``[..., N, n, n]``; log_weights: ``[..., N]`` (normalised).
        log_likelihood: ``log Σᵢ wᵢ βᵢ``, the measurement log-likelihood of the mixture, ``[...]``.
        nis: normalised innovation squared of each component, ``νᵀS⁻¹ν``, ``[..., N]``.
        dof: number of valid measurement entries, ``[...]``.
        innovation: ``ν = ỹ − h(μ)`` ``[..., N, d]`` (zero at masked entries).
        innovation_cov: ``S`` ``[..., N, d, d]``.
    """

    means: Tensor
    covs: Tensor
    log_weights: Tensor
    log_likelihood: Tensor
    nis: Tensor
    dof: Tensor
    innovation: Tensor
    innovation_cov: Tensor


def moment_matched_innovation(log_weights: Tensor, nu: Tensor, S: Tensor) -> tuple[Tensor, Tensor]:
    """The mixture's predicted innovation, moment-matched over its components:

    .. math:: \\bar ν = \\sum_i w_i ν_i,\\qquad
              \\bar S = \\sum_i w_i \\left(S_i + (ν_i - \\bar ν)(ν_i - \\bar ν)^T\\right).

    Used for the mixture NIS of an update and by the innovation gate (per block).

    Args:
        log_weights: ``[..., N]``; nu: component innovations ``[..., N, k]``;
        S: their covariances ``[..., N, k, k]``.

    Returns:
        ``(ν̄ [..., k], S̄ [..., k, k])``.
    """
    w = log_weights.exp()
    nu_bar = (w[..., None] * nu).sum(-2)
    dn = nu - nu_bar.unsqueeze(-2)
    S_bar = (w[..., None, None] * (S + dn[..., :, None] * dn[..., None, :])).sum(-3)
    return nu_bar, S_bar


def evaluate_measurement(measurement: MeasurementModel, means: Tensor) -> tuple[Tensor, Tensor]:
    """``h(μᵢ)`` and ``Hᵢ`` for every component.

    The component dim is moved to the front for the call, so a measurement whose
    own tensors carry only the trajectory dims (``[..., M, 3]``) broadcasts
    against ``[N, ..., n]``.

    Args:
        means: ``[..., N, n]``.

    Returns:
        ``(h [..., N, d], H [..., N, d, n])``.
    """
    x = means.movedim(-2, 0)
    h = measurement.predict(x).movedim(0, -2)
    H = measurement.jacobian(x).movedim(0, -3)
    return h, H


def kalman_update(
    log_weights: Tensor,
    means: Tensor,
    covs: Tensor,
    y: Tensor,
    measurement: MeasurementModel,
    iterations: int = 1,
    mask: Tensor | None = None,
) -> ComponentUpdate:
    """Joseph-form EKF update of all components and Bayes' rule on the weights.

    With ``iterations = 1`` this is the EKF update of method.md §2 (``H`` and
    ``βᵢ`` at the predicted mean).  With ``iterations > 1`` it is the iterated
    EKF (Gauss–Newton on the MAP problem of each component): the measurement is
    relinearised at the current iterate ``xⱼ``,

    .. math:: x_{j+1} = μ + K_j\\left(\\tilde y - h(x_j) - H_j(μ - x_j)\\right),

    and the covariance, the innovation and ``βᵢ`` use the last linearisation.
    It removes the linearisation error of the first star frame after a wide
    prior, where one EKF step leaves errors many σ outside its covariance.

    Args:
        log_weights: ``[..., N]`` normalised.
        means: ``[..., N, n]``.
        covs: ``[..., N, n, n]``.
        y: measurement ``[..., d]``.
        measurement: the measurement model (``h``, ``H``, ``R``, mask).
        iterations: linearisations (≥ 1).
        mask: entry validity ``[..., d]`` bool to use instead of the model's
            ``measurement.mask()`` (e.g. after innovation gating).

    Returns:
        :class:`ComponentUpdate`.
    """
    R = measurement.noise_cov().to(means)
    if mask is None:
        mask = measurement.mask()
    y = y.unsqueeze(-2)  # [..., 1, d]
    R = R.unsqueeze(-3) if R.dim() > 2 else R
    n = means.shape[-1]
    eye_n = torch.eye(n, dtype=means.dtype, device=means.device)
    x = means
    for _ in range(int(iterations)):
        h, H = evaluate_measurement(measurement, x)
        d = h.shape[-1]
        if y.shape[-1] != d:
            raise ValueError(f"y has {y.shape[-1]} entries but the measurement model predicts {d}")
        if mask is None:
            valid = torch.ones(h.shape[:-1] + (d,), dtype=means.dtype, device=means.device)
        else:
            valid = mask.to(means.dtype).unsqueeze(-2).expand(h.shape)
        R_eff = valid[..., :, None] * valid[..., None, :] * R + torch.diag_embed(1.0 - valid)
        H = valid[..., None] * H
        nu = y - h
        if x is not means:
            nu = nu - (H @ (means - x).unsqueeze(-1)).squeeze(-1)
        nu = valid * nu

        PHt = covs @ H.transpose(-1, -2)  # [..., N, n, d]
        S = H @ PHt + R_eff
        S = 0.5 * (S + S.transpose(-1, -2))
        L, info = torch.linalg.cholesky_ex(S)
        if bool((info != 0).any()):
            idx = (info != 0).nonzero()[0].tolist()
            raise ValueError(f"innovation covariance is not positive definite at (trajectory…, component) index {tuple(idx)}")
        K = torch.cholesky_solve(PHt.transpose(-1, -2), L).transpose(-1, -2)  # [..., N, n, d]
        x = means + (K @ nu.unsqueeze(-1)).squeeze(-1)
    new_means = x
    IKH = eye_n - K @ H
    new_covs = IKH @ covs @ IKH.transpose(-1, -2) + K @ R_eff @ K.transpose(-1, -2)
    new_covs = 0.5 * (new_covs + new_covs.transpose(-1, -2))

    z = torch.linalg.solve_triangular(L, nu.unsqueeze(-1), upper=False).squeeze(-1)
    nis = (z * z).sum(-1)
    dof = valid.sum(-1)  # [..., N]
    log_det = 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
    log_beta = -0.5 * (nis + log_det + dof * math.log(2.0 * math.pi))
    joint = log_weights + log_beta
    log_lik = torch.logsumexp(joint, -1)
    new_log_weights = joint - log_lik.unsqueeze(-1)

    # trajectories without a valid entry are left exactly as they were
    any_valid = dof[..., 0] > 0
    new_means = torch.where(any_valid[..., None, None], new_means, means)
    new_covs = torch.where(any_valid[..., None, None, None], new_covs, covs)
    new_log_weights = torch.where(any_valid[..., None], new_log_weights, log_weights)
    log_lik = torch.where(any_valid, log_lik, torch.zeros_like(log_lik))
    return ComponentUpdate(new_means, new_covs, new_log_weights, log_lik, nis, dof[..., 0], nu, S)
