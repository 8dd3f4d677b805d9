"""On a linear-Gaussian system the EKF is the exact Kalman filter, and a GSF is a
bank of Kalman filters with Bayes-weighted components."""

from __future__ import annotations

import numpy as np
import torch
from filterpy.kalman import KalmanFilter
from scipy.stats import multivariate_normal

from agsf_torch import GaussianMixture
from agsf_torch.filters import ExtendedKalmanFilter, GaussianSumFilter
from tests import linear_system as ls
from tests.helpers import assert_within, relative_bound

SUBSTEPS = 40  # RK4 global error ∝ h⁴: 20 substeps give 1.1e-10 relative in P, 40 give ~1e-11


def _filterpy_kf(x0, P0):
    F, Qd, Bd = ls.discretise()
    kf = KalmanFilter(dim_x=3, dim_z=2, dim_u=1)
    kf.x, kf.P, kf.F, kf.Q, kf.B, kf.H, kf.R = x0.copy(), P0.copy(), F, Qd, Bd, ls.H, ls.R
    return kf


def test_ekf_equals_filterpy_kalman_filter():
    us, ys = ls.simulate(60, seed=7)
    x0, P0 = np.array([0.5, -0.2, 0.1]), np.diag([0.5, 0.3, 0.2])
    kf = _filterpy_kf(x0, P0)
    ekf = ExtendedKalmanFilter(ls.model(), substeps=SUBSTEPS)
    meas = ls.measurement()
    mix = GaussianMixture.from_gaussian(torch.tensor(x0), torch.tensor(P0))
    worst_x = worst_P = worst_ll = 0.0
    for u, y in zip(us, ys):
        kf.predict(u=u)
        mix = ekf.predict(mix, torch.tensor(u), ls.DT)
        kf.update(y)
        mix = ekf.update(mix, torch.tensor(y), meas)
        mean, cov = ekf.estimate(mix)
        # relative to the largest entry: the RK4 error of SUBSTEPS (~1e-11 relative in P) and its rounding
        assert_within(mean, kf.x, 1e-10 * np.abs(kf.x).max(), "EKF mean against filterpy's Kalman filter")
        assert_within(cov, kf.P, 1e-10 * np.abs(kf.P).max(), "EKF covariance against filterpy's Kalman filter")
        ll = float(ekf.diagnostics["log_likelihood"])
        assert_within(ll, kf.log_likelihood, 1e-10, "EKF log-likelihood against filterpy's")
        worst_x = max(worst_x, np.abs(mean.numpy() - kf.x).max() / np.abs(kf.x).max())
        worst_P = max(worst_P, np.abs(cov.numpy() - kf.P).max() / np.abs(kf.P).max())
        worst_ll = max(worst_ll, abs(ll - kf.log_likelihood))
    print(f"relative error: mean {worst_x:.2e}, cov {worst_P:.2e}, loglik {worst_ll:.2e}")


def test_gsf_is_a_weighted_bank_of_kalman_filters(gen):
    us, ys = ls.simulate(30, seed=11)
    N = 4
    means0 = torch.randn(N, 3, generator=gen, dtype=torch.float64)
    covs0 = torch.stack([torch.diag(torch.rand(3, generator=gen, dtype=torch.float64) + 0.1) for _ in range(N)])
    w0 = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=torch.float64)
    gsf = GaussianSumFilter(ls.model(), substeps=SUBSTEPS)
    mix = GaussianMixture(weights=w0, means=means0, covs=covs0)
    bank = [_filterpy_kf(means0[i].numpy(), covs0[i].numpy()) for i in range(N)]
    log_w = np.log(w0.numpy())
    meas = ls.measurement()
    for u, y in zip(us, ys):
        mix = gsf.predict(mix, torch.tensor(u), ls.DT)
        for kf in bank:
            kf.predict(u=u)
        lik = np.array([multivariate_normal(ls.H @ kf.x, kf.H @ kf.P @ kf.H.T + kf.R).logpdf(y) for kf in bank])
        for kf in bank:
            kf.update(y)
        log_w = log_w + lik
        log_w -= np.logaddexp.reduce(log_w)
        mix = gsf.update(mix, torch.tensor(y), meas)
        means, covs = np.stack([kf.x for kf in bank]), np.stack([kf.P for kf in bank])
        assert_within(mix.means, means, relative_bound(means, 1e-10, 1e-10), "GSF means against a Kalman bank")
        assert_within(mix.covs, covs, relative_bound(covs, 1e-10, 1e-12), "GSF covariances against a Kalman bank")
        assert_within(mix.log_weights, log_w, relative_bound(log_w, 1e-10, 1e-10), "GSF log-weights (Bayes)")
