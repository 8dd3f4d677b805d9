"""Where the C allocator serves a filter step's buffers from: the heap, not fresh memory maps.

Torch allocates CPU tensors with the C library's ``malloc``.  glibc serves a request of at least its *mmap
threshold* with a fresh memory map and unmaps it on ``free``; that threshold starts at 128 KiB and only
grows as such blocks are freed.  A batched filter step allocates and frees the same few-MB intermediates
every step (the penalty update's pair products, the Galerkin matrices, the update's gains), so each step
maps them again and faults every page back in; with the threshold fixed at 32 MiB they come from the heap, at
the same peak memory (the timings: ``agsf bench``, docs/results/performance.md).

:func:`set_mmap_threshold` fixes the threshold (``mallopt(M_MMAP_THRESHOLD, …)``); the ``agsf`` command and
the sweep's Ray tasks call it at their start.  A script of your own calls it once before its filter loop, or
is started with ``MALLOC_MMAP_THRESHOLD_=33554432`` in its environment (which this function then leaves as
it is).  Buffers above the threshold are still mapped and unmapped each time.
"""

from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["set_mmap_threshold", "MAX_MMAP_THRESHOLD"]

#: glibc's largest accepted mmap threshold on 64-bit systems (``4 MiB · sizeof(long)``; larger values are refused).
MAX_MMAP_THRESHOLD = 32 * 1024 * 1024
_M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number
_ENV = "MALLOC_MMAP_THRESHOLD_"


def set_mmap_threshold(nbytes: int = MAX_MMAP_THRESHOLD) -> bool:
    """Serve allocations below ``nbytes`` from the heap, where freed memory is reused without page faults.

    Args:
        nbytes: the threshold (bytes), ``1 ≤ nbytes ≤`` :data:`MAX_MMAP_THRESHOLD` (the default).

    Returns:
        ``True`` if the threshold was set; ``False`` where there is nothing to set (not glibc, e.g. macOS,
        Windows or musl) or when the environment already sets ``MALLOC_MMAP_THRESHOLD_`` (the user's choice
        is kept).

    Raises:
        ValueError: ``nbytes`` not an integer in that range.
    """
    if isinstance(nbytes, bool) or not isinstance(nbytes, int) or not 1 <= nbytes <= MAX_MMAP_THRESHOLD:
        raise ValueError(f"nbytes must be an integer from 1 to {MAX_MMAP_THRESHOLD} (32 MiB), got {nbytes!r}")
    if _ENV in os.environ or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # glibc only: other C libraries' mallopt differ or are absent
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, nbytes))
