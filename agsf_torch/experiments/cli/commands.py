"""What each ``agsf`` subcommand does with its parsed arguments (:mod:`agsf_torch.experiments.cli.main` builds the parser and runs them):
one function per subcommand, returning the exit code, and the shared printing of a run's summary."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from .terminal import interruption, tensorboard_command


def simulate_command(args: argparse.Namespace) -> int:
    """``agsf simulate``: record simulated spacecraft data (truth, gyro, star observations) to a file. Returns the exit code."""
    import envs

    from ...attitude.recordings import FORMAT
    from ...storage.files import write_json
    from ..run.experiment import prepare_output
    from ..run.recorded import record_environment
    from ..run.resources import refuse_if_too_large, simulation_memory

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


def run_command(args: argparse.Namespace) -> int:
    """``agsf run``: one experiment (a preset or a recording), its outputs written under ``--out``. Returns the exit code."""
    from ..config.loader import load_config
    from ..run.experiment import run_experiment

    cfg = load_config(args.config, args.set)
    _threads(args)
    summary = run_experiment(
        cfg, Path(args.out), progress=not args.quiet, kind="run", recording=args.recording, force=args.force
    )
    _print_summary(cfg.name, summary)
    print(f"results: {args.out}/summary.json, figures {args.out}/*.png")
    print(f"TensorBoard: {tensorboard_command(args.out)}")
    return 0


def reproduce_command(args: argparse.Namespace) -> int:
    """``agsf reproduce``: the paper's cases side by side, with their combined summary and table. Returns the exit code."""
    from ..studies.reproduce import reproduce

    _threads(args)
    cases = [1, 2, 3] if args.case == "all" else [int(args.case)]
    _refuse_set(args.set, {k: f"--{k}" for k in ("runs", "duration") if getattr(args, k) is not None})
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
        threads=args.threads,
        jobs=args.jobs,
    )
    print(table)
    print(f"results: {args.out}/ — tables {args.out}/results.md, numbers {args.out}/summary.json")
    print(f"per case: {args.out}/case*/ — figures rms.png, axes.png, weights.png, fpke.png; every run's data runs.npz")
    print(f"TensorBoard: {tensorboard_command(args.out)}")
    return 0


def adaptation_command(args: argparse.Namespace) -> int:
    """``agsf adaptation``: the study of what the adaptive weight update buys. Returns the exit code."""
    from ..studies.adaptation import SCENARIOS, run_adaptation_study, study_table

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


def validate_command(args: argparse.Namespace) -> int:
    """``agsf validate``: every scenario × filter scored against the floor. Returns the exit code."""
    from ..studies.validate import SCENARIOS, run_validation, validation_table

    _threads(args)
    names = list(SCENARIOS) if "all" in args.scenario else list(dict.fromkeys(args.scenario))
    summaries = run_validation(
        names,
        Path(args.out),
        runs=args.runs,
        filters=None if args.filter is None else list(dict.fromkeys(args.filter)),
        density_samples=args.density_samples,
        overrides=list(args.set),
        progress=not args.quiet,
        force=args.force,
    )
    print(validation_table(summaries))
    print(f"results: {args.out}/validation.json, {args.out}/results.md, {args.out}/*.png")
    return 0


def sweep_command(args: argparse.Namespace) -> int:
    """``agsf sweep``: a resumable grid of configurations, locally or on Ray. Returns the exit code."""
    from ..config.loader import load_config
    from ..sweep import RayUnavailable, SweepFailed, parse_grid, run_sweep

    if args.address is not None and args.backend != "ray":
        raise ValueError("--address needs --backend ray")
    base = load_config(args.config, args.set)
    grid = parse_grid(args.grid, base)
    _refuse_set(args.set, {key: f"--grid {key}=…" for key in grid})
    if args.backend == "ray":
        kw = {"address": args.address, "cpus_per_task": max(1, args.threads or 1)}
    else:
        _threads(args)
        kw = {"threads": args.threads}
    try:
        rows = run_sweep(
            base, grid, Path(args.out), progress=not args.quiet, backend=args.backend, force=args.force, **kw
        )
    except (RayUnavailable, SweepFailed) as exc:
        print(f"agsf: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        from ...storage.files import read_json_lines

        status, how = interruption()
        results = Path(args.out) / "results.jsonl"
        done = len(read_json_lines(results))
        print(
            f"\nagsf: {how}; {done} finished configurations are in {results}: rerun the same command to resume",
            file=sys.stderr,
        )
        return status
    from ...storage.files import write_text
    from ..sweep import results_table

    table = results_table(rows)
    write_text(Path(args.out) / "results.md", table + "\n")
    print(table)
    print(
        f"{len(rows)} configurations: {args.out}/results.md (this table), {args.out}/results.jsonl (the rows), "
        f"{args.out}/configs/<config>/ (each one's figures and data)"
    )
    print(f"TensorBoard (hparams): {tensorboard_command(args.out)}")
    return 0


def bench_command(args: argparse.Namespace) -> int:
    """``agsf bench``: the speed and memory measurements and their report. Returns the exit code."""
    from ..bench import format_table, run_bench

    _threads(args)
    from ...storage.files import write_text
    from ..bench.run import check_reference

    reference = check_reference(args.main_job_reference)  # refused before anything runs
    report = run_bench(Path(args.out), compile=not args.no_compile, quick=args.quick, main_job_reference=reference)
    table = format_table(report)
    write_text(Path(args.out) / "bench.md", table + "\n")
    print(table)
    print(f"report: {args.out}/bench.json, {args.out}/bench.md")
    return 0


def soak_command(args: argparse.Namespace) -> int:
    """``agsf soak``: a long run, checked for drift and consistency. Returns the exit code."""
    from ...storage.files import write_json
    from ..config.loader import parse_override
    from ..studies.soak import run_soak, soak_config, soak_verdict

    owners = {"runs": "--runs", "duration": "--duration", "seed": "--seed", "filters": "--filter"}
    _refuse_set(args.set, owners | ({"compile": "--no-compile"} if args.no_compile else {}))
    changes = dict(parse_override(item) for item in args.set or [])
    changes.update(runs=args.runs, duration=args.duration, seed=args.seed)
    if args.no_compile:
        changes["compile"] = False
    cfg = soak_config(args.filter, **changes)
    _threads(args)
    out = Path(args.out)
    rows = run_soak(
        cfg, out, report_every=args.report_every, warmup=args.warmup, progress=not args.quiet, force=args.force
    )
    verdict = soak_verdict(rows, warmup=args.warmup)
    write_json(out / "verdict.json", verdict, indent=2)
    print(json.dumps(verdict, indent=2))
    return 0 if verdict["passed"] else 1


def diagnose_command(args: argparse.Namespace) -> int:
    """``agsf diagnose``: the consistency checks of a recording's run, in words. Returns the exit code."""
    from ..config.loader import load_config
    from ..studies.diagnose import diagnose

    cfg = load_config(args.config, args.set)
    _threads(args)
    report, passed = diagnose(cfg, Path(args.out), progress=not args.quiet, force=args.force, recording=args.recording)
    print(report)
    return 0 if passed else 1


def learn_command(args: argparse.Namespace) -> int:
    """``agsf learn``: fit the noise model to a recording through the filter's likelihood. Returns the exit code."""
    from ..config.loader import load_config
    from ..studies.learn import learn

    cfg = load_config(args.config, args.set)
    _threads(args)
    names = [n.strip() for n in args.learn.split(",") if n.strip()]
    report = learn(cfg, names, Path(args.out), recording=args.recording, max_iter=args.max_iter, force=args.force)
    print(report)
    return 0


def _refuse_set(items: list[str] | None, owners: dict[str, str]) -> None:
    """Refuse a ``--set KEY=…`` of a key another option of the command sets (``owners``: key → that option):
    one of the two values would be dropped without a word."""
    from ..config.loader import parse_override

    for item in items or []:
        key = parse_override(item)[0]
        if key in owners:
            raise ValueError(f"--set {key}=… conflicts with {owners[key]}, which sets {key} here: give it once")


def _threads(args: argparse.Namespace) -> None:
    """Torch threads: ``--threads`` if given, else torch's count (its default, the machine's cores, or
    ``OMP_NUM_THREADS``) capped at the CPUs this process may use (``joblib.cpu_count``:
    torch does not count a container's CPU quota, and more threads than the quota allows take turns and run slower
    than fewer)."""
    import joblib

    if getattr(args, "threads", None):
        torch.set_num_threads(max(1, args.threads))
    elif torch.get_num_threads() > joblib.cpu_count(only_physical_cores=False):
        torch.set_num_threads(joblib.cpu_count(only_physical_cores=False))


def _print_summary(name: str, summary: dict) -> None:
    """The run's per-filter numbers and every adaptive filter's paired difference against the GSF, aligned (without
    the truth, a replay of flight data: the NIS ratio alone)."""
    from ..report.statistics import WINDOW_TEXT, minus_gsf_key

    filters = summary["filters"]
    width = max((len(f"{f} − GSF") for f in filters), default=0)
    if not summary.get("scored_against_truth", True):
        print(f"{name}: NIS / expected (1 when consistent); no truth in the recording, so no errors or NEES")
        for fname, f in filters.items():
            nis = f.get("nis_per_expected")
            print(f"  {fname:<{width}}  NIS / expected {'—' if nis is None else format(nis, '.4g')}")
        return
    print(f"{name}: mean RMS between star frames (deg), time-averaged NEES and NIS / expected (1 when consistent)")
    for fname, f in filters.items():
        bu = f.get("between_frames", {}).get("mean_rms_deg")  # none without a star frame: "—", as in the tables
        nis = f.get("nis_per_expected")
        nis_text = f"   NIS / expected {'—' if nis is None else format(nis, '.4g')}"
        rms_text = "—" if bu is None else format(bu, ".6g")
        print(f"  {fname:<{width}}  {rms_text:>11}       NEES {f['time_averaged_nees']:.4g}{nis_text}")
    for fname in filters:
        d = (summary.get(minus_gsf_key(fname)) or {}).get("between_frames")
        if d:
            label = f"{fname} − GSF"
            lo, hi = d["ci95_deg"]
            print(f"  {label:<{width}}  {d['mean_deg']:>11.3g} deg,  95% CI [{lo:.3g}, {hi:.3g}]")
    print(f"  (window — {WINDOW_TEXT['between_frames']})")


def calibrate_command(args: argparse.Namespace) -> int:
    """``agsf calibrate``: how often the learned and diagnosed verdicts flag a correct filter. Returns the exit code."""
    from ...storage.files import write_json, write_text
    from ..config.loader import load_config
    from ..run.experiment import prepare_output
    from ..studies.calibration import QUICK_STUDY, STUDY, run_study, settings_named, verdict_study
    from ..studies.calibration_report import calibration_figure, calibration_markdown

    cfg = load_config(args.config, args.set)
    study = QUICK_STUDY if args.quick else STUDY
    settings = settings_named(args.setting, study)
    if args.datasets < 2:
        raise ValueError(f"--datasets must be at least 2 (rates over data sets), got {args.datasets}")
    import joblib

    workers = args.workers or max(1, min(2, joblib.cpu_count(only_physical_cores=False), len(settings)))
    params = {"datasets": args.datasets, "settings": [s.label for s in settings], "seed": cfg.seed}
    out = prepare_output(Path(args.out), "calibrate", json.dumps({**params, **cfg.to_dict()}, sort_keys=True), params)
    t0 = time.perf_counter()
    results = run_study(cfg, settings, datasets=args.datasets, seed=cfg.seed, workers=workers, progress=not args.quiet)
    verdicts = verdict_study(cfg, datasets=args.datasets, seed=cfg.seed, quick=args.quick) if not args.setting else []
    elapsed = time.perf_counter() - t0
    write_json(
        out / "calibration.json", {**params, "seconds": elapsed, "results": results, "verdicts": verdicts}, indent=2
    )
    report = calibration_markdown(results, verdicts)
    write_text(out / "calibration.md", report)
    calibration_figure(results, out / "calibration.png")
    print(report)
    print(f"{len(settings)} settings × {args.datasets} data sets in {elapsed:.0f} s → {out}")
    return 0
