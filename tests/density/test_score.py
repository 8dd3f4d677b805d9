"""The density score and its standard errors (agsf_torch.density.score)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from agsf_torch.density import density_score, effective_sample_size
from tests.density.conftest import gaussian


def test_density_score_error_formulas_brute_force():
    """Self-normalised mean, delta-method error, and the lineage (Chan–Lai) error."""
    mix = gaussian(np.array([[0.1, -0.2]]), np.array([[[0.5, 0.1], [0.1, 0.3]]]))
    x = np.array([[0.0, 0.0], [0.3, -0.1], [1.0, 0.5], [-0.4, 0.2], [0.2, 0.2]])
    lw = np.array([0.1, -1.0, 0.5, -0.3, 0.0])
    phi = multivariate_normal([0.1, -0.2], [[0.5, 0.1], [0.1, 0.3]]).logpdf(x)
    wn = np.exp(lw) / np.exp(lw).sum()
    mean = (wn * phi).sum()
    dev = wn * (phi - mean)
    samples, log_w = torch.tensor(x)[None], torch.tensor(lw)[None]
    score, se = density_score(samples, log_w, mix)
    assert float(score) == pytest.approx(mean, rel=1e-12)
    assert float(se) == pytest.approx(np.sqrt((dev**2).sum()), rel=1e-10)
    lineage = torch.tensor([[0, 0, 2, 4, 4]])
    _, se_l = density_score(samples, log_w, mix, lineage=lineage)
    grouped = np.array([dev[0] + dev[1], dev[2], dev[3] + dev[4]])
    assert float(se_l) == pytest.approx(np.sqrt((grouped**2).sum()), rel=1e-10)
    _, se_own = density_score(samples, log_w, mix, lineage=torch.arange(5)[None])
    assert float(se_own) == pytest.approx(float(se), rel=1e-12)
    assert float(effective_sample_size(log_w)) == pytest.approx(np.exp(lw).sum() ** 2 / np.exp(2 * lw).sum())
