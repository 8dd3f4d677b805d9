"""Charts and the folded MRP mixture density (agsf_torch.density.charts).

Expected values are computed independently of the code under test: the folded MRP
density with scipy's Gaussian and a finite-difference Jacobian.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import multivariate_normal

from agsf_torch.density import canonical_points, density_score, mixture_log_density
from agsf_torch.mixture import GaussianMixture
from tests.density.conftest import f64, gaussian
from tests.helpers import assert_within, relative_bound


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
    # the finite difference (step 1e-6) is good to ~1e-10 relative: its error, not rounding, sets the bound
    assert_within(got, np.log(dens), relative_bound(np.log(dens), 1e-7, 1e-7), "folded MRP log-density")
    # the Euclidean chart is the plain mixture density; a logarithm's absolute error is its argument's relative
    # error (a few ε of the O(10) quadratic forms), so the floor is 1e-10 where the log-density crosses 0
    plain = np.log(sum(w[i] * multivariate_normal(mu[i], covs[i]).pdf(x) for i in range(2)))
    got_plain = mixture_log_density(mix, torch.tensor(x)).numpy()
    assert_within(got_plain, plain, relative_bound(plain, 1e-10, 1e-10), "Euclidean mixture log-density")


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
    assert_within(folded, brute, relative_bound(brute, 1e-9, 1e-9), "folded log-density across |p| = 1")
    s_orig, se = density_score(samples, lw, original, chart="mrp")
    s_shadow, _ = density_score(samples, lw, shadow, chart="mrp")
    assert_within(s_orig, brute.mean(), 1e-9, "score of the original component")
    # equal far below the Monte Carlo error
    assert_within(s_shadow, s_orig, 1e-3, "score of the shadow component against the original's")
    assert 1e-3 < float(se)
    s_plain, _ = density_score(samples, lw, original, chart="euclidean")
    assert float(s_plain) < float(s_orig) - 100.0
    # canonical_points performs the same switch
    # the shadow −x/|x|² is a quotient: relative in each entry, which vanishes only where both sides do
    assert_within(
        canonical_points(torch.tensor(x), "mrp").numpy(), y, relative_bound(y, 1e-12, 0.0), "canonical points"
    )
