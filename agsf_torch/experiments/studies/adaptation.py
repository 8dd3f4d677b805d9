"""``agsf adaptation``: where does adapting the weights pay?  The paper's three claims, measured.

The paper claims that adapting the weights during propagation gives better
estimates between frames, a more accurate density, and better behaviour with
ambiguous measurements.  This study measures all three for five filters — EKF,
GSF, the adaptive GSF with the paper's weight QP (``AGSF``) and with the authors'
later Galerkin update (``AGSF-galerkin``), and the multiplicative EKF (``MEKF``, the
industry baseline) — on identical truth and data, in the scenarios of
:data:`SCENARIOS`.  Per filter and scenario:

* RMS attitude error (deg) and NEES, per run and averaged over time windows;
* the **density score**: the mean log-density, under the filter's mixture, of
  samples of the exact filtering density of the filter's own model (prior
  ``N(x̂₀, P₀)``, the attitude SDE driven by the recorded gyro, the star-vector
  likelihoods) — :class:`agsf_torch.density.PosteriorReference`.  It is a
  proper scoring rule: higher is better; differences between filters are
  differences of KL divergences from the exact density (nats);
* 95 % Student-t intervals over runs for every window mean, and paired
  differences against the GSF.

The reference is run at two sample sizes with independent generators; their
score difference (with its interval) is the convergence check, and the reference's
effective sample size is reported.

Output folder: ``summary.json`` (every number), ``<scenario>.png`` (RMS, NEES and
density score against time), ``scores.png`` (the density score of every filter in
every scenario), ``tensorboard/<scenario>/<filter>/`` (per-step scalars ``rms_deg``, ``nees``,
``density_score``; ``tensorboard/<scenario>/reference/``: ``ess_median``; time in milliseconds as the step).
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...consistency import nees, rms
from ...density import PosteriorReference
from ...rotations import attitude_error_angle
from ...storage.files import save_figure, write_json, write_text
from ..config.factories import filter_model, loop_options
from ..config.loader import ExperimentConfig, load_config
from ..report.statistics import WINDOW_TEXT, error_windows
from ..report.tensorboard import clear_runs, time_steps
from ..run.experiment import make_env, make_filters, mean_ci95, prepare_output
from ..run.resources import check_memory
from ..run.runner import monte_carlo_steps

__all__ = ["SCENARIOS", "STUDY_FILTERS", "run_scenario", "run_adaptation_study", "study_table"]

#: scenario → (preset, overrides).  The paper's cases with the plain EKF update (as the
#: paper) and with an iterated, consistent update; the wide prior; and an ambiguous one —
#: one star per frame, so every frame leaves the rotation about that star unobserved.
SCENARIOS: dict[str, tuple[str, list[str]]] = {
    "case1": ("case1", []),
    "case2": ("case2", []),
    "case3": ("case3", []),
    "case1-iterated": ("case1", ["update_iterations=3"]),
    "case2-iterated": ("case2", ["update_iterations=3"]),
    "case3-iterated": ("case3", ["update_iterations=3"]),
    "wide_prior": ("wide_prior", []),
    "ambiguous": ("case1", ["max_stars=1", "update_iterations=3"]),
}

#: The filters compared, in table order.
STUDY_FILTERS = ("EKF", "GSF", "AGSF", "AGSF-galerkin", "MEKF")


def scenario_config(name: str, runs: int, overrides: list[str] | None = None) -> ExperimentConfig:
    """The configuration of a scenario with ``runs`` trajectories (and extra ``key=value`` overrides)."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose from {', '.join(SCENARIOS)}")
    preset, base = SCENARIOS[name]
    filters = "[" + ", ".join(f'"{f}"' for f in STUDY_FILTERS) + "]"
    cfg = load_config(preset, [*base, f"runs={runs}", f"filters={filters}", f'name="{name}"', *(overrides or [])])
    if list(cfg.filters) != list(STUDY_FILTERS):
        raise ValueError(f"the study compares {', '.join(STUDY_FILTERS)}; config key 'filters' cannot be overridden")
    return cfg


def run_scenario(
    cfg: ExperimentConfig, *, samples: int, seed: int = 0, lineage_threshold: float = 0.02, progress: bool = False
) -> dict[str, Any]:
    """Run one scenario: the filters on the simulated runs and the exact-density reference beside them.

    Args:
        cfg: the scenario's configuration (:func:`scenario_config`).
        samples: reference samples per run ``K``; a second reference with ``K/4`` checks convergence.
        seed: seeds the references (the runs themselves are seeded by ``cfg.seed``).
        lineage_threshold: of :class:`~agsf_torch.density.PosteriorReference`: a redraw
            re-simulates from ``t₀`` and costs O(elapsed time), so the study redraws on
            lineages only below 2 % of ``K`` (the ESS trigger stays at 10 %); the
            smaller reference checks what that costs in accuracy.

    Returns:
        per-step arrays (numpy): ``time [T]``, ``frame [T]``, and per filter ``error_angle``,
        ``nees``, ``score``, ``score_se``, ``score_small`` ``[T, B]``; ``ess`` ``[T, B]`` and
        ``ess_small`` of the two references.
    """
    env = make_env(cfg)
    filters = make_filters(cfg)
    model = next(iter(filters.values())).filter.model
    options = loop_options(cfg)
    P0 = options["prior_cov"]
    steps = monte_carlo_steps(env, filters, **options)
    if progress:
        from ..run.progress import progress_bar

        steps = progress_bar(steps, desc=cfg.name, unit="step", total=cfg.num_steps)
    rec: dict[str, list] = {"time": [], "frame": [], "ess": [], "ess_small": []}
    per: dict[str, dict[str, list]] = {
        f: {"error_angle": [], "nees": [], "score": [], "score_se": [], "score_small": []} for f in filters
    }
    refs: list[PosteriorReference] = []
    for step in steps:
        if not refs:
            for k, (K, s) in enumerate(((samples, seed), (max(2, samples // 4), seed + 1))):
                gen = torch.Generator().manual_seed(int(s) * 1000 + 17)
                refs.append(
                    PosteriorReference(
                        model, step.prior_mean, P0, num_samples=K, generator=gen, lineage_threshold=lineage_threshold
                    )
                )
        for ref in refs:
            ref.predict(step.u, cfg.dt)
        if step.measurement is not None:
            y, meas = step.measurement
            hints = torch.stack([fs.mean for fs in step.filters.values()], -2)  # each filter's estimate
            for ref in refs:
                ref.update(y, meas, hints=hints)
        rec["time"].append(step.time)
        rec["frame"].append(step.star_frame)
        rec["ess"].append(refs[0].ess)
        rec["ess_small"].append(refs[1].ess)
        for name, fs in step.filters.items():
            r = per[name]
            r["error_angle"].append(attitude_error_angle(fs.mean[:, :3], step.truth_mrp))
            r["nees"].append(nees(step.chart_error[name], fs.cov))
            score, se = refs[0].score(fs.mixture)
            r["score"].append(score)
            r["score_se"].append(se)
            r["score_small"].append(refs[1].score(fs.mixture)[0])
    out: dict[str, Any] = {
        "time": np.array(rec["time"]),
        "frame": np.array(rec["frame"], dtype=bool),
        "ess": torch.stack(rec["ess"]).numpy(),
        "ess_small": torch.stack(rec["ess_small"]).numpy(),
        "samples": samples,
        "lineage_threshold": lineage_threshold,
        "filters": {name: {k: torch.stack(v).numpy() for k, v in r.items()} for name, r in per.items()},
    }
    return out


def summarize_scenario(res: dict[str, Any], cfg: ExperimentConfig) -> dict[str, Any]:
    """Window means over time, then mean and 95 % interval over runs; paired differences against the GSF."""
    frames = res["frame"]
    windows = error_windows(frames)
    n = filter_model(cfg).state_dim
    out: dict[str, Any] = {
        "config": cfg.to_dict(),
        "state_dim": n,
        "reference": {
            "samples": res["samples"],
            "lineage_threshold": res["lineage_threshold"],
            "ess_median": float(np.median(res["ess"])),
            "ess_min": float(np.min(res["ess"])),
            "ess_median_at_frames": float(np.median(res["ess"][frames])) if frames.any() else None,
        },
        "filters": {},
        "minus_gsf": {},
    }
    per_run: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    for name, r in res["filters"].items():
        entry: dict[str, Any] = {}
        per_run[name] = {}
        for wname, mask in windows.items():
            if not mask.any():
                continue
            rms_deg = np.degrees(rms(r["error_angle"][mask], 0))  # [B]
            ne = r["nees"][mask].mean(0)
            sc = r["score"][mask].mean(0)
            sc_small = r["score_small"][mask].mean(0)
            per_run[name][wname] = {"rms_deg": rms_deg, "nees": ne, "score": sc}
            m, lo, hi = mean_ci95(rms_deg)
            mn, lon, hin = mean_ci95(ne)
            ms, los, his = mean_ci95(sc)
            dc, dlo, dhi = mean_ci95(sc - sc_small)
            entry[wname] = {
                "rms_deg": m,
                "rms_deg_ci95": [lo, hi],
                "nees": mn,
                "nees_ci95": [lon, hin],
                "density_score": ms,
                "density_score_ci95": [los, his],
                "density_score_minus_small_reference": dc,
                "density_score_minus_small_reference_ci95": [dlo, dhi],
            }
        entry["rms_deg_t"] = np.degrees(rms(r["error_angle"], 1)).tolist()
        entry["nees_t"] = r["nees"].mean(1).tolist()
        entry["density_score_t"] = r["score"].mean(1).tolist()
        out["filters"][name] = entry
    if "GSF" in per_run:
        for name in per_run:
            if name == "GSF":
                continue
            out["minus_gsf"][name] = {}
            for wname in per_run[name]:
                d = {}
                for key in ("rms_deg", "nees", "score"):
                    m, lo, hi = mean_ci95(per_run[name][wname][key] - per_run["GSF"][wname][key])
                    d[key] = {"mean": m, "ci95": [lo, hi]}
                out["minus_gsf"][name][wname] = d
    out["time_s"] = res["time"].tolist()
    out["star_frame"] = frames.tolist()
    return out


def _figure(path: Path, name: str, summary: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array(summary["time_s"])
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    styles = {"EKF": ":", "GSF": "-", "AGSF": "--", "AGSF-galerkin": "-.", "MEKF": (0, (1, 3))}
    for fname, f in summary["filters"].items():
        ls = styles.get(fname, "-")
        axes[0].semilogy(t, f["rms_deg_t"], linestyle=ls, label=fname)
        axes[1].semilogy(t, f["nees_t"], linestyle=ls, label=fname)
        axes[2].plot(t, f["density_score_t"], linestyle=ls, label=fname)
    n = summary["state_dim"]
    axes[1].axhline(n, color="k", lw=0.6, alpha=0.6)
    axes[0].set(xlabel="time (s)", ylabel="RMS attitude error (deg)", title=f"{name}: RMS over runs")
    axes[1].set(xlabel="time (s)", ylabel=f"mean NEES (ideal {n})", title="consistency")
    axes[2].set(
        xlabel="time (s)", ylabel="mean log-density of exact samples (nats)", title="density score (higher is better)"
    )
    axes[2].set_yscale("symlog", linthresh=10.0)  # scores span a few nats to −10⁵ for overconfident filters
    for a in axes:
        a.grid(True, which="both", alpha=0.3)
    for a in axes:
        for tf, fr in zip(t, summary["star_frame"]):
            if fr:
                a.axvline(tf, color="0.85", lw=0.5, zorder=0)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def _scores_figure(path: Path, summaries: dict[str, dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summaries)
    fig, ax = plt.subplots(figsize=(max(7, 1.3 * len(names)), 4))
    width = 0.8 / len(STUDY_FILTERS)
    for k, f in enumerate(STUDY_FILTERS):
        vals, errs = [], []
        for s in names:
            d = summaries[s]["minus_gsf"][f]["all"]["score"] if f != "GSF" else {"mean": 0.0, "ci95": [0.0, 0.0]}
            vals.append(d["mean"])
            errs.append(d["mean"] - d["ci95"][0])
        offset = (k - (len(STUDY_FILTERS) - 1) / 2) * width
        ax.bar(np.arange(len(names)) + offset, vals, width, yerr=errs, label=f, capsize=2)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(np.arange(len(names)), names, rotation=20)
    ax.set(
        ylabel="density score − GSF's (nats, 95 % CI)", title="time-averaged density score relative to the classic GSF"
    )
    ax.set_yscale("symlog", linthresh=0.1)
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def _tensorboard(folder: Path, summary: dict[str, Any], res: dict[str, Any]) -> None:
    """One run per filter (tags ``rms_deg``, ``nees``, ``density_score``) and one ``reference`` run (``ess_median``)
    under the scenario's ``folder``, steps in simulated ms (:mod:`agsf_torch.experiments.report.tensorboard`)."""
    from torch.utils.tensorboard import SummaryWriter

    clear_runs(folder)  # a rerun replaces this scenario's events, never appends to them
    steps, _ = time_steps(np.array(summary["time_s"]))
    for fname, f in summary["filters"].items():
        with SummaryWriter(str(folder / fname)) as writer:
            for k, step in enumerate(steps):
                writer.add_scalar("rms_deg", f["rms_deg_t"][k], int(step))
                writer.add_scalar("nees", f["nees_t"][k], int(step))
                writer.add_scalar("density_score", f["density_score_t"][k], int(step))
    with SummaryWriter(str(folder / "reference")) as writer:
        for k, step in enumerate(steps):
            writer.add_scalar("ess_median", float(np.median(res["ess"][k])), int(step))


def run_adaptation_study(
    scenarios: list[str],
    out: Path,
    *,
    runs: int = 32,
    samples: int = 1024,
    overrides: list[str] | None = None,
    progress: bool = True,
    force: bool = False,
) -> dict[str, Any]:
    """Run the scenarios, write ``summary.json``, figures, TensorBoard logs and ``results.md`` under ``out``.

    Raises:
        ValueError: an unknown scenario, ``runs``/``samples`` out of range, or a scenario whose
            memory estimate (:func:`~agsf_torch.experiments.run.resources.check_memory`) exceeds the memory available
            (unless ``force``), before anything is written.
    """
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 2:
        raise ValueError(f"runs must be an integer ≥ 2 (intervals need two runs), got {runs!r}")
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 64:
        raise ValueError(f"samples must be an integer ≥ 64, got {samples!r}")
    configs = {s: scenario_config(s, runs, overrides) for s in scenarios}
    for cfg in configs.values():
        check_memory(cfg, force=force)
    digest = hashlib.sha256(
        json.dumps(
            {"configs": {k: c.digest() for k, c in configs.items()}, "samples": samples}, sort_keys=True
        ).encode()
    ).hexdigest()[:16]
    out = prepare_output(
        Path(out), "adaptation", digest, {"samples": samples, **{k: c.to_dict() for k, c in configs.items()}}
    )
    summaries: dict[str, Any] = {}
    for name, cfg in configs.items():
        res = run_scenario(cfg, samples=samples, progress=progress)
        summaries[name] = summarize_scenario(res, cfg)
        _figure(out / f"{name}.png", name, summaries[name])
        _tensorboard(out / "tensorboard" / name, summaries[name], res)
        write_json(out / "summary.json", summaries)
    _scores_figure(out / "scores.png", summaries)
    table = "\n\n".join(
        f"{w.replace('_', ' ')}:\n\n{study_table(summaries, w)}"
        for w in ("before_first_frame", "between_frames", "all")
    )
    write_text(out / "results.md", table + "\n")
    return summaries


def _fmt(v: float, lo: float, hi: float, digits: int = 3) -> str:
    if not math.isfinite(lo):
        return f"{v:.{digits}g}"
    return f"{v:.{digits}g} [{lo:.{digits}g}, {hi:.{digits}g}]"


def study_table(summaries: dict[str, Any], window: str = "all") -> str:
    """Markdown: per scenario and filter, RMS (deg), NEES and density score (nats) with 95 % intervals
    over the ``window`` (``all``, ``before_first_frame``, ``between_frames``), and the score relative to the GSF."""
    lines = [
        "| scenario | filter | RMS (deg) | NEES | density score (nats) | score − GSF (nats) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for sname, s in summaries.items():
        for fname, f in s["filters"].items():
            w = f.get(window)
            if w is None:
                continue
            d = s["minus_gsf"].get(fname, {}).get(window, {}).get("score")
            diff = "—" if d is None else _fmt(d["mean"], *d["ci95"])
            lines.append(
                f"| {sname} | {fname} | {_fmt(w['rms_deg'], *w['rms_deg_ci95'])} | {_fmt(w['nees'], *w['nees_ci95'])} | "
                f"{_fmt(w['density_score'], *w['density_score_ci95'], digits=5)} | {diff} |"
            )
    return "\n".join(lines) + f"\n\nWindow — {WINDOW_TEXT[window]}."
