"""Will a configuration fit in memory?  An estimate, checked before any work starts.

``agsf run`` keeps every step of every filter for its figures, ``runs.npz`` and
statistics, so its memory grows as ``runs × steps``; the filters' working set grows
as ``runs × components × n²`` and the star camera's as ``runs × max_stars``.
:func:`estimated_memory` adds these up from the configuration alone; the byte counts
per sample are the arrays the runner keeps (:class:`~agsf_torch.experiments.run.runner.FilterTrace`), and
:data:`RETAINED_OVERHEAD` (the per-step tensors, their stacked copies and the numpy
copies written to ``runs.npz`` coexisting at the end of a run) is a multiple of the kept
bytes with a margin above what ``agsf run case1`` peaks at; a slow test
(``tests/experiments/test_outputs.py``) checks the estimate against a measured peak.  :func:`check_memory` refuses a configuration whose estimate exceeds
the memory this machine has available, naming the estimate, the budget and the keys
that drive it; ``force=True`` (``--force`` on the command line) runs it anyway.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from ..config.loader import ExperimentConfig
from .cgroups import memory_headroom

__all__ = [
    "MemoryEstimate",
    "estimated_memory",
    "simulation_memory",
    "available_memory",
    "peak_resident_memory",
    "resident_memory",
    "check_memory",
    "writer_memory",
    "refuse_if_too_large",
    "TooLarge",
]

#: Bytes of a float64.
_F64 = 8
#: Resident memory of a process that has imported torch, numpy, matplotlib and the package (bytes).
BASE_PROCESS = 550 * 2**20
#: Copies of each kept sample alive at the end of a run (per-step tensors, stacked tensors,
#: the numpy arrays of ``runs.npz`` and of the statistics).
RETAINED_OVERHEAD = 3
#: Temporaries of one filter step per covariance entry (prediction, update, Joseph form,
#: the adaptive filter's chunked FPKE integrals).
WORKING_OVERHEAD = 64
#: Diagnostics a filter may record per step and trajectory besides its trace fields.
_EXTRA_DIAGNOSTICS = 16


class TooLarge(ValueError):
    """A configuration's memory estimate exceeds what the machine has."""


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes a configuration needs: ``retained`` (kept steps), ``working`` (one step's
    temporaries and the environment), ``base`` (the process); ``total`` their sum."""

    retained: int
    working: int
    base: int

    @property
    def total(self) -> int:
        return self.retained + self.working + self.base


def estimated_memory(cfg: ExperimentConfig, *, keep_steps: bool = True) -> MemoryEstimate:
    """Estimate the peak memory of running ``cfg`` (bytes).

    With ``N`` components, ``n`` states (3 or 6), ``F`` filters, ``T`` steps, ``B`` runs and
    ``M`` stars per frame:

    .. math::
        retained = c_r · 8 · T · B · Σ_f (n² + 3n + N_f + 5 + e),\\qquad
        working = c_w · 8 · B · (Σ_f N_f n² + 3 M)

    (``N_f = 1`` for the single-Gaussian filters, ``e`` the per-step diagnostics,
    ``c_r`` = :data:`RETAINED_OVERHEAD`, ``c_w`` = :data:`WORKING_OVERHEAD`).
    ``keep_steps=False`` (the soak, which keeps running statistics) drops ``retained``.
    """
    from ...filters.registry import filter_spec

    n = 6 if cfg.estimate_bias else 3
    N = [cfg.components if filter_spec(f).mixture else 1 for f in cfg.filters]
    per_sample = sum(n * n + 3 * n + Nf + 5 + _EXTRA_DIAGNOSTICS for Nf in N)  # cov; estimate, error, sigma; …
    retained = RETAINED_OVERHEAD * _F64 * cfg.num_steps * cfg.runs * per_sample if keep_steps else 0
    working = WORKING_OVERHEAD * _F64 * cfg.runs * (sum(Nf * n * n for Nf in N) + 3 * cfg.max_stars)
    return MemoryEstimate(retained, working, BASE_PROCESS)


def writer_memory(cfg: ExperimentConfig, writers: int) -> int:
    """Memory a run of ``cfg`` shares with ``writers`` file-writing workers (:func:`agsf_torch.experiments.run.file_writer.writing_beside`),
    bytes: the workers (:data:`~agsf_torch.experiments.run.file_writer.WORKER_MEMORY` each) and, where the run's arrays are too large to hand
    to one (:data:`~agsf_torch.experiments.run.file_writer.HANDOVER_BYTES`), one copy of them, which a thread of this process holds while it
    writes the previous run's ``runs.npz`` beside this run.  0 without workers."""
    from .file_writer import HANDOVER_BYTES, WORKER_MEMORY

    if writers == 0:
        return 0
    arrays = estimated_memory(cfg).retained // RETAINED_OVERHEAD
    return writers * WORKER_MEMORY + (arrays if arrays > HANDOVER_BYTES else 0)


def simulation_memory(runs: int, steps: int, max_stars: int) -> MemoryEstimate:
    """Estimate the peak memory of recording ``runs × (steps + 1)`` samples (``agsf simulate``, bytes).

    A sample holds the gyro (3), truth (6) and ``max_stars`` body and inertial vectors
    (6 per star) as float64 and ``max_stars + 1`` flags, kept
    :data:`RETAINED_OVERHEAD` times (per-step tensors, stacked arrays, the archive).
    """
    per_sample = _F64 * (9 + 6 * max_stars) + max_stars + 1
    retained = RETAINED_OVERHEAD * runs * (steps + 1) * per_sample
    working = WORKING_OVERHEAD * _F64 * runs * 3 * max_stars
    return MemoryEstimate(retained, working, BASE_PROCESS)


def _read_int(path: str, prefix: str = "", scale: int = 1) -> int | None:
    """The integer after ``prefix`` on the first matching line of ``path`` (× ``scale``), or None."""
    try:
        with open(path, encoding="ascii") as fh:
            for line in fh:
                if line.startswith(prefix):
                    word = line[len(prefix) :].split()[0]
                    return int(word) * scale if word.isdigit() else None
    except (OSError, IndexError):
        pass
    return None


def _own_memory(field: str) -> int:
    """``field`` of ``/proc/self/status`` (bytes), else ``getrusage``'s max RSS (where there is no ``/proc``)."""
    value = _read_int("/proc/self/status", field, 1024)
    if value is not None:
        return value
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux


def resident_memory() -> int:
    """This process's resident memory now (bytes): ``VmRSS``; its peak where there is no ``/proc``."""
    return _own_memory("VmRSS:")


def peak_resident_memory() -> int:
    """This process's own peak resident memory (bytes): ``VmHWM`` of ``/proc/self/status`` where there is one
    (Linux), else ``getrusage``'s max RSS.  Not ``getrusage`` on Linux: its max RSS survives ``exec``, so a
    process started by a large one reports the parent's resident memory at the fork, not its own."""
    return _own_memory("VmHWM:")


def available_memory() -> int:
    """Memory this process may grow to (bytes), comparable with :attr:`MemoryEstimate.total`:
    what the machine has available (``MemAvailable`` of ``/proc/meminfo``, else the physical
    memory) plus what this process already holds (its resident set, which the estimate counts in
    ``base``); what the machine has is capped by what this process's control groups still allow
    (:func:`agsf_torch.experiments.run.cgroups.memory_headroom`: cgroup v1 or v2, the tightest enclosing group)."""
    page = os.sysconf("SC_PAGE_SIZE")
    free = _read_int("/proc/meminfo", "MemAvailable:", 1024) or page * os.sysconf("SC_PHYS_PAGES")
    headroom = memory_headroom()
    if headroom is not None:
        free = min(free, headroom)
    try:
        with open("/proc/self/statm", encoding="ascii") as fh:
            rss = int(fh.read().split()[1]) * page  # resident pages
    except (OSError, IndexError, ValueError):
        rss = 0
    return free + rss


def _gb(b: int) -> str:
    return f"{b / 2**30:.3g} GB"


def refuse_if_too_large(
    est: MemoryEstimate, what: str, *, force: bool = False, budget: int | None = None
) -> MemoryEstimate:
    """Raise :class:`TooLarge` if ``est.total`` exceeds ``budget`` (default :func:`available_memory`)
    and not ``force``; ``what`` names the work and the keys that drive its size."""
    budget = available_memory() if budget is None else budget
    if est.total > budget and not force:
        raise TooLarge(
            f"{what} needs an estimated {_gb(est.total)} of memory but {_gb(budget)} is available; "
            "make it smaller, or pass --force to run it anyway"
        )
    return est


#: A forked process's own memory beside its parent's, bytes (the pages it writes: its kernels, its figures, the
#: allocator's arenas, with a margin above what one of ``agsf reproduce``'s cases writes), besides its
#: configuration's estimated arrays.
FORKED_PROCESS = 200 * 2**20


def check_memory_side_by_side(configs: list[ExperimentConfig], jobs: int, *, force: bool = False) -> int:
    """Refuse ``configs`` run ``jobs`` at once, each in a forked process (:mod:`agsf_torch.experiments.run.worker_pool`), if the largest ``jobs`` of
    them need more than :func:`available_memory` together: each its :func:`estimated_memory` but the process
    (shared with the parent) plus :data:`FORKED_PROCESS`, and one process.  Returns the estimate (bytes).

    Raises:
        TooLarge: naming the estimate, what is available and ``--jobs 1`` (unless ``force``).
    """
    sizes = sorted((e.retained + e.working + FORKED_PROCESS for e in map(estimated_memory, configs)), reverse=True)
    total = BASE_PROCESS + sum(sizes[:jobs])
    budget = available_memory()
    if total > budget and not force:
        raise TooLarge(
            f"{min(jobs, len(configs))} configurations side by side need an estimated {_gb(total)} of memory but "
            f"{_gb(budget)} is available; run them one after another (--jobs 1), make them smaller, or pass --force "
            "to run them anyway"
        )
    return total


def check_memory(
    cfg: ExperimentConfig, *, force: bool = False, keep_steps: bool = True, budget: int | None = None
) -> MemoryEstimate:
    """Refuse ``cfg`` if :func:`estimated_memory` exceeds ``budget`` (default :func:`available_memory`).

    Raises:
        TooLarge: naming the estimate, the budget and the configuration's driving keys
            (unless ``force``).
    """
    what = (
        f"configuration '{cfg.name}' (runs={cfg.runs}, {cfg.num_steps} steps from duration={cfg.duration:g} and "
        f"dt={cfg.dt:g}, components={cfg.components}, max_stars={cfg.max_stars})"
    )
    return refuse_if_too_large(estimated_memory(cfg, keep_steps=keep_steps), what, force=force, budget=budget)
