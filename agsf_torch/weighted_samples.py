"""Weighted samples: the effective sample size, systematic resampling and the weighted moments of a cloud.

The primitives of sequential Monte Carlo shared by the particle filter (:mod:`agsf_torch.filters.particle`) and
the density reference (:class:`agsf_torch.density.PosteriorReference`); every function is batched over the leading
dims (one cloud per trajectory), the samples along the last (weights) or second-to-last (points) dim.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["effective_sample_size", "systematic_resample", "weighted_moments"]


def effective_sample_size(log_weights: Tensor) -> Tensor:
    """Kish's effective sample size ``(Σwᵢ)²/Σwᵢ²`` of (unnormalised) log-weights ``[..., M]`` → ``[...]``, in ``[1, M]``
    (one exponential per weight, scaled by the largest)."""
    w = torch.exp(log_weights - log_weights.amax(-1, keepdim=True))
    return w.sum(-1) ** 2 / (w * w).sum(-1)


def systematic_resample(log_weights: Tensor, offset: Tensor) -> Tensor:
    """Ancestor indices of systematic resampling (Kitagawa 1996; Carpenter, Clifford & Fearnhead 1999).

    The ``k``-th new particle, ``k = 0 … M−1``, is the first ``i`` with ``cᵢ > (u + k)/M`` (``cᵢ = Σ_{j≤i} wⱼ`` of
    the normalised weights, ``c_M = 1``), one uniform ``u ∈ [0, 1)`` per trajectory.  Counted instead of
    searched: particle ``i`` is drawn

    .. math:: N_i - N_{i-1}\\ \\text{times},\\qquad N_i = \\min(M, \\max(0, ⌈M c_i − u⌉)),\\ N_0 = 0,

    which is ``⌊Mwᵢ⌋`` or ``⌈Mwᵢ⌉`` (to the rounding of ``cᵢ``; never for a zero weight) and ``Mwᵢ`` in
    expectation; the indices follow from the counts by one scatter and one cumulative sum.

    Args:
        log_weights: ``[..., M]`` (normalised or not).
        offset: ``u ∈ [0, 1)``, ``[...]``.

    Returns:
        ``[..., M]`` int64 indices, non-decreasing along the last dim.
    """
    M = log_weights.shape[-1]
    c = torch.cumsum(torch.softmax(log_weights, -1), -1)
    c = torch.cat((c[..., :-1], torch.ones_like(c[..., -1:])), -1)  # the last edge exactly 1: M draws in all
    drawn = torch.ceil(M * c - offset.to(c).unsqueeze(-1)).clamp(0, M).to(torch.int64)  # N_i
    starts = torch.cat((torch.zeros_like(drawn[..., :1]), drawn[..., :-1]), -1)  # N_{i-1}: particle i's first draw
    marks = torch.zeros((*drawn.shape[:-1], M + 1), dtype=torch.int64, device=drawn.device)
    marks.scatter_add_(-1, starts, torch.ones_like(starts))
    # the k-th draw is the last particle whose first draw is at or before k (one drawn 0 times shares the next start)
    return torch.cumsum(marks[..., :M], -1) - 1


def weighted_moments(x: Tensor, log_weights: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted mean and covariance of points.

    .. math:: \\hat m = Σ_i w_i x_i,\\qquad \\hat Σ = Σ_i w_i (x_i - \\hat m)(x_i - \\hat m)^T

    Args:
        x: ``[..., M, n]``; log_weights: ``[..., M]`` (normalised or not).

    Returns:
        ``(m̂ [..., n], Σ̂ [..., n, n])``, ``Σ̂`` symmetric.
    """
    w = torch.softmax(log_weights, -1)
    mean = (w.unsqueeze(-2) @ x).squeeze(-2)
    d = x - mean.unsqueeze(-2)
    cov = (d * w.unsqueeze(-1)).transpose(-1, -2) @ d
    return mean, 0.5 * (cov + cov.transpose(-1, -2))
