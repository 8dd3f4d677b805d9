"""The density score of a mixture on weighted samples, and its Monte Carlo standard error.

The **density score** of a filter at time ``t`` is the expected log-density of its
mixture ``p̂`` under the *exact* filtering density ``p`` of the filter's own model
(same prior, same SDE, same inputs, same measurements):

.. math:: S(\\hat p) = E_{x \\sim p}[\\log \\hat p(x)] = -H(p) - \\mathrm{KL}(p \\,\\|\\, \\hat p).

It is a proper scoring rule (higher is better, maximal for ``p̂ = p``), and the
difference of two filters' scores is the difference of their KL divergences from
the exact density.

Standard errors account for resampling by the lineage (Chan–Lai) variance
estimator: particles are grouped by their ancestor at the last independent draw.
It needs many lineages: treat errors computed from fewer than ~100 with suspicion.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..mixture import GaussianMixture
from .charts import check_chart, mixture_log_density

__all__ = ["density_score"]


def density_score(
    samples: Tensor,
    log_weights: Tensor,
    mixture: GaussianMixture,
    *,
    chart: str = "euclidean",
    lineage: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Self-normalised estimate of ``E_p[log p̂(x)]`` and its Monte Carlo standard error.

    With normalised weights ``w̄ᵢ`` of samples ``xᵢ ~ p`` and ``φᵢ = log p̂(xᵢ)``
    (:func:`mixture_log_density` in ``chart``):

    .. math:: \\hat S = Σ_i \\bar w_i φ_i,\\qquad
              \\mathrm{se}^2 = Σ_e \\Big(Σ_{i: e_i = e} \\bar w_i (φ_i - \\hat S)\\Big)^2

    where ``eᵢ`` is the sample's lineage (its ancestor at the last independent draw).
    Without ``lineage`` every sample is its own lineage and ``se`` is the delta-method
    error of self-normalised importance sampling, ``(Σ w̄ᵢ² (φᵢ − Ŝ)²)^{1/2}``; with it,
    the estimator of Chan & Lai (2013) / Lee & Whiteley (2018), which accounts for the
    correlation that resampling introduces.

    Args:
        samples: ``[B, K, n]``.
        log_weights: ``[B, K]`` (unnormalised; ``−inf`` allowed, not all).
        mixture: batch shape ``[B]`` or ``[]``, state dimension ``n``.
        chart: ``"euclidean"`` or ``"mrp"`` (see :func:`mixture_log_density`).
        lineage: optional ``[B, K]`` integer ancestor indices in ``[0, K)``.

    Returns:
        ``(score [B], standard_error [B])`` in nats.
    """
    if not isinstance(mixture, GaussianMixture):
        raise ValueError(f"mixture must be a GaussianMixture, got {type(mixture).__name__}")
    if not torch.is_tensor(samples) or samples.dim() != 3:
        raise ValueError(f"samples must be a tensor [B, K, n], got shape {tuple(torch.as_tensor(samples).shape)}")
    B, K, n = samples.shape
    if not torch.is_tensor(log_weights) or log_weights.shape != (B, K):
        raise ValueError(f"log_weights must have shape {(B, K)}, got {tuple(torch.as_tensor(log_weights).shape)}")
    if mixture.state_dim != n:
        raise ValueError(f"mixture state dimension {mixture.state_dim} != samples' {n}")
    if tuple(mixture.batch_shape) not in ((), (B,)):
        raise ValueError(f"mixture batch shape {tuple(mixture.batch_shape)} must be [] or [{B}]")
    if not bool(torch.isfinite(samples).all()):
        raise ValueError("samples must be finite")
    if bool(torch.isnan(log_weights).any()) or bool(torch.isposinf(log_weights).any()):
        raise ValueError("log_weights must not be NaN or +inf")
    if bool(torch.isneginf(log_weights).all(-1).any()):
        raise ValueError("every trajectory needs at least one sample with positive weight")
    check_chart(chart, n)
    if lineage is not None:
        if not torch.is_tensor(lineage) or lineage.shape != (B, K) or lineage.dtype not in (torch.int32, torch.int64):
            raise ValueError(f"lineage must be an integer tensor of shape {(B, K)}")
        if bool((lineage < 0).any()) or bool((lineage >= K).any()):
            raise ValueError(f"lineage entries must lie in [0, {K})")
    phi = mixture_log_density(mixture, samples.to(mixture.means.dtype), chart=chart)  # [B, K]
    w = torch.softmax(log_weights.to(phi.dtype), -1)
    live = w > 0
    phi_live = torch.where(live, phi, torch.zeros_like(phi))
    mean = (w * phi_live).sum(-1)
    dev = torch.where(live, w * (phi_live - mean[:, None]), torch.zeros_like(phi))
    if lineage is None:
        var = (dev * dev).sum(-1)
    else:
        grouped = torch.zeros_like(dev).scatter_add_(1, lineage.long(), dev)
        var = (grouped * grouped).sum(-1)
    return mean, torch.sqrt(var)
