"""One configured Monte Carlo experiment: run it and write everything it produces.

The pieces live one concept per module: the output folder and ``runs.npz``
(:mod:`agsf_torch.experiments.run.outputs`), what a configuration builds (:mod:`agsf_torch.experiments.config.factories`), the
statistics (:mod:`agsf_torch.experiments.report.statistics`), the figures (:mod:`agsf_torch.experiments.report.figures`) and the
TensorBoard events (:mod:`agsf_torch.experiments.report.tensorboard`); the names are re-exported here.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ...storage.files import write_json
from ..config.factories import loop_options, make_env, make_filters, prior_covariance
from ..config.loader import REPLAY_IGNORED, ExperimentConfig
from ..report.figures import write_figures
from ..report.statistics import mean_ci95, paired_difference, summarize
from ..report.tensorboard import write_tensorboard
from .file_writer import FileWriter
from .outputs import OutputConflict, load_filter_runs, prepare_output, save_runs
from .resources import check_memory
from .runner import run_monte_carlo

__all__ = [
    "make_env",
    "make_filters",
    "prior_covariance",
    "run_experiment",
    "summarize",
    "prepare_output",
    "OutputConflict",
    "mean_ci95",
    "paired_difference",
]


def run_experiment(
    cfg: ExperimentConfig,
    out: Path,
    *,
    progress: bool = True,
    kind: str = "run",
    recording: str | Path | None = None,
    force: bool = False,
    label: str | None = None,
    reuse: Mapping[str, Path] | None = None,
    writer: FileWriter | None = None,
) -> dict[str, Any]:
    """Run one configuration and write everything it produces under ``out``.

    ``writer`` (a :class:`~agsf_torch.experiments.run.file_writer.FileWriter`) writes the figures, the event files and ``runs.npz``, in worker
    processes if it has them (``runs.npz`` above :data:`~agsf_torch.experiments.run.file_writer.HANDOVER_BYTES` in a thread of this process):
    the call then returns before they are written, and they are complete when the writer is closed.

    ``label`` names the run on its progress bar and in its figures' titles (``summary["label"]``; default: the
    configuration's ``name``; a sweep passes the configuration's parameters).

    ``reuse`` maps filters of the configuration to the folder of an earlier experiment that ran them with the
    same :meth:`~agsf_torch.experiments.config.loader.ExperimentConfig.filter_digest` (the same simulation, prior and options): their arrays
    are copied from its ``runs.npz`` instead of running them again (a sweep over an option only some filters
    read), and ``summary["reused"]`` names the folder each came from.  The simulation of the filters that do
    run must match theirs (times and star frames), else ``RuntimeError``.

    With ``recording`` the filters replay that file (it must hold ``cfg.runs`` trajectories of at least
    ``cfg.num_steps`` steps, and the truth or an initial estimate: without the truth the filters start at the
    file's ``initial_mrp`` / ``initial_bias`` and nothing is scored against a truth) instead of a simulation;
    the experiment is identified by the configuration and the recording's *contents*
    (:meth:`~agsf_torch.attitude.recordings.Recording.content_digest`), so new contents at the same
    path are a different experiment and never replace earlier results.

    Everything is validated (the recording, the memory estimate of :func:`agsf_torch.experiments.run.resources.check_memory`,
    unless ``force``, and the output folder) before ``out`` is created.
    """
    if recording is not None:
        from ...attitude.recordings import Recording
        from .recorded import RecordingEnv, check_recording

        rec = Recording.load(recording)
        check_recording(rec, cfg, str(recording))
        env = RecordingEnv(rec)
        digest = f"{cfg.digest(replay=True)}:recording={rec.content_digest()}"
        check_memory(cfg, force=force)
    else:
        check_memory(cfg, force=force)
        env, digest = make_env(cfg), cfg.digest()
    reuse = dict(reuse or {})
    unknown = sorted(set(reuse) - set(cfg.filters))
    if unknown:
        raise ValueError(f"cannot reuse results of {unknown}: the configuration runs {cfg.filters}")
    if reuse and recording is not None:
        raise ValueError("results are reused between simulated experiments only, not with a recording")
    for name, folder in reuse.items():
        _check_reusable(cfg, name, Path(folder))
    reused = {name: load_filter_runs(Path(folder) / "runs.npz", name) for name, folder in reuse.items()}
    filters = {name: setup for name, setup in make_filters(cfg).items() if name not in reuse}
    out = prepare_output(Path(out), kind, digest, cfg.to_dict(), REPLAY_IGNORED if recording is not None else ())
    if not filters:
        data = save_runs(out / "runs.npz", None, reused, writer)
        return _write_results(out, data, cfg, reuse, writer, label)
    res = run_monte_carlo(
        env, filters, progress=progress, label=cfg.name if label is None else label, **loop_options(cfg)
    )
    data = save_runs(out / "runs.npz", res, reused, writer)
    return _write_results(out, data, cfg, reuse, writer, label)


def _check_reusable(cfg: ExperimentConfig, name: str, folder: Path) -> None:
    """Refuse to reuse ``name``'s results from ``folder`` unless its experiment had the same filter digest."""
    import json

    from ..config.loader import config_from_mapping

    try:
        theirs = config_from_mapping(json.loads((folder / "experiment.json").read_text())["config"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"cannot reuse results of {name} from {folder}: no readable experiment.json ({exc})") from None
    if theirs.filter_digest(name) != cfg.filter_digest(name):
        raise ValueError(
            f"cannot reuse results of {name} from {folder}: that experiment differs in what {name} reads "
            "(its simulation, prior or options)"
        )


def _write_results(
    out: Path,
    data: dict,
    cfg: ExperimentConfig,
    reuse: dict[str, Path],
    writer: FileWriter | None,
    label: str | None = None,
) -> dict[str, Any]:
    """The summary, figures (through ``writer``) and TensorBoard events of an experiment's data."""
    summary = summarize(data, cfg)
    if label is not None:
        summary["label"] = label
    if reuse:
        summary["reused"] = {name: Path(folder).name for name, folder in reuse.items()}
    write_json(out / "summary.json", summary)
    write_figures(out, summary, writer)
    write_tensorboard(out, data, summary, writer)
    return summary
