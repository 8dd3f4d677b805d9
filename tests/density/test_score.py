"""The density score and its standard errors (agsf_torch.density.score)."""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import multivariate_normal

from agsf_torch.density import density_score, effective_sample_size
from tests.density.conftest import gaussian
from tests.helpers import assert_within, relative_bound


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
    # pytest.approx's tolerances (rel as given, abs 1e-12: a few thousand ε of the O(1) log-densities averaged)
    assert_within(score, mean, relative_bound(mean, 1e-12, 1e-12), "self-normalised mean")
    se_want = np.sqrt((dev**2).sum())
    assert_within(se, se_want, relative_bound(se_want, 1e-10, 1e-12), "delta-method standard error")
    lineage = torch.tensor([[0, 0, 2, 4, 4]])
    _, se_l = density_score(samples, log_w, mix, lineage=lineage)
    grouped = np.array([dev[0] + dev[1], dev[2], dev[3] + dev[4]])
    se_lineage = np.sqrt((grouped**2).sum())
    assert_within(se_l, se_lineage, relative_bound(se_lineage, 1e-10, 1e-12), "lineage standard error")
    _, se_own = density_score(samples, log_w, mix, lineage=torch.arange(5)[None])
    assert_within(se_own, se, relative_bound(se, 1e-12, 1e-12), "standard error with a lineage of its own each")
    ess = np.exp(lw).sum() ** 2 / np.exp(2 * lw).sum()
    assert_within(effective_sample_size(log_w), ess, relative_bound(ess, 1e-6, 1e-12), "effective sample size")
