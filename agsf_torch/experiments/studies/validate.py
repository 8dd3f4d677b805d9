"""``agsf validate``: every scenario × filter scored against the physical floor, with intervals over runs.

The check a GNC engineer makes first: does a consistent filter reach the accuracy the sensors allow, and where
does a Gaussian sum beat the single-Gaussian filters (the EKF, the multiplicative EKF started from the prior or
from a star fix, USQUE) and a particle filter?  Every filter of a scenario sees the same truth and data (one
simulation, :func:`~agsf_torch.experiments.run.runner.monte_carlo_steps`).  Per scenario and filter
(:func:`scenario_measures`; 95 % intervals over runs):

* ``rms_steady_arcsec``: the RMS per body axis of the attitude error over the *steady-state window*, the last
  half of the run (arcsec), beside ``floor_arcsec``, the time-averaged steady-state σ per axis of the
  scenario's linearised model from the discrete Riccati equation (:func:`agsf_torch.attitude.floor.riccati_floor`,
  :attr:`~agsf_torch.attitude.floor.Floor.arcsec_mean`: what an RMS over every gyro step measures), with the
  scenario's gyro, frame interval and camera noise, its mean number of valid stars per frame (rounded) and the
  per-star information averaged over the measured body-frame directions of the run's stars (up to 4,096), at
  the scenario's constant body rate (the body turning carries the error past the narrow field's directions, so
  the boresight axis is observed through the others);
* ``anees`` over the whole run and over the steady-state window (``nees_undefined``: the fraction of steps × runs
  whose covariance was not positive definite, left out of it), and ``anees_band``, the two-sided 95 % band of
  the average of ``R`` NEES values of ``n`` degrees of freedom (:func:`agsf_torch.consistency.chi2_band`): at
  each time the average over runs lies in it with 95 % probability if the filter is consistent;
* ``nis_ratio``: the frames' NIS summed over the run and the runs, divided by the measurement dimensions (1 for
  a consistent filter);
* ``diverged_fraction``: runs whose attitude error at the end exceeds 1° (with the Clopper–Pearson interval):
  every scenario's floor is below 10″, so a filter still 1° off at the end has lost the attitude rather than
  converging slowly;
* ``converge_time_s``: the median over runs of the time from which the error stays below 3× the floor's
  attitude error (``3·|floor|``, the root-sum-square of the per-axis floors); runs that never settle count as
  not converged (``converged_fraction``);
* ``density_score``: where the path-space reference is tractable (the scenarios marked ``density``), the mean
  log-density under the filter's belief of samples of the exact filtering density
  (:class:`agsf_torch.density.PosteriorReference`) at ten steps evenly spread over the run, higher is better
  (not for the particle filter, whose mixture of a thousand kernels costs too much to score: ``None``);
* ``cost_per_step_s``: the filter's own predict + update time per step (the first predict and the first update,
  which may compile the filter's kernels, left out).

Output folder: ``validation.json`` (scenario → filter → measures, and each scenario's floor), ``results.md`` (the
table and, per scenario, which filter to use in words), ``<scenario>.png`` (error RMS and mean 3σ against time per
filter, with the floor) and ``summary.png`` (divergence fraction and ANEES per scenario).
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...attitude.floor import ARCSEC_PER_RAD, riccati_floor
from ...consistency import chi2_band, nees
from ...filter_loop import FilterSetup
from ...rotations import attitude_error_vector
from ...storage.files import save_figure, write_json, write_text
from ..config.factories import filter_model, loop_options, make_filters
from ..config.loader import ExperimentConfig, load_config
from ..report.statistics import clopper_pearson, mean_ci95, median_ci95
from ..run.experiment import make_env
from ..run.outputs import prepare_output
from ..run.resources import check_memory
from ..run.runner import monte_carlo_steps, rotation_sigma

__all__ = [
    "Scenario",
    "SCENARIOS",
    "VALIDATION_FILTERS",
    "SINGLE_GAUSSIAN_FILTERS",
    "paired_divergence",
    "managed_comparisons",
    "DIVERGED_DEG",
    "scenario_config",
    "run_validation_scenario",
    "scenario_measures",
    "run_validation",
    "validation_table",
]

#: Every filter the study compares, in table order.
VALIDATION_FILTERS = (
    "EKF",
    "GSF",
    "AGSF",
    "AGSF-galerkin",
    "GSF-managed",
    "AGSF-managed",
    "AGSF-galerkin-managed",
    "MEKF",
    "MEKF-fix",
    "USQUE",
    "PF",
)
#: A run whose attitude error at the end exceeds this (deg) has diverged.
DIVERGED_DEG = 1.0
#: At how many steps of a run (evenly spread, the last included) the density score is evaluated: scoring a
#: particle filter's mixture of thousands of kernels at every step would cost more than the whole run.
DENSITY_SCORES = 10
#: The largest mixture the density score is evaluated for: the particle filter's kernel mixture (1,024
#: components here) at 256 reference samples per run costs ~20 s an evaluation on 2 cores; its score is not given.
SCORED_MAX_COMPONENTS = 64
#: The study's own setting of the particle filter (its ``particles`` option): the particle count that keeps the
#: whole study on 2 cores within its time budget (the filter's default is 4,096).
STUDY_OVERRIDES = ("particles=1024",)
#: How many measured star directions (body frame) the floor's information is averaged over.
_DIRECTIONS = 4096
#: The error (in multiples of the floor's) below which a run counts as converged once it stays there.
CONVERGED_FLOOR_MULTIPLE = 3.0


def _prior_var(deg: float) -> str:
    """``prior_var`` of an initial error of ``deg`` per axis: ``tan²(θ/4)`` (an MRP of rotation θ is tan(θ/4))."""
    return f"prior_var={math.tan(math.radians(deg) / 4) ** 2!r}"


@dataclass(frozen=True)
class Scenario:
    """A scenario: a preset, its overrides, what it shows, the filters it runs and whether the exact density's
    path-space reference is run beside them."""

    preset: str
    overrides: tuple[str, ...]
    description: str
    filters: tuple[str, ...] = VALIDATION_FILTERS
    density: bool = False


_ITERATED = ("update_iterations=3",)
_SINGLE = ("max_stars=1", "update_iterations=3", "components=9", "duration=120.0")

SCENARIOS: dict[str, Scenario] = {
    "case1": Scenario("case1", (), "the paper's case 1 (frames at 1 Hz, the plain EKF update)", density=True),
    "case2": Scenario("case2", (), "the paper's case 2 (frames every 2 s)", density=True),
    "case3": Scenario("case3", (), "the paper's case 3 (frames every 5 s)", density=True),
    "case1-iterated": Scenario("case1", _ITERATED, "case 1 with the iterated update"),
    "case2-iterated": Scenario("case2", _ITERATED, "case 2 with the iterated update"),
    "case3-iterated": Scenario("case3", _ITERATED, "case 3 with the iterated update"),
    "case1-600s": Scenario(
        "case1",
        ("duration=600.0", *_ITERATED),
        "case 1 for 600 s with the iterated update: where the floor is checked",
        filters=("EKF", "GSF", "MEKF", "MEKF-fix", "USQUE"),
    ),
    "single_vector-10deg": Scenario("case1", (*_SINGLE, _prior_var(10.0)), "one star per frame, 10° per axis"),
    "single_vector-30deg": Scenario("case1", (*_SINGLE, _prior_var(30.0)), "one star per frame, 30° per axis"),
    "single_vector-90deg": Scenario(
        "case1", (*_SINGLE, _prior_var(90.0)), "one star per frame, 90° per axis", density=True
    ),
    "single_vector-uniform": Scenario(
        "case1",
        (*_SINGLE, 'prior_attitude="uniform"', "prior_var=1.0"),
        "one star per frame, a uniformly random prior attitude",
        density=True,
    ),
    "outage": Scenario(
        "outage", (), "ten minutes without frames after convergence, then two stars a frame again", density=True
    ),
    "lost_in_space": Scenario("lost_in_space", (), "a uniformly random prior attitude, the paper's frames"),
    "wide_prior": Scenario("wide_prior", (), "30° per axis, two stars every 10 s"),
}


def scenario_config(
    name: str, runs: int, filters: list[str] | None = None, overrides: list[str] | None = None
) -> ExperimentConfig:
    """The configuration of scenario ``name`` with ``runs`` trajectories, its filters (or those of ``filters`` it
    runs) and extra ``key=value`` ``overrides``."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose from {', '.join(SCENARIOS)}")
    sc = SCENARIOS[name]
    chosen = [f for f in sc.filters if filters is None or f in filters]
    if not chosen:
        raise ValueError(f"scenario {name!r} runs none of the filters {filters} (it runs {', '.join(sc.filters)})")
    names = "[" + ", ".join(f'"{f}"' for f in chosen) + "]"
    return load_config(
        sc.preset,
        [*STUDY_OVERRIDES, *sc.overrides, f"runs={runs}", f"filters={names}", f'name="{name}"', *(overrides or [])],
    )


class _TimedFilter:
    """A filter whose predict and update are timed (``seconds`` over ``steps`` steps), everything else delegated.
    The first call of each is left out: it may compile the filter's kernels."""

    def __init__(self, filt) -> None:
        self._filter = filt
        self.seconds = 0.0
        self.steps = 0
        self._called: set[str] = set()

    def __getattr__(self, name: str):
        return getattr(self._filter, name)

    def _timed(self, fn, *args):
        t0 = time.perf_counter()
        out = fn(*args)
        if fn.__name__ in self._called:
            self.seconds += time.perf_counter() - t0
        self._called.add(fn.__name__)
        return out

    def predict(self, mixture, u, dt):
        self.steps += "predict" in self._called
        return self._timed(self._filter.predict, mixture, u, dt)

    def update(self, mixture, y, measurement):
        return self._timed(self._filter.update, mixture, y, measurement)


def scenario_floor(cfg: ExperimentConfig, stars_per_frame: int | None = None, directions: np.ndarray | None = None):
    """The scenario's steady-state floor (:func:`~agsf_torch.attitude.floor.riccati_floor`): its gyro noise (the
    bias estimated or known), frame interval, stars per frame (``max_stars`` unless given), camera noise and the
    body-frame star directions the per-star information is averaged over (``None``: isotropic), at the scenario's
    constant body rate ``omega0 · rate_axes``."""
    return riccati_floor(
        cfg.sigma_v,
        cfg.sigma_u if cfg.estimate_bias else None,
        cfg.star_period,
        stars_per_frame or cfg.max_stars,
        cfg.sigma_s,
        dt=cfg.dt,
        directions=directions,
        rate=[cfg.omega0 * a for a in cfg.rate_axes],
    )


def run_validation_scenario(
    cfg: ExperimentConfig, *, density_samples: int = 0, seed: int = 0, progress: bool = False
) -> dict[str, Any]:
    """Run one scenario's filters on its simulated runs (and, with ``density_samples``, the exact-density reference).

    Returns:
        ``time [T]``, ``frame [T]``, ``stars [T, B]`` (valid stars per frame, 0 between frames) and per filter
        ``error [T, B, 3]`` (attitude error vector, rad), ``sigma3 [T, B]`` (3σ of the attitude error angle,
        rad), ``nees [T, B]``, ``nis [T, B]``, ``dof [T, B]``, ``score [T, B]`` (at :data:`DENSITY_SCORES` steps
        evenly spread over the run, the last included; NaN elsewhere and without the reference),
        ``seconds`` and ``steps`` (the filter's own time; its first predict and first update left out).
    """
    from ...density import PosteriorReference

    env = make_env(cfg)
    setups = {
        name: FilterSetup(_TimedFilter(s.filter), s.num_components, s.spread) for name, s in make_filters(cfg).items()
    }
    options = loop_options(cfg)
    steps = monte_carlo_steps(env, setups, **options)
    score_every = max(1, cfg.num_steps // DENSITY_SCORES)
    if progress:
        from ..run.progress import progress_bar

        steps = progress_bar(steps, desc=cfg.name, unit="step", total=cfg.num_steps)
    rec: dict[str, list] = {"time": [], "frame": [], "stars": [], "directions": []}
    per = {f: {k: [] for k in ("error", "sigma3", "nees", "nis", "dof", "score")} for f in setups}
    reference = None
    for step in steps:
        if density_samples and reference is None:
            gen = torch.Generator().manual_seed(int(seed) * 1000 + 17)
            model = filter_model(cfg)
            reference = PosteriorReference(  # redraws on lineages below 2 % only, as the adaptation study
                model,
                step.prior_mean,
                options["prior_cov"],
                num_samples=density_samples,
                generator=gen,
                lineage_threshold=0.02,
            )
        if reference is not None:
            reference.predict(step.u, cfg.dt)
            if step.measurement is not None:
                hints = torch.stack([fs.mean for fs in step.filters.values()], -2)
                reference.update(*step.measurement, hints=hints)
        rec["time"].append(step.time)
        rec["frame"].append(step.star_frame)
        if step.measurement is not None and sum(len(d) for d in rec["directions"]) < _DIRECTIONS:
            y, meas = step.measurement
            body = y.reshape(*y.shape[:-1], -1, 3)
            valid = torch.ones(body.shape[:-1], dtype=torch.bool) if meas.star_mask is None else meas.star_mask
            rec["directions"].append(torch.nn.functional.normalize(body[valid], dim=-1))
        B = step.truth_mrp.shape[0]
        stars = torch.zeros(B)
        for name, fs in step.filters.items():
            r = per[name]
            r["error"].append(attitude_error_vector(fs.mean[:, :3], step.truth_mrp))
            r["sigma3"].append(3.0 * rotation_sigma(fs.mean, fs.cov)[:, :3].square().sum(-1).sqrt())
            r["nees"].append(_nees(step.chart_error[name], fs.cov))
            r["nis"].append(torch.nan_to_num(fs.nis, nan=0.0))
            r["dof"].append(fs.dof)
            stars = fs.dof / 3.0  # valid stars of the frame (3 entries each), the same for every filter
            scored = (
                reference is not None
                and (step.index + 1) % score_every == 0
                and fs.mixture.num_components <= SCORED_MAX_COMPONENTS
            )
            r["score"].append(reference.score(fs.mixture)[0] if scored else torch.full((B,), float("nan")))
        rec["stars"].append(stars)
    out: dict[str, Any] = {
        "time": np.array(rec["time"]),
        "frame": np.array(rec["frame"], dtype=bool),
        "stars": torch.stack(rec["stars"]).numpy(),
        "directions": torch.cat(rec["directions"]).numpy() if rec["directions"] else None,
        "filters": {},
    }
    for name, r in per.items():
        timed = setups[name].filter
        out["filters"][name] = {k: torch.stack(v).numpy() for k, v in r.items()}
        out["filters"][name].update(seconds=timed.seconds, steps=max(timed.steps, 1))
    return out


def _nees(error: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """:func:`~agsf_torch.consistency.nees` ``[B]``, NaN where the filter's covariance is not positive definite
    (counted in the measures as ``nees_undefined``, never hidden)."""
    ok = torch.linalg.cholesky_ex(cov).info == 0
    safe = torch.where(ok[:, None, None], cov, torch.eye(cov.shape[-1], dtype=cov.dtype).expand_as(cov))
    return torch.where(ok, nees(error, safe), torch.full_like(ok, float("nan"), dtype=cov.dtype))


def _interval(values: np.ndarray) -> dict[str, Any]:
    m, lo, hi = mean_ci95(values)
    return {"mean": m, "ci95": [lo, hi]}


def _converge_time(angle: np.ndarray, t: np.ndarray, threshold: float) -> np.ndarray:
    """Per run, the first time from which ``angle [T, B]`` stays below ``threshold`` (``inf``: never)."""
    above = angle >= threshold  # [T, B]
    last_above = np.where(above.any(0), above.shape[0] - 1 - np.argmax(above[::-1], 0), -1)
    return np.where(last_above + 1 < len(t), t[np.minimum(last_above + 1, len(t) - 1)], np.inf)


def scenario_measures(res: dict[str, Any], cfg: ExperimentConfig) -> dict[str, Any]:
    """The measures of every filter of one scenario (module docstring), and the scenario's floor."""
    t, frames = res["time"], res["frame"]
    T = len(t)
    steady = np.arange(T) >= T // 2  # the last half of the run
    counted = res["stars"][frames]
    mean_stars = float(counted.mean()) if counted.size else 0.0
    stars = max(1, round(mean_stars)) if counted.size else None
    floor = scenario_floor(cfg, stars, res["directions"])
    floor_arcsec = floor.arcsec_mean.tolist()
    floor_angle = math.sqrt(sum(v * v for v in floor_arcsec)) / ARCSEC_PER_RAD
    n = filter_model(cfg).state_dim
    R = cfg.runs
    band = list(chi2_band(n, R))
    out: dict[str, Any] = {
        "description": SCENARIOS[cfg.name].description if cfg.name in SCENARIOS else cfg.name,
        "floor_arcsec": floor_arcsec,
        "floor_arcsec_after_frame": floor.arcsec_after.tolist(),
        "floor_arcsec_before_frame": floor.arcsec_before.tolist(),
        "stars_per_frame_assumed": stars,
        "stars_per_frame_mean": mean_stars,
        "floor_directions": 0 if res["directions"] is None else len(res["directions"]),
        "runs": R,
        "steady_from_s": float(t[T // 2]),
        "filters": {},
    }
    for name, r in res["filters"].items():
        err = r["error"] * ARCSEC_PER_RAD  # [T, B, 3]
        per_axis = np.sqrt((err[steady] ** 2).mean(0))  # [B, 3]: each run's RMS per axis over the window
        rms_axis = [_interval(per_axis[:, k]) for k in range(3)]
        angle = np.linalg.norm(r["error"], axis=-1)  # small-angle magnitude (rad)
        final = np.degrees(_angle(r["error"][-1]))  # [B], the exact angle at the end
        diverged = final > DIVERGED_DEG
        ci = clopper_pearson(diverged.sum(), diverged.size)
        settle = _converge_time(angle, t, CONVERGED_FLOOR_MULTIPLE * floor_angle)
        converged = np.isfinite(settle)
        dof = r["dof"].sum(0)
        nis_ratio = r["nis"].sum(0) / np.where(dof > 0, dof, np.nan)
        score = r["score"]
        out["filters"][name] = {
            "rms_steady_arcsec": [a["mean"] for a in rms_axis],
            "rms_steady_arcsec_ci95": [a["ci95"] for a in rms_axis],
            "floor_arcsec": floor_arcsec,
            "rms_over_floor": max(a["mean"] / f for a, f in zip(rms_axis, floor_arcsec)),
            "anees": {
                "run": _interval(np.nanmean(r["nees"], 0)),
                "steady": _interval(np.nanmean(r["nees"][steady], 0)),
            },
            "nees_undefined": float(np.isnan(r["nees"]).mean()),
            "anees_band": band,
            "nis_ratio": _interval(nis_ratio[np.isfinite(nis_ratio)]) if np.isfinite(nis_ratio).any() else None,
            "diverged_fraction": float(diverged.mean()),
            "diverged_ci95": [float(v) for v in ci],
            "converge_time_s": float(np.median(settle)) if converged.mean() >= 0.5 else None,
            "converged_fraction": float(converged.mean()),
            "density_score": None if np.isnan(score).all() else _interval(np.nanmean(score, 0)),
            "cost_per_step_s": r["seconds"] / r["steps"],
            "diverged_runs": diverged.astype(int).tolist(),
            "density_score_runs": None if np.isnan(score).all() else np.nanmean(score, 0).tolist(),
            "rms_t_arcsec": (np.sqrt((angle**2).mean(1)) * ARCSEC_PER_RAD).tolist(),
            "sigma3_t_arcsec": (r["sigma3"].mean(1) * ARCSEC_PER_RAD).tolist(),
        }
    out["comparisons"] = managed_comparisons(out["filters"])
    out["time_s"] = t.tolist()
    return out


#: The filters a managed Gaussian sum is compared with, pair by pair over the same runs: the single Gaussians.
SINGLE_GAUSSIAN_FILTERS = ("EKF", "MEKF", "MEKF-fix", "USQUE")


def paired_divergence(baseline: np.ndarray, managed: np.ndarray) -> dict[str, Any]:
    """The difference of divergence fractions ``p_baseline − p_managed`` over the same runs, with McNemar's exact
    conditional 95 % interval.

    Of the ``d = b + c`` discordant runs (``b``: only the baseline diverged, ``c``: only the managed filter), ``b``
    is binomial ``(d, π)`` given ``d``; the difference is ``(b − c)/R = (d/R)(2π̂ − 1)`` and its interval
    ``(d/R)(2[π_lo, π_hi] − 1)`` from the Clopper–Pearson interval of ``π``.  It excludes zero exactly where McNemar's
    exact test rejects equal fractions at 5 %.  With no discordant run the difference is 0 and the interval
    ``[0, 0]`` (no evidence either way).

    Args:
        baseline, managed: ``[R]`` 0/1 per run (diverged).

    Returns:
        ``{"difference", "ci95": [lo, hi], "discordant": d}``.
    """
    a, m = np.asarray(baseline, dtype=bool), np.asarray(managed, dtype=bool)
    b, c, R = int((a & ~m).sum()), int((m & ~a).sum()), a.size
    d = b + c
    if d == 0:
        return {"difference": 0.0, "ci95": [0.0, 0.0], "discordant": 0}
    lo, hi = clopper_pearson(b, d)
    return {"difference": (b - c) / R, "ci95": [d / R * (2 * lo - 1), d / R * (2 * hi - 1)], "discordant": d}


def managed_comparisons(filters: dict[str, Any]) -> dict[str, Any]:
    """Each managed filter against each single-Gaussian filter of the scenario (:data:`SINGLE_GAUSSIAN_FILTERS`),
    run by run: ``"{managed} vs {baseline}"`` → ``diverged`` (:func:`paired_divergence`, > 0: the managed filter
    diverged in fewer runs) and ``density_score`` (the per-run score's difference managed − baseline: its mean and
    Student-t 95 % interval, its median and distribution-free 95 % interval (:func:`~..report.statistics.median_ci95`:
    a few runs' scores far in a single Gaussian's tail make the t interval uninformative) and the runs in which the
    managed filter scored higher; > 0: the managed filter's density is the better; ``None`` without scores)."""
    out: dict[str, Any] = {}
    for m in (f for f in filters if f.endswith("-managed")):
        for b in (f for f in SINGLE_GAUSSIAN_FILTERS if f in filters):
            fm, fb = filters[m], filters[b]
            score = None
            if fm["density_score_runs"] is not None and fb["density_score_runs"] is not None:
                diff = np.asarray(fm["density_score_runs"]) - np.asarray(fb["density_score_runs"])
                diff = diff[np.isfinite(diff)]
                if diff.size >= 2:
                    mean, lo, hi = mean_ci95(diff)
                    med, med_lo, med_hi = median_ci95(diff)
                    score = {
                        "difference": mean,
                        "ci95": [lo, hi],
                        "median": med,
                        "median_ci95": [med_lo, med_hi],
                        "managed_better": int((diff > 0).sum()),
                        "runs": int(diff.size),
                    }
            out[f"{m} vs {b}"] = {
                "diverged": paired_divergence(fb["diverged_runs"], fm["diverged_runs"]),
                "density_score": score,
            }
    return out


def _angle(error: np.ndarray) -> np.ndarray:
    """The rotation angle (rad) of the error vectors ``δθ = 2 sin(θ/2) e`` (:func:`~agsf_torch.rotations.attitude_error_vector`)."""
    return 2.0 * np.arcsin(np.clip(np.linalg.norm(error, axis=-1) / 2.0, 0.0, 1.0))


def _scenario_figure(path: Path, name: str, summary: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array(summary["time_s"])
    filters = list(summary["filters"])
    cols = min(4, len(filters))
    rows = math.ceil(len(filters) / cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(3.6 * cols, 2.9 * rows), sharex=True, sharey=True, squeeze=False, layout="constrained"
    )
    floor = math.sqrt(sum(v * v for v in summary["floor_arcsec"]))
    for ax, fname in zip(axes.flat, filters):
        f = summary["filters"][fname]
        ax.semilogy(t, f["rms_t_arcsec"], color="C0", lw=1.0, label="RMS error over runs")
        ax.semilogy(t, f["sigma3_t_arcsec"], color="C1", lw=1.0, ls="--", label="mean 3σ")
        ax.axhline(floor, color="k", lw=0.7, ls=":", label="Riccati floor")
        ax.set_title(fname, fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes.flat[len(filters) :]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    for ax in axes[:, 0]:
        ax.set_ylabel("attitude error (arcsec)")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"{name}: {summary['description']}", fontsize=10)
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def _summary_figure(path: Path, summaries: dict[str, dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summaries)
    filters = [f for f in VALIDATION_FILTERS if any(f in s["filters"] for s in summaries.values())]
    width = 0.8 / len(filters)
    palette = plt.get_cmap("tab20").colors  # the ten tab10 colours first, then their light variants: 20 distinct
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(max(8, 1.1 * len(names)), 7), sharex=True, layout="constrained")
    x = np.arange(len(names))
    for k, f in enumerate(filters):
        offset = (k - (len(filters) - 1) / 2) * width
        frac, err, anees = [], [[], []], []
        for s in names:
            m = summaries[s]["filters"].get(f)
            if m is None:
                frac.append(np.nan)
                err[0].append(0)
                err[1].append(0)
                anees.append(np.nan)
                continue
            frac.append(m["diverged_fraction"])
            err[0].append(m["diverged_fraction"] - m["diverged_ci95"][0])
            err[1].append(m["diverged_ci95"][1] - m["diverged_fraction"])
            anees.append(m["anees"]["steady"]["mean"])
        color = palette[(2 * k) % 20 + (2 * k) // 20]
        top.bar(x + offset, frac, width, yerr=err, capsize=1.5, label=f, color=color)
        bottom.bar(x + offset, anees, width, label=f, color=color)
    for k, s in enumerate(names):
        lo, hi = next(iter(summaries[s]["filters"].values()))["anees_band"]
        bottom.fill_between([k - 0.45, k + 0.45], lo, hi, color="k", alpha=0.15, lw=0)
    top.set(ylabel=f"runs diverged (> {DIVERGED_DEG:g}° at the end)", ylim=(0, 1.05))
    bottom.set(ylabel="steady ANEES (grey: 95 % band)")
    bottom.set_yscale("log")
    bottom.set_xticks(x, names, rotation=30, ha="right")
    # one legend above the panels (an axes legend of every filter in one row squeezes the axes it sits in)
    fig.legend(*top.get_legend_handles_labels(), loc="outside upper center", ncol=min(len(filters), 6), fontsize=8)
    for ax in (top, bottom):
        ax.grid(True, axis="y", alpha=0.3)
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def run_validation(
    scenarios: list[str],
    out: Path,
    *,
    runs: int = 32,
    filters: list[str] | None = None,
    density_samples: int = 256,
    overrides: list[str] | None = None,
    progress: bool = True,
    force: bool = False,
) -> dict[str, Any]:
    """Run the scenarios (each with extra ``key=value`` ``overrides``, e.g. ``compile_fused=false``); write
    ``validation.json``, ``results.md`` and the figures under ``out``.

    Raises:
        ValueError: an unknown scenario or filter, ``runs < 2`` (no interval), ``density_samples`` out of range, or
            a scenario whose memory estimate exceeds the memory available (unless ``force``), before anything is
            written.
    """
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 2:
        raise ValueError(f"runs must be an integer ≥ 2 (intervals need two runs), got {runs!r}")
    if (
        isinstance(density_samples, bool)
        or not isinstance(density_samples, int)
        or not (density_samples == 0 or density_samples >= 64)
    ):
        raise ValueError(f"density_samples must be 0 (no density score) or an integer ≥ 64, got {density_samples!r}")
    unknown = [f for f in filters or [] if f not in VALIDATION_FILTERS]
    if unknown:
        raise ValueError(f"unknown filter {unknown[0]!r}; choose from {', '.join(VALIDATION_FILTERS)}")
    configs = {s: scenario_config(s, runs, filters, overrides) for s in scenarios}
    for cfg in configs.values():
        check_memory(cfg, force=force)
    digest = hashlib.sha256(
        json.dumps({"configs": {k: c.digest() for k, c in configs.items()}, "samples": density_samples}).encode()
    ).hexdigest()[:16]
    out = prepare_output(
        Path(out),
        "validation",
        digest,
        {"density_samples": density_samples, **{k: c.to_dict() for k, c in configs.items()}},
    )
    summaries: dict[str, Any] = {}
    for name, cfg in configs.items():
        samples = density_samples if SCENARIOS[name].density else 0
        res = run_validation_scenario(cfg, density_samples=samples, progress=progress)
        summaries[name] = scenario_measures(res, cfg)
        _scenario_figure(out / f"{name}.png", name, summaries[name])
        write_json(out / "validation.json", _without_series(summaries))
    _summary_figure(out / "summary.png", summaries)
    write_text(out / "results.md", validation_table(summaries) + "\n")
    return summaries


def _without_series(summaries: dict[str, Any]) -> dict[str, Any]:
    """The summaries without the time series of the figures (``time_s``, ``*_t_arcsec``)."""
    out = {}
    for name, s in summaries.items():
        out[name] = {k: v for k, v in s.items() if k != "time_s"}
        out[name]["filters"] = {
            f: {k: v for k, v in m.items() if not k.endswith("_t_arcsec")} for f, m in s["filters"].items()
        }
    return out


def _fmt(value: float | None, digits: int = 3) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


def recommendation(summary: dict[str, Any]) -> str:
    """Which filter to use in a scenario, in words: among the filters whose steady-state ANEES lies in its band
    and that diverged in no run, the one of the lowest steady-state RMS; otherwise the one that diverged least
    (then the lowest RMS), named as inconsistent."""
    filters = summary["filters"]

    def rms(m):
        return math.sqrt(sum(v * v for v in m["rms_steady_arcsec"]))

    lo, hi = next(iter(filters.values()))["anees_band"]
    consistent = {
        f: m for f, m in filters.items() if lo <= m["anees"]["steady"]["mean"] <= hi and m["diverged_fraction"] == 0
    }
    if consistent:
        best = min(consistent, key=lambda f: rms(consistent[f]))
        m = consistent[best]
        return (
            f"use {best}: consistent (steady ANEES {_fmt(m['anees']['steady']['mean'])} in [{_fmt(lo)}, {_fmt(hi)}]), "
            f"no run diverged, steady RMS {_fmt(rms(m))}″ = {_fmt(m['rms_over_floor'])}× the floor per axis at most"
        )
    best = min(filters, key=lambda f: (filters[f]["diverged_fraction"], rms(filters[f])))
    m = filters[best]
    return (
        f"no filter is consistent here; {best} diverged least ({_fmt(100 * m['diverged_fraction'])} % of runs, "
        f"steady RMS {_fmt(rms(m))}″, steady ANEES {_fmt(m['anees']['steady']['mean'])} against [{_fmt(lo)}, {_fmt(hi)}])"
    )


def validation_table(summaries: dict[str, Any]) -> str:
    """Markdown: per scenario and filter, the steady RMS per axis against the floor, ANEES, NIS ratio, divergence,
    convergence time, density score and cost; then, per scenario, :func:`recommendation`."""
    lines = [
        "| scenario | filter | steady RMS x/y/z (″) | floor (″) | ANEES steady [band] | NIS ratio | diverged | "
        "converged at (s) | density score | cost/step (ms) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for sname, s in summaries.items():
        for fname, m in s["filters"].items():
            rms = "/".join(_fmt(v) for v in m["rms_steady_arcsec"])
            floor = "/".join(_fmt(v) for v in m["floor_arcsec"])
            lo, hi = m["anees_band"]
            nis = m["nis_ratio"]
            score = m["density_score"]
            lines.append(
                f"| {sname} | {fname} | {rms} | {floor} | {_fmt(m['anees']['steady']['mean'])} "
                f"[{_fmt(lo)}, {_fmt(hi)}] | {_fmt(None if nis is None else nis['mean'])} | "
                f"{_fmt(100 * m['diverged_fraction'])} % [{_fmt(100 * m['diverged_ci95'][0])}, "
                f"{_fmt(100 * m['diverged_ci95'][1])}] | {_fmt(m['converge_time_s'])} | "
                f"{_fmt(None if score is None else score['mean'], 5)} | {_fmt(1e3 * m['cost_per_step_s'])} |"
            )
    lines.append("")
    for sname, s in summaries.items():
        lines.append(f"- **{sname}** ({s['description']}): {recommendation(s)}.")
    pairs = [(sname, pair, c) for sname, s in summaries.items() for pair, c in s.get("comparisons", {}).items()]
    if pairs:
        lines += [
            "",
            "Managed Gaussian sums against the single Gaussians, run by run (the same runs): the divergence fraction's "
            "difference baseline − managed (> 0: the managed filter diverged less; McNemar's exact interval) and the "
            "density score's difference managed − baseline (> 0: the managed density is the better): its mean "
            "(Student-t interval), its median (distribution-free sign-test interval) and the runs the managed filter "
            "scored higher in.",
            "",
            "| scenario | pair | diverged: difference [95 %] (discordant runs) | density score: mean difference [95 %] "
            "| median difference [95 %] | managed higher |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for sname, pair, c in pairs:
            d, sc = c["diverged"], c["density_score"]
            if sc is None:
                score = "— | — | —"
            else:
                score = (
                    f"{_fmt(sc['difference'], 4)} [{_fmt(sc['ci95'][0], 4)}, {_fmt(sc['ci95'][1], 4)}] | "
                    f"{_fmt(sc['median'], 4)} [{_fmt(sc['median_ci95'][0], 4)}, {_fmt(sc['median_ci95'][1], 4)}] | "
                    f"{sc['managed_better']} of {sc['runs']}"
                )
            lines.append(
                f"| {sname} | {pair} | {_fmt(100 * d['difference'])} % [{_fmt(100 * d['ci95'][0])}, "
                f"{_fmt(100 * d['ci95'][1])}] ({d['discordant']}) | {score} |"
            )
    return "\n".join(lines)
