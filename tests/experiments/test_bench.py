"""The benchmark's pieces on small sizes (timings are reported by `agsf bench`, never asserted)."""

from __future__ import annotations

import torch

from agsf_torch.experiments import bench


def test_qp_comparison_reports_agreement():
    r = bench.bench_qp(B=64, N=5, clarabel_samples=10)
    assert r["torch_max_kkt_residual"] < 1e-9 and r["clarabel_max_kkt_residual"] < 1e-9
    assert r["max_abs_difference"] < 1e-8
    assert r["speedup"] > 0


def test_filterpy_baseline_runs_the_same_model():
    r = bench.bench_filterpy(samples=20)
    assert r["samples"] == 20 and r["component_steps_per_s"] > 0


def test_flop_counts_follow_the_algorithm():
    # one RK4 stage of a 3-state component: 4n³ + 2n² + 60 + 4n + 8n² = 108 + 18 + 60 + 12 + 72 = 270,
    # then ΦPΦᵀ + S: 4n³ + 3n² = 108 + 27
    assert bench.propagation_flops(3) == 4 * 270 + 135
    # 15 pairs for N = 5; per node 2n² + 40 + 2(4n² + 10n) + 3 = 18 + 40 + 132 + 3 = 193 for n = 3
    assert bench.lmatrix_flops(3, 5, 343) == 15 * 343 * 193


def test_table_marks_targets():
    report = {
        "machine": {"torch": torch.__version__},
        "matmul_peak_gflops": 10.0,
        "throughput": [{"filter": "GSF", "state_dim": 6, "N": 5, "B": 64, "seconds_per_step": 0.01, "component_steps_per_s": 3.2e4, "how": "measured"}],
        "qp": {"N": 5, "B": 64, "torch_seconds_per_problem": 1e-5, "clarabel_seconds_per_problem": 2e-3, "speedup": 200.0,
               "torch_max_kkt_residual": 1e-16, "clarabel_max_kkt_residual": 1e-13, "max_abs_difference": 1e-11},
        "filterpy": {"component_steps_per_s": 1e3},
        "gsf_6state_N5_B8192": {"B": 64, "component_steps_per_s": 3.2e4},
        "gsf_vs_filterpy_per_component_step": 32.0,
        "flop_rates": {k: {"propagation_gflops": 0.1, "propagation_fraction_of_peak": 0.01, "lmatrix_B": 8, "lmatrix_gflops": 3.0,
                           "lmatrix_fraction_of_peak": 0.3, "lmatrix_compiled": False} for k in ("3-state", "6-state")},
        "memory": {"B": 65536, "N": 5, "steps": 100, "chunk": 4096, "peak_rss_mib": 1000.0},
        "total_seconds": 1.0,
    }
    report["targets"] = bench._targets(report)
    table = bench.format_table(report)
    met = {line.split("|")[1].strip(): line.split("|")[4].strip() for line in table.splitlines() if line.startswith("| ") and "≥" in line or "under" in line}
    assert met["weight QP N=5 B=8192 ≥ 100× Clarabel per problem"] == "yes"
    assert met["classic GSF 6-state N=5 B=8192 ≥ 300× filterpy per component-step"] == "no"
    assert met["L-matrix assembly ≥ 20 % of matmul peak (3-state)"] == "yes"
    assert met["B=65,536 run under 4 GB peak RSS"] == "yes"
