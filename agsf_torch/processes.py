"""Worker interpreters: the CPUs this process may use, and the environment of a new interpreter that imports what
its caller imports.

The package starts new interpreters (``python -m …``), not multiprocessing children, where it hands work to other
processes (compiling kernels side by side, :func:`agsf_torch.fused.lanes.compiling_in_parallel`; writing files,
:class:`agsf_torch.experiments.file_writer.FileWriter`): a multiprocessing child would run the caller's
``__main__`` again.
"""

from __future__ import annotations

import os
import sys

__all__ = ["available_cpus", "interpreter_env"]


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity where the system reports one, else the CPU count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def interpreter_env(**extra: str) -> dict[str, str]:
    """The environment of a new interpreter: this one's, ``PYTHONPATH`` set to this interpreter's ``sys.path`` (so
    that it imports the same modules, wherever they came from), and ``extra``."""
    paths = [os.fspath(p) for p in sys.path if isinstance(p, (str, os.PathLike)) and os.fspath(p)]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths), **extra}
