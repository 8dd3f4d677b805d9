"""Worker interpreters: the CPUs this process may use, and the environment of a new interpreter that imports what
its caller imports.

The kernel compiler starts new interpreters (``python -m …``, :func:`agsf_torch.fused.lanes.compiling_in_parallel`),
not spawned multiprocessing children, which would run the caller's ``__main__`` again; the experiments' workers are
a forked :class:`concurrent.futures.ProcessPoolExecutor` (:mod:`agsf_torch.experiments.run.worker_pool`).
"""

from __future__ import annotations

import os
import sys

__all__ = ["available_cpus", "interpreter_env"]


def available_cpus() -> int:
    """The CPUs this process may use, at least 1: :func:`joblib.cpu_count`, the least of the CPU count, this
    process's affinity (``os.sched_getaffinity``), its control group's CPU quota rounded up (a quota of 1.5 CPUs lets
    two threads run half the time each; cgroup v2 ``cpu.max`` or v1 ``cpu.cfs_quota_us`` of the group the container
    sees as its own, as Docker ``--cpus`` and Kubernetes set it) and ``LOKY_MAX_CPU_COUNT`` where it is set."""
    import joblib

    return joblib.cpu_count(only_physical_cores=False)


def interpreter_env(**extra: str) -> dict[str, str]:
    """The environment of a new interpreter: this one's, ``PYTHONPATH`` set to this interpreter's ``sys.path`` (so
    that it imports the same modules, wherever they came from), and ``extra``."""
    paths = [os.fspath(p) for p in sys.path if isinstance(p, (str, os.PathLike)) and os.fspath(p)]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths), **extra}
