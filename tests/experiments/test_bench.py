"""The benchmark's pieces on small sizes (timings are reported by `agsf bench`, never asserted)."""

from __future__ import annotations

import numpy as np
import torch

from agsf_torch.experiments.bench import run as bench
from agsf_torch.experiments.bench.peers import _problem, attitude_rk4_step, filterpy_loop, numpy_batch


def test_qp_comparison_reports_agreement():
    # the bench times Clarabel unpolished, as its users call it: its iterates approach a face of the
    # simplex as √gap, so against the exact solution it agrees to ~1e-8 (the polished comparison is in test_qp)
    for N, agree in ((5, 1e-8), (32, 1e-7)):
        r = bench.bench_qp(B=64, N=N, clarabel_samples=10)
        assert r["torch_max_kkt_residual"] < 1e-12 and r["clarabel_max_kkt_residual"] < 1e-9
        assert r["max_abs_difference"] < agree
        assert r["speedup"] > 0


def test_peers_do_the_gsf_propagation_work():
    """The NumPy step the peers run equals propagate_moments on the same 6-state model (same RK4 (μ, Φ, S) work)."""
    from agsf_torch.models import AttitudeModel
    from agsf_torch.propagation import propagate_moments

    x, P, w = _problem(7)
    model = AttitudeModel(estimate_bias=True, sigma_v=1e-13**0.5, sigma_u=1e-19**0.5)
    mt, Pt = propagate_moments(model, torch.tensor(x), torch.tensor(P), torch.tensor(w), 0.1)
    xn, Pn = attitude_rk4_step(x, P, w, 0.1, 1e-13, 1e-19)
    np.testing.assert_allclose(xn, mt.numpy(), rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(Pn, Pt.numpy(), rtol=1e-12, atol=1e-14 * np.abs(Pn).max())
    assert filterpy_loop(5)["component_steps_per_s"] > 0 and numpy_batch(10, repeats=1)["component_steps_per_s"] > 0


def test_adaptive_side_by_side_reports_ratios():
    r = bench.bench_adaptive(False, B=4, repeats=1)
    assert set(r["seconds"]) == {"GSF", "AGSF-galerkin", "AGSF-penalty"}
    assert r["galerkin_ratio"] == r["seconds"]["AGSF-galerkin"] / r["seconds"]["GSF"]


def test_flop_counts_follow_the_algorithm():
    # one RK4 stage of a 3-state component: 4n³ + 2n² + 60 + 4n + 8n² = 108 + 18 + 60 + 12 + 72 = 270,
    # then ΦPΦᵀ + S: 4n³ + 3n² = 108 + 27
    assert bench.propagation_flops(3) == 4 * 270 + 135


def test_table_marks_targets():
    seconds = {"GSF": 0.01, "AGSF-galerkin": 0.04, "AGSF-penalty": 0.5}
    adaptive = {
        "state_dim": 6,
        "N": 5,
        "B": 256,
        "seconds": seconds,
        "galerkin_ratio": 4.0,
        "penalty_ratio": 50.0,
        "penalty_seconds": 0.5,
    }
    qp = {
        "N": 5,
        "B": 64,
        "torch_seconds_per_problem": 1e-5,
        "clarabel_seconds_per_problem": 2e-3,
        "speedup": 200.0,
        "torch_max_kkt_residual": 1e-16,
        "clarabel_max_kkt_residual": 1e-13,
        "max_abs_difference": 1e-11,
    }
    report = {
        "machine": {
            "torch": torch.__version__,
            "threads": 2,
            "cpu_count": 2,
            "python": "3",
            "load_average_at_start": 0.1,
        },
        "matmul_peak_gflops": 10.0,
        "adaptive": [adaptive, {**adaptive, "state_dim": 3, "B": 1024}],
        "first_step": [{"update": "galerkin", "compile": False, "first_process_s": 3.0, "second_process_s": 2.5}],
        "qp": [qp],
        "peers": {
            "B": 64,
            "gsf_component_steps_per_s": 1e5,
            "filterpy": {"what": "loop", "component_steps_per_s": 1e3},
            "numpy": {"what": "batch", "component_steps_per_s": 5e4},
            "vs_filterpy": 100.0,
            "vs_numpy": 2.0,
        },
        "memory_sweep": {"what": "sweep", "batch": 65536, "peak_rss_mib": 1000.0, "seconds": 1.0},
        "memory_adaptive": [
            {"what": "adaptive", "update": "galerkin", "batch": 8192, "peak_rss_mib": 9000.0, "seconds": 1.0}
        ],
        "total_seconds": 1.0,
    }
    report["targets"] = bench.targets(report)
    table = bench.format_table(report)
    met = {
        line.split("|")[1].strip(): line.split("|")[4].strip()
        for line in table.splitlines()
        if line.startswith("| ") and line.count("|") == 5
    }
    assert met["Galerkin AGSF predict ÷ GSF, 6-state N=5 B=256"] == "yes"
    assert met["penalty AGSF predict ÷ GSF, 6-state N=5 B=256"] == "no"
    assert met["weight QP N=5 B=64: speed-up per problem over Clarabel"] == "yes"
    assert met["GSF 6-state N=5 B=64 ÷ filterpy loop (component-steps/s)"] == "no"
    assert met["peak RSS, B=65536 × N=5 GSF sweep (GB)"] == "yes"
    assert met["peak RSS, galerkin adaptive step at B=8192 (GB)"] == "no"
    assert met["first galerkin step in a new process (s)"] == "yes"
