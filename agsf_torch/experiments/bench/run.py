"""``agsf bench``: the adaptive filter's cost against the classic one, honest peers, machine limits.

Every ratio comes from one run on one machine, the two sides timed alternately
(median of repeats after a warm-up), so a load change affects both.  Compilation
is measured on its own, in fresh processes.  The report ends with each target,
the measured value and whether it is met (:mod:`.report`).

Measured:

* the fused paths beside the landed (generic) ones and the peers (:mod:`.fused`): the GSF's
  predict against a filterpy loop, a NumPy batch and JAX ``jit(vmap(step))``, the star update,
  one spacecraft's predict + update, the first compiled step cold and warm, the fraction of the
  float64 peak;
* one predict step (one gyro interval) of the classic GSF (generic and fused), the adaptive GSF
  with the Galerkin update and with the paper's (penalty) update, 6-state N = 5 B = 256 and 4096
  (Galerkin) and 3-state N = 5 B = 1024;
* the first adaptive step in a new process (import, construction, first predict),
  twice, so the second run shows what the on-disk caches reuse;
* the weight QP against Clarabel called per problem (as its users call it, :mod:`.weight_qp`), on random
  strictly convex problems at N = 5, 16 and 32 and on the filters' own (the Galerkin and the penalty updates' at
  N = 5, 16 and 32, the managed Galerkin filter's held QP at capacity 16), B = 8192;
* mixture management (:mod:`.managed`): GSF-managed predict + update and AGSF-galerkin-managed predict at
  capacity 16, B = 4096, beside the fused GSF at N = 5;
* peak resident memory of a B = 65,536 × N = 5 GSF sweep, of an adaptive step at B = 8192 and of one predict +
  update of each managed filter at capacity 16, B = 8192, each in a fresh process.

Each group of rows is a key of the report (:data:`SECTIONS`); ``run_bench(only=...)`` (and
``python -m agsf_torch.experiments.bench --only KEY ...``) runs the named groups alone.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...storage.files import write_json
from .fused import bench_compile, bench_propagation, bench_spacecraft, bench_update
from .harness import IMPORT_ROOT, MANAGED_FILTERS, WEIGHT_UPDATE_FILTERS, attitude_mixture, median_time, side_by_side
from .managed import bench_managed_galerkin, bench_managed_gsf
from .report import format_table, targets
from .weight_qp import bench_qp, bench_qp_filter

__all__ = ["run_bench", "format_table", "targets", "SECTIONS", "check_sections"]

#: The report's groups of rows, each the key it is stored under in ``bench.json``, in the order they run.
SECTIONS = (
    "propagation",
    "update",
    "spacecraft",
    "adaptive",
    "first_step",
    "qp",
    "qp_filter",
    "managed",
    "compile",
    "main_job",
    "memory_sweep",
    "memory_adaptive",
    "memory_managed",
)
#: The random QP sizes (``qp``) and the filters' QP problems with their sizes (``qp_filter``, :mod:`.weight_qp`).
QP_SIZES = (5, 16, 32)
QP_FILTER_PROBLEMS = (
    ("galerkin", 5),
    ("penalty", 5),
    ("galerkin", 16),
    ("penalty", 16),
    ("galerkin-managed", 16),
    ("galerkin", 32),
    ("penalty", 32),
)

F64 = torch.float64


def bench_adaptive(
    estimate_bias: bool, B: int, N: int = 5, repeats: int = 5, compile: bool = False, penalty: bool = True
) -> dict[str, Any]:
    """One predict step of the GSF (generic, and fused: compiled if ``compile``), AGSF (Galerkin) and AGSF
    (penalty, if ``penalty``), the adaptive ones with the same fused propagation, timed side by side; the
    penalty update with ``L`` by the batched route (the reference row) after them, on its own; the ratios
    are to the fused GSF."""
    from ...filters.registry import make_filter
    from ...models import AttitudeModel

    model = AttitudeModel(estimate_bias=estimate_bias)
    mix = attitude_mixture(B, N, estimate_bias, torch.Generator().manual_seed(0))
    u = torch.full((B, 3), 0.06, dtype=F64)
    filters = {
        "GSF (generic)": make_filter("GSF", model, fused=False),
        "GSF": make_filter("GSF", model, compile_fused=compile),
        "AGSF-galerkin": make_filter("AGSF-galerkin", model, compile_fused=compile),
    }
    if penalty:
        filters["AGSF-penalty"] = make_filter("AGSF", model, compile=compile, compile_fused=compile)

        class BatchedAttitudeModel(AttitudeModel):
            def fpke_pair_products(self, u, pairs, *, compile=False):  # the reference row: the batched route
                if not self.estimate_bias:
                    return None  # the generic 84-node interpolatory rule
                from ...models.attitude_bias_block import attitude_pair_products

                return attitude_pair_products(self, u, pairs)

            def fused_penalty_pairs(self, means, covs, u, *, compile=False):  # nor the pairs' moments on lanes
                return None

        reference = make_filter(
            "AGSF", BatchedAttitudeModel(estimate_bias=estimate_bias), compile=compile, compile_fused=compile
        )
    sec = side_by_side({k: (lambda f=f: f.predict(mix, u, 0.1)) for k, f in filters.items()}, repeats)
    if penalty:
        # timed on its own: alternated with the others, its frees of hundreds of MB (returned to the system by
        # the allocator) make the next calls fault their memory back in
        sec["AGSF-penalty (batched)"] = median_time(lambda: reference.predict(mix, u, 0.1), repeats)
    out = {
        "state_dim": model.state_dim,
        "N": N,
        "B": B,
        "compiled": compile,
        "seconds": sec,
        "galerkin_ratio": sec["AGSF-galerkin"] / sec["GSF"],
        "galerkin_ratio_to_generic_gsf": sec["AGSF-galerkin"] / sec["GSF (generic)"],
    }
    if penalty:
        out["penalty_ratio"] = sec["AGSF-penalty"] / sec["GSF"]
        out["penalty_seconds"] = sec["AGSF-penalty"]
        out["penalty_batched_ratio"] = sec["AGSF-penalty (batched)"] / sec["GSF"]
    return out


_FIRST_STEP_SCRIPT = """
import time, sys
t0 = time.perf_counter()
import torch
sys.path.insert(0, {root!r})
from agsf_torch.experiments.bench.harness import attitude_mixture
from agsf_torch.filters.registry import make_filter
from agsf_torch.models import AttitudeModel
model = AttitudeModel(estimate_bias=True)
filt = make_filter({name!r}, model, compile={compile})
mix = attitude_mixture(256, 5, True, torch.Generator().manual_seed(0))
filt.predict(mix, torch.full((256, 3), 0.06, dtype=torch.float64), 0.1)
print(time.perf_counter() - t0)
"""


def _source_env(root: Path = IMPORT_ROOT) -> dict[str, str]:
    """The environment of a subprocess that imports the package of the checkout ``root`` (this one by default) first."""
    return {**os.environ, "PYTHONPATH": str(root) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def bench_first_step(cases: tuple[tuple[str, bool], ...]) -> list[dict[str, Any]]:
    """Seconds from a new process's start to its first adaptive predict (6-state, N = 5, B = 256), twice per case."""
    root = str(IMPORT_ROOT)
    rows = []
    for update, compile in cases:
        secs = []
        for _ in range(2):
            script = _FIRST_STEP_SCRIPT.format(root=root, name=WEIGHT_UPDATE_FILTERS[update], compile=compile)
            out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
            secs.append(float(out.stdout.strip().splitlines()[-1]))
        rows.append({"update": update, "compile": compile, "first_process_s": secs[0], "second_process_s": secs[1]})
    return rows


def bench_matmul_peak(size: int = 2048) -> float:
    a = torch.randn(size, size, dtype=F64)
    b = torch.randn(size, size, dtype=F64)
    sec = median_time(lambda: a @ b, repeats=5, budget=20.0)
    return 2.0 * size**3 / sec


def _peak_rss(module_args: list[str]) -> dict[str, Any]:
    """Run ``python -m agsf_torch.experiments.bench.memory ARGS`` and return its JSON line with the wall time."""
    t = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-m", "agsf_torch.experiments.bench.memory", *module_args],
        capture_output=True,
        text=True,
        check=True,
        env=_source_env(),
    )
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "seconds": time.perf_counter() - t}


def check_reference(reference: str | Path | None) -> Path | None:
    """Validate ``agsf bench --main-job-reference``: a checkout of the package (a folder holding the command,
    ``agsf_torch/experiments/cli/__main__.py`` or, in earlier layouts, ``agsf_torch/experiments/cli.py``), or None.

    Raises:
        ValueError: naming the folder and what it lacks.
    """
    if reference is None:
        return None
    folder = Path(reference).resolve()
    cli = folder / "agsf_torch" / "experiments" / "cli"
    if not ((cli / "__main__.py").is_file() or cli.with_suffix(".py").is_file()):
        raise ValueError(
            f"--main-job-reference {reference} is not a checkout of agsf-torch (no agsf_torch/experiments/cli there)"
        )
    return folder


def _main_job_seconds(extra: list[str], code: Path = IMPORT_ROOT) -> float:
    """Wall seconds of ``agsf reproduce --case all`` in a new process running the checkout ``code`` (its working
    folder and the first entry of its ``PYTHONPATH``: ``python -m`` puts the working folder first, so another
    checkout's package would not be found), into a temporary folder."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "agsf_torch.experiments.cli", "reproduce"]
            + ["--case", "all", "--out", str(Path(tmp) / "reproduce"), "--quiet", *extra],
            capture_output=True,
            text=True,
            check=True,
            env=_source_env(code),
            cwd=code,
        )
        return time.perf_counter() - t


def bench_main_job(reference: Path | None = None, rounds: int = 3) -> dict[str, Any]:
    """Wall seconds of the main job, ``agsf reproduce --case all`` (100 runs × 30 s per case, every figure and
    event file), each in a new process running the ``agsf`` command into a temporary folder, in the same run: on
    the generic path with the cases one after another (``--set fused=false --jobs 1``: every filter and weight
    update as before the fused kernels, each case's files written beside the next case), as shipped but with the
    cases one after another (``--jobs 1``), and as shipped (the fused paths, the cases side by side in forked
    processes on a machine of two CPUs or more).  With ``reference`` (a checkout of earlier code, a git worktree
    say) its main job and this one's, as shipped, alternate ``rounds`` times, and each is the median of its
    rounds (``reference_seconds``, ``seconds``; ``reference_commit`` names it if it is a git checkout)."""
    result: dict[str, Any] = {
        "generic_seconds": _main_job_seconds(["--set", "fused=false", "--jobs", "1"]),
        "sequential_seconds": _main_job_seconds(["--jobs", "1"]),
    }
    if reference is None:
        result["seconds"] = _main_job_seconds([])
        return result
    ours, theirs = [], []
    for _ in range(rounds):
        theirs.append(_main_job_seconds([], reference))
        ours.append(_main_job_seconds([]))
    commit = subprocess.run(
        ["git", "-C", str(reference), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    )
    result |= {
        "seconds": float(np.median(ours)),
        "rounds_seconds": ours,
        "reference_seconds": float(np.median(theirs)),
        "reference_rounds_seconds": theirs,
        "reference": str(reference),
        "reference_commit": commit.stdout.strip() if commit.returncode == 0 else None,
    }
    return result


def check_sections(only: Any) -> tuple[str, ...]:
    """Validate ``run_bench(only=...)``: ``None`` (every group) or names of :data:`SECTIONS`.

    Raises:
        ValueError: naming the unknown groups and the known ones.
    """
    if only is None:
        return SECTIONS
    names = (only,) if isinstance(only, str) else tuple(only)
    unknown = [k for k in names if k not in SECTIONS]
    if unknown or not names:
        raise ValueError(f"unknown bench section(s) {unknown}; known: {', '.join(SECTIONS)}")
    return tuple(k for k in SECTIONS if k in names)


def run_bench(
    out: Path | None = None,
    *,
    compile: bool = True,
    quick: bool = False,
    main_job_reference: Path | None = None,
    only: Any = None,
) -> dict[str, Any]:
    """Run every measurement, or the groups named in ``only`` (:data:`SECTIONS`); write ``bench.json`` under
    ``out`` if given (``quick``: small sizes, a smoke run; ``main_job_reference``: a checkout of earlier code whose
    main job is timed beside this one's, :func:`bench_main_job`)."""
    main_job_reference = check_reference(main_job_reference)
    sections = check_sections(only)
    t0 = time.perf_counter()
    report: dict[str, Any] = {
        "machine": {
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "cpu_count": os.cpu_count(),
            "python": sys.version.split()[0],
            "load_average_at_start": os.getloadavg()[0],
        },
        "sections": list(sections),
    }
    report["matmul_peak_gflops"] = bench_matmul_peak(512 if quick else 2048) / 1e9
    reps = 2 if quick else 5
    if "propagation" in sections:
        report["propagation"] = bench_propagation(
            B=256 if quick else 8192,
            repeats=reps,
            compile=compile,
            filterpy_samples=100 if quick else 2000,
            peak_flops=report["matmul_peak_gflops"] * 1e9,
        )
    if "update" in sections:
        report["update"] = bench_update(B=64 if quick else 4096, repeats=reps, compile=compile)
    if "spacecraft" in sections:
        report["spacecraft"] = bench_spacecraft(repeats=5 if quick else 50, compile=compile)
    if "adaptive" in sections:
        report["adaptive"] = [
            bench_adaptive(True, 16 if quick else 256, repeats=reps, compile=compile),
            bench_adaptive(True, 64 if quick else 4096, repeats=reps, compile=compile, penalty=False),
            bench_adaptive(False, 32 if quick else 1024, repeats=reps, compile=compile),
        ]
    if "first_step" in sections:
        cases = (("galerkin", False), ("penalty", False)) + ((("penalty", True),) if compile else ())
        report["first_step"] = bench_first_step(cases[:1] if quick else cases)
    qp_batch, qp_samples = (256, 20) if quick else (8192, 300)
    if "qp" in sections:
        report["qp"] = [bench_qp(B=qp_batch, N=N, clarabel_samples=qp_samples, repeats=reps) for N in QP_SIZES]
    if "qp_filter" in sections:
        report["qp_filter"] = [
            bench_qp_filter(p, B=qp_batch, N=N, clarabel_samples=qp_samples, repeats=reps, compile=compile)
            for p, N in QP_FILTER_PROBLEMS
        ]
    if "managed" in sections:
        B = 64 if quick else 4096
        report["managed"] = {
            "gsf": bench_managed_gsf(B=B, repeats=reps, compile=compile),
            "galerkin": bench_managed_galerkin(B=B, repeats=reps, compile=compile),
        }
    if compile and not quick and "compile" in sections:
        report["compile"] = bench_compile()
    if not quick and "main_job" in sections:
        report["main_job"] = bench_main_job(main_job_reference)
    if "memory_sweep" in sections:
        report["memory_sweep"] = _peak_rss(
            ["gsf", "--batch", str(4096 if quick else 65536), "--chunk", "4096" if quick else "16384"]
        )
    if "memory_adaptive" in sections:
        report["memory_adaptive"] = [
            _peak_rss(["adaptive", "--update", up, "--batch", str(64 if quick else 8192)])
            for up in ("galerkin", "penalty")
        ]
    if "memory_managed" in sections:
        report["memory_managed"] = [
            _peak_rss(
                ["managed", "--filter", name, "--batch", str(64 if quick else 8192), "--capacity", "16"]
                + (["--compile"] if compile else [])
            )
            for name in MANAGED_FILTERS
        ]
    report["machine"]["load_average_at_end"] = os.getloadavg()[0]
    report["total_seconds"] = time.perf_counter() - t0
    report["targets"] = targets(report)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "bench.json", report, indent=2)
    return report
