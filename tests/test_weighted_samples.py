"""Weighted samples (:mod:`agsf_torch.weighted_samples`): the effective sample size, systematic resampling and the
weighted moments against their definitions."""

from __future__ import annotations

import math

import numpy as np
import torch

from agsf_torch.weighted_samples import effective_sample_size, systematic_resample, weighted_moments
from tests.helpers import F64, assert_within, relative_bound


def test_the_effective_sample_size_is_kishs():
    """``(Σwᵢ)²/Σwᵢ²`` of unnormalised weights, in float64 numpy: equal weights give ``M``, one weight that carries
    everything 1, a zero weight (``log w = −inf``) takes no part; the result does not depend on the weights' scale
    (log-weights shifted by 700, beyond ``exp``'s range)."""
    lw = np.array(
        [[0.3, -1.2, 2.0, 0.0, -0.5], [0.0] * 5, [0.0, -800.0, -900.0, -1000.0, -1e4], [1.0, -np.inf, 1.0, 1.0, 1.0]]
    )
    w = np.exp(lw - lw.max(-1, keepdims=True))
    ess = w.sum(-1) ** 2 / (w * w).sum(-1)
    got = effective_sample_size(torch.tensor(lw, dtype=F64))
    assert_within(got, ess, relative_bound(ess, 16 * np.finfo(np.float64).eps, 0.0), "ESS")
    assert got[1].item() == 5.0 and got[2].item() == 1.0 and got[3].item() == 4.0
    shifted = effective_sample_size(torch.tensor(lw[:1] + 700.0, dtype=F64))
    assert_within(shifted, ess[:1], relative_bound(ess[:1], 64 * np.finfo(np.float64).eps, 0.0), "shifted")


def test_the_weighted_moments_are_the_weighted_mean_and_covariance(gen):
    """``m̂ = Σwᵢxᵢ`` and ``Σ̂ = Σwᵢ(xᵢ − m̂)(xᵢ − m̂)ᵀ`` with the normalised weights, in numpy; ``Σ̂`` symmetric."""
    x = torch.randn(3, 50, 4, generator=gen, dtype=F64)
    lw = torch.randn(3, 50, generator=gen, dtype=F64)
    mean, cov = weighted_moments(x, lw)
    w = torch.softmax(lw, -1).numpy()
    xn = x.numpy()
    m = np.einsum("bm,bmi->bi", w, xn)
    d = xn - m[:, None]
    C = np.einsum("bm,bmi,bmj->bij", w, d, d)
    scale = 64 * np.finfo(np.float64).eps * float(np.abs(xn).max()) ** 2
    assert_within(mean, m, 64 * np.finfo(np.float64).eps * float(np.abs(xn).max()), "weighted mean")
    assert_within(cov, C, scale, "weighted covariance")
    assert torch.equal(cov, cov.transpose(-1, -2))


def test_systematic_resampling_draws_every_particle_floor_or_ceil_of_M_w(gen):
    """Exact: particle ``i`` is drawn ``⌊Mwᵢ⌋`` or ``⌈Mwᵢ⌉`` times (to the rounding of the cumulative weights:
    ``2M²ε`` in ``Mwᵢ``), zero weights never, ``M`` draws in all, indices sorted; batched over trajectories with
    their own offsets equal to one at a time; and unbiased: averaged over offsets ``u`` on a grid of ``K`` points the
    counts are ``Mwᵢ`` to ``2/K`` (each count is a difference of two step functions of ``u``, each off by at most
    ``1/K`` on the grid)."""
    B, M = 6, 1000
    lw = 3.0 * torch.randn(B, M, generator=gen, dtype=F64)
    lw[1] = 0.0  # equal weights (but the zeros below)
    lw[2, 5] = 40.0  # one particle carries nearly all
    lw[:, ::7] = -math.inf  # zero weights
    u = torch.rand(B, generator=gen, dtype=F64)
    u[0], u[3] = 0.0, 1.0 - 2.0**-53
    idx = systematic_resample(lw, u)
    counts = torch.zeros(B, M, dtype=F64).scatter_add_(-1, idx, torch.ones_like(idx, dtype=F64))
    Mw = M * torch.softmax(lw, -1)
    slack = 2.0 * M * M * torch.finfo(F64).eps
    assert bool((counts >= torch.floor(Mw - slack)).all()) and bool((counts <= torch.ceil(Mw + slack)).all())
    assert bool((counts[:, ::7] == 0).all())
    assert counts.sum(-1).tolist() == [M] * B
    assert bool((idx[:, 1:] >= idx[:, :-1]).all())
    for b in range(B):
        assert torch.equal(systematic_resample(lw[b], u[b]), idx[b])
    K = 4096
    grid = (torch.arange(K, dtype=F64) + 0.5) / K
    many = systematic_resample(lw[0].expand(K, M), grid)
    mean_counts = torch.zeros(K, M, dtype=F64).scatter_add_(-1, many, torch.ones_like(many, dtype=F64)).mean(0)
    assert_within(mean_counts, Mw[0], 2.0 / K + slack, "counts averaged over the offset")
