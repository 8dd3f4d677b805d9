"""The benchmark's pieces on small sizes (timings are reported by `agsf bench`, never asserted)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agsf_torch.experiments.bench import report as report_module
from agsf_torch.experiments.bench import run as bench
from agsf_torch.experiments.bench.peers import _problem, attitude_rk4_step, filterpy_loop, numpy_batch
from tests.helpers import assert_within, relative_bound


def test_qp_comparison_reports_agreement():
    # the bench times Clarabel unpolished, as its users call it: its iterates approach a face of the
    # simplex as √gap, so against the exact solution it agrees to ~1e-8 (the polished comparison is in test_qp)
    for N, agree in ((5, 1e-8), (32, 1e-7)):
        r = bench.bench_qp(B=64, N=N, clarabel_samples=10)
        assert_within(r["torch_max_kkt_residual"], 0.0, 1e-12, f"KKT residual of the torch QP, N = {N}")
        assert_within(r["clarabel_max_kkt_residual"], 0.0, 1e-9, f"KKT residual of Clarabel, N = {N}")
        assert_within(r["max_abs_difference"], 0.0, agree, f"torch QP against Clarabel, N = {N}")
        assert r["speedup"] > 0


def test_managed_rows_report_their_sides_and_what_management_did():
    """Small sizes, eager: each row times its two sides (and the reference) and reports what management did."""
    from agsf_torch.experiments.bench.managed import bench_managed_galerkin, bench_managed_gsf
    from agsf_torch.filters.management import MANAGEMENT_DIAGNOSTICS

    g = bench_managed_gsf(B=4, capacity=16, repeats=1, compile=False)
    assert set(g["seconds"]) == {"GSF", "GSF-managed"}
    assert g["ratio"] == g["seconds"]["GSF-managed"] / g["seconds"]["GSF"]
    assert (g["B"], g["N"], g["capacity"]) == (4, 5, 16) and "padded to 16 slots" in g["what"]
    assert set(g["management"]) == {"predict", "update"}
    for counts in g["management"].values():
        assert set(counts) == set(MANAGEMENT_DIAGNOSTICS) and 1 <= counts["active_components"] <= 16
    a = bench_managed_galerkin(B=4, capacity=16, repeats=1, compile=False)
    assert set(a["seconds"]) == {"GSF", "AGSF-galerkin", "AGSF-galerkin-managed"}
    assert a["ratio"] == a["seconds"]["AGSF-galerkin-managed"] / a["seconds"]["GSF"]
    assert a["unmanaged_ratio"] == a["seconds"]["AGSF-galerkin"] / a["seconds"]["GSF"]
    assert set(a["management"]) == {"predict"}


def test_qp_rows_on_the_filters_problems_report_agreement():
    """Every problem set of the QP rows, small: both solvers meet the KKT conditions of the same problems (Clarabel
    unpolished to its tolerance; on the Galerkin update's ill-conditioned M at N ≥ 16 the two weights then differ
    in the flat directions of the objective, so only the residuals are compared)."""
    from agsf_torch.experiments.bench.run import QP_FILTER_PROBLEMS, QP_SIZES
    from agsf_torch.experiments.bench.weight_qp import bench_qp_filter

    for problems, N in QP_FILTER_PROBLEMS:
        r = bench_qp_filter(problems, B=4, N=N, clarabel_samples=2, repeats=1)
        assert (r["problems"], r["N"], r["B"], r["clarabel_samples"]) == (problems, N, 4, 2)
        assert_within(r["torch_max_kkt_residual"], 0.0, 1e-12, f"KKT residual of the torch QP, {problems} N = {N}")
        assert_within(r["clarabel_max_kkt_residual"], 0.0, 1e-9, f"KKT residual of Clarabel, {problems} N = {N}")
        assert r["speedup"] > 0 and r["what"].startswith("AGSF")
        assert r["active_components"] == (5 if problems == "galerkin-managed" else N)
    assert set(QP_SIZES) == {N for _, N in QP_FILTER_PROBLEMS} == {5, 16, 32}


def test_the_captured_qp_is_the_one_the_filter_solves():
    """The Galerkin filter's new weights are the solution of the captured (H, c), renormalised; the managed one's
    QP covers the 6 slots its 5 active components need (slots 0–5 of the padded prior), its captured problem is the
    one in v (w = κw⁰ + (1 − κ)v, each active component keeping κ of its weight), zero on the held slot, and its
    other slots stay inactive."""
    from agsf_torch.experiments.bench.harness import attitude_mixture
    from agsf_torch.experiments.bench.weight_qp import filter_qp_problems
    from agsf_torch.filters.management import pad_mixture
    from agsf_torch.filters.registry import make_filter
    from agsf_torch.filters.weight_updates.base import MANAGED_WEIGHT_KEPT
    from agsf_torch.models import AttitudeModel
    from agsf_torch.qp import solve_simplex_qp

    u = torch.full((3, 3), 0.06, dtype=torch.float64)
    for problems, name, N in (("galerkin", "AGSF-galerkin", 5), ("galerkin-managed", "AGSF-galerkin-managed", 16)):
        H, c, _ = filter_qp_problems(problems, 3, N)
        mix = attitude_mixture(3, 5 if problems == "galerkin-managed" else N, True, torch.Generator().manual_seed(5))
        if problems == "galerkin-managed":
            mix = pad_mixture(mix, N)
        filt = make_filter(name, AttitudeModel(estimate_bias=True), **({"capacity": N} if N == 16 else {}))
        w = solve_simplex_qp(H, c).w.clamp_min(0.0)
        if problems == "galerkin-managed":
            assert H.shape[-1] == 6 and (w[:, 5:] == 0).all()
            w = MANAGED_WEIGHT_KEPT * mix.weights[:, :6] + (1.0 - MANAGED_WEIGHT_KEPT) * w
        w = w / w.sum(-1, keepdim=True)
        weights = filt.predict(mix, u, 0.1).weights
        if problems == "galerkin-managed":
            assert (weights[:, 6:] == 0).all()
            weights = weights[:, :6]
        assert_within(weights, w, 1e-12, f"{name}'s weights against the captured QP's")
    # built a chunk of trajectories at a time (a new filter each), the problems are those of one piece
    H1, c1, info1 = filter_qp_problems("penalty", 4, 5, chunk=None)
    H2, c2, info2 = filter_qp_problems("penalty", 4, 5, chunk=2)
    assert_within(H2, H1, relative_bound(H1, 1e-13, 1e-15), "H built in chunks against one piece")
    assert_within(c2, c1, relative_bound(c1, 1e-13, 1e-15), "c built in chunks against one piece")
    assert info1 == info2 == {"active_components": 5.0}


def test_managed_memory_workload_reports_its_peak():
    for name in ("GSF-managed", "AGSF-managed", "AGSF-galerkin-managed"):
        row = bench._peak_rss(["managed", "--filter", name, "--batch", "4", "--capacity", "16"])
        assert (row["filter"], row["batch"], row["capacity"], row["compiled"]) == (name, 4, 16, False)
        assert row["peak_rss_mib"] > 0 and name in row["what"]


def test_sections_run_alone():
    """``run_bench(only=...)`` runs the named groups and its report and table hold those alone."""
    r = bench.run_bench(quick=True, compile=False, only=["managed"])
    assert r["sections"] == ["managed"] and set(r) == {
        "machine",
        "sections",
        "matmul_peak_gflops",
        "managed",
        "total_seconds",
        "targets",
    }
    assert [t["goal"] for t in r["targets"]] == [5.0, 15.0]
    table = bench.format_table(r)
    assert "GSF-managed predict + update (capacity 16) ÷ fused GSF (N=5), 6-state B=64" in table
    assert "star update, 6-state" not in table and "peak RSS" not in table and "| n | N | B |" not in table
    with pytest.raises(ValueError, match="unknown bench section"):
        bench.check_sections(["managed", "qp_random"])
    assert bench.check_sections(None) == bench.SECTIONS
    assert bench.check_sections(["qp", "managed"]) == ("qp", "managed")  # in the order they run


def test_peers_do_the_gsf_propagation_work():
    """The NumPy step the peers run equals propagate_moments on the same 6-state model (same RK4 (μ, Φ, S) work)."""
    from agsf_torch.models import AttitudeModel
    from agsf_torch.propagation import propagate_moments

    x, P, w = _problem(7)
    model = AttitudeModel(estimate_bias=True, sigma_v=1e-13**0.5, sigma_u=1e-19**0.5)
    mt, Pt = propagate_moments(model, torch.tensor(x), torch.tensor(P), torch.tensor(w), 0.1)
    xn, Pn = attitude_rk4_step(x, P, w, 0.1, 1e-13, 1e-19)
    assert xn.shape == mt.shape and Pn.shape == Pt.shape
    assert_within(xn, mt, relative_bound(mt, 1e-14, 1e-16), "propagated means")
    assert_within(Pn, Pt, relative_bound(Pt, 1e-12, 1e-14 * np.abs(Pn).max()), "propagated covariances")
    assert filterpy_loop(5)["component_steps_per_s"] > 0 and numpy_batch(10, repeats=1)["component_steps_per_s"] > 0


def test_adaptive_side_by_side_reports_ratios():
    """The penalty's batched route (the landed one) is kept as a reference row beside the lanes route."""
    for estimate_bias in (False, True):
        r = bench.bench_adaptive(estimate_bias, B=4, repeats=1)
        assert set(r["seconds"]) == {"GSF (generic)", "GSF", "AGSF-galerkin", "AGSF-penalty", "AGSF-penalty (batched)"}
        assert r["penalty_batched_ratio"] == r["seconds"]["AGSF-penalty (batched)"] / r["seconds"]["GSF"]
        assert r["galerkin_ratio"] == r["seconds"]["AGSF-galerkin"] / r["seconds"]["GSF"]


def test_the_fused_kernel_counts_fewer_flops_than_the_dense_algorithm():
    """The unrolled graph skips structural zeros and ones: the dense RK4 (μ, Φ, S) step (per stage the
    products AΦ and AS, n²(2n − 1) each, and the Φ, S increments, then ΦPΦᵀ) grows 7× from 3 to 6 states,
    the fused kernel's count (its model evaluation included) less than half as fast: the 6-state model's
    zero bias rows of A and Φ's identity bias block emit nothing."""
    from agsf_torch.experiments.bench.fused import propagation_kernel_flops

    def dense(n):
        return 4 * (2 * n * n * (2 * n - 1) + 6 * n * n) + 2 * n * n * (2 * n - 1)

    f3, f6 = propagation_kernel_flops(3), propagation_kernel_flops(6)
    assert 0 < f3 < f6 < dense(6)
    assert f6 / f3 < 0.5 * dense(6) / dense(3)


def test_table_marks_targets():
    adaptive = {
        "state_dim": 6,
        "N": 5,
        "B": 256,
        "compiled": True,
        "seconds": {"GSF (generic)": 0.02, "GSF": 0.01, "AGSF-galerkin": 0.04, "AGSF-penalty": 0.5},
        "galerkin_ratio": 4.0,
        "galerkin_ratio_to_generic_gsf": 2.0,
        "penalty_ratio": 50.0,
        "penalty_seconds": 0.5,
    }
    big = {**adaptive, "B": 4096, "galerkin_ratio": 6.0}
    del big["penalty_ratio"]
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
        "propagation": {
            "B": 64,
            "N": 5,
            "component_steps_per_s": {"landed (generic)": 1e5, "fused eager": 2e5, "fused compiled": 1e6},
            "peers": {
                "filterpy": {"what": "loop", "component_steps_per_s": 1e3},
                "numpy": {"what": "batch", "component_steps_per_s": 5e5},
                "jax": {"skipped": "no JAX"},
            },
            "vs": {"filterpy": 1000.0, "numpy": 2.0},
            "vs_landed": 10.0,
            "kernel_flops_per_component_step": 1900,
            "fraction_of_peak": 0.2,
        },
        "update": {
            "B": 64,
            "N": 5,
            "stars": 5,
            "seconds": {"landed (generic)": 1.0, "fused compiled": 0.05},
            "speedup": 20.0,
        },
        "spacecraft": {
            "N": 5,
            "seconds": {"landed (generic)": 3e-3, "fused compiled": 8e-4},
            "best_seconds": 8e-4,
            "filterpy": {"what": "filterpy", "seconds": 2e-3},
            "vs_filterpy": 2.5,
        },
        "compile": {"cold_s": 50.0, "warm_s": 3.0},
        "main_job": {
            "seconds": 12.0,
            "sequential_seconds": 20.0,
            "generic_seconds": 30.0,
            "reference_seconds": 48.0,
            "rounds_seconds": [11.0, 12.0],
            "reference_rounds_seconds": [47.0, 48.0],
            "reference": "/tmp/filed",
            "reference_commit": "abc1234",
        },
        "adaptive": [adaptive, big, {**adaptive, "state_dim": 3, "B": 1024}],
        "first_step": [{"update": "galerkin", "compile": False, "first_process_s": 3.0, "second_process_s": 2.5}],
        "qp": [qp],
        "memory_sweep": {"what": "sweep", "batch": 65536, "peak_rss_mib": 1000.0, "seconds": 1.0},
        "memory_adaptive": [
            {"what": "adaptive", "update": "galerkin", "batch": 8192, "peak_rss_mib": 9000.0, "seconds": 1.0}
        ],
        "qp_filter": [{**qp, "B": 8192, "N": 16, "problems": "galerkin-managed", "active_components": 5.0}],
        "managed": {
            "gsf": {
                "what": "managed GSF",
                "B": 4096,
                "N": 5,
                "capacity": 16,
                "compiled": True,
                "seconds": {"GSF": 0.5, "GSF-managed": 10.0},
                "ratio": 20.0,
                "management": {"predict": {"active_components": 5.0, "splits": 0.0, "merges": 0.0, "prunes": 0.0}},
            },
            "galerkin": {
                "what": "managed Galerkin",
                "B": 4096,
                "N": 5,
                "capacity": 16,
                "compiled": True,
                "seconds": {"GSF": 0.5, "AGSF-galerkin": 1.0, "AGSF-galerkin-managed": 5.0},
                "ratio": 10.0,
                "unmanaged_ratio": 2.0,
                "management": {"predict": {"active_components": 5.0, "splits": 0.0, "merges": 0.0, "prunes": 0.0}},
            },
        },
        "memory_managed": [
            {
                "what": "managed",
                "filter": "AGSF-managed",
                "batch": 8192,
                "capacity": 16,
                "compiled": True,
                "peak_rss_mib": 5000.0,
                "seconds": 1.0,
            }
        ],
        "total_seconds": 1.0,
    }
    report["targets"] = bench.targets(report)
    table = bench.format_table(report)
    rows = {
        line.split("|")[1].strip(): (line.split("|")[4].strip(), line.split("|")[5].strip())
        for line in table.splitlines()
        if line.startswith("| ") and line.count("|") == 6
    }
    met = {k: v[0] for k, v in rows.items()}
    assert met["GSF predict 6-state N=5 B=64: fused ÷ filterpy (component-steps/s)"] == "yes"
    assert met["GSF predict 6-state N=5 B=64: fused ÷ numpy (component-steps/s)"] == "no"
    assert not any("÷ jax" in k for k in met)  # a skipped peer has no target row
    assert "| jax | skipped: no JAX | — |" in table
    assert met["star update (5 stars) 6-state N=5 B=64: speed-up over the landed update"] == "yes"
    assert met["one spacecraft (B=1, N=5, 6-state): predict + update (ms)"] == "yes"
    assert met["Galerkin AGSF predict ÷ fused GSF, 6-state N=5 B=256"] == "yes"
    assert met["Galerkin AGSF predict ÷ fused GSF, 6-state N=5 B=4096"] == "no"
    assert rows["Galerkin AGSF predict ÷ fused GSF, 6-state N=5 B=4096"][1].startswith("the pairs' kernel")
    assert met["penalty AGSF predict ÷ fused GSF, 6-state N=5 B=256"] == "no"
    side_by_side = "first compiled fused step in a new process, cache cold, each kernel compiled when first called (s)"
    assert met[side_by_side] == "yes"
    assert not any(k.startswith("reference") for k in met)  # the reference is a measurement, not a target
    assert "50 s cold (each kernel compiled when first called), 3.0 s warm" in table
    assert met["weight QP N=5 B=64: speed-up per problem over Clarabel"] == "yes"
    assert met["peak RSS, B=65536 × N=5 GSF sweep (GB)"] == "yes"
    assert met["peak RSS, galerkin adaptive step at B=8192 (GB)"] == "no"
    assert met["first galerkin step in a new process (s)"] == "yes"
    managed = "GSF-managed predict + update (capacity 16) ÷ fused GSF (N=5), 6-state B=4096"
    assert met[managed] == "no" and rows[managed][1] == report_module.MANAGED_GSF_LIMIT
    assert met["AGSF-galerkin-managed predict (capacity 16) ÷ fused GSF predict (N=5), 6-state B=4096"] == "yes"
    assert met["weight QP, galerkin-managed problems N=16 B=8192: speed-up per problem over Clarabel"] == "yes"
    assert met["peak RSS, AGSF-managed predict + update at B=8192, capacity 16 (GB)"] == "no"
    assert "weight QP, galerkin-managed problems N=16 B=8192, 5 active on average: torch 10.00 µs/problem" in table
    assert "GSF 500.0 ms, GSF-managed 10000.0 ms → 20.0×" in table
    main = (
        "main job (agsf reproduce --case all): speed-up over the reference code (abc1234), medians of alternated rounds"
    )
    assert met[main] == "no" and rows[main][1].startswith("the cases side by side take turns")  # 48 / 12 = 4 < 5
    assert (
        "main job (agsf reproduce --case all) in a new process: 12.0 s as shipped (cases side by side), 20.0 s with "
        "the cases one after another (--jobs 1), 30.0 s on the generic path one after another (--set fused=false "
        "--jobs 1)" in table
    )
    assert (
        "main job, alternated with the reference code (abc1234): 11.0 s against 47.0 s, 12.0 s against 48.0 s" in table
    )
    del report["main_job"]["reference_seconds"]  # without a reference: no target row, and a line saying how to get it
    report["targets"] = bench.targets(report)
    table = bench.format_table(report)
    assert main not in table and "agsf bench --main-job-reference DIR" in table
    assert "20.0 % of the float64 matmul peak" in table
    lines = table.splitlines()
    for k, line in enumerate(lines[1:], 1):  # every Markdown table: a rule with one cell per header cell
        if set(line.replace("|", "").split()) == {"---"}:
            assert line.count("|") == lines[k - 1].count("|"), lines[k - 1]


def test_peak_memory_is_the_processs_own_not_its_parents_at_the_fork():
    """A process started by a large one: getrusage's max RSS would report the parent's resident memory."""
    import subprocess
    import sys

    code = "from agsf_torch.experiments.run.resources import peak_resident_memory; print(peak_resident_memory())"
    ballast = torch.ones(2**27, dtype=torch.float64)  # 1 GiB resident in this process
    ballast.add_(1.0)
    child = int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    assert 2**20 < child < 2**29  # torch's import: tens to a few hundred MiB, far below the parent's GiB


def test_a_main_job_reference_that_is_not_a_checkout_is_refused_naming_it(tmp_path):
    import pytest

    with pytest.raises(ValueError, match=f"--main-job-reference {tmp_path} is not a checkout of agsf-torch"):
        bench.check_reference(tmp_path)
    assert bench.check_reference(None) is None
    assert bench.check_reference(bench.IMPORT_ROOT) == bench.IMPORT_ROOT.resolve()


@pytest.mark.parametrize("command", ["cli.py", "cli/__main__.py"])
def test_the_main_job_of_a_reference_checkout_runs_that_checkouts_code(tmp_path, command):
    """``python -m`` puts the working folder first on the path: the reference's job runs there, or it would
    silently time this checkout's code (as a first version of the option did).  The command is a module in
    earlier layouts, a package's ``__main__`` in this one."""
    package = tmp_path / "agsf_torch" / "experiments"
    package.mkdir(parents=True)
    (tmp_path / "agsf_torch" / "__init__.py").write_text("")
    (package / "__init__.py").write_text("")
    marker = tmp_path / "ran"
    (package / command).parent.mkdir(exist_ok=True)
    (package / command).write_text(f"import sys\nopen({str(marker)!r}, 'w').write(' '.join(sys.argv[1:]))\n")
    seconds = bench._main_job_seconds(["--jobs", "1"], bench.check_reference(tmp_path))
    assert seconds > 0 and marker.read_text().startswith("reproduce --case all --out ")
    assert marker.read_text().endswith("--quiet --jobs 1")
