"""``agsf bench``: throughput, peers and machine limits measured in one run.

Every timing is the median of repeats after a warm-up; ratios come from the same
run on the same machine.  Configurations whose single step would take longer
than the time budget are *extrapolated* linearly in B from the largest measured
batch and flagged as such — never silently.

Reported:

* GSF and adaptive-GSF throughput in component-steps/s (one step = one gyro
  interval of propagation; the adaptive step includes the weight update) for
  B ∈ {1, 64, 1024, 8192}, N ∈ {1, 5, 9}, 3- and 6-state;
* the same GSF work with filterpy's ``ExtendedKalmanFilter``, one object per
  component and trajectory, in a Python loop (a sample, scaled per component-step);
* the weight QP: the batched torch solver against Clarabel called per problem;
* the float64 matrix-multiply peak, and the achieved FLOP rate of the propagation
  and of the L-matrix assembly as a fraction of it (FLOPs of the algorithm as written);
* the peak resident memory of a sweep-sized run (B = 65,536, N = 5, 6-state, 100 steps).
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["run_bench", "format_table"]

F64 = torch.float64


def _median_time(fn: Callable[[], Any], repeats: int, budget: float) -> float:
    fn()  # warm-up
    times = []
    start = time.perf_counter()
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
        if time.perf_counter() - start > budget:
            break
    return statistics.median(times)


def _mixture(B: int, N: int, estimate_bias: bool, gen: torch.Generator):
    from ..mixture import GaussianMixture

    n = 6 if estimate_bias else 3
    p = 0.3 * torch.randn(B, 3, generator=gen, dtype=F64)
    mean = torch.cat((p, torch.zeros(B, 3, dtype=F64)), -1)[:, :n]
    P0 = torch.diag(torch.tensor([1e-3] * 3 + [1e-12] * 3, dtype=F64)[:n])
    return GaussianMixture.from_gaussian(mean, P0.expand(B, n, n), N)


def bench_filters(budget: float, compile: bool) -> list[dict[str, Any]]:
    from ..filters import AdaptiveGaussianSumFilter, GaussianSumFilter
    from ..models import AttitudeModel

    rows = []
    gen = torch.Generator().manual_seed(0)
    for estimate_bias in (False, True):
        model = AttitudeModel(estimate_bias=estimate_bias)
        for kind in ("GSF", "AGSF"):
            filt = GaussianSumFilter(model) if kind == "GSF" else AdaptiveGaussianSumFilter(model, compile=compile)
            for N in (1, 5, 9):
                last = None  # (B, seconds) of the largest measured batch
                for B in (1, 64, 1024, 8192):
                    mix = _mixture(B, N, estimate_bias, gen)
                    u = torch.full((B, 3), 0.06, dtype=F64)
                    predicted = None if last is None else last[1] * B / last[0]
                    if predicted is not None and predicted > budget:
                        sec, how = predicted, "extrapolated"
                    else:
                        sec = _median_time(lambda: filt.predict(mix, u, 0.1), repeats=5, budget=budget)
                        how = "measured"
                        last = (B, sec)
                    rows.append(
                        {
                            "filter": kind,
                            "state_dim": model.state_dim,
                            "N": N,
                            "B": B,
                            "seconds_per_step": sec,
                            "component_steps_per_s": B * N / sec,
                            "how": how,
                        }
                    )
    return rows


def bench_filterpy(samples: int = 300) -> dict[str, Any]:
    """The GSF's work done component by component with filterpy's EKF (6-state, star frame every 10 steps)."""
    from filterpy.kalman import ExtendedKalmanFilter

    from ..models import AttitudeModel, StarVectorMeasurement

    model = AttitudeModel(estimate_bias=True)
    rng = np.random.default_rng(0)
    r = rng.normal(size=(5, 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    meas = StarVectorMeasurement(torch.tensor(r), sigma=1e-5)
    R = 1e-10 * np.eye(15)
    Q = model.noise_psd().numpy()
    dt = 0.1
    w = np.array([0.06, 0.06, 0.0])

    def drift(x):
        return model.drift(torch.from_numpy(x), torch.from_numpy(w)).numpy()

    class AttitudeEKF(ExtendedKalmanFilter):
        def predict_x(self, u=0):  # RK4 of the kinematics, as a user would write it
            x = self.x.ravel()
            k1 = drift(x)
            k2 = drift(x + 0.5 * dt * k1)
            k3 = drift(x + 0.5 * dt * k2)
            k4 = drift(x + dt * k3)
            self.x = (x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)).reshape(-1, 1)

    ekf = AttitudeEKF(dim_x=6, dim_z=15)
    ekf.x = np.array([[0.1, 0.2, -0.1, 0.0, 0.0, 0.0]]).T
    ekf.P = np.diag([1e-3] * 3 + [1e-12] * 3)
    z = meas.predict(torch.from_numpy(ekf.x.ravel())).numpy().reshape(-1, 1)

    def step(k):
        x = ekf.x.ravel()
        A = model.drift_jacobian(torch.from_numpy(x), torch.from_numpy(w)).numpy()
        g = model.noise_gain(torch.from_numpy(x)).numpy()
        ekf.F = np.eye(6) + A * dt + 0.5 * (A @ A) * dt * dt
        ekf.Q = g @ Q @ g.T * dt
        ekf.predict()
        if k % 10 == 9:
            ekf.update(
                z,
                lambda xx: meas.jacobian(torch.from_numpy(xx.ravel())).numpy(),
                lambda xx: meas.predict(torch.from_numpy(xx.ravel())).numpy().reshape(-1, 1),
                R=R,
            )

    step(0)
    t = time.perf_counter()
    for k in range(samples):
        step(k)
    sec = (time.perf_counter() - t) / samples
    return {"seconds_per_component_step": sec, "component_steps_per_s": 1.0 / sec, "samples": samples}


def bench_gsf_with_updates(B: int = 8192, N: int = 5, steps: int = 20) -> dict[str, Any]:
    """Our GSF on the same work as :func:`bench_filterpy` (6-state, one star frame per 10 steps)."""
    from ..filters import GaussianSumFilter
    from ..models import AttitudeModel, StarVectorMeasurement

    gen = torch.Generator().manual_seed(1)
    model = AttitudeModel(estimate_bias=True)
    filt = GaussianSumFilter(model)
    mix = _mixture(B, N, True, gen)
    u = torch.full((B, 3), 0.06, dtype=F64)
    r = torch.randn(B, 5, 3, generator=gen, dtype=F64)
    r = r / r.norm(dim=-1, keepdim=True)
    meas = StarVectorMeasurement(r, sigma=1e-5)
    y = meas.predict(mix.means[:, 0])

    def run():
        m = mix
        for k in range(steps):
            m = filt.predict(m, u, 0.1)
            if k % 10 == 9:
                m = filt.update(m, y, meas)
        return m

    sec = _median_time(run, repeats=3, budget=60.0) / steps
    return {"B": B, "N": N, "seconds_per_step": sec, "component_steps_per_s": B * N / sec}


def bench_qp(B: int = 8192, N: int = 5, clarabel_samples: int = 300) -> dict[str, Any]:
    from ..qp import kkt_residual, solve_simplex_qp, solve_simplex_qp_clarabel

    gen = torch.Generator().manual_seed(2)
    A = torch.randn(B, N, N, generator=gen, dtype=F64)
    H = A @ A.transpose(-1, -2) / N + torch.eye(N, dtype=F64)  # the filter's form: L̃ + λI
    c = -torch.softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    t_torch = _median_time(lambda: solve_simplex_qp(H, c), repeats=5, budget=30.0)
    res = solve_simplex_qp(H, c)
    t = time.perf_counter()
    w_ref = solve_simplex_qp_clarabel(H[:clarabel_samples], c[:clarabel_samples], polish=False)
    t_clar = (time.perf_counter() - t) / clarabel_samples
    kkt_clar = kkt_residual(H[:clarabel_samples], c[:clarabel_samples], torch.as_tensor(w_ref))
    return {
        "B": B,
        "N": N,
        "torch_seconds_per_problem": t_torch / B,
        "clarabel_seconds_per_problem": t_clar,
        "speedup": t_clar / (t_torch / B),
        "torch_max_kkt_residual": float(res.kkt_residual.max()),
        "clarabel_max_kkt_residual": float(kkt_clar.max()),
        "max_abs_difference": float((res.w[:clarabel_samples] - torch.as_tensor(w_ref)).abs().max()),
    }


def bench_matmul_peak(size: int = 2048) -> float:
    a = torch.randn(size, size, dtype=F64)
    b = torch.randn(size, size, dtype=F64)
    sec = _median_time(lambda: a @ b, repeats=5, budget=20.0)
    return 2.0 * size**3 / sec


def propagation_flops(n: int) -> float:
    """FLOPs of one component's RK4 step as written (transition-matrix form): per stage the
    products ``AΦ`` and ``AS`` (4n³), ``AS + (AS)ᵀ + gQgᵀ`` (2n²), the closed-form Jacobian and
    drift (~60) and the increments of μ, Φ, S (4n + 8n²); then ``ΦPΦᵀ + S`` (4n³ + 3n²)."""
    stage = 4 * n**3 + 2 * n**2 + 60 + 4 * n + 8 * n**2
    return 4 * stage + 4 * n**3 + 3 * n**2


def lmatrix_flops(n: int, N: int, nodes: int) -> float:
    """FLOPs of the L-matrix assembly as written, per trajectory: for each of N(N+1)/2 pairs and
    each node, the node map (2n²), the model terms (~40), and two residual factors
    (Π d: 2n², zᵀṖz: 2n² + 2n, diffusion and transport terms: ~8n), plus the product and sum (3)."""
    pairs = N * (N + 1) // 2
    per_node = 2 * n**2 + 40 + 2 * (4 * n**2 + 10 * n) + 3
    return pairs * nodes * per_node


def bench_flop_rates(peak: float, B: int = 1024, N: int = 5, compile: bool = True) -> dict[str, Any]:
    from ..filters import AdaptiveGaussianSumFilter
    from ..fpke import ComponentRates, fpke_matrix
    from ..models import AttitudeModel
    from ..propagation import moment_derivatives, propagate_moments

    gen = torch.Generator().manual_seed(3)
    out = {}
    for estimate_bias in (False, True):
        model = AttitudeModel(estimate_bias=estimate_bias)
        n = model.state_dim
        mix = _mixture(B, N, estimate_bias, gen)
        u = torch.full((B, 1, 3), 0.06, dtype=F64)
        t_prop = _median_time(lambda: propagate_moments(model, mix.means, mix.covs, u, 0.1), repeats=7, budget=20.0)
        rates = moment_derivatives(model, mix.means, mix.covs, u)
        comp = ComponentRates(mix.means, torch.linalg.cholesky(mix.covs), rates.mean_rate, rates.cov_rate)
        agsf = AdaptiveGaussianSumFilter(model)
        nodes, weights = agsf.weight_update.nodes, agsf.weight_update.node_weights
        Bl = B if n == 3 else 64  # the 6-D rule has 9261 nodes: a smaller batch keeps the bench short
        sub = ComponentRates(*(t[:Bl] for t in (comp.means, comp.chol, comp.mean_rates, comp.cov_rates)))
        t_l = _median_time(lambda: fpke_matrix(model, u[:Bl, 0], sub, nodes, weights, compile=compile), repeats=3, budget=60.0)
        out[f"{n}-state"] = {
            "propagation_gflops": propagation_flops(n) * B * N / t_prop / 1e9,
            "propagation_fraction_of_peak": propagation_flops(n) * B * N / t_prop / peak,
            "propagation_seconds": t_prop,
            "lmatrix_B": Bl,
            "lmatrix_gflops": lmatrix_flops(n, N, nodes.shape[0]) * Bl / t_l / 1e9,
            "lmatrix_fraction_of_peak": lmatrix_flops(n, N, nodes.shape[0]) * Bl / t_l / peak,
            "lmatrix_seconds": t_l,
            "lmatrix_compiled": compile,
        }
    return out


_MEMORY_SCRIPT = """
import resource, sys, torch
sys.path.insert(0, {root!r})
from agsf_torch.experiments.bench import _mixture
from agsf_torch.filters import GaussianSumFilter
from agsf_torch.models import AttitudeModel
B, N, steps, chunk = 65536, 5, 100, {chunk}
gen = torch.Generator().manual_seed(4)
filt = GaussianSumFilter(AttitudeModel(estimate_bias=True))
for start in range(0, B, chunk):
    mix = _mixture(chunk, N, True, gen)
    u = torch.full((chunk, 3), 0.06, dtype=torch.float64)
    for k in range(steps):
        mix = filt.predict(mix, u, 0.1)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def bench_memory(chunk: int = 16384) -> dict[str, Any]:
    """Peak RSS of a B = 65,536, N = 5, 6-state, 100-step GSF run in a fresh process (chunks of ``chunk``)."""
    root = str(Path(__file__).resolve().parents[2])
    t = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", _MEMORY_SCRIPT.format(root=root, chunk=chunk)], capture_output=True, text=True, check=True
    )
    kib = int(out.stdout.strip().splitlines()[-1])
    return {"B": 65536, "N": 5, "steps": 100, "chunk": chunk, "peak_rss_mib": kib / 1024, "seconds": time.perf_counter() - t}


def run_bench(out: Path | None = None, *, budget: float = 20.0, compile: bool = True, quick: bool = False) -> dict[str, Any]:
    """Run every measurement; write ``bench.json`` under ``out`` if given."""
    t0 = time.perf_counter()
    report: dict[str, Any] = {
        "machine": {
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "cpu_count": __import__("os").cpu_count(),
            "python": sys.version.split()[0],
        }
    }
    peak = bench_matmul_peak()
    report["matmul_peak_gflops"] = peak / 1e9
    report["qp"] = bench_qp(clarabel_samples=100 if quick else 300)
    report["filterpy"] = bench_filterpy(100 if quick else 300)
    report["gsf_6state_N5_B8192"] = bench_gsf_with_updates(B=1024 if quick else 8192)
    report["gsf_vs_filterpy_per_component_step"] = (
        report["gsf_6state_N5_B8192"]["component_steps_per_s"] / report["filterpy"]["component_steps_per_s"]
    )
    report["throughput"] = bench_filters(budget=2.0 if quick else budget, compile=compile)
    report["flop_rates"] = bench_flop_rates(peak, B=256 if quick else 1024, compile=compile)
    report["memory"] = bench_memory(chunk=4096) if quick else bench_memory()
    report["total_seconds"] = time.perf_counter() - t0
    report["targets"] = _targets(report)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "bench.json").write_text(json.dumps(report, indent=2))
    return report


def _targets(r: dict[str, Any]) -> list[dict[str, Any]]:
    fr = r["flop_rates"]
    return [
        {"target": "classic GSF 6-state N=5 B=8192 ≥ 300× filterpy per component-step", "measured": r["gsf_vs_filterpy_per_component_step"], "goal": 300.0},
        {"target": "weight QP N=5 B=8192 ≥ 100× Clarabel per problem", "measured": r["qp"]["speedup"], "goal": 100.0},
        {"target": "propagation ≥ 10 % of matmul peak (6-state)", "measured": fr["6-state"]["propagation_fraction_of_peak"], "goal": 0.10},
        {"target": "L-matrix assembly ≥ 20 % of matmul peak (3-state)", "measured": fr["3-state"]["lmatrix_fraction_of_peak"], "goal": 0.20},
        {"target": "B=65,536 run under 4 GB peak RSS", "measured": r["memory"]["peak_rss_mib"] / 1024, "goal": 4.0, "lower_is_better": True},
    ]


def format_table(r: dict[str, Any]) -> str:
    lines = [
        f"machine: {r['machine']}  float64 matmul peak {r['matmul_peak_gflops']:.1f} GFLOP/s",
        "",
        "| filter | n | N | B | s/step | component-steps/s | |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in r["throughput"]:
        lines.append(
            f"| {row['filter']} | {row['state_dim']} | {row['N']} | {row['B']} | {row['seconds_per_step']:.3g} | "
            f"{row['component_steps_per_s']:.3g} | {row['how']} |"
        )
    q = r["qp"]
    lines += [
        "",
        f"filterpy EKF loop: {r['filterpy']['component_steps_per_s']:.3g} component-steps/s; "
        f"GSF 6-state N=5 B={r['gsf_6state_N5_B8192']['B']}: {r['gsf_6state_N5_B8192']['component_steps_per_s']:.3g} "
        f"→ {r['gsf_vs_filterpy_per_component_step']:.0f}×",
        f"weight QP N={q['N']} B={q['B']}: torch {q['torch_seconds_per_problem'] * 1e6:.2f} µs/problem, Clarabel "
        f"{q['clarabel_seconds_per_problem'] * 1e6:.0f} µs/problem → {q['speedup']:.0f}× (KKT torch {q['torch_max_kkt_residual']:.1e}, "
        f"Clarabel {q['clarabel_max_kkt_residual']:.1e}, max |Δw| {q['max_abs_difference']:.1e})",
    ]
    for key, f in r["flop_rates"].items():
        lines.append(
            f"{key}: propagation {f['propagation_gflops']:.2f} GFLOP/s ({100 * f['propagation_fraction_of_peak']:.1f} % of peak); "
            f"L-matrix (B={f['lmatrix_B']}, compiled={f['lmatrix_compiled']}) {f['lmatrix_gflops']:.2f} GFLOP/s "
            f"({100 * f['lmatrix_fraction_of_peak']:.1f} % of peak)"
        )
    m = r["memory"]
    lines.append(f"memory: B={m['B']} N={m['N']} 6-state {m['steps']} steps (chunks of {m['chunk']}): peak RSS {m['peak_rss_mib']:.0f} MiB")
    lines += ["", "| target | measured | goal | met |", "| --- | --- | --- | --- |"]
    for t in r["targets"]:
        met = t["measured"] <= t["goal"] if t.get("lower_is_better") else t["measured"] >= t["goal"]
        lines.append(f"| {t['target']} | {t['measured']:.3g} | {t['goal']:g} | {'yes' if met else 'no'} |")
    lines.append(f"\ntotal bench time {r['total_seconds']:.0f} s")
    return "\n".join(lines)

