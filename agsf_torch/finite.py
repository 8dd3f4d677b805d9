"""Finiteness checks: one reduction per tensor instead of a boolean mask.

``bool(torch.isfinite(t).all())`` allocates a boolean tensor as large as ``t`` and reads it again;
for the ``[B, N, n, n]`` covariances of a batched step that is a large temporary per check.  The extremes of
``t`` carry the same answer in one pass without a temporary: ``torch.aminmax`` propagates NaN, and a ``±inf``
entry is an
extreme, so every entry is finite exactly when both extremes are.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["all_finite", "check_finite"]


def all_finite(*tensors: Tensor) -> bool:
    """Whether every entry of every tensor is finite (no NaN, no ``±inf``); integer and boolean tensors
    always are, and an empty tensor is.

    Args:
        tensors: any shapes and dtypes.
    """
    for t in tensors:
        if t.numel() == 0 or not (t.is_floating_point() or t.is_complex()):
            continue
        if t.is_complex():  # no extremes of complex numbers
            if not bool(torch.isfinite(t).all()):
                return False
            continue
        lo, hi = torch.aminmax(t)
        if not (bool(torch.isfinite(lo)) and bool(torch.isfinite(hi))):
            return False
    return True


def check_finite(name: str, value: Tensor) -> None:
    """Raise ``ValueError`` naming ``name`` and the first non-finite entry's index if ``value`` holds a
    NaN or ``±inf``."""
    if not all_finite(value):
        bad = (~torch.isfinite(value)).nonzero()
        raise ValueError(f"{name} must be finite; non-finite entry at index {tuple(bad[0].tolist())}")
