"""GaussianMixture: moments, densities, the moment-preserving split, validation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from agsf_torch import GaussianMixture
from agsf_torch.mixture import split_gaussian
from tests.helpers import assert_within, random_spd, relative_bound


@pytest.mark.parametrize("N", [1, 2, 3, 5, 9])
@pytest.mark.parametrize("n", [1, 3, 6])
def test_split_preserves_moments(gen, N, n):
    mean = torch.randn(7, n, generator=gen, dtype=torch.float64)
    cov = random_spd(gen, 7, n=n, scale=1e-3)
    mix = GaussianMixture.from_gaussian(mean, cov, N)
    assert mix.weights.shape == (7, N) and mix.means.shape == (7, N, n)
    m, P = mix.moments()
    assert_within(m, mean, 1e-12 * float(mean.abs().max()), "mixture mean")
    assert_within(P, cov, 1e-12 * float(cov.abs().max()), "mixture covariance")
    assert bool((torch.linalg.eigvalsh(mix.covs) > 0).all())


def test_split_spread_controls_component_width(gen):
    cov = torch.diag(torch.tensor([4.0, 1.0], dtype=torch.float64))
    w, mu, P = split_gaussian(torch.zeros(2, dtype=torch.float64), cov, 5, spread=0.75)
    eye = torch.eye(2, dtype=torch.float64)
    assert_within(P[0], eye, relative_bound(eye, 1e-7, 1e-7), "component covariance")
    assert_within(mu[:, 1], 0.0, 1e-8, "means across the principal axis")  # along the principal axis only
    assert_within(w.flip(0), w, relative_bound(w, 1e-7, 1e-7), "mirrored weights")  # symmetric weights


def test_log_prob_matches_scipy(gen):
    N, n = 4, 3
    w = torch.rand(2, N, generator=gen, dtype=torch.float64)
    mu = torch.randn(2, N, n, generator=gen, dtype=torch.float64)
    P = random_spd(gen, 2, N, n=n)
    mix = GaussianMixture(weights=w, means=mu, covs=P)
    x = torch.randn(2, 11, n, generator=gen, dtype=torch.float64)
    lp = mix.log_prob(x)
    # log p sums the terms ½ (x − μ)ᵀP⁻¹(x − μ), ½ log det P and (n/2) log 2π of each component: both sides round
    # to a few ε of them (|log p| is at most the largest such sum, and equals it where they do not cancel)
    d = x[:, None] - mu[:, :, None]  # [2, N, 11, n]
    maha = (d * torch.linalg.solve(P[:, :, None], d.unsqueeze(-1)).squeeze(-1)).sum(-1)
    terms = 0.5 * maha + 0.5 * torch.logdet(P).abs()[..., None] + 0.5 * n * np.log(2 * np.pi)
    scale = terms.amax(1)  # [2, 11]
    for b in range(2):
        wn = (w[b] / w[b].sum()).numpy()
        ref = sum(wn[i] * multivariate_normal(mu[b, i].numpy(), P[b, i].numpy()).pdf(x[b].numpy()) for i in range(N))
        assert_within(lp[b], np.log(ref), 1e-12 * scale[b], "mixture log-density against scipy")


def test_log_weights_constructor_and_entropy(gen):
    lw = torch.tensor([[0.0, -1000.0, float("-inf")]], dtype=torch.float64)
    mix = GaussianMixture(
        log_weights=lw,
        means=torch.zeros(1, 3, 2, dtype=torch.float64),
        covs=torch.eye(2, dtype=torch.float64).expand(1, 3, 2, 2),
    )
    assert_within(mix.weights.sum(-1), 1.0, relative_bound(1.0, 1e-7, 1e-7), "sum of the weights")
    assert float(mix.entropy_of_weights()) == 0.0  # the weights are exactly (1, 0, 0): exp(−1000) underflows
    uni = GaussianMixture(
        weights=torch.ones(1, 4),
        means=torch.zeros(1, 4, 1, dtype=torch.float64),
        covs=torch.ones(1, 4, 1, 1, dtype=torch.float64),
    )
    assert_within(uni.entropy_of_weights(), np.log(4), 1e-14 * np.log(4), "entropy of uniform weights")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"weights": torch.tensor([[1.0, -1.0]])}, "non-negative"),
        ({"weights": torch.tensor([[0.0, 0.0]])}, "positive sum"),
        ({"weights": torch.tensor([[1.0, 1.0, 1.0]])}, "weights must have shape"),
        ({"weights": torch.ones(1, 2), "covs": -torch.eye(2).expand(1, 2, 2, 2)}, "positive definite"),
        ({"weights": torch.ones(1, 2), "covs": torch.tensor([[1.0, 0.5], [0.0, 1.0]]).expand(1, 2, 2, 2)}, "symmetric"),
        ({"weights": torch.ones(1, 2), "means": torch.full((1, 2, 2), float("nan"))}, "means must be finite"),
        ({"weights": torch.ones(1, 2), "covs": torch.eye(3).expand(1, 2, 3, 3)}, "covs must have shape"),
        ({"weights": torch.ones(1, 2), "log_weights": torch.zeros(1, 2)}, "exactly one"),
    ],
)
def test_bad_input_raises(kwargs, match):
    args = {
        "means": torch.zeros(1, 2, 2, dtype=torch.float64),
        "covs": torch.eye(2, dtype=torch.float64).expand(1, 2, 2, 2),
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        GaussianMixture(**args)


def test_from_gaussian_rejects_bad_prior():
    with pytest.raises(ValueError, match="positive definite"):
        GaussianMixture.from_gaussian(
            torch.zeros(2, dtype=torch.float64), torch.diag(torch.tensor([1.0, -1.0], dtype=torch.float64)), 3
        )
    with pytest.raises(ValueError, match="num_components"):
        GaussianMixture.from_gaussian(torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64), 0)
    with pytest.raises(ValueError, match="spread"):
        GaussianMixture.from_gaussian(
            torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64), 3, spread=1.0
        )


def test_integer_and_bool_inputs_become_float64():
    """Integer means no longer drag the weights to integers (0.5 → 0, 'positive sum'): every field is float64."""
    mix = GaussianMixture(
        weights=torch.tensor([[0.5, 0.5]], dtype=torch.float64),
        means=torch.tensor([[[0, 0, 0], [1, 1, 1]]]),
        covs=torch.eye(3, dtype=torch.int64).expand(1, 2, 3, 3),
    )
    assert mix.means.dtype == mix.covs.dtype == mix.log_weights.dtype == torch.float64
    assert mix.weights.tolist() == [[0.5, 0.5]]
    flags = GaussianMixture(weights=[[2, 2]], means=torch.zeros(1, 2, 1, dtype=torch.bool), covs=[[[[1]], [[2]]]])
    assert flags.means.dtype == torch.float64 and flags.weights.tolist() == [[0.5, 0.5]]


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("means", "abc", "means must be a real tensor"),
        ("means", torch.zeros(1, 2, 2, dtype=torch.complex128), "means must be real"),
        ("covs", None, "covs must be a real tensor"),
        ("weights", {"a": 1}, "weights must be a real tensor"),
    ],
)
def test_non_numeric_fields_are_named(field, value, match):
    args = {
        "weights": torch.ones(1, 2),
        "means": torch.zeros(1, 2, 2, dtype=torch.float64),
        "covs": torch.eye(2, dtype=torch.float64).expand(1, 2, 2, 2),
    }
    args[field] = value
    with pytest.raises(ValueError, match=match):
        GaussianMixture(**args)


def test_check_covariance_refuses_integer_matrices():
    from agsf_torch.mixture import check_covariance

    with pytest.raises(ValueError, match="P must be a floating-point tensor, got a torch.int64 tensor"):
        check_covariance("P", torch.eye(2, dtype=torch.int64))


def test_replace_validates_by_default():
    mix = GaussianMixture(
        weights=torch.ones(2, 3),
        means=torch.zeros(2, 3, 2, dtype=torch.float64),
        covs=torch.eye(2, dtype=torch.float64).expand(2, 3, 2, 2),
    )
    nan_means = mix.means.clone()
    nan_means[1, 2, 0] = float("nan")
    with pytest.raises(ValueError, match=r"means must be finite; non-finite entry at batch index \(1, 2\)"):
        mix.replace(means=nan_means)
    not_pd = mix.covs.clone()
    not_pd[0, 1] = torch.diag(torch.tensor([1.0, -1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"covs is not positive definite at batch index \(0, 1\)"):
        mix.replace(covs=not_pd)
    with pytest.raises(ValueError, match="log_weights must not be NaN"):
        mix.replace(log_weights=torch.full((2, 3), float("nan"), dtype=torch.float64))
    with pytest.raises(ValueError, match="covs must have shape"):
        mix.replace(covs=torch.eye(3, dtype=torch.float64).expand(2, 3, 3, 3))
    with pytest.raises(ValueError, match="replace\\(\\) takes log_weights, means and covs, got weights"):
        mix.replace(weights=torch.ones(2, 3))
    # the filters' own outputs skip the check explicitly, and keep weights they do not replace as they are
    assert bool(torch.isnan(mix.replace(means=nan_means, validate=False).means).any())
    kept = mix.replace(means=mix.means.float(), covs=mix.covs, validate=False)
    assert kept.log_weights.dtype == kept.covs.dtype == torch.float32
    assert torch.equal(kept.log_weights, mix.log_weights.float())
    assert mix.replace(covs=2 * mix.covs, validate=False).log_weights is mix.log_weights
    ok = mix.replace(means=mix.means + 1.0)
    assert torch.equal(ok.means, mix.means + 1.0) and torch.equal(ok.covs, mix.covs)


def test_entropy_of_weights_is_shannons_in_nats(gen):
    from scipy.stats import entropy

    w = torch.rand(3, 6, generator=gen, dtype=torch.float64)
    w[1, 2] = 0.0
    mix = GaussianMixture(
        weights=w,
        means=torch.zeros(3, 6, 1, dtype=torch.float64),
        covs=torch.ones(3, 6, 1, 1, dtype=torch.float64),
    )
    want = entropy(w.numpy(), axis=-1)  # normalises the rows itself
    # −Σ wᵢ log wᵢ sums terms of one sign: the entropy itself is the scale of its rounding
    assert_within(mix.entropy_of_weights(), want, 1e-14 * want, "entropy of the weights against scipy")


def test_a_mixture_of_expanded_views_filters_as_one_of_copies():
    """Means and covariances given as expanded (stride-0) views of one Gaussian — the natural way to start every
    component at the prior — had failed at the first predict with a user model (torch.func refuses to differentiate
    through aliased memory); the mixture holds its own copies, so both give the same numbers, bit for bit."""
    from agsf_torch.filters import GaussianSumFilter
    from agsf_torch.models import ContinuousModel

    class Oscillator(ContinuousModel):  # no closed-form Jacobian: torch.func differentiates the drift
        state_dim = 2

        def drift(self, x, u=None):
            return torch.stack((x[..., 1], -x[..., 0] - 0.2 * x[..., 1]), -1)

        def noise_gain(self, x):
            return torch.tensor([[0.0], [1.0]], dtype=x.dtype).expand(*x.shape[:-1], 2, 1)

        def noise_psd(self):
            return torch.eye(1, dtype=torch.float64)

    B, N = 3, 4
    m0 = torch.arange(6, dtype=torch.float64).reshape(B, 2)
    P0 = torch.eye(2, dtype=torch.float64).expand(B, 2, 2)
    w = torch.full((B, N), 1.0 / N, dtype=torch.float64)
    model = Oscillator()
    filt = GaussianSumFilter(model)
    views = GaussianMixture(weights=w, means=m0[:, None].expand(B, N, 2), covs=P0[:, None].expand(B, N, 2, 2))
    copies = GaussianMixture(weights=w, means=m0[:, None].repeat(1, N, 1), covs=P0[:, None].repeat(1, N, 1, 1))
    a, b = filt.predict(views, None, 0.1), GaussianSumFilter(model).predict(copies, None, 0.1)
    assert torch.equal(a.means, b.means) and torch.equal(a.covs, b.covs)


def test_from_gaussian_broadcasts_a_shared_mean_or_covariance_and_refuses_shapes_that_do_not():
    """A covariance ``[n, n]`` (or ``[1, n, n]``) shared by every trajectory's mean, or one mean for every
    covariance, gives the split of the expanded Gaussians bit for bit; leading dims that do not broadcast had been
    raw torch errors inside the split and are refused naming both shapes."""
    gen = torch.Generator().manual_seed(3)
    mean = torch.randn(3, 2, generator=gen, dtype=torch.float64)
    cov = torch.tensor([[1.0, 0.3], [0.3, 0.5]], dtype=torch.float64)
    full = GaussianMixture.from_gaussian(mean, cov.expand(3, 2, 2), 3)
    for shared in (cov, cov[None]):
        got = GaussianMixture.from_gaussian(mean, shared, 3)
        assert torch.equal(got.means, full.means) and torch.equal(got.covs, full.covs)
    one_mean = GaussianMixture.from_gaussian(mean[0], cov.expand(3, 2, 2), 3)
    assert torch.equal(
        one_mean.means, GaussianMixture.from_gaussian(mean[0].expand(3, 2), cov.expand(3, 2, 2), 3).means
    )
    with pytest.raises(
        ValueError, match=r"mean \(4, 2\) and cov \(3, 2, 2\) have leading \(trajectory\) dims that do not broadcast"
    ):
        GaussianMixture.from_gaussian(torch.zeros(4, 2, dtype=torch.float64), cov.expand(3, 2, 2), 3)
