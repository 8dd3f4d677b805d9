"""The ``agsf`` command.

Subcommands:

* ``agsf simulate`` — simulate B trajectories of the star-tracker environment and
  write the truth, gyro and star data (``simulation.npz``) and their statistics
  (``summary.json``) under ``--out``.
* ``agsf montecarlo`` — EKF, classic GSF and adaptive GSF on one star-tracker
  case, batched over ``--runs`` trajectories that all filters share; writes
  ``summary.json`` (the numbers behind the figure) and ``rms.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

__all__ = ["main"]


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite positive number, got {text}")
    return value


def _prepare_out(path: str, kind: str) -> Path:
    """Create the output folder; refuse to overwrite one that holds a different kind of run."""
    out = Path(path)
    marker = out / "summary.json"
    if marker.exists():
        previous = json.loads(marker.read_text()).get("command")
        if previous != kind:
            raise SystemExit(f"agsf: {out} already holds a '{previous}' run; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    return out


def _simulate(args: argparse.Namespace) -> int:
    import envs

    out = _prepare_out(args.out, "simulate")
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=args.runs, max_steps=args.steps, star_period=args.star_period)
    t0 = time.perf_counter()
    sim = env.simulate(args.steps, seed=args.seed)
    elapsed = time.perf_counter() - t0
    data = {k: v.numpy() for k, v in sim.items() if torch.is_tensor(v)}
    np.savez_compressed(out / "simulation.npz", **data)
    stars = data["star_mask"].sum(-1)
    counts = np.bincount(stars.ravel(), minlength=env.config.max_stars + 1)
    summary = {
        "command": "simulate",
        "runs": args.runs,
        "steps": args.steps,
        "seed": args.seed,
        "star_period_s": args.star_period,
        "seconds": elapsed,
        "stars_per_frame_histogram": counts.tolist(),
        "keys": sorted(data),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"simulated {args.runs} trajectories × {args.steps} steps in {elapsed:.1f} s → {out}")
    print(f"stars per frame (0..{env.config.max_stars}): {counts.tolist()}")
    return 0


def _montecarlo(args: argparse.Namespace) -> int:
    import envs

    from ..filters import AdaptiveGaussianSumFilter, ExtendedKalmanFilter, GaussianSumFilter
    from ..metrics import chi2_band
    from ..models import AttitudeModel
    from .runner import FilterSetup, run_monte_carlo

    torch.set_num_threads(max(1, args.threads))
    out = _prepare_out(args.out, "montecarlo")
    steps = int(round(args.duration / 0.1))
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=args.runs, max_steps=steps, star_period=args.star_period)
    model = AttitudeModel()
    kw = {"update_iterations": args.update_iterations}
    filters = {
        "EKF": FilterSetup(ExtendedKalmanFilter(model, **kw), 1),
        "GSF": FilterSetup(GaussianSumFilter(model, **kw), args.components),
        "AGSF": FilterSetup(AdaptiveGaussianSumFilter(model, **kw), args.components),
    }
    P0 = args.prior_var * torch.eye(3, dtype=torch.float64)
    t0 = time.perf_counter()
    res = run_monte_carlo(
        env, filters, num_steps=steps, prior_cov=P0, sigma_s=10e-6, seed=args.seed, progress=not args.quiet
    )
    elapsed = time.perf_counter() - t0
    lo, hi = chi2_band(3, args.runs)
    summary = {
        "command": "montecarlo",
        "runs": args.runs,
        "duration_s": args.duration,
        "star_period_s": args.star_period,
        "components": args.components,
        "prior_var_mrp2": args.prior_var,
        "update_iterations": args.update_iterations,
        "seed": args.seed,
        "seconds": elapsed,
        "time_s": res.time.tolist(),
        "nees_band_95": [lo, hi],
        "filters": {},
    }
    for name, tr in res.traces.items():
        rms = tr.rms_error()
        summary["filters"][name] = {
            "rms_error_rad": rms.tolist(),
            "final_rms_error_urad": float(rms[-1] * 1e6),
            "time_averaged_nees": float(tr.nees.mean()),
            "mean_weight_entropy": float(tr.weight_entropy.mean()),
        }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    _plot_rms(res, out / "rms.png")
    print(f"{args.runs} runs × {args.duration:g} s in {elapsed:.1f} s → {out}")
    for name, s in summary["filters"].items():
        print(f"  {name:5s} final RMS {s['final_rms_error_urad']:8.2f} µrad   time-averaged NEES {s['time_averaged_nees']:.3f}")
    print(f"  95% NEES band for {args.runs} runs: [{lo:.3f}, {hi:.3f}]")
    return 0


def _plot_rms(res, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, tr in res.traces.items():
        ax.semilogy(res.time, np.degrees(tr.rms_error()), label=name)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("RMS attitude error (deg)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agsf", description="Gaussian sum filters for spacecraft attitude")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate the star-tracker environment")
    p.add_argument("--runs", type=_positive_int, default=64, help="trajectories (batch)")
    p.add_argument("--steps", type=_positive_int, default=600, help="gyro periods of 0.1 s")
    p.add_argument("--star-period", type=_positive_float, default=1.0, help="s between star frames")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/simulation")
    p.set_defaults(func=_simulate)

    p = sub.add_parser("montecarlo", help="EKF, GSF and adaptive GSF on one case, batched")
    p.add_argument("--runs", type=_positive_int, default=100)
    p.add_argument("--duration", type=_positive_float, default=30.0, help="s")
    p.add_argument("--star-period", type=_positive_float, default=1.0, help="s between star frames")
    p.add_argument("--components", type=_positive_int, default=5)
    p.add_argument("--prior-var", type=_positive_float, default=1e-3, help="prior MRP variance per axis")
    p.add_argument("--update-iterations", type=_positive_int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--out", default="runs/montecarlo")
    p.set_defaults(func=_montecarlo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
