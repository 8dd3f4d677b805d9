"""Torch's own deprecation warnings from inside the library's compile calls are hidden from library users;
every other warning, and those raised anywhere else, still show."""

from __future__ import annotations

import warnings

import torch

from agsf_torch import compiled_kernels
from agsf_torch.fused import lanes
from agsf_torch.torch_internals import torch_internal_deprecations_hidden

MESSAGE = "`torch._prims_common.check` is deprecated and will be removed in the future."
LEAF = "`isinstance(treespec, LeafSpec)` is deprecated, use `isinstance(treespec, TreeSpec) and treespec.is_leaf()` instead."


def _emit():
    warnings.warn_explicit(MESSAGE, FutureWarning, "lowering.py", 1, module="torch._inductor.lowering", registry={})
    warnings.warn_explicit(MESSAGE, FutureWarning, "ours.py", 1, module="agsf_torch.ours", registry={})
    warnings.warn_explicit(
        "something else", FutureWarning, "lowering.py", 2, module="torch._inductor.lowering", registry={}
    )
    warnings.warn_explicit(LEAF, FutureWarning, "copyreg.py", 105, module="copyreg", registry={})


def _shown(block) -> list[tuple[str, str]]:
    with warnings.catch_warnings():
        warnings.resetwarnings()  # only the library's own filter (not the test configuration's)
        warnings.simplefilter("default")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")
            block()
    return [(str(w.message), w.filename) for w in caught]


def test_the_context_hides_exactly_torchs_internal_deprecation():
    def block():
        with torch_internal_deprecations_hidden():
            _emit()

    assert _shown(block) == [(MESSAGE, "ours.py"), ("something else", "lowering.py")]
    assert _shown(_emit) == [
        (MESSAGE, "lowering.py"),
        (MESSAGE, "ours.py"),
        ("something else", "lowering.py"),
        (LEAF, "copyreg.py"),
    ]


def test_a_compiled_fused_kernel_call_hides_it(monkeypatch, tmp_path):
    """The fused layer's compile call (a stand-in that raises the warnings as export and inductor do)."""

    def compile_ahead_of_time(kernel, inputs, shared, path, serial, threads=None):
        _emit()
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"package")

    def kernel(x):
        return (2.0 * x,)

    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(lanes, "_COMPILED", {})
    monkeypatch.setattr(compiled_kernels, "compile_ahead_of_time", compile_ahead_of_time)
    monkeypatch.setattr(compiled_kernels, "load_package", lambda path: kernel)
    x = torch.arange(5.0, dtype=torch.float64)
    out = []
    shown = _shown(lambda: out.append(lanes.run_in_chunks(kernel, [x], compile=True, key=("test",))))
    assert shown == [(MESSAGE, "ours.py"), ("something else", "lowering.py")]
    assert torch.equal(out[0][0], 2.0 * x)
