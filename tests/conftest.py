"""Shared fixtures: seeded generators and random attitudes."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)  # one thread per xdist worker: no oversubscription of the cores


@pytest.fixture
def gen() -> torch.Generator:
    """A fixed-seed CPU generator (every test's randomness goes through one)."""
    return torch.Generator().manual_seed(1234)


def random_mrps(num: int, gen: torch.Generator, max_norm: float = 1.0) -> torch.Tensor:
    """Uniformly random attitudes as MRPs ``[num, 3]`` with ``|p| ≤ 1``, scaled to ``max_norm``."""
    q = torch.randn(num, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = q * torch.where(q[:, 3:] < 0, -1.0, 1.0)
    return max_norm * q[:, :3] / (1.0 + q[:, 3:])


@pytest.fixture
def mrps(gen) -> torch.Tensor:
    """4000 random attitudes including rotations near 0°, 180° and 360° (|p| → 0, 1, ∞)."""
    base = random_mrps(4000, gen)
    axis = torch.randn(300, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    tiny = axis[:100] * 1e-9  # ~0°
    half = axis[100:200] * (1.0 - 1e-7)  # ~180°: |p| = tan(45°) = 1
    near_full = axis[200:] * np.tan(np.deg2rad(359.9) / 4)  # ~360°: |p| large
    return torch.cat((base, tiny, half, near_full))
