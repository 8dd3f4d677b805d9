"""The benchmark's report: each target with its measured value and met / not met, and the Markdown table."""

from __future__ import annotations

from typing import Any

__all__ = ["targets", "format_table"]

#: What bounds the managed rows and the weight QP's speed-up, where a target is not met (profiled; see
#: docs/results/performance.md, "Mixture management").
MANAGED_GSF_LIMIT = (
    "the second-order update (management's default): the generic Kalman update of the slots the active "
    "components need (all 16 here: the update's splits leave 15 active) with the measurement's second-order terms, "
    "whose noise covariance is dense over the 15 star entries (the fused star update, which the EKF update takes, "
    "goes star by star), about four fifths of the step; the measurement's second differences over the MRP (10 "
    "points per slot) and, for the split test before the pass, along every axis (13 points per slot); the "
    "management passes' pair bounds and entropy test are a small part (profile: performance.md)"
)
MANAGED_GALERKIN_LIMIT = (
    "the Galerkin update over the 6 slots the 5 active components need (management.slot_count: 21 pairs) and its "
    "QP, the management pass (pair bounds, the entropy test over those 6 slots) and their propagation (profile: "
    "performance.md)"
)
QP_LIMIT = (
    "the torch solver's active-set iterations, each a batched LAPACK solve of the [B, N+1, N+1] KKT systems, with "
    "the convexity Cholesky and the KKT residual, against Clarabel's per-problem solve (its setup included): the "
    "per-problem times in the rows above say how far each N is from 100×"
)


def targets(r: dict[str, Any]) -> list[dict[str, Any]]:
    """Each target: ``{"target", "measured", "goal", "lower_is_better", "limit"}`` (``limit``: what bounds it);
    a group of rows the report lacks (``run_bench(only=...)``) has none."""
    t = []

    def add(name: str, measured: float, goal: float, lower: bool = True, limit: str = "") -> None:
        t.append({"target": name, "measured": measured, "goal": goal, "lower_is_better": lower, "limit": limit})

    if "propagation" in r:
        p = r["propagation"]
        for peer, goal in (("filterpy", 300.0), ("numpy", 5.0), ("jax", 5.0)):
            if peer in p["vs"]:
                add(
                    f"GSF predict 6-state N=5 B={p['B']}: fused ÷ {peer} (component-steps/s)",
                    p["vs"][peer],
                    goal,
                    lower=False,
                )
    if "update" in r:
        u = r["update"]
        add(
            f"star update (5 stars) 6-state N=5 B={u['B']}: speed-up over the landed update",
            u["speedup"],
            10.0,
            lower=False,
            limit="the mixture NIS (a batched LAPACK factorisation per trajectory) and the wrapper's reshapes",
        )
    if "spacecraft" in r:
        sc = r["spacecraft"]
        add(
            "one spacecraft (B=1, N=5, 6-state): predict + update (ms)",
            sc["best_seconds"] * 1e3,
            1.0,
            limit="per-call overhead, ~100 small torch calls of 3–10 µs each (best of 300, AMD EPYC VM): validation "
            "~0.09 ms in the predict and ~0.10 ms in the update, the mixture NIS ~0.2 ms, each compiled kernel call "
            "with its wrapping ~0.12–0.15 ms, the chart check and the posterior ~0.09 ms",
        )
        add(
            "one spacecraft: speed-up over the filterpy loop on the same components",
            sc["vs_filterpy"],
            1.0,
            lower=False,
        )
    if "adaptive" in r:
        six, six_big, three = r["adaptive"]
        add(
            f"Galerkin AGSF predict ÷ fused GSF, 6-state N=5 B={six['B']}",
            six["galerkin_ratio"],
            5.0,
            limit="the pairs' kernel (M, K: 2,864 lane operations per pair, 3 pairs per component) and, outside the "
            "fused layer, the components' moment rates, Cholesky factors and the weight QP",
        )
        add(
            f"Galerkin AGSF predict ÷ fused GSF, 6-state N=5 B={six_big['B']}",
            six_big["galerkin_ratio"],
            5.0,
            limit="the pairs' kernel (M, K: 2,864 lane operations per pair, 3 pairs per component) and, outside the "
            "fused layer, the components' moment rates, Cholesky factors and the weight QP",
        )
        add(
            f"penalty AGSF predict ÷ fused GSF, 6-state N=5 B={six['B']}",
            six["penalty_ratio"],
            20.0,
            limit="the FPKE matrix L's compiled kernels, ~80 % of the step (profiled at B = 256, 2 cores: 3,840 pairs "
            "× 84 MRP nodes, ~700 lane operations per node and side and a [10, 84] × [84, 84] product per pair, in "
            "chunks of 128 pairs, the 1,280 pairs (i, i) with one side; the pairs' product Gaussians and rates); the "
            "propagation, the precisions and the weight QP are the rest",
        )
    if "managed" in r:
        g, a = r["managed"]["gsf"], r["managed"]["galerkin"]
        add(
            f"GSF-managed predict + update (capacity {g['capacity']}) ÷ fused GSF (N=5), 6-state B={g['B']}",
            g["ratio"],
            5.0,
            limit=MANAGED_GSF_LIMIT,
        )
        add(
            f"AGSF-galerkin-managed predict (capacity {a['capacity']}) ÷ fused GSF predict (N=5), 6-state B={a['B']}",
            a["ratio"],
            15.0,
            limit=MANAGED_GALERKIN_LIMIT,
        )
    if "compile" in r:
        c = r["compile"]
        add(
            "first compiled fused step in a new process, cache cold, each kernel compiled when first called (s)",
            c["cold_s"],
            60.0,
            limit="the kernels' compilations one after another (~2,100 graph nodes each: export, inductor's fusion "
            "search and code generation in Python, then the C++ compiler)",
        )
        add(
            "first compiled fused step in a new process, cache warm (s)",
            c["warm_s"],
            5.0,
            limit="importing torch (~2 s) and the first call of each loaded package",
        )
    if "main_job" in r and "reference_seconds" in r["main_job"]:
        mj = r["main_job"]
        add(
            f"main job (agsf reproduce --case all): speed-up over the reference code ({mj.get('reference_commit') or mj['reference']}), "
            "medians of alternated rounds",
            mj["reference_seconds"] / mj["seconds"],
            5.0,
            lower=False,
            limit="the cases side by side take turns on the cores, each in a forked process that runs one case end to "
            "end (its filters, runs.npz, four figures, event files); what is left is the parent's imports before it "
            "forks (torch, matplotlib: ~1.4 s on one core), 3,600 filter steps at 100 trajectories (the penalty "
            "update's 1,500 pairs × 84 nodes a step, the QPs, per-call overhead) and matplotlib's drawing (0.6 s a "
            "case)",
        )
    for row in r.get("first_step", ()):
        add(
            f"first {row['update']} step in a new process{' (compiled)' if row['compile'] else ''} (s)",
            row["first_process_s"],
            10.0,
            limit="compiling the lanes kernels ahead of time the first time on a machine (later processes load them)",
        )
    for q in r.get("qp", ()):
        add(
            f"weight QP N={q['N']} B={q['B']}: speed-up per problem over Clarabel",
            q["speedup"],
            100.0,
            lower=False,
            limit=QP_LIMIT,
        )
    for q in r.get("qp_filter", ()):
        add(
            f"weight QP, {q['problems']} problems N={q['N']} B={q['B']}: speed-up per problem over Clarabel",
            q["speedup"],
            100.0,
            lower=False,
            limit=QP_LIMIT,
        )
    if "memory_sweep" in r:
        m = r["memory_sweep"]
        add(f"peak RSS, B={m['batch']} × N=5 GSF sweep (GB)", m["peak_rss_mib"] / 1024, 4.0)
    for m in r.get("memory_adaptive", ()):
        add(f"peak RSS, {m['update']} adaptive step at B={m['batch']} (GB)", m["peak_rss_mib"] / 1024, 8.0)
    for m in r.get("memory_managed", ()):
        add(
            f"peak RSS, {m['filter']} predict + update at B={m['batch']}, capacity {m['capacity']} (GB)",
            m["peak_rss_mib"] / 1024,
            4.0,
        )
    return t


def met(t: dict[str, Any]) -> bool:
    """Whether a target of :func:`targets` is met."""
    return t["measured"] <= t["goal"] if t["lower_is_better"] else t["measured"] >= t["goal"]


def format_table(r: dict[str, Any]) -> str:
    """The report as Markdown: the measurements, then every target with met / not met (a group of rows the
    report lacks, ``run_bench(only=...)``, is left out)."""
    m = r["machine"]
    load_end = f", {m['load_average_at_end']:.2f} at end" if "load_average_at_end" in m else ""
    lines = [
        f"machine: torch {m['torch']}, {m['threads']} threads, {m['cpu_count']} CPUs, Python {m['python']}, "
        f"load {m['load_average_at_start']:.2f} at start{load_end}; float64 matmul peak "
        f"{r['matmul_peak_gflops']:.1f} GFLOP/s",
    ]
    if "adaptive" in r:
        lines += [
            "",
            "| n | N | B | GSF generic s | GSF fused s | AGSF Galerkin s | AGSF penalty s | AGSF penalty, batched L s "
            "| Galerkin ÷ fused GSF | penalty ÷ fused GSF | penalty (batched L) ÷ fused GSF |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
    for a in r.get("adaptive", ()):
        s = a["seconds"]
        pen = f"{s['AGSF-penalty']:.3f}" if "AGSF-penalty" in s else "—"
        pen_ratio = f"{a['penalty_ratio']:.0f}×" if "penalty_ratio" in a else "—"
        ref = s.get("AGSF-penalty (batched)")
        ref_s = "—" if ref is None else f"{ref:.3f}"
        ref_ratio = f"{a['penalty_batched_ratio']:.0f}×" if "penalty_batched_ratio" in a else "—"
        lines.append(
            f"| {a['state_dim']} | {a['N']} | {a['B']} | {s['GSF (generic)']:.4f} | {s['GSF']:.4f} | "
            f"{s['AGSF-galerkin']:.4f} | {pen} | {ref_s} | {a['galerkin_ratio']:.1f}× | {pen_ratio} | {ref_ratio} |"
        )
    if "propagation" in r:
        p = r["propagation"]
        lines += ["", f"GSF predict, 6-state N={p['N']} B={p['B']} ({p['B'] * p['N']} components), component-steps/s:"]
        lines += ["", "| implementation | component-steps/s | fused ÷ it |", "| --- | --- | --- |"]
        best = max(p["component_steps_per_s"].values())
        for name, v in p["component_steps_per_s"].items():
            lines.append(f"| ours, {name} | {v:.3g} | {best / v:.1f}× |")
        for key, peer in p["peers"].items():
            if "skipped" in peer:
                lines.append(f"| {key} | skipped: {peer['skipped']} | — |")
            else:
                lines.append(
                    f"| {peer['what']} | {peer['component_steps_per_s']:.3g} | "
                    f"{best / peer['component_steps_per_s']:.1f}× |"
                )
        frac = f"; {100 * p['fraction_of_peak']:.1f} % of the float64 matmul peak" if "fraction_of_peak" in p else ""
        lines.append(
            f"\nfused kernel: {p['kernel_flops_per_component_step']} FLOPs per component-step (counted from the "
            f"unrolled graph){frac}"
        )
    if "update" in r:
        u = r["update"]
        lines.append(
            f"star update, 6-state N={u['N']} B={u['B']}, 5 stars: "
            + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in u["seconds"].items())
            + f" → {u['speedup']:.1f}×"
        )
    if "spacecraft" in r:
        sc = r["spacecraft"]
        lines.append(
            f"one spacecraft (B=1, N={sc['N']}, 6-state) predict + update: "
            + ", ".join(f"{k} {v * 1e3:.2f} ms" for k, v in sc["seconds"].items())
            + f"; {sc['filterpy']['what']}: {sc['filterpy']['seconds'] * 1e3:.2f} ms"
        )
    if "compile" in r:
        lines.append(
            f"first compiled fused step in a new process: {r['compile']['cold_s']:.0f} s cold (each kernel compiled "
            f"when first called), {r['compile']['warm_s']:.1f} s warm"
        )
    lines.append("")
    if "main_job" in r:
        mj = r["main_job"]
        lines.append(
            f"main job (agsf reproduce --case all) in a new process: {mj['seconds']:.1f} s as shipped (cases "
            f"side by side), {mj['sequential_seconds']:.1f} s with the cases one after another (--jobs 1), "
            f"{mj['generic_seconds']:.1f} s on the generic path one after another (--set fused=false --jobs 1)"
        )
        if "reference_seconds" in mj:
            lines.append(
                f"main job, alternated with the reference code ({mj.get('reference_commit') or mj['reference']}): "
                + ", ".join(
                    f"{a:.1f} s against {b:.1f} s" for a, b in zip(mj["rounds_seconds"], mj["reference_rounds_seconds"])
                )
                + f" → {mj['reference_seconds'] / mj['seconds']:.2f}× (medians)"
            )
        else:
            lines.append(
                "main job: no reference code given (agsf bench --main-job-reference DIR times a checkout of earlier "
                "code beside this one's, for the speed-up target)"
            )
    for row in r.get("first_step", ()):
        lines.append(
            f"first {row['update']} step{' (compiled)' if row['compile'] else ''} in a new process: "
            f"{row['first_process_s']:.1f} s, again in a second process: {row['second_process_s']:.1f} s"
        )
    if "managed" in r:
        for key in ("gsf", "galerkin"):
            g = r["managed"][key]
            done = "; ".join(
                f"after the {step}: " + ", ".join(f"{k.replace('_', ' ')} {v:.2g}" for k, v in counts.items())
                for step, counts in g["management"].items()
            )
            lines.append(
                f"managed: {g['what']}{' (compiled)' if g['compiled'] else ''}: "
                + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in g["seconds"].items())
                + f" → {g['ratio']:.1f}×"
                + (f" (unmanaged Galerkin N=5: {g['unmanaged_ratio']:.1f}×)" if "unmanaged_ratio" in g else "")
                + f"; management per trajectory, mean: {done}"
            )
    for q in (*r.get("qp", ()), *r.get("qp_filter", ())):
        kind = "" if q.get("problems", "random") == "random" else f", {q['problems']} problems"
        active = f", {q['active_components']:.3g} active on average" if "active_components" in q else ""
        lines.append(
            f"weight QP{kind} N={q['N']} B={q['B']}{active}: torch {q['torch_seconds_per_problem'] * 1e6:.2f} "
            f"µs/problem, Clarabel {q['clarabel_seconds_per_problem'] * 1e6:.0f} µs/problem → {q['speedup']:.0f}× "
            f"(KKT torch {q['torch_max_kkt_residual']:.1e}, Clarabel {q['clarabel_max_kkt_residual']:.1e}, max |Δw| "
            f"{q['max_abs_difference']:.1e})"
        )
    memory = (*((r["memory_sweep"],) if "memory_sweep" in r else ()), *r.get("memory_adaptive", ()))
    for mem in (*memory, *r.get("memory_managed", ())):
        lines.append(f"memory: {mem['what']}: peak RSS {mem['peak_rss_mib']:.0f} MiB ({mem['seconds']:.0f} s)")
    lines += ["", "| target | measured | goal | met | what limits it |", "| --- | --- | --- | --- | --- |"]
    for t in r["targets"]:
        goal = f"{'≤' if t['lower_is_better'] else '≥'} {t['goal']:g}"
        limit = "" if met(t) else t.get("limit", "")
        lines.append(f"| {t['target']} | {t['measured']:.3g} | {goal} | {'yes' if met(t) else 'no'} | {limit} |")
    lines.append(f"\ntotal bench time {r['total_seconds']:.0f} s")
    return "\n".join(lines)
