"""Fixtures for the environment tests: an isolated catalogue cache and shared cameras."""

from __future__ import annotations

import pytest
import torch

from envs.camera import StarCamera
from envs.catalog import StarCatalog


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """One intra-op thread per test process while an env test runs (restored after).

    The suite runs as ``pytest -n 2`` on 2 cores: two workers with two OpenMP
    threads each oversubscribe the CPU, and torch's many small parallel kernels then
    wait on descheduled threads (measured: a 400-attitude dense camera call went from
    0.12 s to 10 s).  One thread per worker is the right setting for that layout.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session", autouse=True)
def _isolated_cache_dir(tmp_path_factory):
    """Point ``AGSF_CACHE_DIR`` at a per-session temp dir (no writes to the user's home)."""
    mp = pytest.MonkeyPatch()
    mp.setenv("AGSF_CACHE_DIR", str(tmp_path_factory.mktemp("agsf-cache")))
    yield
    mp.undo()


@pytest.fixture(scope="session")
def default_catalog(_isolated_cache_dir) -> StarCatalog:
    """The Hipparcos catalogue at the default magnitude cut."""
    return StarCatalog.from_hipparcos()


@pytest.fixture(scope="session")
def default_camera(default_catalog) -> StarCamera:
    """The default camera (8°×8°, f = 65 mm, 5 stars, σ = 10 µrad, focal-plane noise)."""
    return StarCamera(default_catalog)
