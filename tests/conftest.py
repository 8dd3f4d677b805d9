"""Shared fixtures: the seeded generator (``pytest --seed N``) and random attitudes."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from tests.helpers import random_mrps

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)  # one thread per xdist worker: no oversubscription of the cores


#: The shared generator's seed unless ``pytest --seed N`` chooses another.
DEFAULT_SEED = 1234


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--seed",
        type=int,
        default=DEFAULT_SEED,
        help=f"seed of the shared random generator fixture `gen` (default {DEFAULT_SEED}); the tests must hold for any",
    )


@pytest.fixture
def gen(request: pytest.FixtureRequest) -> torch.Generator:
    """A seeded CPU generator (every test's randomness goes through one); ``pytest --seed N`` reseeds it."""
    return torch.Generator().manual_seed(request.config.getoption("--seed"))


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
