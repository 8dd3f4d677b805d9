"""One configured Monte Carlo experiment: run, save per-run data, summarise, plot, log.

Output folder layout (``out``)::

    experiment.json   the configuration and its digest (guards against overwriting another experiment)
    runs.npz          per-run data of every filter (the source of every number below)
    summary.json      the numbers behind every figure and the between-update statistics
    rms.png, axes.png, weights.png, fpke.png
    tensorboard/      event files (scalars per step, weight histograms)
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.stats import t as student_t

from ..filters import AdaptiveGaussianSumFilter, ExtendedKalmanFilter, GaussianSumFilter, MultiplicativeEKF
from ..metrics import chi2_band
from ..models import AttitudeModel
from .config import DEG_PER_HOUR, FILTER_NAMES, ExperimentConfig
from .runner import FilterSetup, MonteCarloResult, run_monte_carlo

__all__ = [
    "make_env", "make_filters", "run_experiment", "summarize", "prepare_output", "OutputConflict", "mean_ci95", "paired_difference",
]


class OutputConflict(ValueError):
    """The output folder holds a different experiment."""


def prepare_output(out: Path, kind: str, digest: str, config: dict[str, Any]) -> Path:
    """Create ``out`` for an experiment; refuse one that holds a different experiment."""
    out = Path(out)
    marker = out / "experiment.json"
    if marker.exists():
        prev = json.loads(marker.read_text())
        if prev.get("kind") != kind or prev.get("digest") != digest:
            raise OutputConflict(
                f"{out} already holds a different experiment ({prev.get('kind')} {prev.get('digest')}); "
                "choose another --out or remove it"
            )
    elif out.exists() and any(out.iterdir()):
        raise OutputConflict(f"{out} exists and is not an agsf experiment folder; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"kind": kind, "digest": digest, "config": config}, indent=2))
    return out


def make_env(cfg: ExperimentConfig):
    """The batched star-tracker environment of a configuration."""
    import envs

    return envs.StarTrackerAttitudeVectorEnv(
        num_envs=cfg.runs,
        max_steps=cfg.num_steps,
        dt=cfg.dt,
        star_period=cfg.star_period,
        sigma_v=cfg.sigma_v,
        sigma_u=cfg.sigma_u,
        initial_bias=cfg.gyro_bias_deg_per_hr * DEG_PER_HOUR,
        sigma_s=cfg.sigma_s,
        fov_deg=cfg.fov_deg,
        focal_length=cfg.focal_length,
        max_stars=cfg.max_stars,
        rate=[cfg.omega0 * a for a in cfg.rate_axes],
        faults=cfg.faults,
    )


def make_filters(cfg: ExperimentConfig) -> dict[str, FilterSetup]:
    """The filters a configuration names (``FILTER_NAMES``), all on the same attitude model."""
    model = AttitudeModel(estimate_bias=cfg.estimate_bias, sigma_v=cfg.sigma_v * cfg.filter_sigma_v_scale, sigma_u=cfg.sigma_u)
    kw = {"update_iterations": cfg.update_iterations, "gate_probability": cfg.gate_probability or None}
    made = {
        "EKF": lambda: FilterSetup(ExtendedKalmanFilter(model, **kw), 1),
        "GSF": lambda: FilterSetup(GaussianSumFilter(model, **kw), cfg.components, cfg.spread),
        "AGSF": lambda: FilterSetup(
            AdaptiveGaussianSumFilter(
                model, reg=cfg.reg, scaling=cfg.scaling, weight_ref=cfg.weight_ref, compile=cfg.compile,
                cadence=cfg.adapt_cadence, **kw
            ),
            cfg.components,
            cfg.spread,
        ),
        "AGSF-galerkin": lambda: FilterSetup(
            AdaptiveGaussianSumFilter(model, weight_update="galerkin", compile=cfg.compile, cadence=cfg.adapt_cadence, **kw),
            cfg.components,
            cfg.spread,
        ),
        "MEKF": lambda: FilterSetup(MultiplicativeEKF(model, **kw), 1),
    }
    return {name: made[name]() for name in cfg.filters}


def prior_covariance(cfg: ExperimentConfig) -> torch.Tensor:
    n = 6 if cfg.estimate_bias else 3
    sb = (cfg.prior_bias_sigma_deg_per_hr * DEG_PER_HOUR) ** 2
    return torch.diag(torch.tensor([cfg.prior_var] * 3 + [sb] * 3, dtype=torch.float64)[:n])


def _save_runs(path: Path, res: MonteCarloResult) -> dict[str, np.ndarray]:
    data: dict[str, np.ndarray] = {"time": res.time, "star_frame": res.star_frame}
    for name, tr in res.traces.items():
        data[f"{name}/error_angle"] = tr.error_angle
        data[f"{name}/error"] = tr.error
        data[f"{name}/sigma"] = tr.sigma
        data[f"{name}/nees"] = tr.nees
        data[f"{name}/nis"] = tr.nis
        data[f"{name}/nis_dof"] = tr.nis_dof
        data[f"{name}/weights"] = tr.weights
        data[f"{name}/weight_entropy"] = tr.weight_entropy
        for key in ("fpke_error_before", "fpke_error_after", "galerkin_residual_change", "gate_rejected", "gyro_held"):
            if key in tr.extra:
                data[f"{name}/{key}"] = tr.extra[key]
    np.savez_compressed(path, **data)
    return data


def summarize(data: dict[str, np.ndarray], cfg: ExperimentConfig) -> dict[str, Any]:
    """Summary statistics from the per-run data alone (``runs.npz``).

    * ``rms_deg [T]``: ``sqrt(mean_b θ_b(t)²)`` in degrees;
    * ``between_updates``: per run ``r_b = sqrt(mean_{t ∉ frames} θ_b(t)²)`` over the
      steps that are not star frames; ``mean_rms_deg`` is ``mean_b r_b``;
    * ``before_first_update``: the same over the steps before the first frame;
    * ``agsf_minus_gsf`` (``agsf_galerkin_minus_gsf``): paired differences
      ``r_b(AGSF) − r_b(GSF)`` (the Galerkin filter's), mean and a Student-t 95 %
      confidence interval; every per-run mean above carries its own interval
      (``ci95_rms_deg``, ``time_averaged_nees_ci95``, over runs).
    """
    time = data["time"]
    frames = data["star_frame"].astype(bool)
    first = int(np.argmax(frames)) if frames.any() else len(frames)
    windows = {"between_updates": ~frames, "before_first_update": np.arange(len(frames)) < first}
    names = [n for n in FILTER_NAMES if f"{n}/error_angle" in data]
    n_state = data[f"{names[0]}/error"].shape[-1]
    runs = data[f"{names[0]}/error_angle"].shape[1]
    lo, hi = chi2_band(n_state, runs)
    out: dict[str, Any] = {
        "config": cfg.to_dict(),
        "time_s": time.tolist(),
        "star_frame": frames.tolist(),
        "nees_band_95": [lo, hi],
        "filters": {},
    }
    per_run: dict[str, dict[str, np.ndarray]] = {}
    for name in names:
        theta = data[f"{name}/error_angle"]  # [T, B]
        entry: dict[str, Any] = {
            "rms_deg": np.degrees(np.sqrt((theta**2).mean(1))).tolist(),
            "nees_mean": data[f"{name}/nees"].mean(1).tolist(),
            "time_averaged_nees": float(data[f"{name}/nees"].mean()),
            "time_averaged_nees_ci95": list(mean_ci95(data[f"{name}/nees"].mean(0))[1:]),
            "weights_run0": data[f"{name}/weights"][:, 0].tolist(),
            "error_run0_rad": data[f"{name}/error"][:, 0].tolist(),
            "sigma_run0_rad": data[f"{name}/sigma"][:, 0].tolist(),
            "mean_weight_entropy": float(data[f"{name}/weight_entropy"].mean()),
        }
        for key in ("fpke_error_before", "fpke_error_after"):
            if f"{name}/{key}" in data:
                entry[f"{key}_mean"] = data[f"{name}/{key}"].mean(1).tolist()
        for key in ("gate_rejected", "gyro_held"):
            if f"{name}/{key}" in data:
                entry[f"{key}_total"] = int(data[f"{name}/{key}"].sum())
        per_run[name] = {}
        for wname, mask in windows.items():
            if mask.any():
                r = np.degrees(np.sqrt((theta[mask] ** 2).mean(0)))  # [B]
                per_run[name][wname] = r
                entry[wname] = {
                    "mean_rms_deg": float(r.mean()),
                    "std_rms_deg": float(r.std(ddof=1)) if runs > 1 else 0.0,
                    "ci95_rms_deg": list(mean_ci95(r)[1:]),
                }
        out["filters"][name] = entry
    for adaptive, key in (("AGSF", "agsf_minus_gsf"), ("AGSF-galerkin", "agsf_galerkin_minus_gsf")):
        if "GSF" in per_run and adaptive in per_run:
            out[key] = {
                wname: paired_difference(per_run[adaptive][wname], per_run["GSF"][wname])
                for wname in windows
                if wname in per_run["GSF"]
            }
    return out


def mean_ci95(values: np.ndarray) -> tuple[float, float, float]:
    """Mean of per-run values ``[B]`` and its Student-t 95 % interval ``(mean, low, high)``."""
    values = np.asarray(values, dtype=np.float64)
    m = float(values.mean())
    if values.size < 2:
        return m, float("nan"), float("nan")
    half = float(student_t.ppf(0.975, values.size - 1) * values.std(ddof=1) / math.sqrt(values.size))
    return m, m - half, m + half


def paired_difference(a: np.ndarray, b: np.ndarray) -> dict[str, Any]:
    """Paired per-run difference ``a − b`` (deg): mean, Student-t 95 % interval and relative to ``mean(b)``."""
    m, lo, hi = mean_ci95(np.asarray(a) - np.asarray(b))
    return {"mean_deg": m, "ci95_deg": [lo, hi], "relative": float(m / np.mean(b))}


def _figures(out: Path, summary: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array(summary["time_s"])
    filters = summary["filters"]
    title = summary["config"]["name"]

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, f in filters.items():
        ax.semilogy(t, f["rms_deg"], label=name)
    ax.set(xlabel="time (s)", ylabel="RMS attitude error (deg)", title=f"{title}: RMS over {summary['config']['runs']} runs")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "rms.png", dpi=110)
    plt.close(fig)

    shown = [n for n in ("GSF", "AGSF", "AGSF-galerkin") if n in filters] or list(filters)
    fig, axes = plt.subplots(len(shown), 3, figsize=(11, 3 * len(shown)), squeeze=False)
    for row, name in enumerate(shown):
        err = np.degrees(np.array(filters[name]["error_run0_rad"]))[:, :3] * 3600
        sig = np.degrees(np.array(filters[name]["sigma_run0_rad"]))[:, :3] * 3600
        for k in range(3):
            a = axes[row, k]
            a.plot(t, err[:, k], lw=1, label="error")
            a.plot(t, 3 * sig[:, k], "r--", lw=0.8, label="±3σ")
            a.plot(t, -3 * sig[:, k], "r--", lw=0.8)
            a.set_yscale("symlog", linthresh=1.0)
            a.set(title=f"{name} axis {k + 1} (run 0)", xlabel="time (s)", ylabel="arcsec")
            a.grid(True, alpha=0.3)
    axes[0, 0].legend()
    fig.tight_layout()
    fig.savefig(out / "axes.png", dpi=100)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(shown), figsize=(5.5 * len(shown), 3.5), squeeze=False)
    for col, name in enumerate(shown):
        w = np.array(filters[name]["weights_run0"])
        axes[0, col].plot(t, w, lw=1)
        axes[0, col].set(title=f"{name} weights (run 0)", xlabel="time (s)", ylabel="weight", ylim=(-0.02, 1.02))
        axes[0, col].grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "weights.png", dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, f in filters.items():
        if "fpke_error_before_mean" in f:
            ax.semilogy(t, f["fpke_error_before_mean"], label=f"{name}: before weight update")
            ax.semilogy(t, f["fpke_error_after_mean"], "--", label=f"{name}: after weight update")
    ax.set(xlabel="time (s)", ylabel="FPKE error wᵀLw (mean over runs)", title=f"{title}: FPKE error")
    ax.grid(True, which="both", alpha=0.3)
    if ax.lines:
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "fpke.png", dpi=110)
    plt.close(fig)


def _tensorboard(out: Path, data: dict[str, np.ndarray], summary: dict[str, Any]) -> None:
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(out / "tensorboard"))
    frames = data["star_frame"]
    for name, f in summary["filters"].items():
        rms = f["rms_deg"]
        nees = f["nees_mean"]
        nis = data[f"{name}/nis"]
        weights = data[f"{name}/weights"]
        entropy = data[f"{name}/weight_entropy"].mean(1)
        for k in range(len(rms)):
            writer.add_scalar(f"{name}/rms_deg", rms[k], k)
            writer.add_scalar(f"{name}/nees", nees[k], k)
            writer.add_scalar(f"{name}/weight_entropy", entropy[k], k)
            if frames[k]:
                writer.add_scalar(f"{name}/nis", float(np.nanmean(nis[k])), k)
            for i in range(weights.shape[-1]):
                writer.add_scalar(f"{name}/weight_{i}_run0", weights[k, 0, i], k)
            if "fpke_error_before_mean" in f:
                writer.add_scalar(f"{name}/fpke_error_before", f["fpke_error_before_mean"][k], k)
                writer.add_scalar(f"{name}/fpke_error_after", f["fpke_error_after_mean"][k], k)
            if weights.shape[-1] > 1 and (frames[k] or k % 10 == 0):
                writer.add_histogram(f"{name}/weights", weights[k].reshape(-1), k)
    writer.close()


def run_experiment(
    cfg: ExperimentConfig, out: Path, *, progress: bool = True, kind: str = "run", recording: str | Path | None = None
) -> dict[str, Any]:
    """Run one configuration and write everything it produces under ``out``.

    With ``recording`` the filters replay that file (it must hold the truth and
    ``cfg.runs`` trajectories of at least ``cfg.num_steps`` steps) instead of a simulation.
    """
    if recording is not None:
        from ..recordings import Recording
        from .recorded import RecordingEnv

        env = RecordingEnv(Recording.load(recording))
        if env.num_envs != cfg.runs or env.config.max_steps < cfg.num_steps or abs(env.config.dt - cfg.dt) > 1e-9 * cfg.dt:
            raise ValueError(
                f"recording {recording} has {env.num_envs} trajectories × {env.config.max_steps} steps of {env.config.dt} s; "
                f"the configuration needs runs={cfg.runs}, ≥ {cfg.num_steps} steps of dt={cfg.dt}"
            )
        digest = cfg.digest() + ":" + str(Path(recording).resolve())
    else:
        env, digest = make_env(cfg), cfg.digest()
    out = prepare_output(Path(out), kind, digest, cfg.to_dict())
    res = run_monte_carlo(
        env,
        make_filters(cfg),
        num_steps=cfg.num_steps,
        prior_cov=prior_covariance(cfg),
        sigma_s=cfg.sigma_s * cfg.filter_sigma_s_scale,
        seed=cfg.seed,
        estimate_bias=cfg.estimate_bias,
        progress=progress,
        noise_model=cfg.star_noise_model,
    )
    data = _save_runs(out / "runs.npz", res)
    summary = summarize(data, cfg)
    (out / "summary.json").write_text(json.dumps(summary))
    _figures(out, summary)
    _tensorboard(out, data, summary)
    return summary
