"""Shared helpers of the density tests (agsf_torch.density)."""

from __future__ import annotations

import numpy as np
import torch

from agsf_torch.mixture import GaussianMixture

f64 = torch.float64


def gaussian(mean: np.ndarray, cov: np.ndarray) -> GaussianMixture:
    """One-component mixtures from numpy ``[B, n]``, ``[B, n, n]``."""
    mean, cov = torch.as_tensor(mean, dtype=f64), torch.as_tensor(cov, dtype=f64)
    return GaussianMixture(weights=torch.ones(mean.shape[0], 1, dtype=f64), means=mean[:, None], covs=cov[:, None])
