"""Worker interpreters: the CPUs this process may use, and the environment of a new interpreter that imports what
its caller imports.

The package starts new interpreters (``python -m …``), not multiprocessing children, where it hands work to other
processes (compiling kernels side by side, :func:`agsf_torch.fused.lanes.compiling_in_parallel`; writing files,
:class:`agsf_torch.experiments.file_writer.FileWriter`): a multiprocessing child would run the caller's
``__main__`` again.
"""

from __future__ import annotations

import math
import os
import sys

from .cgroups import cpu_limit

__all__ = ["available_cpus", "interpreter_env"]


def available_cpus() -> int:
    """The CPUs this process may use: those it may run on (its affinity where the system reports one, else the CPU
    count), capped by its control groups' CPU quota (:func:`agsf_torch.cgroups.cpu_limit`; rounded up: a quota of
    1.5 CPUs lets two threads run half the time each, as Java's and joblib's CPU counts read it), at least 1."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    quota = cpu_limit()
    return max(1, cpus if quota is None else min(cpus, math.ceil(quota)))


def interpreter_env(**extra: str) -> dict[str, str]:
    """The environment of a new interpreter: this one's, ``PYTHONPATH`` set to this interpreter's ``sys.path`` (so
    that it imports the same modules, wherever they came from), and ``extra``."""
    paths = [os.fspath(p) for p in sys.path if isinstance(p, (str, os.PathLike)) and os.fspath(p)]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths), **extra}
