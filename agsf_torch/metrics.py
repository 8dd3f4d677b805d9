"""Error and consistency metrics: RMS, NEES and the χ² band of an averaged NEES or NIS.

(The NIS itself comes with each measurement update, ``filt.diagnostics``; the weight
entropy is :meth:`agsf_torch.GaussianMixture.entropy_of_weights`.)
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import chi2
from torch import Tensor

__all__ = ["nees", "rms", "chi2_band"]


def nees(error: Tensor, cov: Tensor) -> Tensor:
    """Normalised estimation error squared ``eᵀ P⁻¹ e`` (Cholesky solve).

    Args:
        error: ``[..., n]``; cov: ``[..., n, n]``.

    Returns:
        ``[...]``.
    """
    L = torch.linalg.cholesky(cov)
    z = torch.linalg.solve_triangular(L, error.unsqueeze(-1), upper=False).squeeze(-1)
    return (z * z).sum(-1)


def rms(values, dim: int = 0):
    """Root mean square along ``dim``: ``sqrt(mean(v²))``, of a tensor or a NumPy array (same type back)."""
    if torch.is_tensor(values):
        return torch.sqrt((values * values).mean(dim))
    values = np.asarray(values)
    return np.sqrt((values * values).mean(dim))


def chi2_band(dof: float, num_samples: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band for the average of ``num_samples`` independent χ²(dof) values.

    The sum is χ²(dof·num_samples), so the average lies in
    ``[χ²_{α/2}, χ²_{1−α/2}] / num_samples`` with probability ``confidence``.
    """
    a = (1.0 - confidence) / 2.0
    k = dof * num_samples
    return float(chi2.ppf(a, k) / num_samples), float(chi2.ppf(1.0 - a, k) / num_samples)
