"""Torch's own deprecation warning from inside the library's compiled calls is hidden from library users;
every other warning, and that one raised anywhere else, still shows."""

from __future__ import annotations

import warnings

import torch

from agsf_torch.fused import lanes
from agsf_torch.torch_internals import torch_internal_deprecations_hidden

MESSAGE = "`torch._prims_common.check` is deprecated and will be removed in the future."


def _emit():
    warnings.warn_explicit(MESSAGE, FutureWarning, "lowering.py", 1, module="torch._inductor.lowering", registry={})
    warnings.warn_explicit(MESSAGE, FutureWarning, "ours.py", 1, module="agsf_torch.ours", registry={})
    warnings.warn_explicit(
        "something else", FutureWarning, "lowering.py", 2, module="torch._inductor.lowering", registry={}
    )


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
    assert _shown(_emit) == [(MESSAGE, "lowering.py"), (MESSAGE, "ours.py"), ("something else", "lowering.py")]


def test_a_compiled_fused_kernel_call_hides_it(monkeypatch):
    """The fused layer's compiled call (a stand-in that raises the warnings as inductor does when it compiles)."""

    def compiled_kernel(x):
        _emit()
        return (2.0 * x,)

    monkeypatch.setattr(lanes, "_compiled", lambda kernel, key: compiled_kernel)
    monkeypatch.setattr(lanes, "_RAN", set())
    x = torch.arange(5.0, dtype=torch.float64)
    out = []
    shown = _shown(lambda: out.append(lanes.run_in_chunks(compiled_kernel, [x], compile=True, key=("test",))))
    assert shown == [(MESSAGE, "ours.py"), ("something else", "lowering.py")]
    assert torch.equal(out[0][0], 2.0 * x)
