"""Discrete gyro model: noise variances, bias random walk, zero-noise limit, bad settings.

Variance checks use the exact sampling law of a normal sample variance,
``(n−1) s²/σ² ~ χ²(n−1)`` (``n s²/σ² ~ χ²(n)`` when the mean is known to be zero
and s² is the mean square): the ratio s²/σ² must lie in the central interval of
probability 1 − 1e-6 (for n = 600 000 pooled samples that is about ±0.9 %, per
axis with n = 200 000 about ±1.55 %).  Means and the correlation go through
:func:`tests.helpers.assert_statistic` with standard errors σ/sqrt(n) and 1/sqrt(n).
A fresh seed would fail a check with probability 1e-6.
"""

from __future__ import annotations

import math

import pytest
import torch
from scipy import stats

from envs.gyro import DEFAULT_SIGMA_U, DEFAULT_SIGMA_V, DEG_PER_HOUR, Gyro
from envs.random import counter_normal
from tests.helpers import assert_statistic

N = 200_000  # trajectories; × 3 axes = 600 000 samples per statistic
ALPHA = 1e-6


def variance_ratio_bounds(n: int, alpha: float = ALPHA) -> tuple[float, float]:
    """Central (1 − α) interval of s²/σ² for n normal samples."""
    lo = stats.chi2.ppf(alpha / 2, n - 1) / (n - 1)
    hi = stats.chi2.ppf(1 - alpha / 2, n - 1) / (n - 1)
    return lo, hi


def _one_step(gyro: Gyro, seed: int = 0):
    omega = torch.tensor([0.05, -0.02, 0.01], dtype=torch.float64).expand(N, 3)
    b0 = gyro.initial_bias_tensor((N,))
    seeds = torch.arange(N, dtype=torch.int64) + seed
    n_v = counter_normal(seeds, 1, 2, (3,))
    n_u = counter_normal(seeds, 1, 3, (3,))
    measured, b1 = gyro.step(omega, b0, n_v, n_u)
    return omega, b0, measured, b1


def test_the_default_gyro_uses_the_default_noise_model():
    g = Gyro()
    assert g.dt == 0.1
    assert g.rate_noise_std == math.sqrt(DEFAULT_SIGMA_V**2 / 0.1 + DEFAULT_SIGMA_U**2 * 0.1 / 12)
    assert g.bias_step_std == DEFAULT_SIGMA_U * math.sqrt(0.1)


@pytest.mark.parametrize(
    "sigma_v, sigma_u, dt",
    [
        (DEFAULT_SIGMA_V, DEFAULT_SIGMA_U, 0.1),  # the defaults: σ_v²/Δt dominates
        (1e-4, 2e-3, 1.0),  # σ_u²Δt/12 = 3.3e-7 dominates σ_v²/Δt = 1e-8: the /12 term is tested
    ],
)
def test_measurement_and_bias_step_variances(sigma_v, sigma_u, dt):
    gyro = Gyro(sigma_v, sigma_u, dt)
    omega, b0, measured, b1 = _one_step(gyro)
    err = (measured - omega - 0.5 * (b1 + b0)).reshape(-1)
    step = (b1 - b0).reshape(-1)
    n = err.numel()
    var_meas = sigma_v**2 / dt + sigma_u**2 * dt / 12.0
    var_bias = sigma_u**2 * dt
    ratio_meas = float((err * err).mean()) / var_meas  # known zero mean: n degrees of freedom
    ratio_bias = float((step * step).mean()) / var_bias
    lo, hi = stats.chi2.ppf(ALPHA / 2, n) / n, stats.chi2.ppf(1 - ALPHA / 2, n) / n
    assert lo <= ratio_meas <= hi, ratio_meas
    assert lo <= ratio_bias <= hi, ratio_bias
    # Zero means and independent noises.
    assert_statistic(float(err.mean()), 0.0, math.sqrt(var_meas / n), "mean measurement error", false_failure=ALPHA)
    assert_statistic(float(step.mean()), 0.0, math.sqrt(var_bias / n), "mean bias step", false_failure=ALPHA)
    corr = float(torch.corrcoef(torch.stack((err, step)))[0, 1])
    assert_statistic(corr, 0.0, 1 / math.sqrt(n), "correlation of the two noises", false_failure=ALPHA)
    # Per axis, too.
    lo3, hi3 = variance_ratio_bounds(N)
    per_axis = (measured - omega - 0.5 * (b1 + b0)).var(0) / var_meas
    assert bool(((per_axis >= lo3) & (per_axis <= hi3)).all()), per_axis


def test_zero_noise_gives_rate_plus_bias_exactly():
    g = Gyro(0.0, 0.0, 0.1, initial_bias=1e-6)
    omega = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64)
    b0 = g.initial_bias_tensor((1,))
    z = torch.randn(1, 3, dtype=torch.float64)
    measured, b1 = g.step(omega, b0, z, z)
    assert torch.equal(b1, b0)
    assert torch.equal(measured, omega + b0)
    assert torch.equal(g.read(omega, b0, z), omega + b0)


def test_initial_bias_scalar_or_vector():
    assert Gyro(initial_bias=2e-7).initial_bias == (2e-7,) * 3
    assert Gyro(initial_bias=(1e-7, 2e-7, 3e-7)).initial_bias_tensor((2,)).tolist() == [[1e-7, 2e-7, 3e-7]] * 2


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(sigma_v=-1e-7), r"sigma_v must be finite and ≥ 0, got -1e-07"),
        (dict(sigma_v=float("nan")), r"sigma_v must be finite and ≥ 0, got nan"),
        (dict(sigma_u=-1e-10), r"sigma_u must be finite and ≥ 0, got -1e-10"),
        (dict(sigma_u=float("inf")), r"sigma_u must be finite and ≥ 0, got inf"),
        (dict(dt=0.0), r"dt must be finite and > 0, got 0.0"),
        (dict(dt=-0.1), r"dt must be finite and > 0, got -0.1"),
        (dict(dt="fast"), r"dt must be a number, got 'fast'"),
        (dict(initial_bias=(1e-7, float("nan"), 0.0)), r"initial_bias must be 3 finite numbers"),
        (dict(initial_bias=(1e-7, 0.0)), r"initial_bias must be 3 finite numbers, got \(1e-07, 0.0\)"),
    ],
)
def test_bad_gyro_settings_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Gyro(**kwargs)


def test_simulated_gyro_defaults_are_the_filters_assumed_ones():
    """The simulator keeps its own constants (it depends on agsf_torch.rotations only); they equal the
    filters' defaults in agsf_torch.constants."""
    from agsf_torch import constants

    assert DEG_PER_HOUR == constants.DEG_PER_HOUR
    assert DEFAULT_SIGMA_V == constants.DEFAULT_SIGMA_V and DEFAULT_SIGMA_U == constants.DEFAULT_SIGMA_U
