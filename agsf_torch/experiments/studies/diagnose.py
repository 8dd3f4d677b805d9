"""``agsf diagnose``: run a configuration and judge its consistency in words."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...consistency import Check, consistency_checks, format_report
from ...storage.files import write_json, write_text
from ..config.factories import filter_model
from ..config.loader import ExperimentConfig
from ..report.tensorboard import clear_events
from ..run.experiment import run_experiment

__all__ = ["diagnose"]


def diagnose(
    cfg: ExperimentConfig,
    out: Path,
    *,
    progress: bool = True,
    force: bool = False,
    recording: str | Path | None = None,
) -> tuple[str, bool]:
    """Run ``cfg`` under ``out`` (on a simulation, or replaying ``recording`` as ``agsf run --recording`` does:
    it must hold the truth or an initial estimate and ``cfg.runs`` trajectories, checked before ``out`` is
    created) and check every filter (without the truth: the NIS and its whiteness, not the NEES); writes
    ``diagnose.json`` / ``diagnose.md``.  The checks' bands are simultaneous
    (:func:`~agsf_torch.consistency.consistency_checks`): a consistent filter fails some check at most 5 % of the
    time.

    Returns:
        ``(report text, whether every check of every filter passed)``.
    """
    run_experiment(cfg, out, progress=progress, kind="diagnose", force=force, recording=recording)
    data = np.load(Path(out) / "runs.npz")
    n = filter_model(cfg).state_dim
    texts, result, passed = [], {}, True
    for name in cfg.filters:
        nees = data[f"{name}/nees"].T if f"{name}/nees" in data else None  # no truth: NIS and whiteness only
        checks = consistency_checks(
            nees=nees, state_dim=n, nis=data[f"{name}/nis"].T, nis_dof=data[f"{name}/nis_dof"].T
        )
        if not checks:  # no truth and no star frame: nothing judged is not a pass
            text = "nothing to judge: no truth (NEES) and no star frame (NIS) in the run"
            checks = [Check("nothing", float("nan"), (float("nan"), float("nan")), False, text)]
        fpke = None
        if f"{name}/fpke_error_before" in data:
            fpke = (float(data[f"{name}/fpke_error_before"].mean()), float(data[f"{name}/fpke_error_after"].mean()))
        texts.append(format_report(name, checks, fpke))
        result[name] = [c.__dict__ for c in checks]
        passed &= all(c.passed for c in checks)
    report = "\n".join(texts)
    write_json(Path(out) / "diagnose.json", {"passed": passed, "filters": result}, indent=2, default=float)
    write_text(Path(out) / "diagnose.md", report + "\n")
    from torch.utils.tensorboard import SummaryWriter

    clear_events(Path(out) / "tensorboard")  # a rerun replaces its events
    with SummaryWriter(str(Path(out) / "tensorboard")) as writer:
        writer.add_text("diagnose", report.replace("\n", "  \n"))
    return report, passed
