"""The merge dissimilarity on lanes (agsf_torch.fused.merge_bound) against numpy's log-determinants."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agsf_torch.fused.merge_bound import pair_dissimilarity_kernel
from tests.helpers import F64, assert_within, random_spd

EPS = float(np.finfo(np.float64).eps)


def _numpy_bound(m_i, P_i, m_j, P_j) -> tuple[float, float]:
    """Runnalls' bound at equal weights and the sum of the log-determinants' magnitudes (their rounding scale)."""
    d = m_i - m_j
    half = 0.5 * (P_i + P_j) + 0.25 * np.outer(d, d)
    ld = [np.linalg.slogdet(A)[1] for A in (half, P_i, P_j)]
    return 0.5 * (ld[0] - 0.5 * ld[1] - 0.5 * ld[2]), sum(abs(v) for v in ld)


def _check(b, means, covs):
    T, N, n = means.shape
    pairs = [(i, j) for i in range(N) for j in range(i + 1, N)]
    assert b.shape == (T, len(pairs))
    m, P = means.numpy(), covs.numpy()
    for t in range(T):
        for p, (i, j) in enumerate(pairs):
            expected, scale = _numpy_bound(m[t, i], P[t, i], m[t, j], P[t, j])
            # each log-determinant is a sum of n logs of Cholesky pivots, each to a few ulps relative to the
            # conditioning of its matrix (the random SPD matrices here are well conditioned)
            assert_within(b[t, p], expected, 16 * n * EPS * (1 + scale), f"b of pair ({i}, {j}), trajectory {t}")


@pytest.mark.parametrize("n", [1, 3, 6])
def test_the_kernel_is_runnalls_bound_of_every_pair(gen, n):
    T, N = 4, 5
    means = torch.randn(T, N, n, generator=gen, dtype=F64)
    covs = random_spd(gen, T, N, n=n)
    (b,) = pair_dissimilarity_kernel(means, covs)
    _check(b, means, covs)
    assert bool((b >= -1e-12).all())  # a KL bound: ≥ 0 up to rounding


def test_identical_components_have_zero_dissimilarity(gen):
    means = torch.randn(1, 1, 6, generator=gen, dtype=F64).expand(1, 3, 6).contiguous()
    covs = random_spd(gen, 1, 1, n=6).expand(1, 3, 6, 6).contiguous()
    (b,) = pair_dissimilarity_kernel(means, covs)
    ld = float(torch.logdet(covs[0, 0]).abs())
    assert_within(b, 0.0, 16 * 6 * EPS * (1 + 2 * ld), "b of identical components")


def test_a_covariance_that_is_not_positive_definite_gives_nan(gen):
    means = torch.randn(1, 3, 2, generator=gen, dtype=F64)
    covs = random_spd(gen, 1, 3, n=2).clone()
    covs[0, 1] = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=F64)
    (b,) = pair_dissimilarity_kernel(means, covs)
    # pairs (0, 1), (0, 2), (1, 2): the two with component 1 are undefined
    assert torch.isnan(b[0, [0, 2]]).all() and torch.isfinite(b[0, 1])


@pytest.mark.slow
def test_the_compiled_kernel_equals_the_eager_one(gen):
    from agsf_torch.fused.lanes import run_in_chunks

    T, N, n = 40, 16, 6
    means = torch.randn(T, N, n, generator=gen, dtype=F64)
    covs = random_spd(gen, T, N, n=n)
    (eager,) = pair_dissimilarity_kernel(means, covs)
    (compiled,) = run_in_chunks(pair_dissimilarity_kernel, (means, covs), compile=True, key=("merge-bound",))
    _check(compiled, means, covs)
    # the same arithmetic, fused: a log-determinant's rounding apart
    scale = eager.abs() + 1.0
    assert_within(compiled, eager, 16 * n * EPS * 8 * scale, "compiled against eager")
