"""One configured Monte Carlo experiment: run it and write everything it produces.

The pieces live one concept per module: the output folder and ``runs.npz``
(:mod:`.outputs`), what a configuration builds (:mod:`.factories`), the
statistics (:mod:`.statistics`), the figures (:mod:`.figures`) and the
TensorBoard events (:mod:`.tensorboard_log`); the names are re-exported here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..storage.files import write_json
from .config import ExperimentConfig
from .factories import make_env, make_filters, prior_covariance
from .figures import write_figures
from .outputs import OutputConflict, prepare_output, save_runs
from .resources import check_memory
from .runner import run_monte_carlo
from .statistics import mean_ci95, paired_difference, summarize
from .tensorboard_log import write_tensorboard

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
) -> dict[str, Any]:
    """Run one configuration and write everything it produces under ``out``.

    ``label`` names the run on its progress bar (default: the configuration's ``name``; a sweep passes
    the configuration's parameters).

    With ``recording`` the filters replay that file (it must hold the truth and
    ``cfg.runs`` trajectories of at least ``cfg.num_steps`` steps) instead of a simulation;
    the experiment is identified by the configuration and the recording's *contents*
    (:meth:`~agsf_torch.attitude.recordings.Recording.content_digest`), so new contents at the same
    path are a different experiment and never replace earlier results.

    Everything is validated (the recording, the memory estimate of :func:`.resources.check_memory`,
    unless ``force``, and the output folder) before ``out`` is created.
    """
    if recording is not None:
        from ..attitude.recordings import Recording
        from .recorded import RecordingEnv, check_recording

        rec = Recording.load(recording)
        env = RecordingEnv(rec)
        check_recording(rec, cfg, str(recording))
        digest = f"{cfg.digest()}:recording={rec.content_digest()}"
        check_memory(cfg, force=force)
    else:
        check_memory(cfg, force=force)
        env, digest = make_env(cfg), cfg.digest()
    filters = make_filters(cfg)
    out = prepare_output(Path(out), kind, digest, cfg.to_dict())
    res = run_monte_carlo(
        env,
        filters,
        num_steps=cfg.num_steps,
        prior_cov=prior_covariance(cfg),
        sigma_s=cfg.sigma_s * cfg.filter_sigma_s_scale,
        seed=cfg.seed,
        estimate_bias=cfg.estimate_bias,
        progress=progress,
        noise_model=cfg.star_noise_model,
        label=cfg.name if label is None else label,
    )
    data = save_runs(out / "runs.npz", res)
    summary = summarize(data, cfg)
    write_json(out / "summary.json", summary)
    write_figures(out, summary)
    write_tensorboard(out, data, summary)
    return summary
