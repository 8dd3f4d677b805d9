"""The ``agsf`` command.

Subcommands:

* ``agsf simulate`` — simulate B trajectories of the star-tracker environment and
  write the truth, gyro and star data (``simulation.npz``) and their statistics
  (``summary.json``) under ``--out``.
* ``agsf run CONFIG [--set key=value …] --out DIR`` — one configuration (a TOML
  file or a preset name): EKF, classic GSF and adaptive GSF batched over the runs,
  all seeing the same truth and measurements.
* ``agsf reproduce --case {1,2,3,all} [--runs R] --out DIR`` — the paper's cases.
* ``agsf adaptation [--scenario …] [--runs R] [--samples K] --out DIR`` — where adapting
  the weights pays: RMS, NEES and the density score against an exact-density reference
  for EKF, GSF, both adaptive filters and the MEKF (:mod:`agsf_torch.experiments.adaptation`).
* ``agsf sweep CONFIG --grid key=v1,v2 … --out DIR [--backend ray [--address ADDR]]`` — a
  resumable grid, in this process or as Ray tasks; ends with a table of every configuration
  (printed and written to ``results.md``).
* ``agsf soak [--filter NAME] [--runs B] [--duration S] --out DIR`` — a long run
  (default one simulated hour, 256 runs, 6-state) with running statistics and a
  pass/fail verdict: no NaN, covariances positive definite, errors inside ±3σ,
  flat memory (:mod:`agsf_torch.experiments.soak`).
* ``agsf diagnose CONFIG [--set …] --out DIR`` — run a configuration and judge its
  consistency in words: NEES, NIS and whiteness against their χ² bands
  (:mod:`agsf_torch.experiments.diagnose`).
* ``agsf learn CONFIG --learn NAMES [--recording FILE] --out DIR`` — maximum-likelihood
  fits of the noise model through the filter, with 95 % intervals
  (:mod:`agsf_torch.experiments.learn`).
* ``agsf bench --out DIR`` — what the filters cost beside their peers, every target met
  or not (:mod:`agsf_torch.experiments.bench`).

Every experiment writes ``summary.json``, ``runs.npz``, PNG figures and
TensorBoard events (see :mod:`agsf_torch.experiments.experiment`); each command ends
by printing where they are and the TensorBoard command of this environment.  Progress
bars and the package's INFO messages (the FPKE kernel's compilation) go to stderr unless
``--quiet``.
"""

from __future__ import annotations

import argparse
import errno
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ..allocator import set_mmap_threshold
from .cli_terminal import (
    FORCE_HELP,
    Parser,
    key_value,
    messages,
    nonnegative_float,
    nonnegative_int,
    one_line,
    positive_float,
    positive_int,
    seed,
    tensorboard_command,
)

__all__ = ["main", "tensorboard_command"]


def _simulate(args: argparse.Namespace) -> int:
    import envs

    from ..attitude.recordings import FORMAT
    from ..storage.files import write_json
    from .experiment import prepare_output
    from .recorded import record_environment
    from .resources import refuse_if_too_large, simulation_memory

    if args.seed > envs.random.SEED_MASK - (args.runs - 1):
        raise ValueError(
            f"--seed must be ≤ {envs.random.SEED_MASK - (args.runs - 1)} with --runs {args.runs}, got {args.seed}"
        )
    params = {"runs": args.runs, "steps": args.steps, "star_period": args.star_period, "seed": args.seed}
    config = envs.StarTrackerConfig(
        max_steps=args.steps, star_period=args.star_period
    )  # validates before anything is created
    refuse_if_too_large(
        simulation_memory(args.runs, args.steps, config.max_stars),
        f"simulating --runs {args.runs} × --steps {args.steps}",
        force=args.force,
    )
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=args.runs, config=config)
    _threads(args)
    out = prepare_output(Path(args.out), "simulate", json.dumps(params, sort_keys=True), params)
    t0 = time.perf_counter()
    rec = record_environment(env, args.steps, args.seed, progress=not args.quiet)
    path = rec.save(out / "recording.npz")
    elapsed = time.perf_counter() - t0
    counts = np.bincount(rec.star_mask[:, rec.star_frames()].sum(-1).ravel(), minlength=env.config.max_stars + 1)
    summary = {
        **params,
        "command": "simulate",
        "format": FORMAT,
        "recording_digest": rec.content_digest(),
        "seconds": elapsed,
        "stars_per_frame_histogram": counts.tolist(),
    }
    write_json(out / "summary.json", summary, indent=2)
    print(f"simulated {args.runs} trajectories × {args.steps} steps in {elapsed:.1f} s → {path} ({FORMAT})")
    print(f"stars per frame (0..{env.config.max_stars}): {counts.tolist()}")
    return 0


def _run(args: argparse.Namespace) -> int:
    from .config import load_config
    from .experiment import run_experiment

    cfg = load_config(args.config, args.set)
    _threads(args)
    summary = run_experiment(
        cfg, Path(args.out), progress=not args.quiet, kind="run", recording=args.recording, force=args.force
    )
    _print_summary(cfg.name, summary)
    print(f"results: {args.out}/summary.json, figures {args.out}/*.png")
    print(f"TensorBoard: {tensorboard_command(args.out)}")
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    from .reproduce import reproduce

    _threads(args)
    cases = [1, 2, 3] if args.case == "all" else [int(args.case)]
    overrides = list(args.set)
    if args.runs is not None:
        overrides.append(f"runs={args.runs}")
    if args.duration is not None:
        overrides.append(f"duration={args.duration}")
    table = reproduce(
        cases,
        Path(args.out),
        overrides,
        progress=not args.quiet,
        force=args.force,
        writers=args.writers,
        threads=args.threads,
    )
    print(table)
    print(f"results: {args.out}/ — tables {args.out}/results.md, numbers {args.out}/summary.json")
    print(f"per case: {args.out}/case*/ — figures rms.png, axes.png, weights.png, fpke.png; every run's data runs.npz")
    print(f"TensorBoard: {tensorboard_command(args.out)}")
    return 0


def _adaptation(args: argparse.Namespace) -> int:
    from .adaptation import SCENARIOS, run_adaptation_study, study_table

    _threads(args)
    names = list(SCENARIOS) if "all" in args.scenario else list(dict.fromkeys(args.scenario))
    summaries = run_adaptation_study(
        names,
        Path(args.out),
        runs=args.runs,
        samples=args.samples,
        overrides=list(args.set),
        progress=not args.quiet,
        force=args.force,
    )
    for window in ("before_first_frame", "between_frames", "all"):
        print(f"\n{window.replace('_', ' ')}:\n{study_table(summaries, window)}")
    print(f"results: {args.out}/summary.json, {args.out}/results.md, {args.out}/*.png")
    print(f"TensorBoard: {tensorboard_command(args.out)}")
    return 0


def _sweep(args: argparse.Namespace) -> int:
    from .config import load_config
    from .sweep import RayUnavailable, SweepFailed, parse_grid, run_sweep

    if args.address is not None and args.backend != "ray":
        raise ValueError("--address needs --backend ray")
    base = load_config(args.config, args.set)
    grid = parse_grid(args.grid, base)
    if args.backend == "ray":
        kw = {"address": args.address, "cpus_per_task": max(1, args.threads or 1)}
    else:
        _threads(args)
        kw = {}
    try:
        rows = run_sweep(
            base, grid, Path(args.out), progress=not args.quiet, backend=args.backend, force=args.force, **kw
        )
    except (RayUnavailable, SweepFailed) as exc:
        print(f"agsf: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        from ..storage.files import read_json_lines

        results = Path(args.out) / "results.jsonl"
        done = len(read_json_lines(results))
        print(
            f"\nagsf: interrupted; {done} finished configurations are in {results}: rerun the same command to resume",
            file=sys.stderr,
        )
        return 130
    from ..storage.files import write_text
    from .sweep import results_table

    table = results_table(rows)
    write_text(Path(args.out) / "results.md", table + "\n")
    print(table)
    print(
        f"{len(rows)} configurations: {args.out}/results.md (this table), {args.out}/results.jsonl (the rows), "
        f"{args.out}/configs/<config>/ (each one's figures and data)"
    )
    print(f"TensorBoard (hparams): {tensorboard_command(args.out)}")
    return 0


def _bench(args: argparse.Namespace) -> int:
    from .bench import format_table, run_bench

    _threads(args)
    from ..storage.files import write_text

    report = run_bench(Path(args.out), compile=not args.no_compile, quick=args.quick)
    table = format_table(report)
    write_text(Path(args.out) / "bench.md", table + "\n")
    print(table)
    print(f"report: {args.out}/bench.json, {args.out}/bench.md")
    return 0


def _soak(args: argparse.Namespace) -> int:
    from ..storage.files import write_json
    from .config import parse_override
    from .soak import run_soak, soak_config, soak_verdict

    changes = dict(parse_override(item) for item in args.set or [])
    changes.update(runs=args.runs, duration=args.duration, seed=args.seed)
    if args.no_compile:
        changes["compile"] = False
    cfg = soak_config(args.filter, **changes)
    _threads(args)
    out = Path(args.out)
    rows = run_soak(cfg, out, report_every=args.report_every, progress=not args.quiet, force=args.force)
    verdict = soak_verdict(rows, warmup=args.warmup)
    write_json(out / "verdict.json", verdict, indent=2)
    print(json.dumps(verdict, indent=2))
    return 0 if verdict["passed"] else 1


def _diagnose(args: argparse.Namespace) -> int:
    from .config import load_config
    from .diagnose import diagnose

    cfg = load_config(args.config, args.set)
    _threads(args)
    report, passed = diagnose(cfg, Path(args.out), progress=not args.quiet, force=args.force)
    print(report)
    return 0 if passed else 1


def _learn(args: argparse.Namespace) -> int:
    from .config import load_config
    from .learn import learn

    cfg = load_config(args.config, args.set)
    _threads(args)
    names = [n.strip() for n in args.learn.split(",") if n.strip()]
    report = learn(cfg, names, Path(args.out), recording=args.recording, max_iter=args.max_iter, force=args.force)
    print(report)
    return 0


def _threads(args: argparse.Namespace) -> None:
    if getattr(args, "threads", None):
        torch.set_num_threads(max(1, args.threads))


def _print_summary(name: str, summary: dict) -> None:
    """The run's per-filter numbers and every adaptive filter's paired difference against the GSF, aligned."""
    from .statistics import WINDOW_TEXT, minus_gsf_key

    print(f"{name}: mean RMS between star frames (deg) and time-averaged NEES")
    filters = summary["filters"]
    width = max((len(f"{f} − GSF") for f in filters), default=0)
    for fname, f in filters.items():
        bu = f.get("between_frames", {}).get("mean_rms_deg", float("nan"))
        print(f"  {fname:<{width}}  {bu:>11.6g}       NEES {f['time_averaged_nees']:.4g}")
    for fname in filters:
        d = (summary.get(minus_gsf_key(fname)) or {}).get("between_frames")
        if d:
            label = f"{fname} − GSF"
            lo, hi = d["ci95_deg"]
            print(f"  {label:<{width}}  {d['mean_deg']:>11.3g} deg,  95% CI [{lo:.3g}, {hi:.3g}]")
    print(f"  (window — {WINDOW_TEXT['between_frames']})")


def keys_epilog() -> str:
    """The configuration keys ``--set`` (and a TOML file) accepts, one per line with its help."""
    from .config import config_key_help

    keys = config_key_help()
    width = max(map(len, keys))
    lines = [f"  {key:<{width}}  {' '.join(text.replace('``', '').split())}" for key, text in keys.items()]
    return "configuration keys (--set KEY=VALUE, or in a TOML file):\n" + "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="agsf", description="Gaussian sum filters for spacecraft attitude")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate the star-tracker environment")
    p.add_argument("--runs", type=positive_int, default=64, help="trajectories (batch)")
    p.add_argument("--steps", type=positive_int, default=600, help="gyro periods of 0.1 s")
    p.add_argument("--star-period", type=positive_float, default=1.0, help="s between star frames")
    p.add_argument("--seed", type=seed, default=0, help="trajectory i is seeded seed + i")
    p.add_argument("--out", default="runs/simulation", help="output folder (default: runs/simulation)")
    p.add_argument("--threads", type=positive_int, default=None, help="torch threads")
    p.add_argument("--quiet", action="store_true", help="no progress bar on stderr")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.set_defaults(func=_simulate)

    def common(p):
        p.add_argument(
            "--set",
            action="append",
            default=[],
            type=key_value("--set", "VALUE"),
            metavar="KEY=VALUE",
            help="override a config key (the keys: below)",
        )
        p.formatter_class = argparse.RawDescriptionHelpFormatter
        p.epilog = keys_epilog()
        p.add_argument("--threads", type=positive_int, default=None, help="torch threads")
        p.add_argument("--quiet", action="store_true", help="no progress bars or progress messages on stderr")
        p.add_argument("--force", action="store_true", help=FORCE_HELP)

    p = sub.add_parser("run", help="one configuration (a TOML file or a preset name)")
    p.add_argument("config", help="TOML file or preset (case1, case2, case3, wide_prior, faults)")
    p.add_argument("--recording", default=None, help="replay a recorded .npz file (with truth) instead of simulating")
    p.add_argument(
        "--out", required=True, help="output folder (created; an existing one must hold the same experiment)"
    )
    common(p)
    p.set_defaults(func=_run)

    p = sub.add_parser("reproduce", help="the paper's three cases (star frames at 1, 0.5, 0.2 Hz)")
    p.add_argument(
        "--case",
        choices=["1", "2", "3", "all"],
        default="all",
        help="the paper's case: star frames at 1 Hz (1), 0.5 Hz (2), 0.2 Hz (3), or all three (default)",
    )
    p.add_argument("--runs", type=positive_int, default=None, help="Monte Carlo runs (preset: 100)")
    p.add_argument("--duration", type=positive_float, default=None, help="simulated seconds per run (preset: 30)")
    p.add_argument(
        "--out", default="runs/reproduce", help="output folder (default: runs/reproduce; one subfolder per case)"
    )
    p.add_argument(
        "--writers",
        type=nonnegative_int,
        default=None,
        help="worker processes drawing each case's figures while the next runs (default: 1 on 2 CPUs or more, "
        "else 0; 0: drawn in this process)",
    )
    common(p)
    p.set_defaults(func=_reproduce)

    from .adaptation import SCENARIOS
    from .config import FILTER_NAMES

    p = sub.add_parser(
        "adaptation",
        help="where adapting the weights pays: RMS, NEES and density score of EKF, GSF, AGSF, AGSF-galerkin and MEKF",
    )
    p.add_argument(
        "--scenario",
        nargs="+",
        default=["all"],
        choices=["all", *SCENARIOS],
        help="scenarios to run (default: all)",
    )
    p.add_argument("--runs", type=positive_int, default=32, help="Monte Carlo runs per scenario")
    p.add_argument("--samples", type=positive_int, default=1024, help="exact-density reference samples per run")
    p.add_argument("--out", default="runs/adaptation", help="output folder")
    common(p)
    p.set_defaults(func=_adaptation)

    p = sub.add_parser("sweep", help="a grid of configurations, each one batched Monte Carlo")
    p.add_argument("config", help="base TOML file or preset")
    p.add_argument(
        "--grid",
        action="append",
        default=[],
        type=key_value("--grid", "V1,V2"),
        metavar="KEY=V1,V2,...",
        help="a swept key",
    )
    p.add_argument("--out", required=True, help="output folder (rerun the same command on it to resume)")
    p.add_argument(
        "--backend",
        choices=["local", "ray"],
        default="local",
        help="local: one configuration after another in this process; ray: one Ray task per configuration "
        "(needs agsf-torch[ray]; --threads then sets each task's CPUs, default 1)",
    )
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster to use (with --backend ray): 'auto' (this node's cluster) or ray://HEAD:10001; "
        "default: RAY_ADDRESS if set, else a new local Ray instance",
    )
    common(p)
    p.set_defaults(func=_sweep)
    p = sub.add_parser("diagnose", help="consistency checks (NEES, NIS, whiteness) of one configuration, in words")
    p.add_argument("config", help="TOML file or preset")
    p.add_argument("--out", required=True, help="output folder")
    common(p)
    p.set_defaults(func=_diagnose)

    p = sub.add_parser("learn", help="maximum-likelihood fit of noise-model parameters through the filter")
    p.add_argument("config", help="TOML file or preset (simulation and filter settings)")
    p.add_argument("--learn", required=True, help="comma-separated: sigma_v, sigma_u, sigma_s, bias, reg, prior_scale")
    p.add_argument(
        "--recording", default=None, help="a recorded .npz file instead of simulating (needs truth for the prior)"
    )
    p.add_argument("--max-iter", type=positive_int, default=40, help="L-BFGS iterations of the fit (default 40)")
    p.add_argument("--out", required=True, help="output folder")
    common(p)
    p.set_defaults(func=_learn)

    p = sub.add_parser("soak", help="a long run checking NaN, positive definiteness, 3σ consistency and flat memory")
    p.add_argument("--filter", choices=FILTER_NAMES, default="GSF", help="the filter to soak")
    p.add_argument("--runs", type=positive_int, default=256, help="Monte Carlo runs (batch, default 256)")
    p.add_argument("--duration", type=positive_float, default=3600.0, help="simulated seconds (default one hour)")
    p.add_argument("--report-every", type=positive_float, default=60.0, help="simulated seconds per report row")
    p.add_argument(
        "--warmup", type=nonnegative_float, default=60.0, help="seconds excluded from the verdict (prior convergence)"
    )
    p.add_argument(
        "--seed",
        type=seed,
        default=1,
        help="seeds truth, noise and prior draws; trajectory i is seeded seed + i (default 1)",
    )
    p.add_argument("--no-compile", action="store_true", help="eager FPKE quadrature (AGSF)")
    p.add_argument("--out", required=True, help="output folder")
    common(p)
    p.set_defaults(func=_soak)

    p = sub.add_parser(
        "bench",
        help="adaptive vs classic filter cost, first step, QP vs Clarabel, filterpy/NumPy peers, memory; targets met or not",
    )
    p.add_argument("--out", default="runs/bench", help="output folder (default: runs/bench)")
    p.add_argument("--quick", action="store_true", help="smaller samples (a smoke run, not the reference numbers)")
    p.add_argument(
        "--no-compile", action="store_true", help="skip the compiled penalty kernel's first-step measurement"
    )
    p.add_argument("--threads", type=positive_int, default=None, help="torch threads")
    p.set_defaults(func=_bench)
    return parser


#: Exit code of a command the machine could not complete (a full disk, a read-only or failing device),
#: apart from 2, refused input.
EXIT_IO_FAILURE = 3
_IO_FAILURES = {errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EROFS}


def main(argv: list[str] | None = None) -> int:
    """Run the ``agsf`` command; refused input (a bad configuration, file or output folder)
    prints one line ``agsf: error: …`` and returns 2, having created nothing; an I/O failure of the
    machine (a full disk, a failing or read-only device) prints ``agsf: I/O failure (file): …`` and returns
    :data:`EXIT_IO_FAILURE`; Ctrl-C prints one line and returns 130.  Long steps
    (the FPKE kernel's compilation) are announced on stderr unless ``--quiet``."""
    args = build_parser().parse_args(argv)
    set_mmap_threshold()  # a step's buffers reused from the heap, not mapped afresh (agsf_torch.allocator)
    with messages(quiet=getattr(args, "quiet", False)):
        try:
            return args.func(args)
        except OSError as exc:
            if exc.errno in _IO_FAILURES:  # the machine failed a write or read: not the user's input
                where = f" ({exc.filename})" if exc.filename else ""
                print(f"agsf: I/O failure{where}: {exc.strerror or one_line(exc)}", file=sys.stderr)
                return EXIT_IO_FAILURE
            print(f"agsf: error: {one_line(exc)}", file=sys.stderr)
            return 2
        except ValueError as exc:
            print(f"agsf: error: {one_line(exc)}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            out = getattr(args, "out", None)
            kept = f"; what was written is in {out}" if out else ""
            print(f"\nagsf: interrupted{kept} (files are written whole or not at all)", file=sys.stderr)
            return 130
        finally:
            from .outputs import release_outputs

            release_outputs()


if __name__ == "__main__":
    sys.exit(main())
