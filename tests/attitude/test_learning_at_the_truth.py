"""Learning on data simulated with exactly the noise the filter is configured with: the maximum-likelihood
estimates are unbiased on both star noise models (the likelihood is the data's, two degrees of freedom per star
vector), and a parameter the data cannot identify gets no verdict, the curvature said in words."""

from __future__ import annotations

import math

import pytest
import torch

import envs
from agsf_torch.attitude.learning import fit_attitude_parameters
from agsf_torch.experiments.run.recorded import record_environment
from tests.attitude.test_learning import BASE
from tests.helpers import F64, assert_statistic


def _fit(gen, learn, *, noise_model="isotropic", B=16, steps=200, estimate_bias=False, **env_kwargs):
    seed = int(torch.randint(0, 2**31 - 1, (), generator=gen))  # the data set: drawn by the test's generator
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=B, max_steps=steps, **env_kwargs)
    rec = record_environment(env, steps, seed=seed)
    n = 6 if estimate_bias else 3
    truth0 = torch.as_tensor(rec.truth_mrp[:, 0])
    if estimate_bias:
        truth0 = torch.cat((truth0, torch.as_tensor(rec.truth_bias[:, 0])), -1)
    P0 = torch.diag(torch.tensor([1e-8] * 3 + [1e-14] * 3, dtype=F64)[:n])
    mean0 = truth0 + torch.randn(B, n, generator=gen, dtype=F64) * P0.diagonal().sqrt()
    return fit_attitude_parameters(
        rec,
        BASE,
        learn,
        prior_mean=mean0,
        prior_cov=P0,
        max_iter=40,
        update_iterations=3,
        noise_model=noise_model,
        estimate_bias=estimate_bias,
    )


def _assert_at_the_truth(r, names, what):
    """The learned log σ against the truth in units of its own standard error (from the curvature, the 95 %
    half-width / 1.96): asymptotically standard normal at the truth, so a false-failure rate of 1e-6 allows
    4.9 of them."""
    assert r.converged, r.message
    for k in names:
        lo, hi = r.interval[k]
        se = (math.log(hi) - math.log(lo)) / (2 * 1.959963984540054)
        assert r.notes[k] is None
        assert_statistic(math.log(r.learned[k]), math.log(BASE[k]), se, f"log {k} ({what})", false_failure=1e-6)


@pytest.mark.parametrize("noise_model", ["isotropic", "tangent"])
def test_the_star_noise_is_recovered_without_bias(gen, noise_model):
    """Before the data's likelihood, the isotropic model's σ_s came out at √(2/3) of the truth: on these data
    (8 runs of 10 s, a standard error of about 2 %) 11.6 standard errors away at the default seed."""
    r = _fit(gen, ["sigma_s"], noise_model=noise_model, B=8, steps=100, sigma_s=BASE["sigma_s"])
    _assert_at_the_truth(r, ["sigma_s"], noise_model)


@pytest.mark.slow
@pytest.mark.parametrize("noise_model", ["isotropic", "tangent"])
def test_the_star_and_gyro_noise_are_recovered_together_without_bias(gen, noise_model):
    """Both at once on 16 runs of 60 s (σ_v shows only in how the attitude drifts between frames: 20 s of data
    leave it within a factor of hundreds)."""
    r = _fit(gen, ["sigma_s", "sigma_v"], noise_model=noise_model, B=16, steps=600)
    _assert_at_the_truth(r, ["sigma_s", "sigma_v"], noise_model)


def test_a_parameter_the_data_cannot_identify_gets_no_verdict_and_the_curvature_in_words(gen):
    """The 6-state filter estimates the bias as a state: the known-bias parameter ``bias`` does not enter its
    likelihood (curvature 0).  σ_u from 3 s of data moves the likelihood by almost nothing."""
    r = _fit(gen, ["bias", "sigma_u"], B=4, steps=30, estimate_bias=True, star_period=1.0)
    for k in ("bias", "sigma_u"):
        assert r.inside[k] is None
        assert r.notes[k].startswith("not identified by these data: −log-likelihood has curvature"), r.notes[k]
    assert "(none to fit)" in r.notes["bias"]
    assert "in log sigma_u" in r.notes["sigma_u"]


def test_the_words_for_an_interval_wider_than_a_float():
    from agsf_torch.attitude.learning import _identification

    note = _identification("sigma_u", torch.tensor([1e-30], dtype=F64), torch.tensor([1e4], dtype=F64))
    assert note.endswith("a 95 % interval of ×/÷ e^1e+04"), note
    assert _identification("sigma_u", torch.tensor([4.0], dtype=F64), torch.tensor([0.5], dtype=F64)) is None
    flat = _identification("bias", torch.tensor([0.0, 1.0, 1.0], dtype=F64), torch.tensor([1e-9] * 3, dtype=F64))
    assert flat.endswith("in bias (rad/s) (none to fit)"), flat
