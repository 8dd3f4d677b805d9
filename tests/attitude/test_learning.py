"""Maximum-likelihood learning through the filter on simulated data."""

from __future__ import annotations

import math

import pytest
import torch

import envs
from agsf_torch.attitude.learning import fit_attitude_parameters
from agsf_torch.experiments.run.recorded import record_environment
from tests.helpers import F64, assert_within

DEG_PER_HOUR = math.pi / 180 / 3600
BASE = dict(
    sigma_v=math.sqrt(10) * 1e-7,
    sigma_u=math.sqrt(10) * 1e-10,
    sigma_s=1e-5,
    bias=[0.1 * DEG_PER_HOUR] * 3,
    reg=1.0,
    prior_scale=1.0,
)


def _fit(learn, configured, B=24, steps=150, noise_model="isotropic", **env_kwargs):
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=B, max_steps=steps, **env_kwargs)
    rec = record_environment(env, steps, seed=11)
    g = torch.Generator().manual_seed(3)
    mean0 = torch.as_tensor(rec.truth_mrp[:, 0]) + 1e-4 * torch.randn(B, 3, generator=g, dtype=F64)
    return fit_attitude_parameters(
        rec,
        {**BASE, **configured},
        learn,
        prior_mean=mean0,
        prior_cov=1e-8 * torch.eye(3, dtype=F64),
        max_iter=30,
        update_iterations=3,
        noise_model=noise_model,
    )


# The recordings are fixed (seed 11, not moved by --seed): each bound is the accuracy the test claims for the
# maximum-likelihood estimate on its recording (10 %, 5 % for σ_s), relative to the truth.


def test_learns_gyro_noise_from_twice_the_configured_value():
    r = _fit(["sigma_v"], {"sigma_v": 1e-5}, sigma_v=2e-5, star_period=5.0)
    assert r.converged
    assert_within(r.learned["sigma_v"], 2e-5, 0.10 * 2e-5, "learned σ_v")
    assert r.inside["sigma_v"] is False  # the configured 1e-5 is flagged


def test_learns_a_constant_gyro_bias():
    b = 2e-5
    r = _fit(["bias"], {"bias": [0.0, 0.0, 0.0]}, initial_bias=b, star_period=2.0)
    assert r.converged and len(r.learned["bias"]) == 3
    assert_within(r.learned["bias"], b, 0.10 * b, "learned gyro bias")
    assert r.inside["bias"] is False


def test_learns_star_noise_from_twice_the_configured_value_with_the_isotropic_model():
    """The camera's noise lies in the 2 directions across the star vector; the filter's gain model σ_s²I₃
    spreads it over 3, but the likelihood learning maximises is the data's (2 per star): σ_s comes out at the
    camera's, not at √(2/3) of it (8.2e-6)."""
    r = _fit(["sigma_s"], {"sigma_s": 5e-6}, sigma_s=1e-5)
    assert r.converged
    assert_within(r.learned["sigma_s"], 1e-5, 0.05 * 1e-5, "learned σ_s under the isotropic model")
    assert r.inside["sigma_s"] is False


def test_learns_star_noise_from_twice_the_configured_value_with_the_tangent_model():
    r = _fit(["sigma_s"], {"sigma_s": 5e-6}, sigma_s=1e-5, noise_model="tangent")
    assert r.converged
    assert_within(r.learned["sigma_s"], 1e-5, 0.10 * 1e-5, "learned σ_s under the tangent model")
    assert r.inside["sigma_s"] is False


def test_a_fit_that_runs_out_of_iterations_is_not_converged_and_gives_no_verdict():
    """max_iter = 1: Newton stops on its budget, not its tolerances — reported as such, and no parameter is
    judged (the learned value is near the starting one; "consistent with the data" would be a wrong verdict)."""
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=4, max_steps=40, sigma_v=2e-5, star_period=2.0)
    rec = record_environment(env, 40, seed=11)
    mean0 = torch.as_tensor(rec.truth_mrp[:, 0])
    r = fit_attitude_parameters(
        rec,
        {**BASE, "sigma_v": 1e-5},
        ["sigma_v"],
        prior_mean=mean0,
        prior_cov=1e-8 * torch.eye(3, dtype=F64),
        max_iter=1,
    )
    assert not r.converged and r.message.startswith("not converged: Newton used all 1 iterations")
    assert r.inside == {"sigma_v": None}


def test_bad_requests():
    with pytest.raises(ValueError, match="unknown parameter"):
        fit_attitude_parameters(None, {**BASE, "gamma": 1.0}, ["gamma"], prior_mean=None, prior_cov=None)
    with pytest.raises(ValueError, match="nothing to learn"):
        fit_attitude_parameters(None, BASE, [], prior_mean=None, prior_cov=None)
    with pytest.raises(ValueError, match="must be > 0"):
        fit_attitude_parameters(None, {**BASE, "sigma_s": 0.0}, ["sigma_s"], prior_mean=None, prior_cov=None)


def test_a_diverging_fit_stops_with_the_last_finite_parameters(monkeypatch):
    import agsf_torch.attitude.learning as learning

    calls = {"n": 0}
    real = learning.attitude_log_likelihood

    def flaky(*args, **kwargs):
        calls["n"] += 1
        value = real(*args, **kwargs)
        return value if calls["n"] <= 3 else value * float("nan")

    monkeypatch.setattr(learning, "attitude_log_likelihood", flaky)
    r = _fit(["sigma_v"], {"sigma_v": 1e-5}, B=4, steps=30, sigma_v=2e-5, star_period=1.0)
    assert not r.converged and "diverged" in r.message
    assert math.isfinite(r.learned["sigma_v"]) and len(r.history) >= 1
