"""``agsf bench``: the adaptive filter's cost against the classic one, honest peers, machine limits.

Every ratio comes from one run on one machine, the two sides timed alternately
(median of repeats after a warm-up), so a load change affects both.  Compilation
is measured on its own, in fresh processes.  The report ends with each target,
the measured value and whether it is met (:func:`_targets`).

Measured:

* one predict step (one gyro interval) of the classic GSF, the adaptive GSF with
  the Galerkin update and with the paper's (penalty) update, 6-state N = 5 B = 256
  and 3-state N = 5 B = 1024;
* the first adaptive step in a new process (import, construction, first predict),
  twice, so the second run shows what the on-disk caches reuse;
* the weight QP against Clarabel called per problem (as its users call it), N = 5 and 32;
* the GSF's propagation against its peers (:mod:`.bench_peers`: a filterpy loop and a
  vectorised NumPy batch, the same RK4 (μ, Φ, S) work), 6-state N = 5 B = 8192;
* peak resident memory of a B = 65,536 × N = 5 GSF sweep and of an adaptive step at B = 8192,
  each in a fresh process.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

__all__ = ["run_bench", "format_table"]

F64 = torch.float64


def _median_time(fn: Callable[[], Any], repeats: int, budget: float = 60.0) -> float:
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


def _side_by_side(fns: dict[str, Callable[[], Any]], repeats: int) -> dict[str, float]:
    """Median seconds of each function, the functions called in turn (after one warm-up call each)."""
    for fn in fns.values():
        fn()
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t)
    return {k: statistics.median(v) for k, v in times.items()}


def _mixture(B: int, N: int, estimate_bias: bool, gen: torch.Generator):
    from ..mixture import GaussianMixture

    n = 6 if estimate_bias else 3
    p = 0.3 * torch.randn(B, 3, generator=gen, dtype=F64)
    mean = torch.cat((p, torch.zeros(B, 3, dtype=F64)), -1)[:, :n]
    P0 = torch.diag(torch.tensor([1e-3] * 3 + [1e-12] * 3, dtype=F64)[:n])
    return GaussianMixture.from_gaussian(mean, P0.expand(B, n, n), N)


def bench_adaptive(estimate_bias: bool, B: int, N: int = 5, repeats: int = 5, compile: bool = False) -> dict[str, Any]:
    """One predict step of GSF, AGSF (Galerkin) and AGSF (penalty; also with its compiled node kernel if
    ``compile``), timed side by side; the penalty ratio is the faster of the two."""
    from ..filters import AdaptiveGaussianSumFilter, GaussianSumFilter
    from ..models import AttitudeModel

    model = AttitudeModel(estimate_bias=estimate_bias)
    mix = _mixture(B, N, estimate_bias, torch.Generator().manual_seed(0))
    u = torch.full((B, 3), 0.06, dtype=F64)
    filters = {
        "GSF": GaussianSumFilter(model),
        "AGSF-galerkin": AdaptiveGaussianSumFilter(model, weight_update="galerkin"),
        "AGSF-penalty": AdaptiveGaussianSumFilter(model),
    }
    if compile:
        filters["AGSF-penalty-compiled"] = AdaptiveGaussianSumFilter(model, compile=True)
    sec = _side_by_side({k: (lambda f=f: f.predict(mix, u, 0.1)) for k, f in filters.items()}, repeats)
    penalty = min(v for k, v in sec.items() if k.startswith("AGSF-penalty"))
    return {"state_dim": model.state_dim, "N": N, "B": B, "seconds": sec,
            "galerkin_ratio": sec["AGSF-galerkin"] / sec["GSF"], "penalty_ratio": penalty / sec["GSF"], "penalty_seconds": penalty}


_FIRST_STEP_SCRIPT = """
import time, sys
t0 = time.perf_counter()
import torch
sys.path.insert(0, {root!r})
from agsf_torch.experiments.bench import _mixture
from agsf_torch.filters import AdaptiveGaussianSumFilter
from agsf_torch.models import AttitudeModel
model = AttitudeModel(estimate_bias=True)
filt = AdaptiveGaussianSumFilter(model, weight_update={update!r}, **({{"compile": True}} if {compile} else {{}}))
mix = _mixture(256, 5, True, torch.Generator().manual_seed(0))
filt.predict(mix, torch.full((256, 3), 0.06, dtype=torch.float64), 0.1)
print(time.perf_counter() - t0)
"""


def bench_first_step(cases: tuple[tuple[str, bool], ...]) -> list[dict[str, Any]]:
    """Seconds from a new process's start to its first adaptive predict (6-state, N = 5, B = 256), twice per case."""
    root = str(Path(__file__).resolve().parents[2])
    rows = []
    for update, compile in cases:
        secs = []
        for _ in range(2):
            script = _FIRST_STEP_SCRIPT.format(root=root, update=update, compile=compile)
            out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
            secs.append(float(out.stdout.strip().splitlines()[-1]))
        rows.append({"update": update, "compile": compile, "first_process_s": secs[0], "second_process_s": secs[1]})
    return rows


def bench_qp(B: int = 8192, N: int = 5, clarabel_samples: int = 300) -> dict[str, Any]:
    """The batched torch solver against Clarabel called directly, one problem at a time (the filter's form ``L̃ + λI``)."""
    from ..qp import kkt_residual, solve_simplex_qp, solve_simplex_qp_clarabel

    gen = torch.Generator().manual_seed(2)
    A = torch.randn(B, N, N, generator=gen, dtype=F64)
    H = A @ A.transpose(-1, -2) / N + torch.eye(N, dtype=F64)
    c = -torch.softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    t_torch = _median_time(lambda: solve_simplex_qp(H, c), repeats=5, budget=30.0)
    res = solve_simplex_qp(H, c)
    solve_simplex_qp_clarabel(H[:2], c[:2], polish=False)  # warm-up (import)
    t = time.perf_counter()
    w_ref = solve_simplex_qp_clarabel(H[:clarabel_samples], c[:clarabel_samples], polish=False)
    t_clar = (time.perf_counter() - t) / clarabel_samples
    kkt_clar = kkt_residual(H[:clarabel_samples], c[:clarabel_samples], torch.as_tensor(w_ref))
    return {
        "B": B, "N": N, "torch_seconds_per_problem": t_torch / B, "clarabel_seconds_per_problem": t_clar,
        "speedup": t_clar / (t_torch / B), "torch_max_kkt_residual": float(res.kkt_residual.max()),
        "clarabel_max_kkt_residual": float(kkt_clar.max()),
        "max_abs_difference": float((res.w[:clarabel_samples] - torch.as_tensor(w_ref)).abs().max()),
    }


def bench_peers(B: int = 8192, N: int = 5, filterpy_samples: int = 2000) -> dict[str, Any]:
    """The GSF's predict (6-state) against the filterpy loop and the NumPy batch (:mod:`.bench_peers`)."""
    from ..filters import GaussianSumFilter
    from ..models import AttitudeModel
    from .bench_peers import filterpy_loop, numpy_batch

    filt = GaussianSumFilter(AttitudeModel(estimate_bias=True))
    mix = _mixture(B, N, True, torch.Generator().manual_seed(1))
    u = torch.full((B, 3), 0.06, dtype=F64)
    ours = B * N / _median_time(lambda: filt.predict(mix, u, 0.1), repeats=5)
    fp = filterpy_loop(filterpy_samples)
    nb = numpy_batch(B * N)
    return {"B": B, "N": N, "gsf_component_steps_per_s": ours, "filterpy": fp, "numpy": nb,
            "vs_filterpy": ours / fp["component_steps_per_s"], "vs_numpy": ours / nb["component_steps_per_s"]}


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


def _peak_rss(module_args: list[str]) -> dict[str, Any]:
    """Run ``python -m agsf_torch.experiments.memory_probe ARGS`` and return its JSON line with the wall time."""
    root = str(Path(__file__).resolve().parents[2])
    t = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, "-m", "agsf_torch.experiments.memory_probe", *module_args],
                         capture_output=True, text=True, check=True, env=env)
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "seconds": time.perf_counter() - t}


def run_bench(out: Path | None = None, *, compile: bool = True, quick: bool = False) -> dict[str, Any]:
    """Run every measurement; write ``bench.json`` under ``out`` if given (``quick``: small sizes, a smoke run)."""
    t0 = time.perf_counter()
    report: dict[str, Any] = {
        "machine": {
            "torch": torch.__version__, "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
            "python": sys.version.split()[0], "load_average_at_start": os.getloadavg()[0],
        }
    }
    report["matmul_peak_gflops"] = bench_matmul_peak(512 if quick else 2048) / 1e9
    report["adaptive"] = [bench_adaptive(True, 16 if quick else 256, repeats=2 if quick else 5, compile=compile),
                          bench_adaptive(False, 32 if quick else 1024, repeats=2 if quick else 5, compile=compile)]
    cases = (("galerkin", False), ("penalty", False)) + ((("penalty", True),) if compile else ())
    report["first_step"] = bench_first_step(cases[:1] if quick else cases)
    report["qp"] = [bench_qp(B=256 if quick else 8192, N=N, clarabel_samples=20 if quick else 300) for N in (5, 32)]
    report["peers"] = bench_peers(B=256 if quick else 8192, filterpy_samples=100 if quick else 2000)
    report["memory_sweep"] = _peak_rss(["gsf", "--batch", str(4096 if quick else 65536), "--chunk", "4096" if quick else "16384"])
    report["memory_adaptive"] = [_peak_rss(["adaptive", "--update", up, "--batch", str(64 if quick else 8192)])
                                 for up in ("galerkin", "penalty")]
    report["total_seconds"] = time.perf_counter() - t0
    report["targets"] = _targets(report)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        tmp = out / "bench.json.tmp"
        tmp.write_text(json.dumps(report, indent=2))
        tmp.replace(out / "bench.json")
    return report


def _targets(r: dict[str, Any]) -> list[dict[str, Any]]:
    """Each target: ``{"target", "measured", "goal", "lower_is_better"}``."""
    six, three = r["adaptive"]
    t = []

    def add(name: str, measured: float, goal: float, lower: bool = True) -> None:
        t.append({"target": name, "measured": measured, "goal": goal, "lower_is_better": lower})

    add(f"Galerkin AGSF predict ÷ GSF, 6-state N=5 B={six['B']}", six["galerkin_ratio"], 5.0)
    add(f"Galerkin AGSF predict (s), 6-state N=5 B={six['B']}", six["seconds"]["AGSF-galerkin"], 0.1)
    add(f"penalty AGSF predict ÷ GSF, 6-state N=5 B={six['B']}", six["penalty_ratio"], 20.0)
    add(f"penalty AGSF predict (s), 6-state N=5 B={six['B']}", six["penalty_seconds"], 0.25)
    add(f"Galerkin AGSF predict ÷ GSF, 3-state N=5 B={three['B']}", three["galerkin_ratio"], 3.0)
    add(f"penalty AGSF predict ÷ GSF, 3-state N=5 B={three['B']}", three["penalty_ratio"], 10.0)
    for row in r["first_step"]:
        add(f"first {row['update']} step in a new process{' (compiled)' if row['compile'] else ''} (s)", row["first_process_s"], 10.0)
    for q in r["qp"]:
        add(f"weight QP N={q['N']} B={q['B']}: speed-up per problem over Clarabel", q["speedup"], 100.0, lower=False)
    p = r["peers"]
    add(f"GSF 6-state N=5 B={p['B']} ÷ filterpy loop (component-steps/s)", p["vs_filterpy"], 300.0, lower=False)
    add(f"GSF 6-state N=5 B={p['B']} ÷ NumPy batch (component-steps/s)", p["vs_numpy"], 3.0, lower=False)
    add(f"peak RSS, B={r['memory_sweep']['batch']} × N=5 GSF sweep (GB)", r["memory_sweep"]["peak_rss_mib"] / 1024, 4.0)
    for m in r["memory_adaptive"]:
        add(f"peak RSS, {m['update']} adaptive step at B={m['batch']} (GB)", m["peak_rss_mib"] / 1024, 8.0)
    return t


def _met(t: dict[str, Any]) -> bool:
    return t["measured"] <= t["goal"] if t["lower_is_better"] else t["measured"] >= t["goal"]


def format_table(r: dict[str, Any]) -> str:
    """The report as Markdown: the measurements, then every target with met / not met."""
    m = r["machine"]
    lines = [f"machine: torch {m['torch']}, {m['threads']} threads, {m['cpu_count']} CPUs, Python {m['python']}, "
             f"load {m['load_average_at_start']:.2f} at start; float64 matmul peak {r['matmul_peak_gflops']:.1f} GFLOP/s", "",
             "| n | N | B | GSF s | AGSF Galerkin s | AGSF penalty s (eager / compiled) | Galerkin ÷ GSF | penalty ÷ GSF (faster) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for a in r["adaptive"]:
        s = a["seconds"]
        compiled = f" / {s['AGSF-penalty-compiled']:.3f}" if "AGSF-penalty-compiled" in s else ""
        lines.append(f"| {a['state_dim']} | {a['N']} | {a['B']} | {s['GSF']:.4f} | {s['AGSF-galerkin']:.4f} | "
                     f"{s['AGSF-penalty']:.3f}{compiled} | {a['galerkin_ratio']:.1f}× | {a['penalty_ratio']:.0f}× |")
    lines.append("")
    for row in r["first_step"]:
        lines.append(f"first {row['update']} step{' (compiled)' if row['compile'] else ''} in a new process: "
                     f"{row['first_process_s']:.1f} s, again in a second process: {row['second_process_s']:.1f} s")
    for q in r["qp"]:
        lines.append(f"weight QP N={q['N']} B={q['B']}: torch {q['torch_seconds_per_problem'] * 1e6:.2f} µs/problem, Clarabel "
                     f"{q['clarabel_seconds_per_problem'] * 1e6:.0f} µs/problem → {q['speedup']:.0f}× (KKT torch "
                     f"{q['torch_max_kkt_residual']:.1e}, Clarabel {q['clarabel_max_kkt_residual']:.1e}, max |Δw| {q['max_abs_difference']:.1e})")
    p = r["peers"]
    lines += [f"GSF predict 6-state N=5 B={p['B']}: {p['gsf_component_steps_per_s']:.3g} component-steps/s; "
              f"{p['filterpy']['what']}: {p['filterpy']['component_steps_per_s']:.3g} ({p['vs_filterpy']:.0f}×); "
              f"{p['numpy']['what']}: {p['numpy']['component_steps_per_s']:.3g} ({p['vs_numpy']:.2f}×)"]
    for mem in (r["memory_sweep"], *r["memory_adaptive"]):
        lines.append(f"memory: {mem['what']}: peak RSS {mem['peak_rss_mib']:.0f} MiB ({mem['seconds']:.0f} s)")
    lines += ["", "| target | measured | goal | met |", "| --- | --- | --- | --- |"]
    for t in r["targets"]:
        goal = f"{'≤' if t['lower_is_better'] else '≥'} {t['goal']:g}"
        lines.append(f"| {t['target']} | {t['measured']:.3g} | {goal} | {'yes' if _met(t) else 'no'} |")
    lines.append(f"\ntotal bench time {r['total_seconds']:.0f} s")
    return "\n".join(lines)
