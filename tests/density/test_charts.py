"""Charts and the folded MRP mixture density (agsf_torch.density.charts).

Expected values are computed independently of the code under test: the folded MRP
density with scipy's Gaussian and a finite-difference Jacobian.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from agsf_torch.density import canonical_points, density_score, mixture_log_density
from agsf_torch.mixture import GaussianMixture
from tests.density.conftest import f64, gaussian


def _np_shadow(x: np.ndarray) -> np.ndarray:
    return -x / (x * x).sum(-1, keepdims=True)


def test_mrp_chart_folded_density_brute_force():
    """The MRP-chart density of a mixture, against a brute-force fold: scipy's Gaussian
    at the point and at its shadow times a finite-difference |det ∂s/∂x|."""
    rng = np.random.default_rng(0)
    mu = np.array([[0.6, -0.5, 0.4], [-0.2, 0.9, 0.3]])
    covs = np.array([0.3 * np.eye(3), np.diag([0.2, 0.5, 0.1])])
    w = np.array([0.3, 0.7])
    mix = GaussianMixture(weights=torch.tensor(w), means=torch.tensor(mu), covs=torch.tensor(covs))
    x = rng.normal(size=(400, 3)) * 0.6
    x = np.where((x * x).sum(-1, keepdims=True) > 1, _np_shadow(x), x)  # canonical points
    got = mixture_log_density(mix, torch.tensor(x), chart="mrp").numpy()
    eps = 1e-6
    jac = np.stack([(_np_shadow(x + eps * e) - _np_shadow(x - eps * e)) / (2 * eps) for e in np.eye(3)], -1)
    det = np.abs(np.linalg.det(jac))
    comps = [multivariate_normal(mu[i], covs[i]) for i in range(2)]
    dens = sum(w[i] * (comps[i].pdf(x) + comps[i].pdf(_np_shadow(x)) * det) for i in range(2))
    np.testing.assert_allclose(got, np.log(dens), rtol=1e-7, atol=1e-7)
    # the Euclidean chart is the plain mixture density
    plain = np.log(sum(w[i] * multivariate_normal(mu[i], covs[i]).pdf(x) for i in range(2)))
    np.testing.assert_allclose(mixture_log_density(mix, torch.tensor(x)).numpy(), plain, rtol=1e-10)


def test_mrp_chart_scores_a_component_on_either_shadow_set_alike():
    """A component straddling |p| = 1 is scored the same on the original and on the
    shadow set, and its score equals the brute-force log-density of the canonicalised
    pushforward, log N(x; μ, P) + 6 log|x|·[|x| > 1]; the plain Euclidean score of the
    unfolded component is far worse."""
    rng = np.random.default_rng(1)
    e = np.array([1.0, 2.0, -2.0]) / 3.0
    mu = 1.0005 * e
    P = 1e-6 * np.eye(3) + 2e-7 * np.outer(e, e)
    x = rng.multivariate_normal(mu, P, size=6000)  # [K, 3]
    outside = (x * x).sum(-1) > 1
    assert 0.2 < outside.mean() < 0.9
    y = np.where(outside[:, None], _np_shadow(x), x)
    brute = multivariate_normal(mu, P).logpdf(x) + 6.0 * np.log(np.linalg.norm(x, axis=-1)) * outside
    s = (mu * mu).sum()
    J = (2 * np.outer(mu, mu) - s * np.eye(3)) / s**2
    original = gaussian(mu[None], P[None])
    shadow = gaussian(_np_shadow(mu)[None], (J @ P @ J.T)[None])
    samples, lw = torch.tensor(y)[None], torch.zeros(1, len(y), dtype=f64)
    folded = mixture_log_density(original, samples, chart="mrp").numpy()[0]
    np.testing.assert_allclose(folded, brute, rtol=1e-9, atol=1e-9)
    s_orig, se = density_score(samples, lw, original, chart="mrp")
    s_shadow, _ = density_score(samples, lw, shadow, chart="mrp")
    assert float(s_orig) == pytest.approx(brute.mean(), abs=1e-9)
    assert abs(float(s_orig - s_shadow)) < 1e-3 < float(se)  # equal far below the Monte Carlo error
    s_plain, _ = density_score(samples, lw, original, chart="euclidean")
    assert float(s_plain) < float(s_orig) - 100.0
    # canonical_points performs the same switch
    np.testing.assert_allclose(canonical_points(torch.tensor(x), "mrp").numpy(), y, rtol=1e-12)
