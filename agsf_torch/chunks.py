"""The size of the chunks a batched evaluation is split into: the one check of the ``chunk_size`` option, shared
by the FPKE matrices, the weight updates that pass it on and the weight QP's batches."""

from __future__ import annotations

import numbers

__all__ = ["check_chunk_size"]


def check_chunk_size(chunk_size: int | None) -> int | None:
    """``chunk_size`` as an ``int ≥ 1`` (or ``None``: sized automatically), else ``ValueError``.

    The one check of the option, shared by the matrices here and the weight updates that
    pass it on (at construction, so that a bad value is refused before any step): zero,
    negative, fractional, bool and non-numeric values are refused.
    """
    if chunk_size is None:
        return None
    ok = isinstance(chunk_size, (numbers.Integral, float)) and not isinstance(chunk_size, bool)
    if not ok or not 1 <= chunk_size < float("inf") or int(chunk_size) != chunk_size:
        raise ValueError(f"chunk_size must be a positive integer or None, got {chunk_size!r}")
    return int(chunk_size)
