"""``agsf sweep``: a resumable grid of configurations, each a batched Monte Carlo.

Every finished configuration is appended as one JSON line to ``results.jsonl``
(with the configuration's digest) before the next starts; a rerun with the same
base and grid skips the digests already there, so an interrupted sweep loses
at most the configuration that was running.  TensorBoard's hparams view gets one
entry per configuration under ``out/tensorboard``.
"""

from __future__ import annotations

import hashlib
import itertools
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .config import ExperimentConfig, parse_override
from .experiment import prepare_output, run_experiment

__all__ = ["parse_grid", "run_sweep"]


def parse_grid(items: list[str]) -> dict[str, list[Any]]:
    """``["key=v1,v2", …]`` → ``{key: [v1, v2]}`` (values parsed as TOML; keys validated)."""
    grid: dict[str, list[Any]] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"grid entry {item!r} must look like key=v1,v2,...")
        key, values = item.split("=", 1)
        grid[key.strip()] = [parse_override(f"{key}={v}")[1] for v in values.split(",")]
        if key.strip() in ("runs", "filters"):
            raise ValueError(f"config key '{key.strip()}' cannot be swept")
    if not grid:
        raise ValueError("a sweep needs at least one --grid key=v1,v2,...")
    return grid


def _metrics(summary: dict[str, Any]) -> dict[str, float]:
    m: dict[str, float] = {}
    for name, f in summary["filters"].items():
        if "between_updates" in f:
            m[f"{name}/mean_rms_between_updates_deg"] = f["between_updates"]["mean_rms_deg"]
        m[f"{name}/time_averaged_nees"] = f["time_averaged_nees"]
    d = summary.get("agsf_minus_gsf", {}).get("between_updates")
    if d:
        m["agsf_minus_gsf_deg"] = d["mean_deg"]
    return m


def run_sweep(
    base: ExperimentConfig,
    grid: dict[str, list[Any]],
    out: Path,
    *,
    progress: bool = True,
    runner: Callable[..., dict[str, Any]] = run_experiment,
) -> list[dict[str, Any]]:
    """Run every combination of ``grid`` on top of ``base``; returns all result rows."""
    configs = []
    for values in itertools.product(*grid.values()):
        params = dict(zip(grid, values))
        configs.append((params, base.replace(**params)))  # validates every configuration first
    digest = hashlib.sha256(json.dumps({"base": base.digest(), "grid": grid}, sort_keys=True).encode()).hexdigest()[:16]
    out = prepare_output(Path(out), "sweep", digest, {"base": base.to_dict(), "grid": grid})
    results = out / "results.jsonl"
    rows = [json.loads(line) for line in results.read_text().splitlines()] if results.exists() else []
    done = {r["digest"] for r in rows}
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(out / "tensorboard"))
    try:
        for params, cfg in configs:
            if cfg.digest() in done:
                continue
            summary = runner(cfg, out / "configs" / cfg.digest(), progress=progress, kind="sweep-config")
            row = {"digest": cfg.digest(), "params": params, "metrics": _metrics(summary)}
            with results.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            rows.append(row)
            hp = {k: (v if isinstance(v, (int, float, str, bool)) else str(v)) for k, v in params.items()}
            writer.add_hparams(hp, row["metrics"], run_name=cfg.digest())
    finally:
        writer.close()
    return rows
