"""Cholesky factorisation and solves for large batches of small SPD matrices.

LAPACK's batched routines loop over the batch one small matrix at a time; for
``n ≤ 8`` and tens of thousands of matrices (every pair of components of every
trajectory) that loop, not the arithmetic, is the cost.  These versions move the
batch to the last (contiguous) dimension and loop over the ``n`` rows instead,
each row done for the whole batch at once, with the textbook arithmetic
(Cholesky–Banachiewicz and forward/back substitution).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["cholesky", "cholesky_solve", "log_det_from_cholesky"]


def _batch_last(A: Tensor) -> Tensor:
    return A.movedim((-2, -1), (0, 1)).contiguous()


def _batch_first(A: Tensor) -> Tensor:
    return A.movedim((0, 1), (-2, -1))


def cholesky(A: Tensor) -> Tensor:
    """Lower Cholesky factor ``L`` (``A = LLᵀ``) of a batch ``[..., n, n]`` of SPD matrices.

    Raises:
        ValueError: if a matrix is not positive definite (a pivot ≤ 0 or NaN).
    """
    n = A.shape[-1]
    a = _batch_last(A)  # [n, n, ...]
    L = torch.zeros_like(a)
    for i in range(n):
        for j in range(i + 1):
            s = a[i, j] - (L[i, :j] * L[j, :j]).sum(0) if j else a[i, j]
            if i == j:
                if not bool((s > 0).all()):
                    raise ValueError("matrix is not positive definite")
                L[i, i] = s.sqrt()
            else:
                L[i, j] = s / L[j, j]
    return _batch_first(L)


def cholesky_solve(B: Tensor, L: Tensor) -> Tensor:
    """``X = (LLᵀ)⁻¹ B`` by forward and back substitution; ``B [..., n, k]``, ``L [..., n, n]`` lower."""
    n = L.shape[-1]
    shape = torch.broadcast_shapes(L.shape[:-2], B.shape[:-2])
    l = _batch_last(L.expand(*shape, n, n))
    b = _batch_last(B.expand(*shape, *B.shape[-2:]))  # [n, k, ...]
    y = torch.empty_like(b)
    for i in range(n):
        r = b[i] - (l[i, :i].unsqueeze(1) * y[:i]).sum(0) if i else b[i]
        y[i] = r / l[i, i]
    x = torch.empty_like(b)
    for i in reversed(range(n)):
        r = y[i] - (l[i + 1 :, i].unsqueeze(1) * x[i + 1 :]).sum(0) if i < n - 1 else y[i]
        x[i] = r / l[i, i]
    return _batch_first(x)


def log_det_from_cholesky(L: Tensor) -> Tensor:
    """``log det(LLᵀ) = 2 Σ log Lᵢᵢ`` ``[...]``."""
    return 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
