"""Lanes: the matrix-major view of a batch of small matrices, and running a kernel over it in chunks.

A batch of ``C`` identically shaped small arrays ``[C, *shape]`` (batch-first, the package's
layout) is seen *matrix-major*: one contiguous ``[C]`` tensor per entry, the *lanes* (the layout
of CMS's Matriplex).  A kernel written on entries (lists of lanes, its small-matrix algebra
unrolled in Python at trace time) then does each entry's arithmetic for every component in one
elementwise operation, and a compiler fuses the whole kernel into one pass over memory.

:func:`run_in_chunks` runs such a kernel over ``C`` lanes in chunks, eagerly or compiled ahead of time
(:mod:`agsf_torch.compiled_kernels`, the package's one compile path) in two variants, each on first use: for large
calls, threaded code for a fixed chunk of :data:`COMPILED_CHUNK` lanes (or the kernel's own ``compiled_chunk``; every
shape known to the compiler; the tail padded), and for smaller calls serial code for any lane count (a dynamic
dimension).  A compilation or compiled-run failure falls back to the eager kernel with one warning (naming the
package when it is one that cannot be loaded); the numbers are the eager ones.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .. import compiled_kernels
from ..compiled_kernels import kernel_name, package_path, variant_threads

__all__ = [
    "entries",
    "stack_entries",
    "pair_index",
    "to_pairs",
    "symmetric_to_pairs",
    "run_in_chunks",
    "worth_fusing",
    "COMPILED_CHUNK",
    "PARALLEL_MIN_LANES",
    "DEFAULT_CHUNK",
    "EAGER_MIN_LANES",
]


def worth_fusing(lanes: int, compile: bool) -> bool:
    """Whether a fused kernel beats the generic path for ``lanes`` lanes: always when compiled, eagerly
    from :data:`EAGER_MIN_LANES` on."""
    return compile or lanes >= EAGER_MIN_LANES


#: Lanes per call of a large call's compiled kernel, which is compiled for exactly this many (a tail is
#: padded with copies of its first lane, valid data whose results are dropped: at most this many lanes of
#: waste per call): with every shape known the compiler vectorises and unrolls what a dynamic lane count
#: leaves generic; the chunk size itself matters little, so it is the smallest that vectorises, to bound the
#: padding.
COMPILED_CHUNK = 1024
#: Lanes per eager call: each of a kernel's thousands of lane operations is one torch call, whose
#: overhead is paid once per chunk, so eager chunks are large; the kernel's temporaries are bounded by it
#: (a few hundred live lanes of 512 KiB).
DEFAULT_CHUNK = 65536
#: Below this many lanes an *eager* fused kernel is slower than the generic batched path (thousands of
#: tiny operations instead of tens of batched ones):
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
    """Nested lists of lanes (or numbers, or ``None``: a structural zero) back to batch-first ``[lanes, *shape]``."""

    def flatten(x) -> list:
        if isinstance(x, (list, tuple)):
            return [v for item in x for v in flatten(item)]
        return [x]

    def shape_of(x) -> list[int]:
        return [len(x), *shape_of(x[0])] if isinstance(x, (list, tuple)) else []

    flat = flatten(nested)
    ref = next(v for v in flat if torch.is_tensor(v))
    cols = [
        v.expand(lanes)
        if torch.is_tensor(v)
        else torch.full((lanes,), 0.0 if v is None else float(v), dtype=ref.dtype, device=ref.device)
        for v in flat
    ]
    return torch.stack(cols, -1).reshape(lanes, *shape_of(nested))


def pair_index(N: int, *, diagonal: bool = True) -> tuple[list[int], list[int]]:
    """The pairs ``i ≤ j`` (``diagonal=False``: ``i < j``) of ``N`` components, in the order of
    ``torch.triu_indices(N, N)`` (``torch.triu_indices(N, N, 1)``): the first and the second index of each."""
    pairs = [(i, j) for i in range(N) for j in range(i if diagonal else i + 1, N)]
    return [i for i, _ in pairs], [j for _, j in pairs]


def to_pairs(v, T: int, N: int, index: list[int]):
    """One entry over ``T·N`` component lanes (trajectory-major) → over ``T·P`` pair lanes, taking
    component ``index[p]`` for pair ``p`` (structural zeros, numbers and 0-d parameters such as ``σ_u²``
    pass through: they are the same on every lane)."""
    if not isinstance(v, Tensor) or v.dim() == 0:
        return v
    return v.reshape(T, N)[:, index].reshape(-1)


def symmetric_to_pairs(A: list, T: int, N: int, index: list[int]) -> list:
    """A symmetric matrix's entries taken to the pairs (:func:`to_pairs`; the lower triangle, mirrored)."""
    n = len(A)
    low = [[to_pairs(A[i][j], T, N, index) for j in range(i + 1)] for i in range(n)]
    return [[low[i][j] if j <= i else low[j][i] for j in range(n)] for i in range(n)]


class _Declined(Exception):
    """A kernel whose compilation failed before: run it eagerly."""


_COMPILED: dict[tuple, Callable] = {}
_FAILED: set[tuple] = set()


#: Below this many lanes (one chunk of :data:`COMPILED_CHUNK`; of a kernel's own ``compiled_chunk`` where it
#: passes one to :func:`run_in_chunks`) a call takes the kernel's *serial* variant, compiled without OpenMP
#: threads for any lane count (on first use, like the threaded one): padding to a full chunk would multiply
#: the work, and the threaded code's parallel loop would wake the other threads for microseconds of work,
#: whose spin-wait afterwards slows the LAPACK calls that follow.  At least two lanes are passed to it (a single one is padded with a
#: copy): sizes 0 and 1 are special cases of an exported dimension.
PARALLEL_MIN_LANES = COMPILED_CHUNK


def _load(
    kernel: Callable, key: tuple, inputs: Sequence[Tensor], shared: Sequence[Tensor], serial: bool = False
) -> Callable:
    """The compiled kernel (``serial``: its variant without threads): loaded from the cache, or compiled into it."""
    path = package_path(kernel, key, inputs, shared, serial)
    name = kernel_name(kernel) + (" (serial)" if serial else "")

    def compile() -> None:
        compiled_kernels.compile_ahead_of_time(kernel, inputs, shared, path, serial, variant_threads(serial))

    return compiled_kernels.load_compiled(path, name, compile)


def _padded(t: Tensor, lanes: int) -> Tensor:
    """``t [c, …]`` contiguous with at least ``lanes`` lanes: the missing ones copies of its first (valid data,
    whatever the kernel; their results are dropped)."""
    c = t.shape[0]
    if c < lanes:
        t = torch.cat((t, t[:1].expand(lanes - c, *t.shape[1:])))
    return t.contiguous()


def run_in_chunks(
    kernel: Callable[..., tuple[Tensor, ...]],
    inputs: Sequence[Tensor],
    *,
    shared: Sequence[Tensor] = (),
    compile: bool = False,
    chunk: int = DEFAULT_CHUNK,
    key: tuple = (),
    compiled_chunk: int | None = None,
) -> tuple[Tensor, ...]:
    """``kernel(*inputs)`` over the leading (lane) dim of ``inputs`` in chunks of ``chunk`` lanes.

    Args:
        kernel: maps batch-first tensors ``[c, …]`` to a tuple of batch-first tensors ``[c, …]``,
            lane by lane (no lane reads another).
        inputs: tensors ``[C, …]`` with the same ``C``.
        shared: tensors passed whole to every call after ``inputs`` (0-d parameters such as
            ``dt`` or a noise density: inputs of the compiled kernel, not constants of it).
        compile: run the kernel compiled ahead of time (module docstring): in chunks of
            ``compiled_chunk`` lanes (the tail padded), or in one serial call below that many;
            ``False`` runs the same code eagerly.
        chunk: lanes per eager call.
        key: identifies the kernel's static configuration in the compile cache.
        compiled_chunk: lanes per call of the threaded compiled variant, a positive integer (``None``:
            :data:`COMPILED_CHUNK`); a kernel whose lanes each carry many temporaries (a row of quadrature
            nodes, say) takes fewer, so that its temporaries stay in cache.

    Returns:
        The outputs ``[C, …]``.
    """
    if compiled_chunk is None:
        compiled_chunk = COMPILED_CHUNK
    elif isinstance(compiled_chunk, bool) or not isinstance(compiled_chunk, int) or compiled_chunk < 1:
        raise ValueError(f"compiled_chunk must be a positive integer, got {compiled_chunk!r}")
    C = inputs[0].shape[0]
    shared = tuple(shared)
    if not compile or C == 0:
        if C <= chunk:
            return kernel(*inputs, *shared)
        parts = [kernel(*(t[a : a + chunk] for t in inputs), *shared) for a in range(0, C, chunk)]
        return tuple(torch.cat(p) for p in zip(*parts))
    serial = C < compiled_chunk  # below one chunk: the serial variant (PARALLEL_MIN_LANES for the default)
    chunk_lanes = None if serial else compiled_chunk  # the threaded variant is compiled for its chunk
    shapes = (*(t.dtype for t in inputs), *(tuple(t.shape[1:]) for t in inputs))
    cache_key = (kernel, chunk_lanes, variant_threads(serial), *key, *shapes)
    try:
        if cache_key in _FAILED:
            raise _Declined
        floor = 2 if serial else compiled_chunk  # the lanes a compiled call takes at least
        step = C if serial else compiled_chunk
        outs = []
        for a in range(0, C, step):
            # contiguous, as the compiled code assumes the strides it was exported with
            part = [_padded(t[a : a + step], floor) for t in inputs]
            if cache_key not in _COMPILED:  # the first chunk is the export's sample
                _COMPILED[cache_key] = _load(kernel, key, part, shared, serial)
            c = min(step, C - a)
            outs.append(tuple(o if o.shape[0] == c else o[:c] for o in _COMPILED[cache_key](*part, *shared)))
    except _Declined:
        return run_in_chunks(kernel, inputs, shared=shared, compile=False, chunk=chunk)
    except Exception as exc:  # noqa: BLE001 - any compiler or runtime failure: the eager path, never a wrong number
        _FAILED.add(cache_key)
        why = " ".join(str(exc).split())  # the loader's messages run over several lines
        warnings.warn(
            f"compiled kernel {kernel_name(kernel)} failed ({type(exc).__name__}: {why}); running it eagerly",
            RuntimeWarning,
            stacklevel=2,
        )
        return run_in_chunks(kernel, inputs, shared=shared, compile=False, chunk=chunk)
    return outs[0] if len(outs) == 1 else tuple(torch.cat(p) for p in zip(*outs))
