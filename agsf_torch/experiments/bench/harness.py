"""The benchmark's harness: timing (median after a warm-up; side by side) and its fixtures."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

import agsf_torch

from ...mixture import GaussianMixture

__all__ = [
    "median_time",
    "side_by_side",
    "attitude_mixture",
    "WEIGHT_UPDATE_FILTERS",
    "MANAGED_FILTERS",
    "IMPORT_ROOT",
]

F64 = torch.float64
#: The registered filter of each weight update.
WEIGHT_UPDATE_FILTERS = {"galerkin": "AGSF-galerkin", "penalty": "AGSF"}
#: The registered filters that manage their mixture (:mod:`agsf_torch.filters.management`).
MANAGED_FILTERS = ("GSF-managed", "AGSF-managed", "AGSF-galerkin-managed")
#: The folder this package is imported from (a checkout, or site-packages where it is installed): the benchmark's
#: subprocesses put it first on their path and import the same code.
IMPORT_ROOT = Path(agsf_torch.__file__).resolve().parent.parent


def median_time(fn: Callable[[], Any], repeats: int, budget: float = 60.0) -> float:
    """Median seconds of ``repeats`` calls of ``fn`` after one warm-up call (stops early after ``budget`` s)."""
    fn()  # warm-up
    times = []
    start = time.perf_counter()
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
        if time.perf_counter() - start > budget:
            break
    return statistics.median(times)


def side_by_side(fns: dict[str, Callable[[], Any]], repeats: int) -> dict[str, float]:
    """Median seconds of each function, the functions called in turn (after one warm-up call each)."""
    for fn in fns.values():
        fn()
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t)
    return {k: statistics.median(v) for k, v in times.items()}


def attitude_mixture(B: int, N: int, estimate_bias: bool, gen: torch.Generator) -> GaussianMixture:
    """The benchmark's belief: ``B`` random attitudes (MRP σ 0.3) with the prior ``1e-3`` MRP², ``1e-12`` (rad/s)²,
    split into ``N`` components (6-state with ``estimate_bias``, else 3-state)."""
    from ...mixture import GaussianMixture

    n = 6 if estimate_bias else 3
    p = 0.3 * torch.randn(B, 3, generator=gen, dtype=F64)
    mean = torch.cat((p, torch.zeros(B, 3, dtype=F64)), -1)[:, :n]
    P0 = torch.diag(torch.tensor([1e-3] * 3 + [1e-12] * 3, dtype=F64)[:n])
    return GaussianMixture.from_gaussian(mean, P0.expand(B, n, n), N)
