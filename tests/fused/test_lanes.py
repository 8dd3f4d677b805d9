"""Lanes and the unrolled algebra: exact layout round trips, chunking, the compile fallback, structural zeros."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from agsf_torch import compiled_kernels
from agsf_torch.fused import algebra, lanes
from agsf_torch.fused.lanes import entries, run_in_chunks, stack_entries
from tests.helpers import F64, assert_within


@pytest.mark.parametrize("shape", [(), (3,), (6, 6), (5, 3)])
def test_entries_round_trip_exactly(gen, shape):
    t = torch.randn(37, *shape, generator=gen, dtype=F64)
    assert torch.equal(stack_entries(entries(t, shape), 37), t)


def _kernel(x, y):
    return (x * 2.0 + y.sum(-1, keepdim=True), (x * x).sum(-1))


def _kernel_rounding(x, y):
    """How far a compiled ``_kernel`` may round from the eager one: the first output takes 2 roundings of
    ``|2x| + |y₀| + |y₁|`` (the sum of ``y``, then the add: in any order, or fused), the second 5 of ``Σx²`` (three
    squares, two sums); each route within ``kε`` of those, 8× headroom as the kernels' own bounds."""
    eps = torch.finfo(F64).eps
    return 8 * 2 * eps * (2 * x.abs() + y.abs().sum(-1, keepdim=True)), 8 * 5 * eps * (x * x).sum(-1)


@pytest.mark.parametrize("C", [0, 1, 5, 4097, 10_001])
def test_chunked_eager_runs_equal_one_pass(gen, C):
    x, y = torch.randn(C, 3, generator=gen, dtype=F64), torch.randn(C, 2, generator=gen, dtype=F64)
    expected = _kernel(x, y)
    for got, want in zip(run_in_chunks(_kernel, (x, y), chunk=1000), expected):
        assert torch.equal(got, want)


def test_a_failing_compile_falls_back_to_the_eager_kernel_with_one_warning(monkeypatch, gen):
    def broken(*args):
        raise RuntimeError("no compiler")

    monkeypatch.setattr(lanes, "_load", broken)
    monkeypatch.setattr(lanes, "_COMPILED", {})
    monkeypatch.setattr(lanes, "_FAILED", set())
    x, y = torch.randn(70, 3, generator=gen, dtype=F64), torch.randn(70, 2, generator=gen, dtype=F64)
    with pytest.warns(RuntimeWarning, match="no compiler.*running it eagerly"):
        out = run_in_chunks(_kernel, (x, y), compile=True)
    assert all(torch.equal(a, b) for a, b in zip(out, _kernel(x, y)))
    with warnings_as_errors():  # the failure is remembered: later calls are eager without a warning
        run_in_chunks(_kernel, (x, y), compile=True)


class warnings_as_errors:
    def __enter__(self):
        import warnings

        self._ctx = warnings.catch_warnings()
        self._ctx.__enter__()
        warnings.simplefilter("error")

    def __exit__(self, *exc):
        return self._ctx.__exit__(*exc)


def test_compiled_calls_take_full_chunks_or_one_serial_call(monkeypatch, gen):
    """Below PARALLEL_MIN_LANES one call of the serial variant (any lane count; a single lane padded to two, an
    exported dimension starts at 2); from there on the threaded variant, compiled for exactly COMPILED_CHUNK lanes,
    sees only full chunks (the tail padded).  The padding never reaches the result."""
    seen = []

    def recording(kernel, key, inputs, shared, serial):
        assert serial or inputs[0].shape[0] == lanes.COMPILED_CHUNK  # the threaded one is compiled for a chunk

        def compiled(*args):
            seen.append((args[0].shape[0], serial))
            return kernel(*args)

        return compiled

    monkeypatch.setattr(lanes, "_load", recording)
    monkeypatch.setattr(lanes, "_COMPILED", {})
    big, small = lanes.COMPILED_CHUNK, lanes.PARALLEL_MIN_LANES
    cases = (
        (1, [(2, True)]),
        (300, [(300, True)]),
        (small - 1, [(small - 1, True)]),
        (small, [(big, False)]),
        (big + 1, [(big, False), (big, False)]),
        (2 * big + 70, [(big, False)] * 3),
    )
    for C, calls in cases:
        seen.clear()
        x, y = torch.randn(C, 3, generator=gen, dtype=F64), torch.randn(C, 2, generator=gen, dtype=F64)
        out = run_in_chunks(_kernel, (x, y), compile=True)
        assert all(torch.equal(a, b) for a, b in zip(out, _kernel(x, y)))
        assert seen == calls


def test_padding_copies_the_first_lane():
    t = torch.arange(6.0, dtype=F64).reshape(3, 2)
    assert torch.equal(lanes._padded(t, 5), torch.tensor([[0, 1], [2, 3], [4, 5], [0, 1], [0, 1]], dtype=F64))
    assert lanes._padded(t, 2) is t or torch.equal(lanes._padded(t, 2), t)
    assert lanes._padded(t.t(), 1).is_contiguous()


@pytest.fixture
def fake_compiler(monkeypatch, tmp_path) -> list:
    """Compilation ahead of time stood in for, into a cache under ``tmp_path / "cache"``: the list of
    ``(package path, serial, threads)`` it was asked for; a package loads as :func:`_kernel`."""
    compiled = []

    def fake_compile(kernel, inputs, shared, path, serial, threads=None):
        compiled.append((path, serial, threads))
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"package")

    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(compiled_kernels, "compile_ahead_of_time", fake_compile)
    monkeypatch.setattr(compiled_kernels, "load_package", lambda path: _kernel)
    monkeypatch.setattr(lanes, "_COMPILED", {})
    return compiled


def test_the_compilation_is_announced_once_and_kept_on_disk(monkeypatch, caplog, gen, tmp_path, fake_compiler):
    """The first use on a machine compiles (announced, start and end) into the cache; a new process (here: the
    in-memory table cleared) loads the package without compiling."""
    import logging

    def compiled() -> list:  # the packages compiled so far
        return [path for path, _, _ in fake_compiler]

    caplog.set_level(logging.INFO, logger="agsf_torch")
    x, y = torch.randn(5, 3, generator=gen, dtype=F64), torch.randn(5, 2, generator=gen, dtype=F64)
    run_in_chunks(_kernel, (x, y), compile=True)
    run_in_chunks(_kernel, (x, y), compile=True)
    assert [r.getMessage().split(" the kernel ")[0] for r in caplog.records] == ["compiling", "compiled"]
    assert "'_kernel (serial)' ahead of time" in caplog.records[0].getMessage()
    assert len(compiled()) == 1 and compiled()[0].parent == tmp_path / "cache"
    assert compiled()[0].name.startswith("_kernel-")
    monkeypatch.setattr(lanes, "_COMPILED", {})  # a new process
    caplog.clear()
    run_in_chunks(_kernel, (x, y), compile=True)
    assert len(compiled()) == 1 and not caplog.records
    big = lanes.PARALLEL_MIN_LANES  # a large call: the threaded variant, in its own package
    run_in_chunks(_kernel, (torch.randn(big, 3, dtype=F64), torch.randn(big, 2, dtype=F64)), compile=True)
    assert len(compiled()) == 2 and compiled()[1] != compiled()[0] and compiled()[1].name.startswith("_kernel-")
    assert "'_kernel' ahead of time" in caplog.records[0].getMessage()


def test_the_cache_key_follows_what_the_compiled_code_depends_on(gen):
    x, y = torch.randn(5, 3, generator=gen, dtype=F64), torch.randn(5, 2, generator=gen, dtype=F64)
    name = compiled_kernels.package_name(_kernel, ("a",), (x, y), ())
    assert compiled_kernels.package_name(_kernel, ("a",), (x[:2], y[:2]), ()) == name  # the lane count is dynamic
    assert compiled_kernels.package_name(_kernel, ("b",), (x, y), ()) != name  # the static configuration
    assert compiled_kernels.package_name(_kernel, ("a",), (x.float(), y), ()) != name  # dtypes
    assert compiled_kernels.package_name(_kernel, ("a",), (x[:, :2], y), ()) != name  # trailing shapes
    assert compiled_kernels.package_name(_kernel, ("a",), (x, y), (torch.tensor(1.0),)) != name  # shared inputs
    assert compiled_kernels.package_name(lambda a, b: a, ("a",), (x, y), ()) != name  # the kernel


def test_a_kernel_is_compiled_again_when_the_physics_it_is_built_from_changes(monkeypatch):
    """The cache key hashes every module of the package the kernel's module imports, directly or through others:
    the propagation kernel lives in fused/ but is built from attitude/physics.py and fused/algebra.py."""
    from agsf_torch.fused.propagation import attitude_propagation_kernel

    root = Path(compiled_kernels.__file__).resolve().parent
    closure = {
        str(p.relative_to(root)) for p in compiled_kernels.source_closure(attitude_propagation_kernel.__module__)
    }
    assert {"fused/propagation.py", "attitude/physics.py", "fused/algebra.py"} <= closure
    x = torch.zeros(4, 6, dtype=F64)
    name = compiled_kernels.package_name(attitude_propagation_kernel, ("a",), (x,), ())
    physics = root / "attitude" / "physics.py"
    read_bytes = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda p: read_bytes(p) + (b"# edited" if p == physics else b""))
    assert compiled_kernels.package_name(attitude_propagation_kernel, ("a",), (x,), ()) != name


def test_the_kernel_cache_lives_where_the_environment_says(monkeypatch, tmp_path):
    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path / "k"))
    assert compiled_kernels.kernel_cache_dir() == tmp_path / "k"
    monkeypatch.delenv("AGSF_TORCH_KERNEL_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compiled_kernels.kernel_cache_dir() == tmp_path / "xdg" / "agsf-torch" / "kernels"


@pytest.mark.slow
def test_a_kernel_compiled_ahead_of_time_equals_the_eager_one_for_every_lane_count(monkeypatch, gen, tmp_path):
    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(lanes, "_COMPILED", {})
    for C in (1, 7, lanes.PARALLEL_MIN_LANES - 1, lanes.PARALLEL_MIN_LANES, 5000):
        x, y = torch.randn(C, 3, generator=gen, dtype=F64), torch.randn(C, 2, generator=gen, dtype=F64)
        out = run_in_chunks(_kernel, (x, y), compile=True)
        # compiled code need not round as eager code does (another order of the sums, contracted multiply–adds)
        for a, b, bound in zip(out, _kernel(x, y), _kernel_rounding(x, y)):
            assert_within(a, b, bound, f"compiled kernel's output on {C} lanes")
    assert len(list(tmp_path.glob("_kernel-*.pt2"))) == 2  # a serial and a threaded package for every lane count


def test_structural_zeros_and_ones_emit_no_arithmetic(gen):
    X = [[torch.randn(4, generator=gen, dtype=F64) for _ in range(6)] for _ in range(6)]
    algebra.count(reset=True)
    assert algebra.matmul(algebra.identity(6), X) == X and algebra.count() == 0
    assert algebra.matmul(algebra.zeros(6), X) == algebra.zeros(6) and algebra.count() == 0
    algebra.matmul(X, X)
    assert algebra.count() == 6 * 6 * (6 + 5)  # 6 products and 5 sums per entry of a dense product


def test_a_kernel_can_take_its_own_compiled_chunk(monkeypatch, gen):
    """``compiled_chunk``: the threaded variant is compiled for that many lanes and sees only full chunks of it
    (the tail padded), below it one serial call; the same kernel with the default chunk is another variant."""
    seen = []

    def recording(kernel, key, inputs, shared, serial):
        size = None if serial else inputs[0].shape[0]

        def compiled(*args):
            assert serial or args[0].shape[0] == size  # a threaded variant only ever sees its own chunk
            seen.append((args[0].shape[0], serial))
            return kernel(*args)

        return compiled

    monkeypatch.setattr(lanes, "_load", recording)
    monkeypatch.setattr(lanes, "_COMPILED", {})
    for C, chunk, calls in (
        (4, 5, [(4, True)]),
        (5, 5, [(5, False)]),
        (12, 5, [(5, False)] * 3),
        (12, None, [(12, True)]),
        (lanes.COMPILED_CHUNK + 1, None, [(lanes.COMPILED_CHUNK, False)] * 2),
        (11, 5, [(5, False)] * 3),
    ):
        seen.clear()
        x, y = torch.randn(C, 3, generator=gen, dtype=F64), torch.randn(C, 2, generator=gen, dtype=F64)
        out = run_in_chunks(_kernel, (x, y), compile=True, compiled_chunk=chunk)
        assert all(torch.equal(a, b) for a, b in zip(out, _kernel(x, y)))
        assert seen == calls


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "128"])
def test_a_bad_compiled_chunk_is_refused(gen, bad):
    x = torch.randn(4, 3, generator=gen, dtype=F64)
    with pytest.raises(ValueError, match="compiled_chunk must be a positive integer"):
        run_in_chunks(_kernel, (x, x[:, :2]), compile=True, compiled_chunk=bad)


def test_the_threaded_variant_is_kept_per_thread_count(gen, fake_compiler):
    """The compiler writes the thread count into the threaded code (one thread: no parallel region), so a kernel
    compiled in a one-thread process (a test worker) and loaded by a two-thread one ran 30 % slower (the penalty
    step at B = 256: 21–23 ms against 16–18 ms).  The threaded variant is compiled and kept per torch thread
    count, and compiled for that count; the serial one is shared."""
    compiled = fake_compiler
    big = lanes.PARALLEL_MIN_LANES
    args = (torch.randn(big, 3, generator=gen, dtype=F64), torch.randn(big, 2, generator=gen, dtype=F64))
    small = tuple(t[:5] for t in args)
    before = torch.get_num_threads()
    try:
        for threads in (1, 2, 1):
            torch.set_num_threads(threads)
            run_in_chunks(_kernel, args, compile=True)
            run_in_chunks(_kernel, small, compile=True)
    finally:
        torch.set_num_threads(before)
    threaded = [(path, n) for path, serial, n in compiled if not serial]
    assert [n for _, n in threaded] == [1, 2]  # one package per thread count, compiled for it, reused after
    assert threaded[0][0] != threaded[1][0]
    assert sum(serial for _, serial, _ in compiled) == 1  # the serial variant: one package for every count
