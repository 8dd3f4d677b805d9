"""Compiling the fused kernels a block needs side by side (agsf_torch.fused.lanes.compiling_in_parallel and its
worker, agsf_torch.fused.compile_worker)."""

from __future__ import annotations

import logging

import pytest
import torch

from agsf_torch.fused import lanes
from agsf_torch.fused.lanes import compiling_in_parallel, run_in_chunks
from tests.helpers import F64, assert_within

#: The real side-by-side compiler (conftest's guard replaces it in every test not marked slow): the two tests that
#: run it give it kernels that cannot compile, so nothing is compiled.
_COMPILE_PENDING = lanes._compile_pending


def _kernel(x, y):
    return (x * 2.0 + y.sum(-1, keepdim=True), (x * x).sum(-1))


def _other_kernel(x, y):
    return (x - y.sum(-1, keepdim=True),)


def _rounding(kernel, x, y):
    """How far a compiled kernel may round from the eager one: ``2x + y₀ + y₁`` and ``x − y₀ − y₁`` take 2 roundings
    of the magnitudes of their terms (in any order, or fused), ``Σx²`` 5 (three squares, two sums); each route within
    ``kε`` of those, 8× headroom as the kernels' own bounds."""
    eps = torch.finfo(F64).eps
    terms = 8 * 2 * eps * ((2 if kernel is _kernel else 1) * x.abs() + y.abs().sum(-1, keepdim=True))
    return (terms, 8 * 5 * eps * (x * x).sum(-1)) if kernel is _kernel else (terms,)


def _failing_kernel(x, y):
    raise RuntimeError("this kernel cannot be traced")


@pytest.fixture
def empty_cache(monkeypatch, tmp_path):
    """An empty kernel cache and no kernel loaded in this process; compilations recorded, not run."""
    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(lanes, "_COMPILED", {})
    monkeypatch.setattr(lanes, "_FAILED", set())
    batches = []
    monkeypatch.setattr(lanes, "_compile_pending", lambda jobs, processes: batches.append(dict(jobs)))
    return batches


def _inputs(gen, C=70):
    return torch.randn(C, 3, generator=gen, dtype=F64), torch.randn(C, 2, generator=gen, dtype=F64)


def test_inside_the_block_missing_kernels_run_eagerly_and_are_compiled_together_at_its_end(gen, empty_cache):
    x, y = _inputs(gen)
    big = _inputs(gen, lanes.PARALLEL_MIN_LANES + 3)
    with compiling_in_parallel():
        out = run_in_chunks(_kernel, (x, y), compile=True)
        run_in_chunks(_kernel, (x, y), compile=True)  # the same kernel again: noted once
        run_in_chunks(_other_kernel, big, compile=True)
        assert empty_cache == []  # nothing compiles before the block ends
    assert all(torch.equal(a, b) for a, b in zip(out, _kernel(x, y)))
    (jobs,) = empty_cache
    assert sorted((job[0], job[4]) for job in jobs.values()) == [("_kernel (serial)", True), ("_other_kernel", False)]
    for path, (name, kernel, inputs, shared, serial, threads) in jobs.items():
        assert path.parent == lanes.kernel_cache_dir() and path.name.startswith(kernel.__name__ + "-")
        # the export sample is what a first call would have compiled: a full chunk for the threaded variant
        assert inputs[0].shape[0] == (x.shape[0] if serial else lanes.COMPILED_CHUNK)
        # the worker compiles for the caller's threads, not its own (the serial variant: one, whatever the caller's)
        assert threads == (1 if serial else torch.get_num_threads())


def test_a_kernel_already_in_the_cache_is_not_noted(gen, empty_cache, monkeypatch):
    x, y = _inputs(gen)
    path = lanes.package_path(_kernel, (), [x, y], [], True)
    path.parent.mkdir(parents=True)
    path.write_bytes(b"package")
    monkeypatch.setattr(lanes, "_load_package", lambda p: _kernel)
    with compiling_in_parallel():
        run_in_chunks(_kernel, (x, y), compile=True)
    assert empty_cache == []


def test_nested_blocks_compile_once_at_the_outermost_end_and_an_exception_compiles_nothing(gen, empty_cache):
    x, y = _inputs(gen)
    with compiling_in_parallel():
        with compiling_in_parallel():
            run_in_chunks(_kernel, (x, y), compile=True)
        assert empty_cache == []
    assert len(empty_cache) == 1
    with pytest.raises(ValueError, match="the step failed"):
        with compiling_in_parallel():
            run_in_chunks(_other_kernel, (x, y), compile=True)
            raise ValueError("the step failed")
    assert len(empty_cache) == 1 and lanes._PENDING.get() is None


def test_outside_a_block_a_kernel_compiles_on_first_call_as_before(gen, empty_cache, monkeypatch):
    loaded = []
    monkeypatch.setattr(lanes, "_load", lambda kernel, key, part, shared, serial: loaded.append(kernel) or kernel)
    x, y = _inputs(gen)
    run_in_chunks(_kernel, (x, y), compile=True)
    assert loaded == [_kernel] and empty_cache == []


def test_a_kernel_a_worker_cannot_compile_is_announced_and_left_to_its_first_call(gen, monkeypatch, tmp_path, caplog):
    """Two jobs in two worker processes: one kernel whose export fails (the worker exits with its message) and
    a local function, which cannot be sent to a worker; neither raises, each is announced as a warning."""
    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    caplog.set_level(logging.INFO, logger="agsf_torch")
    x, y = _inputs(gen, 4)

    def local_kernel(a, b):
        return (a,)

    monkeypatch.setattr(lanes, "_compile_pending", _COMPILE_PENDING)
    jobs = {
        tmp_path / "a.pt2": ("_failing_kernel (serial)", _failing_kernel, [x, y], [], True, 1),
        tmp_path / "b.pt2": ("local_kernel (serial)", local_kernel, [x, y], [], True, 1),
    }
    lanes._compile_pending(jobs, processes=2)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2
    assert any("'_failing_kernel (serial)'" in w and "this kernel cannot be traced" in w for w in warnings)
    assert any("'local_kernel (serial)'" in w for w in warnings)
    assert not list(tmp_path.glob("*.pt2"))


@pytest.mark.slow
def test_kernels_compiled_side_by_side_are_loaded_by_later_calls_and_equal_the_eager_ones(gen, monkeypatch, tmp_path):
    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(lanes, "_COMPILED", {})
    x, y = _inputs(gen)
    with compiling_in_parallel(processes=2):
        run_in_chunks(_kernel, (x, y), compile=True)
        run_in_chunks(_other_kernel, (x, y), compile=True)
    assert len(list(tmp_path.glob("*.pt2"))) == 2
    monkeypatch.setattr(lanes, "compile_ahead_of_time", lambda *a: pytest.fail("compiled again"))
    for kernel in (_kernel, _other_kernel):
        out = run_in_chunks(kernel, (x, y), compile=True)
        # compiled code need not round as eager code does (another order of the sums, contracted multiply–adds)
        for a, b, bound in zip(out, kernel(x, y), _rounding(kernel, x, y)):
            assert_within(a, b, bound, f"output of the compiled {kernel.__name__}")


def test_a_batch_of_kernels_none_of_which_can_be_sent_ends_without_a_worker(gen, monkeypatch, tmp_path, caplog):
    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    caplog.set_level(logging.INFO, logger="agsf_torch")
    x, y = _inputs(gen, 4)
    jobs = {tmp_path / "a.pt2": ("lambda (serial)", lambda a, b: (a,), [x, y], [], True, 1)}
    monkeypatch.setattr("subprocess.Popen", lambda *a, **k: pytest.fail("a worker was started"))
    monkeypatch.setattr(lanes, "_compile_pending", _COMPILE_PENDING)
    lanes._compile_pending(jobs, processes=1)
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING][0].startswith(
        "compiling the fused kernel 'lambda (serial)' ahead of time failed"
    )


def _hold_then_write(path, held, release):
    """Another process's compilation: hold ``path``'s compile lock, then write its package and let go."""
    with lanes.compile_lock(path):
        held.set()
        release.wait(10)
        path.write_bytes(b"package")


def test_a_kernel_another_process_is_compiling_is_waited_for_and_loaded_not_compiled_again(
    gen, monkeypatch, tmp_path, caplog
):
    """Processes started together (reproduce's cases side by side) compile a kernel once: the first call of a kernel
    whose lock another holder has waits for its package (a thread stands in for the other process: the lock is a
    file lock, held per open file)."""
    import threading

    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    x, y = _inputs(gen)
    path = lanes.package_path(_kernel, (), [x, y], [], True)
    held, release = threading.Event(), threading.Event()
    other = threading.Thread(target=_hold_then_write, args=(path, held, release))
    other.start()
    held.wait(10)
    monkeypatch.setattr(lanes, "compile_ahead_of_time", lambda *a: pytest.fail("compiled again"))
    monkeypatch.setattr(lanes, "_load_package", lambda p: ("loaded", p.read_bytes()))
    threading.Timer(0.2, release.set).start()
    caplog.set_level(logging.INFO, logger="agsf_torch")
    assert lanes._load(_kernel, (), [x, y], [], serial=True) == ("loaded", b"package")
    other.join()
    assert "waiting for another process compiling the fused kernel '_kernel (serial)'" in caplog.text


def test_side_by_side_a_kernel_another_process_is_compiling_is_left_to_it(gen, monkeypatch, tmp_path, caplog):
    import subprocess
    import threading

    monkeypatch.setattr(lanes, "_compile_pending", _COMPILE_PENDING)
    caplog.set_level(logging.INFO, logger="agsf_torch")
    x, y = _inputs(gen, 4)
    path = tmp_path / "a.pt2"
    held, release = threading.Event(), threading.Event()
    other = threading.Thread(target=_hold_then_write, args=(path, held, release))
    other.start()
    held.wait(10)
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: pytest.fail("a worker was started"))
    try:
        lanes._compile_pending({path: ("_kernel (serial)", _kernel, [x, y], [], True, 1)}, processes=1)
    finally:
        release.set()
        other.join()
    assert "the fused kernels '_kernel (serial)' are being compiled by another process" in caplog.text
