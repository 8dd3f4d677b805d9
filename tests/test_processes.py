"""The CPUs this process may use (agsf_torch.processes.available_cpus): joblib's count, which reads the affinity and
the control group's CPU quota."""

from __future__ import annotations

import os

import joblib

from agsf_torch import processes


def test_available_cpus_is_joblibs_count_within_the_affinity():
    cpus = processes.available_cpus()
    assert cpus == joblib.cpu_count(only_physical_cores=False)
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert 1 <= cpus <= usable


def test_available_cpus_follows_a_cap_set_for_joblib(monkeypatch):
    """``LOKY_MAX_CPU_COUNT`` caps the count as a quota would: the rest of the package sizes its threads and
    workers from this one function."""
    monkeypatch.setenv("LOKY_MAX_CPU_COUNT", "1")
    assert processes.available_cpus() == 1
