"""The fused paths' measurements: landed (generic) and fused rows side by side, with the peers.

* :func:`bench_propagation` — the GSF's predict, 6-state N = 5 B = 8192: the generic path, the
  fused kernel eagerly and compiled, a filterpy loop, a NumPy batch and JAX ``jit(vmap(step))``
  (:mod:`.peers`), all doing the RK4 ``(μ, Φ, S)`` step (ours also the chart switch and the
  definiteness check); and the fraction of the float64 matmul peak the compiled kernel reaches
  (its FLOPs counted from the unrolled graph, :func:`agsf_torch.fused.algebra.count`);
* :func:`bench_update` — the GSF's star update (5 stars), 6-state N = 5 B = 4096, generic and fused;
* :func:`bench_spacecraft` — one spacecraft (B = 1, N = 5, 6-state): predict + star update, generic
  and fused compiled, beside filterpy's EKF over the same components;
* :func:`bench_compile` — the first fused step (predict + update, compiled) in a new process with
  torch's on-disk cache empty (cold) and filled (warm).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import torch

from .harness import IMPORT_ROOT, attitude_mixture, side_by_side

__all__ = ["bench_propagation", "bench_update", "bench_spacecraft", "bench_compile", "propagation_kernel_flops"]

F64 = torch.float64


def _filters(compile: bool):
    from ...filters.registry import make_filter
    from ...models import AttitudeModel

    model = AttitudeModel(estimate_bias=True)
    rows = {"landed (generic)": make_filter("GSF", model, fused=False), "fused eager": make_filter("GSF", model)}
    if compile:
        rows["fused compiled"] = make_filter("GSF", model, compile_fused=True)
    return rows


def _star_problem(B: int, M: int = 5, sigma: float = 1e-5):
    from ...models import StarVectorMeasurement
    from ...rotations import mrp_to_dcm

    gen = torch.Generator().manual_seed(3)
    r = torch.randn(B, M, 3, generator=gen, dtype=F64)
    r = r / r.norm(dim=-1, keepdim=True)
    p = 0.3 * torch.randn(B, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    y = (mrp_to_dcm(p)[:, None] @ r.unsqueeze(-1)).squeeze(-1).reshape(B, 3 * M)
    return y, StarVectorMeasurement(r, None, sigma)


def propagation_kernel_flops(n: int, substeps: int = 1) -> int:
    """Floating-point operations per component of the fused propagation kernel, counted from its unrolled
    graph (one lane operation = one FLOP per component; structural zeros and ones emit none)."""
    from ...fused import algebra
    from ...fused.propagation import attitude_propagation_kernel

    x = torch.zeros(2, n, dtype=F64)
    P = torch.eye(n, dtype=F64).expand(2, n, n).contiguous()
    algebra.count(reset=True)
    s = torch.tensor(1.0, dtype=F64)
    attitude_propagation_kernel(x, P, torch.zeros(2, 3, dtype=F64), s, s, s, substeps)
    return algebra.count(reset=True)


def bench_propagation(
    B: int = 8192,
    N: int = 5,
    repeats: int = 5,
    compile: bool = True,
    filterpy_samples: int = 2000,
    peak_flops: float | None = None,
) -> dict[str, Any]:
    """Component-steps/s of the GSF predict (generic, fused eager, fused compiled) and of the peers."""
    from .peers import filterpy_loop, jax_batch, numpy_batch

    mix = attitude_mixture(B, N, True, torch.Generator().manual_seed(1))
    u = torch.full((B, 3), 0.06, dtype=F64)
    sec = side_by_side({k: (lambda f=f: f.predict(mix, u, 0.1)) for k, f in _filters(compile).items()}, repeats)
    rows = {k: B * N / s for k, s in sec.items()}
    peers = {"filterpy": filterpy_loop(filterpy_samples), "numpy": numpy_batch(B * N), "jax": jax_batch(B * N)}
    best = rows.get("fused compiled", rows["fused eager"])
    flops = propagation_kernel_flops(6)
    out = {
        "B": B,
        "N": N,
        "component_steps_per_s": rows,
        "peers": peers,
        "vs": {k: best / v["component_steps_per_s"] for k, v in peers.items() if "component_steps_per_s" in v},
        "vs_landed": best / rows["landed (generic)"],
        "kernel_flops_per_component_step": flops,
    }
    if peak_flops:
        out["fraction_of_peak"] = best * flops / peak_flops
    return out


def bench_update(B: int = 4096, N: int = 5, repeats: int = 5, compile: bool = True) -> dict[str, Any]:
    """Seconds of the GSF star update (5 stars), generic and fused (eager, compiled)."""
    mix = attitude_mixture(B, N, True, torch.Generator().manual_seed(1))
    y, meas = _star_problem(B)
    sec = side_by_side({k: (lambda f=f: f.update(mix, y, meas)) for k, f in _filters(compile).items()}, repeats)
    best = sec.get("fused compiled", sec["fused eager"])
    return {"B": B, "N": N, "stars": 5, "seconds": sec, "speedup": sec["landed (generic)"] / best}


def bench_spacecraft(N: int = 5, repeats: int = 50, compile: bool = True) -> dict[str, Any]:
    """Seconds per predict + star update of one spacecraft (B = 1), ours and filterpy's."""
    from .peers import filterpy_spacecraft

    mix = attitude_mixture(1, N, True, torch.Generator().manual_seed(1))
    u = torch.full((1, 3), 0.06, dtype=F64)
    y, meas = _star_problem(1)
    rows = {k: (lambda f=f: f.update(f.predict(mix, u, 0.1), y, meas)) for k, f in _filters(compile).items()}
    sec = side_by_side(rows, repeats)
    fp = filterpy_spacecraft(N)
    best = sec.get("fused compiled", sec["fused eager"])
    return {"N": N, "seconds": sec, "filterpy": fp, "best_seconds": best, "vs_filterpy": fp["seconds"] / best}


_FIRST_FUSED_STEP = """
import time, sys
t0 = time.perf_counter()
import torch
sys.path.insert(0, {root!r})
from agsf_torch.experiments.bench.fused import _star_problem
from agsf_torch.experiments.bench.harness import attitude_mixture
from agsf_torch.filters.registry import make_filter
from agsf_torch.models import AttitudeModel
filt = make_filter("GSF", AttitudeModel(estimate_bias=True), compile_fused=True)
mix = attitude_mixture(256, 5, True, torch.Generator().manual_seed(0))
y, meas = _star_problem(256)
u = torch.full((256, 3), 0.06, dtype=torch.float64)
filt.update(filt.predict(mix, u, 0.1), y, meas)
print(time.perf_counter() - t0)
"""


def bench_compile() -> dict[str, float]:
    """Seconds from a new process's start to its first compiled fused predict + update (6-state, N = 5,
    B = 256): with torch's inductor cache and the kernel cache empty (each kernel compiled when first called,
    in the process), then filled by that run."""
    import os

    out: dict[str, float] = {}
    script = _FIRST_FUSED_STEP.format(root=str(IMPORT_ROOT))
    with tempfile.TemporaryDirectory(prefix="agsf-inductor-") as cache:
        env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache, "AGSF_TORCH_KERNEL_CACHE": str(Path(cache) / "kernels")}
        secs = []
        for _ in range(2):
            run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True, env=env)
            secs.append(float(run.stdout.strip().splitlines()[-1]))
    out["cold_s"], out["warm_s"] = secs
    return out
