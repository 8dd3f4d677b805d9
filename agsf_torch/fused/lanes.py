"""Lanes: the matrix-major view of a batch of small matrices, and running a kernel over it in chunks.

A batch of ``C`` identically shaped small arrays ``[C, *shape]`` (batch-first, the package's
layout) is seen *matrix-major*: one contiguous ``[C]`` tensor per entry, the *lanes* (the layout
of CMS's Matriplex).  A kernel written on entries (lists of lanes, its small-matrix algebra
unrolled in Python at trace time) then does each entry's arithmetic for every component in one
elementwise operation, and ``torch.compile`` fuses the whole kernel into one pass over memory.

:func:`run_in_chunks` runs such a kernel over ``C`` lanes in fixed-size chunks (the tail padded
by repeating the last lane), eagerly or compiled: one compilation per kernel and chunk size,
reused by every batch size; each compilation is announced on the ``agsf_torch`` logger (INFO)
when it starts and ends.  A compilation or compiled-run failure falls back to the eager kernel
with one warning; the numbers are the eager ones.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from ..torch_internals import torch_internal_deprecations_hidden

__all__ = [
    "entries",
    "stack_entries",
    "run_in_chunks",
    "worth_fusing",
    "CHUNK_SIZES",
    "DEFAULT_CHUNK",
    "EAGER_MIN_LANES",
]


def worth_fusing(lanes: int, compile: bool) -> bool:
    """Whether a fused kernel beats the generic path for ``lanes`` lanes: always when compiled, eagerly
    from :data:`EAGER_MIN_LANES` on."""
    return compile or lanes >= EAGER_MIN_LANES


logger = logging.getLogger(__name__)

#: Lanes per compiled call, a ladder of fixed sizes: full chunks of the largest, the rest in one call
#: of the smallest size that holds it (padded).  One compilation per size actually used, reused by
#: every batch size; a single spacecraft (N lanes) pays for 64 lanes, not 4096.
CHUNK_SIZES = (64, 512, 4096)
#: Lanes per eager call: each of a kernel's thousands of lane operations is one torch call, whose
#: overhead (~3 µs) is paid once per chunk, so eager chunks are large (measured on 2 cores: the Galerkin
#: pairs of 4096 six-state mixtures 228 ms in chunks of 4096, 125 ms of 16384, ~100 ms of 65536); the
#: kernel's temporaries are bounded by it (a few hundred live lanes of 512 KiB).
DEFAULT_CHUNK = 65536
#: Below this many lanes an *eager* fused kernel is slower than the generic batched path (thousands of
#: tiny operations instead of tens of batched ones; measured crossover 500–2000 lanes on 2 cores):
#: models then decline their fused path unless it is compiled.
EAGER_MIN_LANES = 1024


def entries(t: Tensor, shape: Sequence[int]) -> list:
    """``t [C, *shape]`` as nested lists (``shape`` deep) of contiguous ``[C]`` lanes (one lane for ``shape = ()``)."""
    C = t.shape[0]
    k = math.prod(shape)
    flat = t.reshape(C, k).t()  # [k, C]: entry-major
    if flat.stride(-1) != 1:  # a batch-first input is transposed once; an entry-major view is read as it is
        flat = flat.contiguous()
    rows = list(flat.unbind(0))

    def nest(items: list, dims: Sequence[int]) -> list:
        if len(dims) == 1:
            return items
        step = math.prod(dims[1:])
        return [nest(items[i * step : (i + 1) * step], dims[1:]) for i in range(dims[0])]

    return nest(rows, list(shape)) if shape else rows[0]


def stack_entries(nested, lanes: int) -> Tensor:
    """Nested lists of lanes (or numbers) back to batch-first ``[lanes, *shape]``."""

    def flatten(x) -> list:
        if isinstance(x, (list, tuple)):
            return [v for item in x for v in flatten(item)]
        return [x]

    def shape_of(x) -> list[int]:
        return [len(x), *shape_of(x[0])] if isinstance(x, (list, tuple)) else []

    flat = flatten(nested)
    ref = next(v for v in flat if torch.is_tensor(v))
    cols = [
        v.expand(lanes) if torch.is_tensor(v) else torch.full((lanes,), float(v), dtype=ref.dtype, device=ref.device)
        for v in flat
    ]
    return torch.stack(cols, -1).reshape(lanes, *shape_of(nested))


class _Declined(Exception):
    """A kernel whose compilation failed before: run it eagerly."""


_COMPILED: dict[tuple, Callable] = {}
_FAILED: set[tuple] = set()
_RAN: set[tuple] = set()  # compiled kernels that have run once (their compilation announced)


def _compiled(kernel: Callable, key: tuple) -> Callable | None:
    if key in _FAILED:
        return None
    if key not in _COMPILED:
        # one graph per kernel, chunk size and static configuration: more than dynamo's default 8 per function
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
        _COMPILED[key] = torch.compile(kernel, fullgraph=True, dynamic=False)
    return _COMPILED[key]


def run_in_chunks(
    kernel: Callable[..., tuple[Tensor, ...]],
    inputs: Sequence[Tensor],
    *,
    shared: Sequence[Tensor] = (),
    compile: bool = False,
    chunk: int = DEFAULT_CHUNK,
    key: tuple = (),
) -> tuple[Tensor, ...]:
    """``kernel(*inputs)`` over the leading (lane) dim of ``inputs`` in chunks of ``chunk`` lanes.

    Args:
        kernel: maps batch-first tensors ``[c, …]`` to a tuple of batch-first tensors ``[c, …]``,
            lane by lane (no lane reads another).
        inputs: tensors ``[C, …]`` with the same ``C``.
        shared: tensors passed whole to every call after ``inputs`` (0-d parameters such as
            ``dt`` or a noise density: inputs of the compiled kernel, not constants of it).
        compile: run ``torch.compile(kernel)`` in chunks of the fixed sizes :data:`CHUNK_SIZES` (the
            last padded by repeating the last lane); ``False`` runs the same code eagerly.
        chunk: lanes per eager call.
        key: identifies the kernel's static configuration in the compile cache (with ``chunk``).

    Returns:
        The outputs ``[C, …]``.
    """
    C = inputs[0].shape[0]
    shared = tuple(shared)
    if not compile or C == 0:
        if C <= chunk:
            return kernel(*inputs, *shared)
        parts = [kernel(*(t[a : a + chunk] for t in inputs), *shared) for a in range(0, C, chunk)]
        return tuple(torch.cat(p) for p in zip(*parts))
    outs = []
    a = 0
    try:
        while a < C:
            size = CHUNK_SIZES[-1] if C - a >= CHUNK_SIZES[-1] else next(s for s in CHUNK_SIZES if s >= C - a)
            cache_key = (kernel, size, *key, *(t.dtype for t in inputs), *(tuple(t.shape[1:]) for t in inputs))
            fn = _compiled(kernel, cache_key)
            if fn is None:
                raise _Declined
            part = [t[a : a + size].contiguous() for t in inputs]  # one memory layout per compiled graph
            c = part[0].shape[0]
            if c < size:  # pad to the compiled shape with copies of the last lane (harmless, valid data)
                part = [torch.cat((t, t[-1:].expand(size - c, *t.shape[1:]))) for t in part]
            first = cache_key not in _RAN
            if first:
                name = getattr(kernel, "__name__", None) or getattr(getattr(kernel, "func", None), "__name__", "kernel")
                logger.info(
                    "compiling the fused kernel %r for %d lanes with torch.compile (first call only: 30–60 s the "
                    "first time on a machine, seconds once torch's on-disk cache holds it)",
                    name,
                    size,
                )
                t0 = time.perf_counter()
            if first:  # compiling: torch's own deprecation warnings from inductor are not the user's concern
                with torch_internal_deprecations_hidden():
                    result = fn(*part, *shared)
            else:
                result = fn(*part, *shared)
            outs.append(tuple(o[:c] for o in result))
            if first:
                _RAN.add(cache_key)
                logger.info("compiled the fused kernel %r for %d lanes in %.1f s", name, size, time.perf_counter() - t0)
            a += c
    except _Declined:
        return run_in_chunks(kernel, inputs, shared=shared, compile=False, chunk=chunk)
    except Exception as exc:  # noqa: BLE001 - any compiler or runtime failure: the eager path, never a wrong number
        _FAILED.add(cache_key)
        warnings.warn(
            f"compiled kernel {getattr(kernel, '__name__', kernel)} failed ({type(exc).__name__}: {exc}); "
            "running it eagerly",
            RuntimeWarning,
            stacklevel=2,
        )
        return run_in_chunks(kernel, inputs, shared=shared, compile=False, chunk=chunk)
    return outs[0] if len(outs) == 1 else tuple(torch.cat(p) for p in zip(*outs))
