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
  for EKF, GSF, both adaptive filters and the MEKF (:mod:`agsf_torch.experiments.studies.adaptation`).
* ``agsf validate [--scenario …] [--filter …] [--runs R] --out DIR`` — every scenario × filter against the
  Riccati floor: steady-state RMS, ANEES, NIS, divergence, convergence time, density score and cost, with
  intervals over runs (:mod:`agsf_torch.experiments.studies.validate`).
* ``agsf sweep CONFIG --grid key=v1,v2 … --out DIR [--backend ray [--address ADDR]]`` — a
  resumable grid, in this process (each configuration's files written by a worker process while the next
  runs) or as Ray tasks; ends with a table of every configuration (printed and written to ``results.md``).
* ``agsf soak [--filter NAME] [--runs B] [--duration S] --out DIR`` — a long run
  (default one simulated hour, 256 runs, 6-state) with running statistics and a
  pass/fail verdict: no NaN, covariances positive definite, errors inside ±3σ,
  flat memory (:mod:`agsf_torch.experiments.studies.soak`).
* ``agsf diagnose CONFIG [--set …] [--recording FILE] --out DIR`` — run a configuration and judge its
  consistency in words: NEES, NIS and whiteness against their χ² bands
  (:mod:`agsf_torch.experiments.studies.diagnose`).
* ``agsf learn CONFIG --learn NAMES [--recording FILE] --out DIR`` — maximum-likelihood
  fits of the noise model through the filter, with 95 % intervals
  (:mod:`agsf_torch.experiments.studies.learn`).
* ``agsf bench --out DIR`` — what the filters cost beside their peers, every target met
  or not (:mod:`agsf_torch.experiments.bench`).

Every experiment writes ``summary.json``, ``runs.npz``, PNG figures and
TensorBoard events (see :mod:`agsf_torch.experiments.run.experiment`); each command ends
by printing where they are and the TensorBoard command of this environment.  Progress
bars and the package's INFO messages (the FPKE kernel's compilation) go to stderr unless
``--quiet``.
The parser and the entry point live here; what each subcommand does, in :mod:`agsf_torch.experiments.cli.commands`.
"""

from __future__ import annotations

import argparse
import errno
import sys

from ...allocator import set_mmap_threshold
from ...storage.files import files_written
from ..run.worker_pool import TaskDied
from .commands import (
    adaptation_command,
    bench_command,
    calibrate_command,
    diagnose_command,
    learn_command,
    reproduce_command,
    run_command,
    simulate_command,
    soak_command,
    sweep_command,
    validate_command,
)
from .terminal import (
    FORCE_HELP,
    Parser,
    ending_signals,
    interruption,
    key_value,
    messages,
    nonnegative_float,
    one_line,
    positive_float,
    positive_int,
    seed,
    tensorboard_command,
)

__all__ = ["main", "tensorboard_command"]


def keys_epilog() -> str:
    """The configuration keys ``--set`` (and a TOML file) accepts, one per line with its help."""
    from ..config.loader import config_key_help

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
    p.set_defaults(func=simulate_command)

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
    p.add_argument(
        "--recording",
        default=None,
        help="replay a recorded .npz file instead of simulating (with the truth, or initial_mrp: flight data)",
    )
    p.add_argument(
        "--out", required=True, help="output folder (created; an existing one must hold the same experiment)"
    )
    common(p)
    p.set_defaults(func=run_command)

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
        "--jobs",
        type=positive_int,
        default=None,
        help="cases at once, each in a worker process that writes its own files (default: every case on Linux "
        "with 2 CPUs or more, else 1: one after another in this process, a worker process writing each case's "
        "files while the next runs where there are 2 CPUs or more)",
    )
    common(p)
    p.set_defaults(func=reproduce_command)

    from ..config.loader import FILTER_NAMES
    from ..studies.adaptation import SCENARIOS

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
    p.set_defaults(func=adaptation_command)

    from ..studies.validate import SCENARIOS as VALIDATION_SCENARIOS
    from ..studies.validate import VALIDATION_FILTERS

    p = sub.add_parser(
        "validate",
        help="every scenario × filter against the Riccati floor: RMS, ANEES, NIS, divergence, convergence, density, cost",
    )
    p.add_argument(
        "--scenario",
        nargs="+",
        default=["all"],
        choices=["all", *VALIDATION_SCENARIOS],
        help="scenarios to run (default: all)",
    )
    p.add_argument(
        "--filter",
        nargs="+",
        default=None,
        choices=list(VALIDATION_FILTERS),
        help="filters to run (default: each scenario's own)",
    )
    p.add_argument("--runs", type=positive_int, default=32, help="Monte Carlo runs per scenario (≥ 2)")
    p.add_argument(
        "--density-samples",
        type=int,
        default=256,
        help="exact-density reference samples per run where the reference is run (0: no density score)",
    )
    p.add_argument("--out", default="runs/validate", help="output folder")
    common(p)
    p.set_defaults(func=validate_command)

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
    p.set_defaults(func=sweep_command)
    p = sub.add_parser("diagnose", help="consistency checks (NEES, NIS, whiteness) of one configuration, in words")
    p.add_argument("config", help="TOML file or preset")
    p.add_argument(
        "--recording",
        default=None,
        help="replay a recorded .npz file instead of simulating (with the truth, or initial_mrp: flight data)",
    )
    p.add_argument("--out", required=True, help="output folder")
    common(p)
    p.set_defaults(func=diagnose_command)

    p = sub.add_parser("learn", help="maximum-likelihood fit of noise-model parameters through the filter")
    p.add_argument("config", help="TOML file or preset (simulation and filter settings)")
    p.add_argument("--learn", required=True, help="comma-separated: sigma_v, sigma_u, sigma_s, bias, reg, prior_scale")
    p.add_argument(
        "--recording", default=None, help="a recorded .npz file instead of simulating (needs truth for the prior)"
    )
    p.add_argument("--max-iter", type=positive_int, default=40, help="Newton iterations of the fit (default 40)")
    p.add_argument("--out", required=True, help="output folder")
    common(p)
    p.set_defaults(func=learn_command)

    p = sub.add_parser(
        "calibrate",
        help="measure learning's calibration: bias, interval coverage, false alarms and detection over many data sets",
    )
    p.add_argument("config", nargs="?", default="case1", help="TOML file or preset, the base (default case1)")
    p.add_argument("--datasets", type=positive_int, default=200, help="data sets per setting (default 200)")
    p.add_argument(
        "--setting",
        action="append",
        default=None,
        help="a setting of the study by its label (repeatable; default: all of them)",
    )
    p.add_argument("--quick", action="store_true", help="the study's few-second version (for a first look)")
    p.add_argument("--workers", type=positive_int, default=None, help="settings side by side (default: the CPUs, ≤ 2)")
    p.add_argument("--out", required=True, help="output folder")
    common(p)
    p.set_defaults(func=calibrate_command)

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
    p.set_defaults(func=soak_command)

    p = sub.add_parser(
        "bench",
        help="adaptive vs classic filter cost, first step, QP vs Clarabel, filterpy/NumPy peers, memory; targets met or not",
    )
    p.add_argument("--out", default="runs/bench", help="output folder (default: runs/bench)")
    p.add_argument("--quick", action="store_true", help="smaller samples (a smoke run, not the reference numbers)")
    p.add_argument(
        "--no-compile", action="store_true", help="skip the compiled penalty kernel's first-step measurement"
    )
    p.add_argument(
        "--main-job-reference",
        default=None,
        metavar="DIR",
        help="a checkout of earlier code (a git worktree, say) whose main job is timed alternately with this one's: "
        "the main job's speed-up target is measured against it",
    )
    p.add_argument("--threads", type=positive_int, default=None, help="torch threads")
    p.set_defaults(func=bench_command)
    return parser


#: Exit code of a command the machine could not complete (a full disk, a read-only or failing device), or that a
#: file error stopped after it had begun writing (a permission denied halfway), apart from 2, refused input (nothing
#: written).
EXIT_IO_FAILURE = 3
_IO_FAILURES = {errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EROFS}


def main(argv: list[str] | None = None) -> int:
    """Run the ``agsf`` command; refused input (a bad configuration, file or output folder)
    prints one line ``agsf: error: …`` and returns 2, having created nothing; an I/O failure of the
    machine (a full disk, a failing or read-only device), and any file error once the command has written a file
    (:func:`~agsf_torch.storage.files.files_written`: a permission denied halfway, after other files were replaced),
    prints ``agsf: I/O failure (file): …`` and returns :data:`EXIT_IO_FAILURE`, as does a case's process that died
    (``agsf: failure: …``); Ctrl-C prints one line and returns 130, and SIGTERM and SIGHUP end the command the same
    way and return 128 + the signal (143, 129: :func:`agsf_torch.experiments.cli.terminal.ending_signals`).  Long steps (the FPKE kernel's
    compilation) are announced on stderr unless ``--quiet``."""
    args = build_parser().parse_args(argv)
    set_mmap_threshold()  # a step's buffers reused from the heap, not mapped afresh (agsf_torch.allocator)
    written = files_written()
    with ending_signals(), messages(quiet=getattr(args, "quiet", False)):
        try:
            return args.func(args)
        except OSError as exc:
            # the machine failed a write or read, or the command had begun writing: not a refusal, which writes nothing
            if exc.errno in _IO_FAILURES or files_written() != written:
                where = f" ({exc.filename})" if exc.filename else ""
                print(f"agsf: I/O failure{where}: {exc.strerror or one_line(exc)}", file=sys.stderr)
                return EXIT_IO_FAILURE
            print(f"agsf: error: {one_line(exc)}", file=sys.stderr)
            return 2
        except ValueError as exc:
            print(f"agsf: error: {one_line(exc)}", file=sys.stderr)
            return 2
        except TaskDied as exc:  # a case's process was killed (out of memory, say): the machine's failure
            print(f"agsf: failure: {one_line(exc)}", file=sys.stderr)
            return EXIT_IO_FAILURE
        except KeyboardInterrupt:
            status, how = interruption()
            out = getattr(args, "out", None)
            kept = f"; what was written is in {out}" if out else ""
            print(f"\nagsf: {how}{kept} (files are written whole or not at all)", file=sys.stderr)
            return status
        finally:
            from ..run.outputs import release_outputs

            release_outputs()


def entry() -> None:
    """The ``agsf`` command: :func:`main` on the command line's arguments, then exit with its code."""
    sys.exit(main(sys.argv[1:]))


if __name__ == "__main__":
    entry()
