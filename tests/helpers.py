"""Test data and readers shared by the test modules: random data (the float64 dtype, unit vectors, SPD matrices,
attitudes) and what an experiment wrote (its files' digests, its TensorBoard records).

Every draw goes through an explicit ``torch.Generator`` (the ``gen`` fixture of ``conftest.py``,
seeded by ``pytest --seed``).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch

from agsf_torch.models import ContinuousModel

__all__ = ["F64", "CubicDrift", "random_unit_vectors", "random_spd", "random_mrps", "file_digests", "event_records"]

#: The package's default dtype.
F64 = torch.float64


class CubicDrift(ContinuousModel):
    """A user's model: ``dx = (x − x³) dt + dβ``, ``E[dβ²] = 0.25 dt``; its drift's slope ``1 − 3x²`` is steep far
    from the wells at ±1 (−805.9 1/s at x = 16.4), where an RK4 step of 0.1 s cannot follow it."""

    state_dim = 1

    def drift(self, x, u=None):
        return x - x**3

    def noise_gain(self, x):
        return torch.ones_like(x).unsqueeze(-1)

    def noise_psd(self):
        return torch.full((1, 1), 0.25, dtype=F64)


def random_unit_vectors(gen: torch.Generator, *shape: int) -> torch.Tensor:
    """Uniformly random unit vectors ``[*shape, 3]``."""
    r = torch.randn(*shape, 3, generator=gen, dtype=F64)
    return r / r.norm(dim=-1, keepdim=True)


def random_spd(gen: torch.Generator, *shape: int, n: int = 3, scale: float = 1.0, floor: float = 0.1) -> torch.Tensor:
    """Random symmetric positive definite matrices ``[*shape, n, n]``: ``scale·(AAᵀ/n + floor·I)`` with
    ``A`` standard normal, symmetrised exactly (a rounded ``AAᵀ`` is not; a covariance must be).
    Eigenvalues lie in ``scale·[floor, floor + O(1)]``."""
    A = torch.randn(*shape, n, n, generator=gen, dtype=F64)
    S = scale * (A @ A.transpose(-1, -2) / n + floor * torch.eye(n, dtype=F64))
    return 0.5 * (S + S.transpose(-1, -2))


def random_mrps(num: int, gen: torch.Generator, max_norm: float = 1.0) -> torch.Tensor:
    """Uniformly random attitudes as MRPs ``[num, 3]`` with ``|p| ≤ 1``, scaled to ``max_norm``."""
    q = torch.randn(num, 4, generator=gen, dtype=F64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = q * torch.where(q[:, 3:] < 0, -1.0, 1.0)
    return max_norm * q[:, :3] / (1.0 + q[:, 3:])


#: Configuration overrides that run a preset eagerly: no kernel compiled (a test compiles nothing: conftest's guard).
EAGER = ["compile=false", "compile_fused=false"]
#: ``agsf`` arguments of the smallest run of a preset: 2 runs of 0.3 s, the EKF alone, eager, no progress output.
TINY_CLI = [*(a for s in ("runs=2", "duration=0.3", 'filters=["EKF"]', *EAGER) for a in ("--set", s)), "--quiet"]


def file_digests(root: Path) -> dict[str, str]:
    """Every file under ``root`` (but the TensorBoard events, whose names hold a time) and a digest of its bytes."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and "tfevents" not in p.name and p.name != ".agsf.lock"
    }


def event_records(root: Path) -> dict[str, dict]:
    """Every TensorBoard run under ``root`` (relative path) → its tags → ``[(step, value)]`` (histograms and the
    text as their serialised protos)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    runs = {}
    for run in sorted({p.parent for p in root.rglob("events.out.tfevents.*")}):
        acc = EventAccumulator(str(run), size_guidance={"scalars": 0, "histograms": 0, "tensors": 0})
        acc.Reload()
        tags = acc.Tags()
        events = {t: [(e.step, e.value) for e in acc.Scalars(t)] for t in tags["scalars"]}
        events |= {t: [(e.step, str(e.histogram_value)) for e in acc.Histograms(t)] for t in tags["histograms"]}
        events |= {t: [(e.step, e.tensor_proto.SerializeToString()) for e in acc.Tensors(t)] for t in tags["tensors"]}
        runs[str(run.relative_to(root))] = events
    assert runs
    return runs
