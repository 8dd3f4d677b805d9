"""Where compiled kernels are kept, and who compiles them: the on-disk cache of :mod:`.lanes`' ahead-of-time kernels.

A compiled kernel is an AOTInductor package in :func:`kernel_cache_dir`, named by a hash of everything its code
depends on (:func:`package_path`: the kernel, its static configuration, the variant and its thread count, the
input dtypes and trailing shapes, the torch version and the source of every module of the package that the
kernel's module imports, directly or through others: :func:`source_closure`, so that an edit of the physics or
the algebra a kernel is built from compiles it again).  A process
compiling one holds its :func:`compile_lock`, so that processes started together compile each kernel once.
Packages are written atomically and, like any new file, readable as the umask allows (``0666`` less the umask),
so that a cache shared by a group serves all its users.  A package that cannot be loaded is judged
(:func:`package_damage`): a damaged one (empty, cut short, a foreign or corrupt archive) is replaced by a new
compilation, a whole one is kept.

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

__all__ = ["kernel_cache_dir", "compile_lock", "package_damage", "source_closure"]

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


_PACKAGE_ROOT = Path(__file__).resolve().parents[1]  # agsf_torch/


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
