"""``agsf soak``: a long run that checks the filters stay healthy, with flat memory.

The soak drives the filters of a configuration (default: case 1 as a 6-state
filter with the iterated update, one simulated hour at 10 Hz) through
:func:`~agsf_torch.experiments.run.runner.monte_carlo_steps` and keeps **running
statistics only**, so its memory does not grow with the length of the run.  Every
``report_every`` seconds of simulated time it records one row:

* ``rss_mb``: the process's resident memory (Linux ``/proc/self/status``);
* per filter: RMS attitude error (arcsec), mean NEES, the share of state errors
  inside ±3σ of the filter's covariance (per state component), non-finite
  values seen, and the smallest ``λ_min/λ_max`` of any component covariance
  (positive: positive definite; a filter raises as soon as one is not).

The verdict (:func:`soak_verdict`) after a warm-up (the first ``warmup`` seconds,
when a 7° prior converges): no non-finite value, all covariances positive
definite, every state component inside ±3σ at least ``min_inside`` of the time
(a consistent Gaussian error is inside 99.73 % of the time; the default
criterion is 99 %), and memory flat: RSS growth from the first report after the
warm-up to the last below ``max_rss_growth_mb``.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...consistency import nees
from ...constants import ARCSEC_PER_RAD, ATTITUDE_RADIANS_PER_MRP
from ...filters.registry import ADAPTIVE_FILTERS
from ...storage.files import append_line, json_text, write_text
from ..config.factories import loop_options
from ..config.loader import ExperimentConfig, load_preset
from ..run.experiment import make_env, make_filters, prepare_output
from ..run.resources import check_memory, resident_memory
from ..run.runner import monte_carlo_steps

__all__ = ["soak_config", "run_soak", "soak_verdict", "rss_mb"]


def rss_mb() -> float:
    """Current resident set size of this process (MiB; :func:`~agsf_torch.experiments.run.resources.resident_memory`)."""
    return resident_memory() / 2**20


def soak_config(filter_name: str = "GSF", **changes: Any) -> ExperimentConfig:
    """The soak's default configuration: case 1, 6-state, iterated update, 256 runs, one hour."""
    base = load_preset("case1").replace(
        name=f"soak-{filter_name}",
        runs=256,
        duration=3600.0,
        estimate_bias=True,
        update_iterations=3,
        filters=[filter_name],
        compile=filter_name in ADAPTIVE_FILTERS,
        compile_fused=False,
    )
    return base.replace(**changes) if changes else base


class _Stats:
    """Running sums of one filter over one report interval."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.reset()

    def reset(self) -> None:
        self.steps = 0
        self.sq_angle = 0.0
        self.count = 0
        self.nees = 0.0
        self.inside = np.zeros(self.n)
        self.nonfinite = 0
        self.min_eig_ratio = math.inf

    def add(self, fs, err, check_eigs: bool) -> None:
        """Add one step of one filter: ``fs`` (:class:`~agsf_torch.filter_loop.FilterStep`) and its
        chart error ``err [B, n]`` (MRP, rad/s)."""
        cov = fs.cov
        sigma = cov.diagonal(dim1=-2, dim2=-1).sqrt()
        self.steps += 1
        self.count += err.shape[0]
        bad = ~torch.isfinite(err).all(-1) | ~torch.isfinite(cov).flatten(-2).all(-1)
        self.nonfinite += int(bad.sum()) + int((~torch.isfinite(fs.mixture.covs)).sum())
        self.sq_angle += float(((ATTITUDE_RADIANS_PER_MRP * err[:, :3].norm(dim=-1)) ** 2).sum())
        self.nees += float(nees(err, cov).sum())
        self.inside += (err.abs() <= 3.0 * sigma).sum(0).double().numpy()
        if check_eigs:
            ev = torch.linalg.eigvalsh(fs.mixture.covs)
            self.min_eig_ratio = min(self.min_eig_ratio, float((ev[..., 0] / ev[..., -1]).min()))

    def row(self) -> dict[str, Any]:
        c = max(self.count, 1)
        return {
            "rms_arcsec": math.sqrt(self.sq_angle / c) * ARCSEC_PER_RAD,
            "mean_nees": self.nees / c,
            "inside_3sigma": (self.inside / c).tolist(),
            "nonfinite": self.nonfinite,
            "min_eig_ratio": self.min_eig_ratio,
        }


def run_soak(
    cfg: ExperimentConfig,
    out: Path | None = None,
    *,
    report_every: float = 60.0,
    warmup: float | None = None,
    progress: bool = False,
    force: bool = False,
) -> list[dict[str, Any]]:
    """Run ``cfg`` for its whole duration keeping running statistics; returns the report rows.

    Args:
        cfg: the configuration (see :func:`soak_config`).
        out: if given, an experiment folder (:func:`~agsf_torch.experiments.run.outputs.prepare_output`, created after
            every check) whose ``soak.jsonl`` gets each row as it is made (complete lines).
        report_every: simulated seconds per report row (a multiple of ``cfg.dt``).
        warmup: if given, the warm-up :func:`soak_verdict` will leave out, checked before anything runs: a
            multiple of ``report_every`` (the verdict leaves out whole rows, so a warm-up inside a row would
            count the rest of that row, the prior's stretch included) and shorter than the run.
        progress: print each row (on stderr).
        force: run even if the memory estimate (:func:`~agsf_torch.experiments.run.resources.check_memory`, running
            statistics only) exceeds the memory available.
    """
    per_report = int(round(report_every / cfg.dt))
    if per_report < 1 or abs(per_report * cfg.dt - report_every) > 1e-9 * report_every:
        raise ValueError(f"report_every must be a positive multiple of dt={cfg.dt}, got {report_every}")
    if warmup is not None:
        rows_out = warmup / report_every
        if abs(rows_out - round(rows_out)) > 1e-9 * max(1.0, rows_out):
            raise ValueError(
                f"the warm-up must be a multiple of report_every={report_every:g} s (the verdict leaves out whole "
                f"report rows), got {warmup:g} s"
            )
        end = cfg.num_steps * cfg.dt
        if warmup >= end * (1.0 - 1e-9):
            raise ValueError(
                f"the warm-up of {warmup:g} s leaves no report to judge in a run of {end:g} s: shorten the warm-up "
                "or lengthen the run"
            )
    check_memory(cfg, force=force, keep_steps=False)
    env, setups = make_env(cfg), make_filters(cfg)
    n = next(iter(setups.values())).filter.model.state_dim
    stats = {name: _Stats(n) for name in setups}
    log = None
    if out is not None:
        out = prepare_output(Path(out), "soak", f"{cfg.digest()}:report_every={report_every}", cfg.to_dict())
        log = write_text(out / "soak.jsonl", "")  # a rerun starts the log afresh
    rows: list[dict[str, Any]] = []
    start = time.perf_counter()
    steps = monte_carlo_steps(env, setups, **loop_options(cfg))
    try:
        for step in steps:
            last = (step.index + 1) % per_report == 0 or step.index + 1 == cfg.num_steps
            for name, fs in step.filters.items():
                stats[name].add(fs, step.chart_error[name], check_eigs=last)
            if not last:
                continue
            row = {
                "time_s": step.time,
                "wall_s": time.perf_counter() - start,
                "rss_mb": rss_mb(),
                "filters": {name: s.row() for name, s in stats.items()},
            }
            for s in stats.values():
                s.reset()
            rows.append(row)
            if log is not None:
                append_line(log, json_text(row))
            if progress:
                f = "  ".join(
                    f"{k}: {v['rms_arcsec']:.3f}″ NEES {v['mean_nees']:.2f} in3σ {min(v['inside_3sigma']):.4f}"
                    for k, v in row["filters"].items()
                )
                print(
                    f"t = {row['time_s']:7.1f} s  wall {row['wall_s']:7.1f} s  RSS {row['rss_mb']:7.1f} MB  {f}",
                    file=sys.stderr,
                    flush=True,
                )
    finally:
        steps.close()
    return rows


def soak_verdict(
    rows: list[dict[str, Any]],
    *,
    warmup: float = 60.0,
    min_inside: float = 0.99,
    max_rss_growth_mb: float = 50.0,
) -> dict[str, Any]:
    """Pass/fail of a soak from its rows (module docstring); ``passed`` is the overall verdict."""
    after = [r for r in rows if r["time_s"] > warmup + 1e-9]
    if not after:
        raise ValueError(f"no report after the warm-up of {warmup} s")
    verdict: dict[str, Any] = {"warmup_s": warmup, "filters": {}}
    ok = True
    for name in after[0]["filters"]:
        fr = [r["filters"][name] for r in after]
        inside = np.mean([f["inside_3sigma"] for f in fr], axis=0)
        entry = {
            "nonfinite": int(sum(r["filters"][name]["nonfinite"] for r in rows)),
            "min_eig_ratio": float(min(r["filters"][name]["min_eig_ratio"] for r in rows)),
            "inside_3sigma": inside.tolist(),
            "mean_nees": float(np.mean([f["mean_nees"] for f in fr])),
            "rms_arcsec_last": fr[-1]["rms_arcsec"],
        }
        entry["passed"] = entry["nonfinite"] == 0 and entry["min_eig_ratio"] > 0 and bool((inside >= min_inside).all())
        ok = ok and entry["passed"]
        verdict["filters"][name] = entry
    growth = after[-1]["rss_mb"] - after[0]["rss_mb"]
    verdict["rss_mb_first"] = after[0]["rss_mb"]
    verdict["rss_mb_last"] = after[-1]["rss_mb"]
    verdict["rss_growth_mb"] = growth
    verdict["memory_flat"] = growth < max_rss_growth_mb
    verdict["passed"] = ok and verdict["memory_flat"]
    return verdict
