"""Torch's own deprecation warnings raised inside the library's compile calls, kept from its users.

Inductor's lowering calls torch's deprecated ``torch._prims_common.check``, and exporting a kernel
(:func:`torch.export.export`, AOTInductor) pickles pytree specs through the deprecated
``isinstance(treespec, LeafSpec)``: compiling any of the library's kernels prints ``FutureWarning`` warnings about
torch's internals that no user of the library can act on.  The library wraps its compile calls in
:func:`torch_internal_deprecations_hidden`, which hides exactly those two warnings (by category and
message) and nothing else.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["torch_internal_deprecations_hidden", "hide_torch_internal_deprecations"]


def hide_torch_internal_deprecations() -> None:
    """Add the filters of :func:`torch_internal_deprecations_hidden` to the current warning filters."""
    warnings.filterwarnings(
        "ignore",
        message=r"`torch\._prims_common\.check` is deprecated",
        category=FutureWarning,
        module=r"torch\._inductor\.",
    )
    warnings.filterwarnings(
        "ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated", category=FutureWarning
    )


@contextmanager
def torch_internal_deprecations_hidden() -> Iterator[None]:
    """While the block runs: torch's ``FutureWarning`` warnings about its own deprecated ``torch._prims_common.check``
    (inductor) and ``isinstance(treespec, LeafSpec)`` (export) are hidden; every other warning is shown as before."""
    with warnings.catch_warnings():
        hide_torch_internal_deprecations()
        yield
