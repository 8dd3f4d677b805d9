"""``agsf reproduce``: the paper's three cases (method.md §4) and their summary table.

Each case's TensorBoard folder (``out/case{k}/tensorboard``) is an HParams session
(:func:`agsf_torch.experiments.report.tensorboard.write_hparams_session`): its hyperparameters are the case name
and the fields of its configuration (lists as JSON; ``compile`` left out: it changes no
number), its metrics the per-filter numbers of the summary table; beneath it one run per
filter (``out/case{k}/tensorboard/GSF``) holds the curves, tags per metric.  So
``tensorboard --logdir out`` overlays the filters of a case in one chart (run filter
``case1``), one filter across the cases (run filter ``GSF``), and its HParams tab
compares the cases.
"""

from __future__ import annotations

import hashlib
import importlib
import json
from pathlib import Path

from ...filters.registry import ADAPTIVE_FILTERS
from ...storage.files import write_json, write_text
from ..config.loader import load_config
from ..report.statistics import WINDOW_TEXT, minus_gsf_key
from ..report.tensorboard import hparam_domains, write_hparams_session
from ..run.experiment import make_filters, prepare_output, run_experiment
from ..run.file_writer import PRELOAD_MODULES, check_threads, default_writers, writing_beside
from ..run.resources import available_memory, check_memory, check_memory_side_by_side, writer_memory
from ..run.worker_pool import fork_available, run_forked

__all__ = ["reproduce", "results_table", "default_jobs", "check_jobs"]


def reproduce(
    cases: list[int],
    out: Path,
    overrides: list[str] | None = None,
    *,
    progress: bool = True,
    force: bool = False,
    threads: int | None = None,
    jobs: int | None = None,
) -> str:
    """Run ``case{k}`` presets (with ``overrides``) under ``out/case{k}``; write the
    combined ``summary.json`` and ``results.md``; return the Markdown table.  Every case is
    validated (and its memory estimated, unless ``force``) before ``out`` is created.

    With ``jobs`` > 1 the cases run side by side, ``jobs`` at once, each in a worker process forked from this one
    that runs it end to end with one torch thread and writes its files (:func:`agsf_torch.experiments.run.worker_pool.run_forked`; ``threads`` must
    be None or 1); their numbers and files are those of the cases run one after another with one torch thread (byte
    for byte; with more threads a threaded kernel may round differently in the last bits), and each case's HParams
    session is written as it completes.  The memory check counts the cases that run at once
    (:func:`~agsf_torch.experiments.run.resources.check_memory_side_by_side`).  Default (``None``): every case at once where fork is available
    and the process may use two CPUs or more (:func:`default_jobs`), else 1.

    With ``jobs`` = 1 the cases run one after another in this process, with ``threads`` torch threads (default:
    torch's, capped so that they and the writer fit the CPUs), restored afterwards; a case's figures, event files and
    ``runs.npz`` are written by a worker process while the next case runs where the process may use two CPUs or more
    (:func:`~agsf_torch.experiments.run.file_writer.writing_beside`; the same files, byte for byte).  The memory check counts that worker
    (:func:`~agsf_torch.experiments.run.resources.writer_memory`)."""
    configs = {f"case{k}": load_config(f"case{k}", overrides) for k in cases}
    jobs = check_jobs(jobs, len(configs), threads)
    if jobs > 1:
        check_memory_side_by_side(list(configs.values()), jobs, force=force)
    else:
        writers = default_writers()
        for cfg in configs.values():
            check_memory(cfg, force=force, budget=available_memory() - writer_memory(cfg, writers))
    digest = hashlib.sha256(
        json.dumps({k: c.digest() for k, c in configs.items()}, sort_keys=True).encode()
    ).hexdigest()[:16]
    out = prepare_output(Path(out), "reproduce", digest, {k: c.to_dict() for k, c in configs.items()})
    hparams = {name: case_hparams(name, cfg.to_dict()) for name, cfg in configs.items()}
    domains = hparam_domains(hparams.values())
    combined = {}
    names = list(configs)

    def record(name: str, case: dict) -> None:  # each case's session as it completes, whatever a later one does
        combined[name] = case
        write_hparams_session(out / name / "tensorboard", hparams[name], case_metrics(case), domains)

    if jobs > 1:
        tasks = [(_run_case, (cfg, out / name, progress, force)) for name, cfg in configs.items()]
        make_filters(next(iter(configs.values())))  # the rules and tables every case's filters share, built once
        for module in CASE_MODULES:  # imported once here, not in every case's process
            importlib.import_module(module)
        run_forked(tasks, jobs, names=names, on_result=lambda i, case: record(names[i], case))
    else:
        with writing_beside(threads) as writer:
            for name, cfg in configs.items():
                summary = run_experiment(
                    cfg, out / name, progress=progress, kind="reproduce-case", force=force, writer=writer
                )
                record(name, _case_summary(cfg, summary))
    combined = {name: combined[name] for name in names}  # in case order, whichever finished first
    write_json(out / "summary.json", combined, indent=2)
    table = results_table(combined)
    write_text(out / "results.md", table + "\n")
    return table


#: What a case's process imports to write its files (:func:`reproduce` imports them before forking, once).
CASE_MODULES = (*PRELOAD_MODULES, "tensorboard.compat.proto.event_pb2", "scipy.special")


def default_jobs(cases: int) -> int:
    """Cases at once by default: all of them where fork is available (:func:`agsf_torch.experiments.run.worker_pool.fork_available`) and the process
    may use two CPUs or more (three cases on two cores take turns on both, which balances better than two at once
    then one), else 1."""
    import joblib

    return cases if cases > 1 and fork_available() and joblib.cpu_count(only_physical_cores=False) >= 2 else 1


def check_jobs(jobs: int | None, cases: int, threads: int | None = None) -> int:
    """Validate ``jobs`` with the ``threads`` they run with (before anything is created) and return it (``None``:
    :func:`default_jobs`).

    Raises:
        ValueError: ``jobs`` not a positive integer; more than 1 where fork is absent, or with ``threads`` above 1
            (each case's process runs one torch thread); ``threads`` not a positive integer.
    """
    check_threads(threads)
    if jobs is None:
        jobs = default_jobs(cases)
        return jobs if jobs == 1 else check_jobs(jobs, cases, threads)
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    jobs = min(jobs, max(1, cases))
    if jobs > 1 and not fork_available():
        raise ValueError(
            "cases run side by side in forked processes, which need Linux and the main thread: run them one after another (jobs=1, --jobs 1)"
        )
    if jobs > 1 and threads not in (None, 1):
        raise ValueError(
            f"cases side by side run one torch thread each, got threads={threads} (a forked process cannot use "
            "OpenMP threads safely); run them one after another (jobs=1, --jobs 1) for more threads"
        )
    return jobs


def _run_case(cfg, out: Path, progress: bool, force: bool) -> dict:
    """A case run end to end in a worker process (:func:`reproduce`; one torch thread, its progress bar drawn by the
    parent: :mod:`agsf_torch.experiments.run.worker_pool`); returns its entry of the combined summary.

    The case runs in :func:`torch.inference_mode` (no autograd bookkeeping on any tensor), which is safe here and nowhere else in the package: no tensor outlives the process,
    whereas in a process that goes on, a cache filled in inference mode (a quadrature rule, say) could not take part
    in a later autograd computation."""
    import torch

    with torch.inference_mode():
        summary = run_experiment(cfg, out, progress=progress, kind="reproduce-case", force=force)
    return _case_summary(cfg, summary)


def _case_summary(cfg, summary: dict) -> dict:
    """A case's entry of the combined summary: its star period, runs and the table's numbers per filter."""
    return {
        "star_period_s": cfg.star_period,
        "runs": cfg.runs,
        "filters": {
            f: {
                "between_frames_mean_rms_deg": s.get("between_frames", {}).get("mean_rms_deg"),
                "before_first_frame_mean_rms_deg": s.get("before_first_frame", {}).get("mean_rms_deg"),
                "final_rms_deg": s["rms_deg"][-1],
                "time_averaged_nees": s["time_averaged_nees"],
                "nis_per_expected": s.get("nis_per_expected"),
            }
            for f, s in summary["filters"].items()
        },
        "agsf_minus_gsf": summary.get("agsf_minus_gsf"),
        "agsf_galerkin_minus_gsf": summary.get("agsf_galerkin_minus_gsf"),
    }


def case_hparams(name: str, config: dict) -> dict:
    """A case's HParams values: ``case`` (its name) and its configuration's fields (but ``name`` and ``compile``)."""
    return {"case": name, **{k: v for k, v in config.items() if k not in ("name", "compile")}}


def case_metrics(case: dict) -> dict[str, float]:
    """A case's HParams metrics from its entry of the combined summary (the numbers of :func:`results_table`)."""
    metrics: dict[str, float] = {}
    for f, s in case["filters"].items():
        for key, metric in (
            ("between_frames_mean_rms_deg", "mean_rms_between_frames_deg"),
            ("before_first_frame_mean_rms_deg", "mean_rms_before_first_frame_deg"),
            ("final_rms_deg", "final_rms_deg"),
            ("time_averaged_nees", "time_averaged_nees"),
            ("nis_per_expected", "nis_per_expected"),
        ):
            if s.get(key) is not None:
                metrics[f"{f}/{metric}"] = float(s[key])
    for label in ADAPTIVE_FILTERS:
        key = minus_gsf_key(label)
        for window, d in (case.get(key) or {}).items():
            if isinstance(d, dict) and d.get("mean_deg") is not None:
                metrics[f"{key}/{window}_deg"] = float(d["mean_deg"])
    return metrics


def results_table(combined: dict) -> str:
    """Markdown table of the combined summary."""
    lines = [
        "| case | star frames | filter | mean RMS between frames (deg) | mean RMS before first frame (deg) | final RMS (deg) | time-avg NEES | NIS / expected |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for case, c in combined.items():
        for f, s in c["filters"].items():
            lines.append(
                f"| {case} | {1 / c['star_period_s']:g} Hz | {f} | {_cell(s['between_frames_mean_rms_deg'], '.5g')} | "
                f"{_cell(s['before_first_frame_mean_rms_deg'], '.5g')} | {s['final_rms_deg']:.3g} | {s['time_averaged_nees']:.4g} | "
                f"{_cell(s.get('nis_per_expected'), '.4g')} |"
            )
    lines += ["", _WINDOWS_NOTE]
    for label in ADAPTIVE_FILTERS:
        key = minus_gsf_key(label)
        rows = [(case, w, d) for case, c in combined.items() for w, d in (c.get(key) or {}).items()]
        if not rows:
            continue
        lines += [
            "",
            f"| case | window | {label} − GSF mean RMS (deg) | 95% CI | relative |",
            "| --- | --- | --- | --- | --- |",
        ]
        for case, window, d in rows:
            lines.append(
                f"| {case} | {window.replace('_', ' ')} | {d['mean_deg']:.3g} | [{d['ci95_deg'][0]:.3g}, {d['ci95_deg'][1]:.3g}] | {100 * d['relative']:.2f} % |"
            )
        lines += ["", _DIFFERENCES_NOTE]
    return "\n".join(lines)


_WINDOWS = f"{WINDOW_TEXT['between_frames']}; {WINDOW_TEXT['before_first_frame']}"
#: The sentences under the tables of :func:`results_table`: what their windows are.
_WINDOWS_NOTE = (
    f"Windows — {_WINDOWS}; final: the last step; NEES: averaged over every step and run; NIS / expected: "
    "Σ NIS ÷ Σ its expectation (2 per valid star) over every star frame and run, 1 for a consistent filter "
    "(needs no truth)."
)
_DIFFERENCES_NOTE = (
    f"Paired per-run differences of the mean RMS, Student-t 95 % interval over runs; windows — {_WINDOWS}."
)


def _cell(value: float | None, fmt: str) -> str:
    """A table number, or ``—`` where the window is empty (a run without star frames has no between-frames window)."""
    return "—" if value is None else format(value, fmt)
