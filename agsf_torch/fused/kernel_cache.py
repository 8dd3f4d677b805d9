"""Where compiled kernels are kept, and who compiles them: the on-disk cache of :mod:`.lanes`' ahead-of-time kernels.

A compiled kernel is an AOTInductor package in :func:`kernel_cache_dir`, named by a hash of everything its code
depends on (:func:`_package_path`: the kernel, its static configuration, the variant and its thread count, the
input dtypes and trailing shapes, the torch version and the source of the package's fused kernels).  A process
compiling one holds its :func:`compile_lock`, so that processes started together compile each kernel once.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

__all__ = ["kernel_cache_dir", "compile_lock"]

logger = logging.getLogger(__name__)


def kernel_cache_dir() -> Path:
    """Where compiled kernels are kept: ``$AGSF_TORCH_KERNEL_CACHE``, else ``$XDG_CACHE_HOME/agsf-torch/kernels``
    (``~/.cache/agsf-torch/kernels``)."""
    if os.environ.get("AGSF_TORCH_KERNEL_CACHE"):
        return Path(os.environ["AGSF_TORCH_KERNEL_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "agsf-torch" / "kernels"


def _kernel_name(kernel: Callable) -> str:
    return getattr(kernel, "__name__", None) or getattr(getattr(kernel, "func", None), "__name__", "kernel")


def _package_name(kernel: Callable, key: tuple, inputs: Sequence[Tensor], shared: Sequence[Tensor]) -> str:
    """The cache file of a compiled kernel: everything its code depends on, hashed."""
    fused = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(fused.glob("*.py")):  # the kernels and the algebra they are written in
        h.update(path.name.encode() + path.read_bytes())
    func = getattr(kernel, "func", kernel)
    h.update(repr((torch.__version__, func.__module__, func.__qualname__, getattr(kernel, "keywords", {}))).encode())
    h.update(repr((key, [(t.dtype, tuple(t.shape[1:])) for t in inputs])).encode())
    h.update(repr([(t.dtype, tuple(t.shape)) for t in shared]).encode())
    return f"{_kernel_name(kernel)}-{h.hexdigest()[:24]}.pt2"


def _variant_threads(serial: bool) -> int:
    """The OpenMP threads a variant is compiled for: none for the serial one, this process's torch threads for the
    threaded one (the compiler writes the count into the code: :func:`_package_path`)."""
    return 1 if serial else torch.get_num_threads()


def _package_path(
    kernel: Callable, key: tuple, inputs: Sequence[Tensor], shared: Sequence[Tensor], serial: bool
) -> Path:
    """Where the compiled kernel of this call is kept (``inputs``: its export sample): the threaded variant per
    lane count and per thread count (this process's torch threads: a kernel compiled in a one-thread process,
    a test worker's say, has no parallel region, and a two-thread process loaded it and ran 30 % slower)."""
    variant = ("serial",) if serial else ("lanes", inputs[0].shape[0], "threads", _variant_threads(serial))
    return kernel_cache_dir() / _package_name(kernel, key + variant, inputs, shared)


@contextlib.contextmanager
def _held(lock, name: str):
    """``lock`` acquired, announcing the wait when another process holds it (it compiles kernel ``name``)."""
    from filelock import Timeout

    try:
        lock.acquire(timeout=0)
    except Timeout:
        logger.info("waiting for another process compiling the fused kernel %r (%s)", name, lock.lock_file)
        lock.acquire()
    try:
        yield
    finally:
        lock.release()


def compile_lock(path: Path):
    """The lock a process holds while it compiles the package ``path`` (a file lock beside it, ``….pt2.lock``):
    processes started together (``agsf reproduce``'s cases side by side, a sweep's tasks, test workers) compile each
    kernel once, the others waiting for its package or, inside :func:`compiling_in_parallel`, leaving it to the
    process that holds it."""
    from filelock import FileLock

    path.parent.mkdir(parents=True, exist_ok=True)
    return FileLock(f"{path}.lock")
