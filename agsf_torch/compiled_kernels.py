"""Compiled kernels, the one compile path: a function of tensors compiled ahead of time once, kept on disk, loaded.

Every compiled kernel of the package — the fused attitude kernels on lanes (:func:`agsf_torch.fused.lanes.run_in_chunks`)
and the FPKE matrices' node kernels of any model (:mod:`agsf_torch.fpke.matrices`) — is exported
(:func:`torch.export.export`) and compiled by inductor into a shared library (AOTInductor,
:func:`torch._inductor.aoti_compile_and_package`) in the calling process, on its first call, announced on the
``agsf_torch`` logger (INFO) when it starts and ends.  The package is kept in :func:`kernel_cache_dir` under a name
that changes whenever the computation does:

* the package's own kernels (:func:`package_path`): the kernel, its static configuration, the variant and its thread
  count, the input dtypes and trailing shapes, the torch version and the source of every module of the package that
  the kernel's module imports, directly or through others (:func:`source_closure`: an edit of the physics or the
  algebra a kernel is built from compiles it again); a later process loads it without tracing the kernel again;
* a kernel that runs a user's code (a model's ``fokker_planck_terms``, :func:`compiled_function`): the exported
  graph itself (its code, the shapes and dtypes of its inputs, and its constants' values), so that a changed model,
  a changed attribute or a new shape is a new package; it is exported (traced) once per process and shape.

A process compiling a package holds its :func:`compile_lock`, so that processes started together compile each kernel
once.  Packages are written atomically and, like any new file, readable as the umask allows (``0666`` less the
umask), so that a cache shared by a group serves all its users.  A package that cannot be loaded is judged
(:func:`package_damage`): a damaged one (empty, cut short, a foreign or corrupt archive) is named, removed and
compiled again, a whole one is kept and the call runs eagerly.

Kept by hand because no library keeps AOTInductor packages between processes, and the alternative that does,
``torch.compile`` with its own caches, traces every unrolled kernel again in each new process before its first
call: the main job then took about four times as long with every cache warm (the performance page).
"""

from __future__ import annotations

import ast
import contextlib
import functools
import hashlib
import logging
import os
import sys
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

__all__ = [
    "kernel_cache_dir",
    "compile_lock",
    "package_damage",
    "source_closure",
    "package_path",
    "compile_ahead_of_time",
    "load_compiled",
    "load_package",
    "compiled_function",
    "export_kernel",
    "package_program",
    "graph_package_name",
]

logger = logging.getLogger(__name__)


def kernel_cache_dir() -> Path:
    """Where compiled kernels are kept: ``$AGSF_TORCH_KERNEL_CACHE``, else ``$XDG_CACHE_HOME/agsf-torch/kernels``
    (``~/.cache/agsf-torch/kernels``)."""
    if os.environ.get("AGSF_TORCH_KERNEL_CACHE"):
        return Path(os.environ["AGSF_TORCH_KERNEL_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "agsf-torch" / "kernels"


def kernel_name(kernel: Callable) -> str:
    """The name a kernel's packages and messages carry: its function's ``__name__`` (a partial's function's)."""
    return getattr(kernel, "__name__", None) or getattr(getattr(kernel, "func", None), "__name__", "kernel")


_PACKAGE_ROOT = Path(__file__).resolve().parent  # agsf_torch/


def _module_file(name: str) -> Path | None:
    """The source file of the package's module ``name`` (``agsf_torch.x.y``), or None if it is not one."""
    parts = name.split(".")
    if parts[0] != _PACKAGE_ROOT.name:
        return None
    base = _PACKAGE_ROOT.joinpath(*parts[1:])
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _imported_modules(name: str, path: Path) -> set[str]:
    """The package's modules that module ``name`` (its source ``path``) imports anywhere in its code."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            targets = [base] + [f"{base}.{alias.name}" for alias in node.names]  # a name may be a submodule
        else:
            continue
        found.update(t for t in targets if _module_file(t) is not None)
    return found


@functools.cache
def source_closure(module: str) -> tuple[Path, ...]:
    """The source files of ``module`` and of every module of the package it imports, directly or through others
    (read from the code, lazy imports included), sorted: what a kernel defined in ``module`` is built from.  A
    module outside the package contributes its own file."""
    seen: dict[str, Path] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        path = _module_file(name)
        if path is None and name == module and getattr(sys.modules.get(name), "__file__", None):
            path = Path(sys.modules[name].__file__)  # a kernel defined outside the package: its own file
        if name in seen or path is None:
            continue
        seen[name] = path
        todo.extend(_imported_modules(name, path) - seen.keys())
    return tuple(sorted(set(seen.values())))


def package_name(kernel: Callable, key: tuple, inputs: Sequence[Tensor], shared: Sequence[Tensor]) -> str:
    """The cache file of a compiled kernel: everything its code depends on, hashed."""
    func = getattr(kernel, "func", kernel)
    h = hashlib.sha256()
    for path in source_closure(func.__module__):  # the kernel, the physics and the algebra it is written in
        where = path.relative_to(_PACKAGE_ROOT) if path.is_relative_to(_PACKAGE_ROOT) else path
        h.update(str(where).encode() + path.read_bytes())
    h.update(repr((torch.__version__, func.__module__, func.__qualname__, getattr(kernel, "keywords", {}))).encode())
    h.update(repr((key, [(t.dtype, tuple(t.shape[1:])) for t in inputs])).encode())
    h.update(repr([(t.dtype, tuple(t.shape)) for t in shared]).encode())
    return f"{kernel_name(kernel)}-{h.hexdigest()[:24]}.pt2"


def variant_threads(serial: bool) -> int:
    """The OpenMP threads a variant is compiled for: none for the serial one, this process's torch threads for the
    threaded one (the compiler writes the count into the code: :func:`package_path`)."""
    return 1 if serial else torch.get_num_threads()


def package_path(
    kernel: Callable, key: tuple, inputs: Sequence[Tensor], shared: Sequence[Tensor], serial: bool
) -> Path:
    """Where the compiled kernel of this call is kept (``inputs``: its export sample): the threaded variant per
    lane count and per thread count (this process's torch threads: a kernel compiled in a one-thread process,
    a test worker's say, has no parallel region, and a two-thread process loaded it and ran 30 % slower)."""
    variant = ("serial",) if serial else ("lanes", inputs[0].shape[0], "threads", variant_threads(serial))
    return kernel_cache_dir() / package_name(kernel, key + variant, inputs, shared)


@contextlib.contextmanager
def held(lock, name: str):
    """``lock`` acquired, announcing the wait when another process holds it (it compiles kernel ``name``)."""
    from filelock import Timeout

    try:
        lock.acquire(timeout=0)
    except Timeout:
        logger.info("waiting for another process compiling the kernel %r (%s)", name, lock.lock_file)
        lock.acquire()
    try:
        yield
    finally:
        lock.release()


def compile_lock(path: Path):
    """The lock a process holds while it compiles the package ``path`` (a file lock beside it, ``….pt2.lock``):
    processes started together (``agsf reproduce``'s cases side by side, a sweep's tasks, test workers) compile each
    kernel once, the others waiting for its package."""
    from filelock import FileLock

    path.parent.mkdir(parents=True, exist_ok=True)
    return FileLock(f"{path}.lock")


#: A package's members as the compiler writes them (a PT2 archive: one root folder holding ``archive_format``, whose
#: text is ``pt2``, and the compiled model ``model`` under ``data/aotinductor/model/``).
_FORMAT_MEMBER, _FORMAT, _MODEL_FOLDER = "archive_format", b"pt2", "data/aotinductor/model/"


def package_damage(path: Path) -> str | None:
    """What is wrong with the package file ``path``, in words, or ``None`` for a whole compiled-kernel package (or a
    file that cannot be read to judge it: another user's, say).

    A package is a zip archive (a PT2 archive): damaged when empty, cut short (no central directory), a member
    failing its checksum (the loader checks none), or an archive that is not a compiled kernel's."""
    try:
        if path.stat().st_size == 0:
            return "empty"
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            corrupt = archive.testzip()
            formats = [name for name in names if name.split("/", 1)[-1] == _FORMAT_MEMBER]
            package_format = archive.read(formats[0]) if formats else None
    except OSError:
        return None
    except Exception as exc:  # noqa: BLE001 - zipfile's errors for a cut-short or corrupt archive vary
        return f"not a whole zip archive: {type(exc).__name__}: {exc}"
    if corrupt is not None:
        return f"its member {corrupt} fails its checksum"
    if package_format != _FORMAT or not any(name.split("/", 1)[-1].startswith(_MODEL_FOLDER) for name in names):
        return "a zip archive that holds no compiled kernel"
    return None


def export_kernel(kernel: Callable, inputs: Sequence[Tensor], shared: Sequence[Tensor] = (), serial: bool = False):
    """``kernel(*inputs, *shared)`` exported (:func:`torch.export.export`, non-strict): for the shapes of ``inputs``,
    or with ``serial`` for any size ≥ 2 of their leading (lane) dim."""
    from torch.export import Dim

    class Kernel(torch.nn.Module):
        def forward(self, *args):
            return kernel(*args)

    dynamic = None
    if serial:
        lanes = Dim("lanes", min=2)
        dynamic = (tuple({0: lanes} for _ in inputs) + tuple(None for _ in shared),)
    return torch.export.export(Kernel(), (*inputs, *shared), dynamic_shapes=dynamic, strict=False)


def package_program(program, path: Path, threads: int) -> None:
    """Compile the exported ``program`` into the package ``path`` for ``threads`` OpenMP threads (one: code without
    a parallel region), written atomically with the permissions of any new file (``0666`` less the umask)."""
    import secrets
    import stat

    from torch._inductor import config as inductor_config

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{secrets.token_hex(6)}.tmp.pt2")  # the compiler takes a name ending .pt2
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        mode = stat.S_IMODE(os.fstat(fd).st_mode)  # 0666 less the umask, as for any new file (mkstemp's is 0600)
    finally:
        os.close(fd)
    try:
        with inductor_config.patch({"cpp.threads": threads}):
            torch._inductor.aoti_compile_and_package(program, package_path=str(tmp))
        os.chmod(tmp, mode)  # the compiler may have written a file of its own in the name's place
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def compile_ahead_of_time(
    kernel: Callable,
    inputs: Sequence[Tensor],
    shared: Sequence[Tensor],
    path: Path,
    serial: bool = False,
    threads: int | None = None,
) -> None:
    """Export ``kernel`` (:func:`export_kernel`) and compile it into the package ``path``: for the lane count of
    ``inputs`` (threaded code for ``threads`` OpenMP threads, by default this process's torch threads), or with
    ``serial`` for any lane count ≥ 2 (code without OpenMP threads).  The thread count is part of the package's
    name (:func:`package_path`)."""
    program = export_kernel(kernel, inputs, shared, serial)
    package_program(program, path, 1 if serial else threads or variant_threads(serial))


def load_package(path: Path) -> Callable:
    """The package's kernel: a function of its tensors in call order returning its outputs as a tuple.

    Loaded by torch's C++ package loader directly (what :func:`torch._inductor.aoti_load_package` wraps with
    pytree specs, which for a flat tuple of tensors are the identity) so that a new process does not import
    torch's compiler stack to run a kernel compiled before; through the public loader where that class is absent."""
    loader_class = getattr(getattr(torch._C, "_aoti", None), "AOTIModelPackageLoader", None)
    if loader_class is None:
        from .torch_internals import torch_internal_deprecations_hidden

        with torch_internal_deprecations_hidden():
            from torch._inductor import aoti_load_package

            return aoti_load_package(str(path))
    loader = loader_class(str(path), "model", False, 1, -1)

    def run(*tensors: Tensor) -> tuple[Tensor, ...]:
        return tuple(loader.boxed_run(list(tensors)))

    return run


def load_compiled(path: Path, name: str, compile: Callable[[], None]) -> Callable:
    """The compiled kernel in the package ``path``: loaded, or compiled into it first by ``compile()`` (announced on
    the ``agsf_torch`` logger, under :func:`compile_lock`).  A damaged package (:func:`package_damage`) is named in a
    warning, removed and compiled again; a whole one that cannot be loaded raises ``RuntimeError`` naming it."""
    import time
    import warnings

    from .torch_internals import torch_internal_deprecations_hidden

    damaged = False
    if path.is_file():
        try:
            return load_package(path)
        except Exception as exc:  # noqa: BLE001 - the loader's errors name neither the file nor what is wrong with it
            damage = package_damage(path)
            if damage is None:  # whole, but not loadable here: compiling it again would fail alike
                raise RuntimeError(f"cannot load {path} ({type(exc).__name__}: {exc})") from exc
            warnings.warn(
                f"the compiled kernel package {path} is damaged ({damage}): removed, compiling it again",
                RuntimeWarning,
                stacklevel=4,
            )
            damaged = True
    with held(compile_lock(path), name):  # another process compiling it: wait for its package, not compile again
        if damaged and path.is_file() and package_damage(path) is not None:  # not yet replaced by another process
            path.unlink(missing_ok=True)
        if not path.is_file():
            logger.info(
                "compiling the kernel %r ahead of time (once per machine, torch version and kernel; later processes "
                "load it from %s)",
                name,
                path.parent,
            )
            t0 = time.perf_counter()
            with torch_internal_deprecations_hidden():  # torch's warnings about its own internals, not the user's
                compile()
            logger.info("compiled the kernel %r in %.1f s", name, time.perf_counter() - t0)
    return load_package(path)


def graph_package_name(name: str, program, threads: int) -> str:
    """The cache file of an exported ``program``: its graph's code, its inputs' shapes and dtypes, its constants'
    values, the thread count and the torch version, hashed."""
    h = hashlib.sha256(repr((torch.__version__, name, threads)).encode())
    h.update(program.graph_module.code.encode())
    for node in program.graph.nodes:
        if node.op == "placeholder":
            val = node.meta.get("val")
            h.update(repr((node.name, getattr(val, "dtype", None), tuple(getattr(val, "shape", ())))).encode())
    for key, value in sorted({**program.state_dict, **program.constants}.items()):
        h.update(key.encode())
        if torch.is_tensor(value):
            value = value.detach().cpu().contiguous()
            h.update(
                repr((value.dtype, tuple(value.shape))).encode() + value.reshape(-1).view(torch.uint8).numpy().tobytes()
            )
        else:
            h.update(repr(value).encode())
    return f"{name}-{h.hexdigest()[:24]}.pt2"


_BY_GRAPH: dict[tuple, Callable] = {}


def compiled_function(name: str, fn: Callable[..., tuple[Tensor, ...]], args: Sequence[Tensor], identity) -> Callable:
    """``fn`` compiled for the shapes and dtypes of ``args``, keyed by its exported graph (module docstring).

    ``fn`` maps tensors to a tuple of tensors and may run a user's code; ``identity`` (hashable) names what ``fn``
    closes over, as of now (a model and a fingerprint of its attributes, say): within a process the compiled
    function is reused for the same ``(name, identity, shapes, dtypes)``, so that the graph is exported once."""
    memo = (name, identity, tuple((t.dtype, tuple(t.shape)) for t in args), torch.get_num_threads())
    if memo not in _BY_GRAPH:
        from .torch_internals import torch_internal_deprecations_hidden

        with torch_internal_deprecations_hidden():
            program = export_kernel(fn, args)
        threads = variant_threads(False)
        path = kernel_cache_dir() / graph_package_name(name, program, threads)
        _BY_GRAPH[memo] = load_compiled(path, name, lambda: package_program(program, path, threads))
    return _BY_GRAPH[memo]
