"""Lanes: the matrix-major view of a batch of small matrices, and running a kernel over it in chunks.

A batch of ``C`` identically shaped small arrays ``[C, *shape]`` (batch-first, the package's
layout) is seen *matrix-major*: one contiguous ``[C]`` tensor per entry, the *lanes* (the layout
of CMS's Matriplex).  A kernel written on entries (lists of lanes, its small-matrix algebra
unrolled in Python at trace time) then does each entry's arithmetic for every component in one
elementwise operation, and a compiler fuses the whole kernel into one pass over memory.

:func:`run_in_chunks` runs such a kernel over ``C`` lanes in chunks, eagerly or compiled.  Compiled
means *ahead of time*: the kernel is exported (:func:`torch.export.export`) and compiled by inductor
into a shared library (AOTInductor, :func:`torch._inductor.aoti_compile_and_package`) in two variants,
each on first use: for large calls, threaded code for a fixed chunk of :data:`COMPILED_CHUNK` lanes (or
the kernel's own ``compiled_chunk``; every shape known to the compiler; the tail padded), and for smaller
calls serial code for any lane count (a dynamic dimension).  Both are stored in
an on-disk cache (:func:`kernel_cache_dir`) keyed by the kernel, its static configuration, the
variant, the input dtypes and trailing shapes, the torch version and the source of this package's
fused kernels; a later process loads them in milliseconds instead of tracing the kernel again, and
each call skips dynamo's guards.  Each compilation is announced on
the ``agsf_torch`` logger (INFO) when it starts and ends.  A compilation or compiled-run failure falls
back to the eager kernel with one warning (naming the package when it is one that cannot be loaded); the numbers
are the eager ones.  A package in the cache that is damaged (:func:`~.kernel_cache.package_damage`: empty, cut
short, a foreign or corrupt archive) is named in a warning, removed and compiled again by the call that found it.
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
import math
import os
import secrets
import stat
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

from ..processes import available_cpus, interpreter_env
from ..torch_internals import torch_internal_deprecations_hidden
from .kernel_cache import (
    compile_lock,
    held,
    kernel_cache_dir,
    kernel_name,
    package_damage,
    package_path,
    variant_threads,
)

__all__ = [
    "entries",
    "stack_entries",
    "run_in_chunks",
    "worth_fusing",
    "COMPILED_CHUNK",
    "PARALLEL_MIN_LANES",
    "DEFAULT_CHUNK",
    "EAGER_MIN_LANES",
    "kernel_cache_dir",
    "compiling_in_parallel",
    "compile_lock",
]


def worth_fusing(lanes: int, compile: bool) -> bool:
    """Whether a fused kernel beats the generic path for ``lanes`` lanes: always when compiled, eagerly
    from :data:`EAGER_MIN_LANES` on."""
    return compile or lanes >= EAGER_MIN_LANES


logger = logging.getLogger(__name__)

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


class _Declined(Exception):
    """A kernel whose compilation failed before: run it eagerly."""


_COMPILED: dict[tuple, Callable] = {}
_FAILED: set[tuple] = set()
#: The kernels the open :func:`compiling_in_parallel` block of this thread (or task) has deferred (cache path →
#: export job), or ``None``: other threads compile on first call as before.
_PENDING: contextvars.ContextVar[dict[Path, tuple] | None] = contextvars.ContextVar(
    "agsf_pending_kernels", default=None
)


#: Below this many lanes (one chunk of :data:`COMPILED_CHUNK`; of a kernel's own ``compiled_chunk`` where it
#: passes one to :func:`run_in_chunks`) a call takes the kernel's *serial* variant, compiled without OpenMP
#: threads for any lane count (on first use, like the threaded one): padding to a full chunk would multiply
#: the work, and the threaded code's parallel loop would wake the other threads for microseconds of work,
#: whose spin-wait afterwards slows the LAPACK calls that follow.  At least two lanes are passed to it (a single one is padded with a
#: copy): sizes 0 and 1 are special cases of an exported dimension.
PARALLEL_MIN_LANES = COMPILED_CHUNK


def compile_ahead_of_time(
    kernel: Callable,
    inputs: Sequence[Tensor],
    shared: Sequence[Tensor],
    path: Path,
    serial: bool = False,
    threads: int | None = None,
) -> None:
    """Export ``kernel`` and compile it into the package ``path`` (written atomically, with the permissions of any
    new file: ``0666`` less the umask): for the lane count of ``inputs`` (threaded code for ``threads`` OpenMP
    threads, by default this process's torch threads), or with ``serial`` for any lane count ≥ 2 (code without
    OpenMP threads).  The compiler writes the thread count into the code (one thread: no parallel region at all),
    so it is part of the package's name (:func:`package_path`)."""
    from torch._inductor import config as inductor_config
    from torch.export import Dim

    class Kernel(torch.nn.Module):
        def forward(self, *args):
            return kernel(*args)

    dynamic = None
    if serial:
        lanes = Dim("lanes", min=2)
        dynamic = (tuple({0: lanes} for _ in inputs) + tuple(None for _ in shared),)
    program = torch.export.export(Kernel(), (*inputs, *shared), dynamic_shapes=dynamic, strict=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{secrets.token_hex(6)}.tmp.pt2")  # the compiler takes a name ending .pt2
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        mode = stat.S_IMODE(os.fstat(fd).st_mode)  # 0666 less the umask, as for any new file (mkstemp's is 0600)
    finally:
        os.close(fd)
    try:
        with inductor_config.patch({"cpp.threads": 1 if serial else threads or variant_threads(serial)}):
            torch._inductor.aoti_compile_and_package(program, package_path=str(tmp))
        os.chmod(tmp, mode)  # the compiler may have written a file of its own in the name's place
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _load(
    kernel: Callable, key: tuple, inputs: Sequence[Tensor], shared: Sequence[Tensor], serial: bool = False
) -> Callable:
    """The compiled kernel (``serial``: its variant without threads): loaded from the cache, or compiled into it
    first (announced)."""
    path = package_path(kernel, key, inputs, shared, serial)
    name = kernel_name(kernel) + (" (serial)" if serial else "")
    damaged = False
    if path.is_file():
        try:
            return _load_package(path)
        except Exception as exc:  # noqa: BLE001 - the loader's errors name neither the file nor what is wrong with it
            damage = package_damage(path)
            if damage is None:  # whole, but not loadable here: compiling it again would fail alike
                raise RuntimeError(f"cannot load {path} ({type(exc).__name__}: {exc})") from exc
            warnings.warn(
                f"the compiled kernel package {path} is damaged ({damage}): removed, compiling it again",
                RuntimeWarning,
                stacklevel=3,
            )
            damaged = True
    if damaged or not path.is_file():
        with held(compile_lock(path), name):  # another process compiling it: wait for its package, not compile again
            if damaged and path.is_file() and package_damage(path) is not None:  # not yet replaced by another process
                path.unlink(missing_ok=True)
            if not path.is_file():
                logger.info(
                    "compiling the fused kernel %r ahead of time (once per machine and torch version; later processes "
                    "load it from %s)",
                    name,
                    path.parent,
                )
                t0 = time.perf_counter()
                with torch_internal_deprecations_hidden():  # torch's warnings about its own internals, not the user's
                    compile_ahead_of_time(kernel, inputs, shared, path, serial, variant_threads(serial))
                logger.info("compiled the fused kernel %r in %.1f s", name, time.perf_counter() - t0)
    return _load_package(path)


def _load_package(path: Path) -> Callable:
    """The package's kernel: a function of its tensors in call order returning its outputs as a tuple.

    Loaded by torch's C++ package loader directly (what :func:`torch._inductor.aoti_load_package` wraps with
    pytree specs, which for a flat tuple of tensors are the identity) so that a new process does not import
    torch's compiler stack to run a kernel compiled before (most of a first step's time); through
    the public loader where that class is absent."""
    loader_class = getattr(getattr(torch._C, "_aoti", None), "AOTIModelPackageLoader", None)
    if loader_class is None:
        with torch_internal_deprecations_hidden():
            from torch._inductor import aoti_load_package

            return aoti_load_package(str(path))
    loader = loader_class(str(path), "model", False, 1, -1)

    def run(*tensors: Tensor) -> tuple[Tensor, ...]:
        return tuple(loader.boxed_run(list(tensors)))

    return run


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
                if _PENDING.get() is not None and _defer(kernel, key, part, shared, serial):
                    return run_in_chunks(kernel, inputs, shared=shared, compile=False, chunk=chunk)
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


def _defer(kernel: Callable, key: tuple, part: Sequence[Tensor], shared: Sequence[Tensor], serial: bool) -> bool:
    """Inside :func:`compiling_in_parallel`: note a kernel that is not compiled yet (``True``: run it eagerly now)."""
    path = package_path(kernel, key, part, shared, serial)
    if path.is_file():
        return False
    name = kernel_name(kernel) + (" (serial)" if serial else "")
    job = (name, kernel, [t.clone() for t in part], [t.clone() for t in shared], serial, variant_threads(serial))
    _PENDING.get().setdefault(path, job)
    return True


@contextlib.contextmanager
def compiling_in_parallel(processes: int | None = None):
    """Compile the fused kernels a block of code needs side by side, in worker processes, instead of one
    after another as each is first called.

    Inside the block every compiled :func:`run_in_chunks` call whose kernel is not in the cache runs its
    eager kernel instead and is noted (its numbers agree with the compiled kernel's to rounding, not
    bit for bit: the compiler may reorder a division or fuse a multiply-add); when the block ends, the
    noted kernels are compiled into the cache, up to ``processes`` at once (default: one per CPU the
    process may use), each in a new interpreter, announced on the ``agsf_torch`` logger, and later calls
    load them.  The block is meant for a *rehearsal* of a first step whose results are dropped
    (:func:`agsf_torch.filter_loop.prepare_fused_kernels`): the real step then runs compiled, with the
    numbers of a process whose cache was warm, and the wait is the longest compilation, not their sum.
    A kernel whose compilation fails is left to its first later call, which compiles it again or falls
    back to the eager kernel with one warning.  Nested blocks compile at the end of the outermost; an
    exception leaving the block compiles nothing.
    """
    if _PENDING.get() is not None:  # the outer block compiles
        yield
        return
    jobs: dict[Path, tuple] = {}
    token = _PENDING.set(jobs)
    try:
        yield
    finally:
        _PENDING.reset(token)
    if jobs:
        _compile_pending(jobs, processes)


def _compile_pending(jobs: dict[Path, tuple], processes: int | None) -> None:
    """Compile ``jobs`` (cache path → (name, kernel, inputs, shared, serial, threads)) into the cache, up to ``processes``
    at once, each in a new interpreter (:mod:`agsf_torch.fused.compile_worker`: the caller's ``__main__`` is not
    imported again, as a multiprocessing worker would)."""
    import pickle
    import subprocess
    import sys

    from filelock import Timeout

    workers = max(1, min(len(jobs), processes or available_cpus()))
    logger.info(
        "compiling the fused kernels %s ahead of time, %d at once (once per machine, torch version and kernel "
        "source; later processes load them from %s)",
        ", ".join(repr(job[0]) for job in jobs.values()),
        workers,
        kernel_cache_dir(),
    )
    t0 = time.perf_counter()
    env = interpreter_env()  # the caller's imports, in a new interpreter
    queue, running, done, elsewhere = list(jobs.items()), [], 0, []
    with tempfile.TemporaryDirectory(prefix="agsf-kernels-") as scratch:
        try:
            while queue or running:
                while queue and len(running) < workers:
                    path, (name, kernel, inputs, shared, serial, threads) = queue.pop(0)
                    lock = compile_lock(path)
                    try:
                        lock.acquire(timeout=0)
                    except Timeout:  # another process compiles it; this one's first call waits for its package
                        elsewhere.append(name)
                        continue
                    if path.is_file():  # compiled by another process meanwhile
                        lock.release()
                        done += 1
                        continue
                    job = Path(scratch) / f"job{len(queue)}"
                    try:
                        job.with_suffix(".pkl").write_bytes(
                            pickle.dumps((kernel, inputs, shared, str(path), serial, threads))
                        )
                        cmd = [sys.executable, "-m", "agsf_torch.fused.compile_worker", str(job.with_suffix(".pkl"))]
                        # output to files, not pipes: a worker never waits for the parent to read it
                        with open(job.with_suffix(".out"), "w") as out, open(job.with_suffix(".err"), "w") as err:
                            running.append((name, subprocess.Popen(cmd, env=env, stdout=out, stderr=err), job, lock))
                    except Exception as exc:  # noqa: BLE001 - e.g. a local function, which cannot be sent
                        lock.release()
                        _compile_failed(name, exc)
                finished = [r for r in running if r[1].poll() is not None]
                if not finished:
                    time.sleep(0.05)
                    continue
                for name, proc, job, lock in finished:  # a free slot for the next job as soon as any worker ends
                    running.remove((name, proc, job, lock))
                    lock.release()
                    said = job.with_suffix(".out").read_text().split()
                    if proc.returncode == 0 and said:
                        done += 1
                        logger.info("compiled the fused kernel %r in %s s", name, said[-1])
                    else:
                        last = (job.with_suffix(".err").read_text().strip().splitlines() or ["no message"])[-1]
                        _compile_failed(name, RuntimeError(f"worker exit code {proc.returncode}: {last}"))
        finally:  # interrupted: no worker outlives the call
            for _, proc, _, lock in running:
                proc.kill()
                proc.wait()
                lock.release()
    if elsewhere:
        logger.info(
            "the fused kernels %s are being compiled by another process (their first calls wait for them)",
            ", ".join(repr(name) for name in elsewhere),
        )
    logger.info("compiled %d of %d fused kernels in %.1f s", done, len(jobs), time.perf_counter() - t0)


def _compile_failed(name: str, exc: BaseException) -> None:
    logger.warning(
        "compiling the fused kernel %r ahead of time failed (%s: %s); its first call compiles it again",
        name,
        type(exc).__name__,
        exc,
    )
