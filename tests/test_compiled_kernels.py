"""The on-disk cache of compiled kernels (agsf_torch.compiled_kernels, through fused.lanes): a damaged package is named, removed
and compiled again; a package is written atomically with the permissions of any new file (0666 less the umask).

No test compiles: the compiler is stood in for (conftest's guard fails a test that compiles)."""

from __future__ import annotations

import io
import os
import stat
import zipfile
from pathlib import Path

import pytest
import torch

from agsf_torch import compiled_kernels
from agsf_torch.fused import lanes
from agsf_torch.fused.lanes import run_in_chunks
from tests.helpers import F64

#: The real compilation ahead of time (conftest's guard replaces it in every test not marked slow): run here with
#: the exporter and the compiler stood in for.
_COMPILE_AHEAD_OF_TIME = compiled_kernels.compile_ahead_of_time
_PACKAGE_PROGRAM = compiled_kernels.package_program


def _kernel(x, y):
    return (x * 2.0 + y.sum(-1, keepdim=True), (x * x).sum(-1))


def _package() -> bytes:
    """A package as the compiler writes one (a PT2 archive holding model ``model``), with a large member."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("pkg/data/aotinductor/model/c123.wrapper.so", os.urandom(4096))
        archive.writestr("pkg/data/aotinductor/model/c123.wrapper.cpp", "// the kernel")
        archive.writestr("pkg/archive_format", "pt2")
        archive.writestr("pkg/archive_version", "1")
    return buffer.getvalue()


PACKAGE = _package()


def _foreign_zip() -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("hello.txt", "not a kernel")
    return buffer.getvalue()


def _flipped() -> bytes:
    data = bytearray(PACKAGE)
    data[len(data) // 3] ^= 0xFF  # inside the compiled library: a checksum failure
    return bytes(data)


DAMAGED = {
    "empty": b"",
    "truncated": PACKAGE[: len(PACKAGE) // 2],
    "foreign zip": _foreign_zip(),
    "not a zip": b"package" * 100,
    "checksum": _flipped(),
}


@pytest.fixture
def cache(monkeypatch, tmp_path) -> list:
    """A kernel cache in ``tmp_path / "cache"`` whose compiler writes :data:`PACKAGE` (the list of the paths it
    was asked for) and whose loader runs :func:`_kernel` for that package and fails on any other file, as torch's
    does on each of :data:`DAMAGED` (which extracts what it can to a folder it leaves in the temporary directory)."""
    compiled = []

    def fake_compile(kernel, inputs, shared, path, serial, threads=None):
        compiled.append(path)
        path.write_bytes(PACKAGE)

    def load(path):
        if Path(path).read_bytes() == PACKAGE:
            return _kernel
        raise RuntimeError("Failed to initialize zip archive: failed finding central directory")

    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(compiled_kernels, "compile_ahead_of_time", fake_compile)
    monkeypatch.setattr(compiled_kernels, "load_package", load)
    monkeypatch.setattr(lanes, "_COMPILED", {})
    monkeypatch.setattr(lanes, "_FAILED", set())
    return compiled


def _inputs(gen, C=70):
    return torch.randn(C, 3, generator=gen, dtype=F64), torch.randn(C, 2, generator=gen, dtype=F64)


@pytest.mark.parametrize("damage", list(DAMAGED))
def test_a_damaged_package_is_named_removed_and_compiled_again_in_the_same_run(gen, cache, damage):
    x, y = _inputs(gen)
    path = compiled_kernels.package_path(_kernel, (), [x, y], [], True)
    path.parent.mkdir(parents=True)
    path.write_bytes(DAMAGED[damage])
    with pytest.warns(RuntimeWarning) as caught:
        out = run_in_chunks(_kernel, (x, y), compile=True)
    messages = [str(w.message) for w in caught]
    assert len(messages) == 1 and str(path) in messages[0] and "damaged" in messages[0], messages
    assert cache == [path] and path.read_bytes() == PACKAGE  # replaced by a package compiled in this run
    assert all(torch.equal(a, b) for a, b in zip(out, _kernel(x, y)))
    assert any(callable(f) for f in lanes._COMPILED.values())  # later calls run compiled
    assert sorted(p.name for p in path.parent.iterdir() if p.suffix != ".lock") == [path.name]


def test_a_whole_package_that_fails_to_load_is_named_and_kept(gen, cache, monkeypatch):
    """A package that is whole but cannot be loaded here (a loader's failure, not the file's) is named in the
    warning, the call runs eagerly, and the package is not compiled again (it would fail alike)."""
    x, y = _inputs(gen)
    path = compiled_kernels.package_path(_kernel, (), [x, y], [], True)
    path.parent.mkdir(parents=True)
    path.write_bytes(PACKAGE)

    def cannot_load(p):
        raise RuntimeError("cannot map the library")

    monkeypatch.setattr(compiled_kernels, "load_package", cannot_load)
    with pytest.warns(RuntimeWarning, match="running it eagerly") as caught:
        out = run_in_chunks(_kernel, (x, y), compile=True)
    assert (
        len(caught) == 1 and str(path) in str(caught[0].message) and "cannot map the library" in str(caught[0].message)
    )
    assert all(torch.equal(a, b) for a, b in zip(out, _kernel(x, y)))
    assert cache == [] and path.read_bytes() == PACKAGE


@pytest.mark.parametrize("damage", list(DAMAGED))
def test_the_damage_of_a_package_is_said_in_words(tmp_path, damage):
    path = tmp_path / "k.pt2"
    path.write_bytes(DAMAGED[damage])
    assert compiled_kernels.package_damage(path)
    path.write_bytes(PACKAGE)
    assert compiled_kernels.package_damage(path) is None


def _fake_export(module, args, dynamic_shapes=None, strict=False):
    return "exported program"


@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_a_package_is_written_atomically_with_the_permissions_of_any_new_file(tmp_path, monkeypatch, umask):
    """0666 less the umask, as ``open`` creates a file (a cache shared by a group, or read by other users, works
    as for any other cache file); the package appears under its name only when whole."""
    import torch._inductor

    seen = []

    def fake_compile_and_package(program, package_path):
        assert str(package_path).endswith(".pt2") and Path(package_path).parent == tmp_path
        assert not (tmp_path / "k.pt2").exists()  # written under another name first
        seen.append(package_path)
        with open(package_path, "wb") as fh:
            fh.write(PACKAGE)
        os.chmod(package_path, 0o600)  # whatever mode the compiler leaves, the package gets the umask's

    monkeypatch.setattr(torch.export, "export", _fake_export)
    monkeypatch.setattr(compiled_kernels, "package_program", _PACKAGE_PROGRAM)
    monkeypatch.setattr(torch._inductor, "aoti_compile_and_package", fake_compile_and_package)
    x, y = torch.zeros(4, 3, dtype=F64), torch.zeros(4, 2, dtype=F64)
    previous = os.umask(umask)
    try:
        _COMPILE_AHEAD_OF_TIME(_kernel, [x, y], [], tmp_path / "k.pt2", serial=True, threads=1)
    finally:
        os.umask(previous)
    assert len(seen) == 1
    assert stat.S_IMODE((tmp_path / "k.pt2").stat().st_mode) == 0o666 & ~umask
    assert [p.name for p in tmp_path.iterdir()] == ["k.pt2"] and (tmp_path / "k.pt2").read_bytes() == PACKAGE


def test_a_failed_compilation_leaves_no_file(tmp_path, monkeypatch):
    import torch._inductor

    def failing(program, package_path):
        Path(package_path).write_bytes(b"half")
        raise RuntimeError("compiler crashed")

    monkeypatch.setattr(torch.export, "export", _fake_export)
    monkeypatch.setattr(compiled_kernels, "package_program", _PACKAGE_PROGRAM)
    monkeypatch.setattr(torch._inductor, "aoti_compile_and_package", failing)
    x, y = torch.zeros(4, 3, dtype=F64), torch.zeros(4, 2, dtype=F64)
    with pytest.raises(RuntimeError, match="compiler crashed"):
        _COMPILE_AHEAD_OF_TIME(_kernel, [x, y], [], tmp_path / "k.pt2", serial=True, threads=1)
    assert list(tmp_path.iterdir()) == []
