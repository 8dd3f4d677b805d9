"""Runnalls' merge dissimilarity of every pair of a mixture's components, on lanes.

For the components ``i < j`` of each trajectory (``P = N(N−1)/2`` pairs, in the order of
``torch.triu_indices(N, N, 1)``), with ``δ = mᵢ − mⱼ``,

.. math:: b_{ij} = ½\\big[\\log\\det\\big(½P_i + ½P_j + ¼ δδ^T\\big) − ½\\log\\det P_i − ½\\log\\det P_j\\big]

(nats): Runnalls' (2007) bound on the Kullback–Leibler discrimination of the moment-matched merge of the pair
from the pair, at equal weights (:mod:`agsf_torch.filters.management`).  The components' own log-determinants
are taken once per component and gathered to the pairs; each pair's is one ``n×n`` Cholesky factorisation
on lanes (:mod:`agsf_torch.fused.algebra`), so the pairs' ``[T, P, n, n]`` matrices are never formed.  The
kernel knows no model: it reads the means as they are stored (their chart).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .algebra import add, cholesky, mul, sub
from .lanes import entries, pair_index, symmetric_to_pairs, to_pairs

__all__ = ["pair_dissimilarity_kernel"]


def _log_det(P: list) -> tuple[Tensor, Tensor]:
    """``log det P`` from the Cholesky factor's pivots, and whether every pivot was positive."""
    L, _, ok = cholesky(P)
    return 2.0 * sum(L[k][k].log() for k in range(len(P))), ok


def pair_dissimilarity_kernel(means: Tensor, covs: Tensor) -> tuple[Tensor]:
    """``(b [T, P],)``: the dissimilarity ``b_ij`` (module docstring) of the pairs ``i < j`` of each trajectory;
    NaN where a covariance (a component's or the pair's) is not positive definite.

    Args:
        means: ``[T, N, n]``; covs: ``[T, N, n, n]`` (symmetric; the lower triangle is read).
    """
    T, N, n = means.shape
    m_c = entries(means.reshape(T * N, n), (n,))
    P_c = entries(covs.reshape(T * N, n, n), (n, n))
    ld_c, ok_c = _log_det(P_c)
    first, second = pair_index(N, diagonal=False)
    m_i, m_j = ([to_pairs(v, T, N, index) for v in m_c] for index in (first, second))
    P_i, P_j = (symmetric_to_pairs(P_c, T, N, index) for index in (first, second))
    d = [sub(m_i[k], m_j[k]) for k in range(n)]
    A = [
        [add(mul(0.5, add(P_i[a][b], P_j[a][b])), mul(0.25, mul(d[a], d[b]))) if b <= a else None for b in range(n)]
        for a in range(n)
    ]
    ld_pair, ok_pair = _log_det(A)
    ld_i, ld_j = (to_pairs(ld_c, T, N, index) for index in (first, second))
    ok = ok_pair & to_pairs(ok_c, T, N, first) & to_pairs(ok_c, T, N, second)
    b = mul(0.5, sub(ld_pair, mul(0.5, add(ld_i, ld_j))))
    b = torch.where(ok, b, torch.full_like(b, math.nan))
    return (b.reshape(T, len(first)),)
