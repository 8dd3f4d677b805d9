"""Torch's own deprecation warnings raised inside the library's ``torch.compile`` calls, kept from its users.

Inductor's lowering calls torch's deprecated ``torch._prims_common.check``: compiling any of the library's
kernels prints a ``FutureWarning`` about torch's internals that no user of the library can act on.  The
library wraps its compiled calls in :func:`torch_internal_deprecations_hidden`, which hides exactly that
warning (by category, message and module) and nothing else.
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


@contextmanager
def torch_internal_deprecations_hidden() -> Iterator[None]:
    """While the block runs: torch's inductor's ``FutureWarning`` about its own deprecated
    ``torch._prims_common.check`` is hidden; every other warning is shown as before."""
    with warnings.catch_warnings():
        hide_torch_internal_deprecations()
        yield
