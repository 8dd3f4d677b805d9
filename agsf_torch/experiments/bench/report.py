"""The benchmark's report: each target with its measured value and met / not met, and the Markdown table."""

from __future__ import annotations

from typing import Any

__all__ = ["targets", "format_table"]


def targets(r: dict[str, Any]) -> list[dict[str, Any]]:
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
        add(
            f"first {row['update']} step in a new process{' (compiled)' if row['compile'] else ''} (s)",
            row["first_process_s"],
            10.0,
        )
    for q in r["qp"]:
        add(f"weight QP N={q['N']} B={q['B']}: speed-up per problem over Clarabel", q["speedup"], 100.0, lower=False)
    p = r["peers"]
    add(f"GSF 6-state N=5 B={p['B']} ÷ filterpy loop (component-steps/s)", p["vs_filterpy"], 300.0, lower=False)
    add(f"GSF 6-state N=5 B={p['B']} ÷ NumPy batch (component-steps/s)", p["vs_numpy"], 3.0, lower=False)
    add(f"peak RSS, B={r['memory_sweep']['batch']} × N=5 GSF sweep (GB)", r["memory_sweep"]["peak_rss_mib"] / 1024, 4.0)
    for m in r["memory_adaptive"]:
        add(f"peak RSS, {m['update']} adaptive step at B={m['batch']} (GB)", m["peak_rss_mib"] / 1024, 8.0)
    return t


def met(t: dict[str, Any]) -> bool:
    """Whether a target of :func:`targets` is met."""
    return t["measured"] <= t["goal"] if t["lower_is_better"] else t["measured"] >= t["goal"]


def format_table(r: dict[str, Any]) -> str:
    """The report as Markdown: the measurements, then every target with met / not met."""
    m = r["machine"]
    lines = [
        f"machine: torch {m['torch']}, {m['threads']} threads, {m['cpu_count']} CPUs, Python {m['python']}, "
        f"load {m['load_average_at_start']:.2f} at start; float64 matmul peak {r['matmul_peak_gflops']:.1f} GFLOP/s",
        "",
        "| n | N | B | GSF s | AGSF Galerkin s | AGSF penalty s (eager / compiled) | Galerkin ÷ GSF | penalty ÷ GSF (faster) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for a in r["adaptive"]:
        s = a["seconds"]
        compiled = f" / {s['AGSF-penalty-compiled']:.3f}" if "AGSF-penalty-compiled" in s else ""
        lines.append(
            f"| {a['state_dim']} | {a['N']} | {a['B']} | {s['GSF']:.4f} | {s['AGSF-galerkin']:.4f} | "
            f"{s['AGSF-penalty']:.3f}{compiled} | {a['galerkin_ratio']:.1f}× | {a['penalty_ratio']:.0f}× |"
        )
    lines.append("")
    for row in r["first_step"]:
        lines.append(
            f"first {row['update']} step{' (compiled)' if row['compile'] else ''} in a new process: "
            f"{row['first_process_s']:.1f} s, again in a second process: {row['second_process_s']:.1f} s"
        )
    for q in r["qp"]:
        lines.append(
            f"weight QP N={q['N']} B={q['B']}: torch {q['torch_seconds_per_problem'] * 1e6:.2f} µs/problem, Clarabel "
            f"{q['clarabel_seconds_per_problem'] * 1e6:.0f} µs/problem → {q['speedup']:.0f}× (KKT torch "
            f"{q['torch_max_kkt_residual']:.1e}, Clarabel {q['clarabel_max_kkt_residual']:.1e}, max |Δw| {q['max_abs_difference']:.1e})"
        )
    p = r["peers"]
    lines += [
        f"GSF predict 6-state N=5 B={p['B']}: {p['gsf_component_steps_per_s']:.3g} component-steps/s; "
        f"{p['filterpy']['what']}: {p['filterpy']['component_steps_per_s']:.3g} ({p['vs_filterpy']:.0f}×); "
        f"{p['numpy']['what']}: {p['numpy']['component_steps_per_s']:.3g} ({p['vs_numpy']:.2f}×)"
    ]
    for mem in (r["memory_sweep"], *r["memory_adaptive"]):
        lines.append(f"memory: {mem['what']}: peak RSS {mem['peak_rss_mib']:.0f} MiB ({mem['seconds']:.0f} s)")
    lines += ["", "| target | measured | goal | met |", "| --- | --- | --- | --- |"]
    for t in r["targets"]:
        goal = f"{'≤' if t['lower_is_better'] else '≥'} {t['goal']:g}"
        lines.append(f"| {t['target']} | {t['measured']:.3g} | {goal} | {'yes' if met(t) else 'no'} |")
    lines.append(f"\ntotal bench time {r['total_seconds']:.0f} s")
    return "\n".join(lines)
