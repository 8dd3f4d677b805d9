"""Lanes and the unrolled algebra: exact layout round trips, chunking, the compile fallback, structural zeros."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.fused import algebra, lanes
from agsf_torch.fused.lanes import entries, run_in_chunks, stack_entries
from tests.helpers import F64


@pytest.mark.parametrize("shape", [(), (3,), (6, 6), (5, 3)])
def test_entries_round_trip_exactly(gen, shape):
    t = torch.randn(37, *shape, generator=gen, dtype=F64)
    assert torch.equal(stack_entries(entries(t, shape), 37), t)


def _kernel(x, y):
    return (x * 2.0 + y.sum(-1, keepdim=True), (x * x).sum(-1))


@pytest.mark.parametrize("C", [0, 1, 5, 4097, 10_001])
def test_chunked_eager_runs_equal_one_pass(gen, C):
    x, y = torch.randn(C, 3, generator=gen, dtype=F64), torch.randn(C, 2, generator=gen, dtype=F64)
    expected = _kernel(x, y)
    for got, want in zip(run_in_chunks(_kernel, (x, y), chunk=1000), expected):
        assert torch.equal(got, want)


def test_a_failing_compile_falls_back_to_the_eager_kernel_with_one_warning(monkeypatch, gen):
    def broken(fn, **kwargs):
        def compiled(*args):
            raise RuntimeError("no compiler")

        return compiled

    monkeypatch.setattr(torch, "compile", broken)
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


def test_the_compiled_ladder_pads_the_last_chunk_to_a_fixed_size(monkeypatch, gen):
    """Compiled calls see only the ladder's sizes (full chunks of the largest, the rest in the smallest
    size that holds it), and the padding never reaches the result."""
    seen = []

    def recording(fn, **kwargs):
        def compiled(*args):
            seen.append(args[0].shape[0])
            return fn(*args)

        return compiled

    monkeypatch.setattr(torch, "compile", recording)
    monkeypatch.setattr(lanes, "_COMPILED", {})
    big = lanes.CHUNK_SIZES[-1]
    for C in (3, 300, big + 70):
        seen.clear()
        x, y = torch.randn(C, 3, generator=gen, dtype=F64), torch.randn(C, 2, generator=gen, dtype=F64)
        out = run_in_chunks(_kernel, (x, y), compile=True)
        assert all(torch.equal(a, b) for a, b in zip(out, _kernel(x, y)))
        assert set(seen) <= set(lanes.CHUNK_SIZES) and sum(seen) >= C
    assert seen == [big, lanes.CHUNK_SIZES[1]]  # 4096 + 70: one full chunk, the rest in a 512-lane call


def test_structural_zeros_and_ones_emit_no_arithmetic(gen):
    X = [[torch.randn(4, generator=gen, dtype=F64) for _ in range(6)] for _ in range(6)]
    algebra.count(reset=True)
    assert algebra.matmul(algebra.identity(6), X) == X and algebra.count() == 0
    assert algebra.matmul(algebra.zeros(6), X) == algebra.zeros(6) and algebra.count() == 0
    algebra.matmul(X, X)
    assert algebra.count() == 6 * 6 * (6 + 5)  # 6 products and 5 sums per entry of a dense product


def test_the_first_compiled_call_is_announced(monkeypatch, caplog, gen):
    import logging

    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)
    monkeypatch.setattr(lanes, "_COMPILED", {})
    monkeypatch.setattr(lanes, "_RAN", set())
    caplog.set_level(logging.INFO, logger="agsf_torch")
    x, y = torch.randn(5, 3, generator=gen, dtype=F64), torch.randn(5, 2, generator=gen, dtype=F64)
    run_in_chunks(_kernel, (x, y), compile=True)
    run_in_chunks(_kernel, (x, y), compile=True)
    assert [r.getMessage().split(" the fused kernel ")[0] for r in caplog.records] == ["compiling", "compiled"]
    assert "'_kernel' for 64 lanes" in caplog.records[0].getMessage()
