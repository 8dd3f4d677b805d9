"""Counter-based RNG: bit-exactness, distribution statistics, independence, batching.

Statistical thresholds.  Every test uses fixed seeds, so it is deterministic; the
bounds are chosen so that a *fresh* seed would fail with probability ~1e-6 or less
(:func:`tests.helpers.assert_statistic`, a false-failure rate of 1e-6 per assertion):

* means and correlations: standard errors σ/sqrt(n) and 1/sqrt(n);
* variances: the relative error of a sample variance has standard deviation
  sqrt(2/(n−1)) for normals and sqrt(4/5/(n−1)) for U(0,1) (from the fourth moment);
* third and fourth moments of normals: standard errors sqrt(15/n) and sqrt(96/n);
* Kolmogorov–Smirnov: the statistic D must stay below the asymptotic α = 1e-3
  critical value 1.949/sqrt(n) (and scipy's p-value above 1e-3).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from envs.random import (
    CounterKey,
    as_int64,
    counter_normal,
    counter_uniform,
    hash_key,
    mix64,
    random_bits,
)
from tests.helpers import assert_statistic

N = 200_000
ALPHA = 1e-6  # the false-failure rate of each statistical assertion
KS_CRIT = 1.949  # sqrt(-ln(α/2)/2) for α = 1e-3
_M = (1 << 64) - 1
_G = 0x9E3779B97F4A7C15


def _mix_ref(z: int) -> int:
    """splitmix64 finaliser on Python ints (the uint64 reference)."""
    z &= _M
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _M
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _M
    return z ^ (z >> 31)


def _word_ref(seed: int, step: int, stream: int, c: int) -> int:
    h = _mix_ref((seed % (1 << 64)) * _G + _G)
    h = _mix_ref(h + (step + 1) * _G)
    h = _mix_ref(h + (stream + 1) * _G)
    return _mix_ref(h + (c + 1) * _G)


def _u64(x: int) -> int:
    return x & _M


def test_mix64_matches_published_splitmix64_sequence():
    # SplitMix64 seeded with 0 outputs mix(G), mix(2G), mix(3G): published values.
    words = mix64(torch.tensor([as_int64(_G * k) for k in (1, 2, 3)], dtype=torch.int64))
    assert [_u64(int(w)) for w in words] == [0xE220A8397B1DCDAF, 0x6E789E6AA1B965F4, 0x06C45D188009454F]


def test_mix64_bit_exact_against_python_reference():
    rng = np.random.default_rng(0)
    vals = [0, 1, -1, (1 << 63) - 1, -(1 << 63), 12345] + [
        int(v) for v in rng.integers(-(1 << 63), 1 << 63, 500, dtype=np.int64)
    ]
    got = mix64(torch.tensor(vals, dtype=torch.int64))
    assert [_u64(int(g)) for g in got] == [_mix_ref(_u64(v)) for v in vals]


@pytest.mark.parametrize("seed", [0, 7, -3, (1 << 64) + 11, (1 << 63) + 5])
def test_counter_words_and_uniforms_match_reference(seed):
    bits = random_bits(seed, 4, 2, (6,))
    ref = [_word_ref(seed, 4, 2, c) for c in range(6)]
    assert [_u64(int(b)) for b in bits] == ref
    u = counter_uniform(seed, 4, 2, (6,))
    assert u.tolist() == [(w >> 11) * 2.0**-53 for w in ref]


def test_as_int64_wraps_modulo_2_pow_64():
    assert as_int64(5) == 5
    assert as_int64((1 << 64) + 5) == 5
    assert as_int64(-1) == -1
    assert as_int64(1 << 63) == -(1 << 63)
    assert as_int64((1 << 64) - 1) == -1


def test_uniform_statistics():
    u = counter_uniform(2024, 0, 0, (N,)).numpy()
    assert u.dtype == np.float64 and u.min() >= 0.0 and u.max() < 1.0
    assert_statistic(u.mean(), 0.5, math.sqrt(1 / 12 / N), "mean of uniforms", false_failure=ALPHA)
    assert_statistic(
        u.var(ddof=1) * 12, 1.0, math.sqrt(0.8 / (N - 1)), "variance of uniforms × 12", false_failure=ALPHA
    )
    ks = stats.kstest(u, "uniform")
    assert ks.statistic < KS_CRIT / math.sqrt(N) and ks.pvalue > 1e-3


def test_normal_statistics():
    z = counter_normal(2024, 0, 1, (N,)).numpy()
    assert np.all(np.isfinite(z))
    assert_statistic(z.mean(), 0.0, 1 / math.sqrt(N), "mean of normals", false_failure=ALPHA)
    assert_statistic(z.var(ddof=1), 1.0, math.sqrt(2 / (N - 1)), "variance of normals", false_failure=ALPHA)
    # Third and fourth moments: E z³ = 0 (sd sqrt(15/n)), E z⁴ = 3 (sd sqrt(96/n)).
    assert_statistic((z**3).mean(), 0.0, math.sqrt(15 / N), "third moment of normals", false_failure=ALPHA)
    assert_statistic((z**4).mean(), 3.0, math.sqrt(96 / N), "fourth moment of normals", false_failure=ALPHA)
    ks = stats.kstest(z, "norm")
    assert ks.statistic < KS_CRIT / math.sqrt(N) and ks.pvalue > 1e-3


def test_normal_cos_and_sin_branches_are_each_normal():
    z = counter_normal(5, 3, 9, (N,)).numpy()
    for half in (z[0::2], z[1::2]):
        n = half.size
        assert_statistic(half.mean(), 0.0, 1 / math.sqrt(n), "mean of one branch", false_failure=ALPHA)
        assert_statistic(half.var(ddof=1), 1.0, math.sqrt(2 / (n - 1)), "variance of one branch", false_failure=ALPHA)
        assert stats.kstest(half, "norm").statistic < KS_CRIT / math.sqrt(n)


@pytest.mark.parametrize(
    "other",
    [
        dict(seed=1, step=0, stream=1),  # another stream
        dict(seed=1, step=1, stream=0),  # another step
        dict(seed=2, step=0, stream=0),  # the neighbouring seed
    ],
)
def test_streams_steps_and_seeds_are_uncorrelated(other):
    a = counter_normal(1, 0, 0, (N,)).numpy()
    b = counter_normal(other["seed"], other["step"], other["stream"], (N,)).numpy()
    assert not np.array_equal(a, b)
    assert_statistic(np.corrcoef(a, b)[0, 1], 0.0, 1 / math.sqrt(N), "correlation of two streams", false_failure=ALPHA)
    # A two-sample KS test: the two streams have the same law.
    assert stats.ks_2samp(a, b).pvalue > 1e-3


def test_neighbouring_elements_are_uncorrelated():
    z = counter_normal(3, 0, 0, (N + 1,)).numpy()
    lag = np.corrcoef(z[:-1], z[1:])[0, 1]
    assert_statistic(lag, 0.0, 1 / math.sqrt(N), "lag-1 correlation of normals", false_failure=ALPHA)
    u = counter_uniform(3, 0, 0, (N + 1,)).numpy()
    lag = np.corrcoef(u[:-1], u[1:])[0, 1]
    assert_statistic(lag, 0.0, 1 / math.sqrt(N), "lag-1 correlation of uniforms", false_failure=ALPHA)


def test_batched_equals_single_and_elements_are_pure():
    seeds = torch.tensor(as_int64(1000), dtype=torch.int64) + torch.arange(64)
    steps = torch.arange(5)
    batched = counter_normal(seeds[:, None], steps[None, :], 3, (4, 3))  # [64, 5, 4, 3]
    for i in (0, 17, 63):
        for k in (0, 4):
            single = counter_normal(1000 + i, k, 3, (4, 3))
            assert torch.equal(batched[i, k], single)
    # Element e depends on e only: a longer draw starts with the shorter one.
    assert torch.equal(counter_normal(9, 2, 1, (7,))[:3], counter_normal(9, 2, 1, (3,)))
    assert torch.equal(counter_uniform(9, 2, 1, (7,))[:5], counter_uniform(9, 2, 1, (5,)))


def test_counter_key_and_hash_key_broadcast():
    key = CounterKey(torch.arange(3), 2, 5)
    assert key.normal((2,)).shape == (3, 2)
    assert torch.equal(key.uniform((4,))[1], counter_uniform(1, 2, 5, (4,)))
    assert hash_key(torch.arange(3)[:, None], torch.arange(4)[None, :], 0).shape == (3, 4)


def test_non_int64_counter_tensor_is_rejected():
    with pytest.raises(ValueError, match="int64"):
        counter_normal(torch.arange(3, dtype=torch.int32), 0, 0, (2,))
