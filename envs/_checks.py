"""Validation of configuration numbers, shared by the simulator's components."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["check_real"]


def check_real(owner: str, name: str, value: Any, *, positive: bool = False) -> float:
    """``value`` as a float, or ``ValueError`` naming ``owner``, ``name`` and the value.

    Args:
        positive: require ``> 0`` (default: ``≥ 0``); non-finite values are always rejected.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}: {name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or (v <= 0.0 if positive else v < 0.0):
        raise ValueError(f"{owner}: {name} must be finite and {'> 0' if positive else '≥ 0'}, got {value!r}")
    return v
