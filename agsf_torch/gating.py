"""Innovation gating: reject outlying measurements before they enter the update.

A measurement vector is split into independent blocks (a star vector: 3
entries; :attr:`MeasurementModel.block_size`).  For each block ``b`` the
mixture's predicted innovation is moment-matched over the components,

.. math::

    \\bar ν_b = \\sum_i w_i ν_{i,b},\\qquad
    \\bar S_b = \\sum_i w_i \\left(S_{i,bb} + (ν_{i,b} - \\bar ν_b)(ν_{i,b} - \\bar ν_b)^T\\right),

with ``ν_{i,b} = ỹ_b − h_b(μᵢ)`` and ``S_{i,bb}`` the block's diagonal block of
``Hᵢ Pᵢ Hᵢᵀ + R`` (the marginal innovation covariance of the block), and the block
is accepted when

.. math:: \\bar ν_b^T \\bar S_b^{-1} \\bar ν_b \\le χ^2_{s}(p),

the ``p`` quantile of the χ² distribution with ``s`` = block size degrees of
freedom.  The NIS solves with the Cholesky factor of ``S̄_b``, or, where that is
unfit (a precise sensor after a wide prior: ``S̄_b`` singular to rounding along the
star direction), with a factor built from square roots
(:func:`~agsf_torch.update.moment_matched_factor`).  **Consistency rule**: with ``V`` valid blocks in the measurement, failing
blocks are rejected only if at least ``min(2, V − 1)`` blocks pass; otherwise the
whole measurement is kept (``overridden``).  When every star of a frame disagrees
with the prediction, the prediction is what is wrong (the first frame after a wide
prior, a filter that has lost track), and gating it away would lock the filter
out for good; a misidentified star is one star that disagrees with the others.
A single-block measurement (V = 1) is gated as it stands.  With ``p = 1 − 10⁻⁴`` and a star block (s = 3) the threshold is 21.11: a
correct star is rejected about once in 10⁴ (less for the two-dimensional noise
of a real camera), while a misidentified star (a wrong catalogue vector, ≳ 0.05°
away) sits thousands of σ out once the filter has converged.  Gating is
**not** able to reject an outlier smaller than the current uncertainty (e.g. in
the first frame after a 7° prior); and an overconfident filter may reject good
stars, which is why gaps must inflate the covariance honestly
(:mod:`agsf_torch.attitude.gyro_hold`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .models.base import MeasurementModel
from .quantiles import chi2_quantile
from .update import (
    check_innovation,
    covariance_form_usable,
    evaluate_measurement,
    moment_matched_factor,
    moment_matched_innovation,
)

__all__ = ["chi2_threshold", "innovation_gate"]


def chi2_threshold(probability: float, dof: int) -> float:
    """``χ²_dof(p)``: the gate on a block's NIS that a correct measurement passes with probability ``p``.

    Raises:
        ValueError: for ``p`` outside (0, 1) or ``dof < 1``.
    """
    if not 0.0 < float(probability) < 1.0:
        raise ValueError(f"gate probability must lie in (0, 1), got {probability}")
    if int(dof) != dof or dof < 1:
        raise ValueError(f"gate degrees of freedom must be a positive integer, got {dof}")
    return chi2_quantile(float(probability), int(dof))


def innovation_gate(
    log_weights: Tensor,
    means: Tensor,
    covs: Tensor,
    y: Tensor,
    measurement: MeasurementModel,
    threshold: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per-block χ² gate of the mixture's predicted innovation (module docstring).

    Args:
        log_weights: ``[..., N]``; means: ``[..., N, n]``; covs: ``[..., N, n, n]``.
        y: measurement ``[..., d]``.
        measurement: the model; its :attr:`block_size` ``s`` must divide ``d``
            (``None``: the whole vector is one block).
        threshold: gate on each block's NIS (e.g. :func:`chi2_threshold`).

    Returns:
        ``(accepted [..., G] bool, nis [..., G], entry_mask [..., d] bool, overridden [...] bool)``:
        blocks kept (invalid blocks count as accepted: they carry nothing), their
        NIS (0 for invalid blocks), the entry validity to update with (the model's
        mask and the gate) and where the consistency rule kept failing blocks.

    Raises:
        ValueError: a non-finite mean, measurement or prediction, or an absurd innovation
            (:func:`~agsf_torch.update.check_innovation`), before anything is computed from them.
    """
    h, H = evaluate_measurement(measurement, means)  # [..., N, d], [..., N, d, n]
    d = h.shape[-1]
    s = measurement.block_size or d
    if d % s:
        raise ValueError(f"measurement block_size {s} does not divide its dimension {d}")
    G = d // s
    model_mask = measurement.mask()
    valid = torch.ones(h.shape[:-2] + (d,), dtype=torch.bool, device=h.device) if model_mask is None else model_mask
    valid = valid.expand(h.shape[:-2] + (d,))
    R = measurement.noise_cov().to(means)
    S = H @ covs @ H.transpose(-1, -2) + (R.unsqueeze(-3) if R.dim() > 2 else R)  # [..., N, d, d]
    check_innovation(y.unsqueeze(-2), means, h, S.diagonal(dim1=-2, dim2=-1), valid.unsqueeze(-2).expand(h.shape))
    blocks = S.reshape(*S.shape[:-2], G, s, G, s).diagonal(dim1=-4, dim2=-2).movedim(-1, -3)  # [..., N, G, s, s]
    nu = (y.unsqueeze(-2) - h).reshape(*h.shape[:-1], G, s)  # [..., N, G, s]
    # per block: components to the second-to-last axis, [..., G, N, s] and [..., G, N, s, s]
    nu_bar, S_bar = moment_matched_innovation(log_weights.unsqueeze(-2), nu.movedim(-3, -2), blocks.movedim(-4, -3))
    block_valid = valid.reshape(*valid.shape[:-1], G, s).all(-1)
    eye = torch.eye(s, dtype=S_bar.dtype, device=S_bar.device)
    S_bar = torch.where(block_valid[..., None, None], S_bar, eye)
    S_bar = 0.5 * (S_bar + S_bar.transpose(-1, -2))
    L, info = torch.linalg.cholesky_ex(S_bar)
    need = ~covariance_form_usable(L, info, torch.ones_like(S_bar[..., 0]), S_bar)
    if bool(need.any()):  # a precise sensor after a wide prior: factor S̄ from square roots instead
        L = torch.where(need[..., None, None], _block_factor(log_weights, nu, H, covs, R, G, s), L)
    z = torch.linalg.solve_triangular(L, nu_bar.unsqueeze(-1), upper=False).squeeze(-1)
    nis = torch.where(block_valid, (z * z).sum(-1), torch.zeros_like(z[..., 0]))
    passing = block_valid & (nis <= threshold)
    n_valid = block_valid.sum(-1)
    needed = torch.clamp(n_valid - 1, max=2)
    failing = (block_valid & ~passing).any(-1)
    overridden = failing & (passing.sum(-1) < needed)
    accepted = ~block_valid | passing | overridden[..., None]
    entry_mask = valid & accepted.repeat_interleave(s, dim=-1)
    return accepted, nis, entry_mask, overridden


def _block_factor(log_weights: Tensor, nu: Tensor, H: Tensor, covs: Tensor, R: Tensor, G: int, s: int) -> Tensor:
    """A lower Cholesky factor of each block's ``S̄_b`` from square roots (:func:`~agsf_torch.update.moment_matched_factor`),
    ``[..., G, s, s]``: for a ``S̄_b`` too ill-conditioned for its own Cholesky factorisation (``H P Hᵀ``
    singular along a star's direction and ``σ_s² ≪ H P Hᵀ``).

    Args:
        nu: ``[..., N, G, s]``; H: ``[..., N, d, n]``; covs: ``[..., N, n, n]``; R: ``[d, d]`` or ``[..., d, d]``.
    """
    L_P, info = torch.linalg.cholesky_ex(covs)
    if bool((info != 0).any()):
        idx = (info != 0).nonzero()[0].tolist()
        raise ValueError(
            f"the component covariance P is not positive definite at trajectory index {tuple(idx[:-1])}, component {idx[-1]}"
        )
    HL = (H @ L_P).reshape(*H.shape[:-2], G, s, covs.shape[-1]).movedim(-3, -4)  # [..., G, N, s, n]
    R_blocks = R.reshape(*R.shape[:-2], G, s, G, s).diagonal(dim1=-4, dim2=-2).movedim(-1, -3)  # [..., G, s, s]
    L_R, info = torch.linalg.cholesky_ex(R_blocks)
    if bool((info != 0).any()):
        idx = (info != 0).nonzero()[0].tolist()
        raise ValueError(
            f"the measurement noise covariance R is not positive definite in block {idx[-1]} (index {tuple(idx)})"
        )
    _, L = moment_matched_factor(log_weights.unsqueeze(-2), nu.movedim(-3, -2), HL, L_R)
    return L
