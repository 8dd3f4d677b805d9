"""Shared fixtures: the seeded generator (``pytest --seed N``) and random attitudes."""

from __future__ import annotations

import os
import zlib

import numpy as np
import pytest
import torch

from tests import helpers
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
    parser.addoption(
        "--jitter-ulps",
        type=int,
        default=0,
        help="move the computed side of every assert_within by 1 to K units in the last place of each nonzero entry "
        "(random sign, seeded from --seed and the test's id) before comparing: a bound that holds only where two "
        "code paths round alike fails on every machine (default 0: no jitter)",
    )


def pytest_configure(config: pytest.Config) -> None:
    if config.getoption("--jitter-ulps") < 0:
        raise pytest.UsageError(f"--jitter-ulps must be 0 or more, got {config.getoption('--jitter-ulps')}")


@pytest.fixture(autouse=True)
def _jitter(request: pytest.FixtureRequest):
    """Arm :func:`tests.helpers.assert_within`'s jitter for this test (``--jitter-ulps``), seeded from ``--seed`` and
    the test's id so that a failure reproduces."""
    helpers.JITTER.ulps = request.config.getoption("--jitter-ulps")
    helpers.JITTER.rng = np.random.default_rng(
        [request.config.getoption("--seed"), zlib.crc32(request.node.nodeid.encode())]
    )
    yield
    helpers.JITTER.ulps, helpers.JITTER.rng = 0, None


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


@pytest.fixture(autouse=True)
def _no_compilation_outside_slow_tests(request: pytest.FixtureRequest, monkeypatch, tmp_path_factory) -> None:
    """A test not marked ``slow`` compiles no kernel: compiling takes 10–100 s per kernel on a machine whose caches
    are empty (a user's, a fresh CI runner), so a test that did would pass quickly here, where the caches are warm,
    and take minutes there.  Such tests see an empty kernel cache (``AGSF_TORCH_KERNEL_CACHE``) and fail where a
    kernel would be compiled ahead of time (:mod:`agsf_torch.compiled_kernels`) or with ``torch.compile``; a test that fakes the compiler
    (or runs the compile machinery on kernels that cannot compile) patches these after this fixture and so
    replaces the guard."""
    if request.node.get_closest_marker("slow") is not None:
        return
    from agsf_torch import compiled_kernels
    from agsf_torch.fpke import matrices
    from agsf_torch.fused import lanes

    def refuse(*_args, **_kwargs):
        pytest.fail(
            "this test compiles a kernel (10–100 s on a machine with empty caches): run it eagerly "
            "(compile=false, compile_fused=false) or mark it slow",
            pytrace=False,
        )

    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path_factory.mktemp("kernels")))
    monkeypatch.setattr(compiled_kernels, "compile_ahead_of_time", refuse)
    monkeypatch.setattr(compiled_kernels, "package_program", refuse)
    monkeypatch.setattr(compiled_kernels, "_BY_GRAPH", {})
    monkeypatch.setattr(lanes, "_COMPILED", {})
    monkeypatch.setattr(matrices, "_FAILED", set())
    monkeypatch.setattr(torch, "compile", refuse)
