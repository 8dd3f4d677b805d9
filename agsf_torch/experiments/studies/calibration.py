"""``agsf calibrate``: how well learning's estimates, intervals and verdicts are calibrated, measured.

For each setting (the parameters learned, the data length, the trajectories per data set, the star noise
model), ``D`` independent data sets are simulated with exactly the noise the filter is configured with and fitted
at once (:func:`~agsf_torch.attitude.learning.fit_datasets`).  Over the data sets, for each learned coordinate
``x`` (``log σ`` for a noise density, rad/s for a bias axis), with ``x̂_d`` the estimate, ``s_d`` its standard
error from the curvature and ``x*`` the truth:

* **bias against its own standard error**: ``mean(x̂ − x*) / (sd(x̂ − x*)/√D)``, a standard normal if unbiased;
* **RMS error** ``√mean((x̂ − x*)²)`` beside the mean standard error ``mean(s)`` (equal if the curvature is right);
* **coverage** of the 95 % interval, and the **false-alarm rate** of the parameter's verdict at the truth
  (``1 −`` coverage for a scalar; the Wald test of its block for the bias), each with its Clopper–Pearson 95 %
  interval; the **joint verdict's** false-alarm rate (the family-wise one);
* **detection rate** of a filter configured at ``c·x*`` for ``c ∈ {1.25, 1.5, 2, 3}`` and their inverses (the
  estimate does not depend on the configured value, so one fit judges them all: by the likelihood ratio at
  ``c·x*``, one more pass of the filter each, where one parameter is learned; by Wald's test on the coordinate
  among several);
* beside ours, the **autocovariance least-squares** estimate of ``σ_s`` and ``σ_v`` on the same data
  (:mod:`agsf_torch.attitude.autocovariance`), where the setting is the 3-state model.

Only data sets whose fit converged and whose parameter is identified are judged (their share is reported).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from ...attitude.learning import DatasetFits, fit_datasets
from ...quantiles import chi2_quantile
from ..config.loader import ExperimentConfig
from ..report.statistics import clopper_pearson
from ..run.experiment import make_env
from ..run.recorded import record_environment
from .learn import learning_problem

__all__ = [
    "CalibrationSetting",
    "STUDY",
    "QUICK_STUDY",
    "MIS_SCALINGS",
    "calibrate_setting",
    "run_study",
    "verdict_study",
    "VERDICT_SETTINGS",
    "TOLERANCE",
]

#: The fits' Newton decrement at convergence (nats): the estimate within ``√(2·10⁻⁴) = 0.014`` of its standard
#: error of the maximum, which moves a 95 % interval's coverage by less than 0.1 %.
TOLERANCE = 1e-4
#: Trajectory-steps of one batched fit (3 states; a sixth of it with 6), which bounds the memory of its autograd
#: graph and the Hessian's (the 6-state model's graph is larger per step).
GRAPH_BUDGET = 120_000
#: The mis-scalings of the configured value whose detection is measured (and their inverses).
MIS_SCALINGS = (1.25, 1.5, 2.0, 3.0)
_Z95 = 1.959963984540054


@dataclass(frozen=True)
class CalibrationSetting:
    """One setting of the study.

    Attributes:
        label: its name in the tables.
        learn: the parameters fitted jointly.
        duration: seconds of data per trajectory.
        trajectories: trajectories per data set.
        overrides: configuration keys changed from the base (``star_noise_model``, ``estimate_bias``, …).
    """

    label: str
    learn: tuple[str, ...]
    duration: float
    trajectories: int = 1
    overrides: dict = field(default_factory=dict)


#: The 3-state settings simulate a constant gyro bias (``sigma_u = 0``): the 3-state model is then exactly the
#: simulator's, so a correctly configured filter is what is judged.  Every setting iterates the update three
#: times: the prior's 1.8° spread makes the first update's linearisation error (≈ |δθ|²/2 on each unit vector,
#: 45 times σ_s) the largest "noise" a single-iteration EKF sees, and its likelihood would learn that instead.
_EXACT = {"sigma_u": 0.0, "update_iterations": 3}
#: The axes of data length and trajectories read the gyro at 1 Hz, with the star frames (``dt = 1``): ten minutes of
#: data are then 600 steps, whose autograd graph for 200 data sets fits in memory (at 10 Hz it would not).
_ONE_HZ = {**_EXACT, "dt": 1.0}
STUDY = (
    CalibrationSetting("σ_s, σ_v · 60 s · isotropic", ("sigma_s", "sigma_v"), 60.0, 1, _EXACT),
    CalibrationSetting(
        "σ_s, σ_v · 60 s · tangent", ("sigma_s", "sigma_v"), 60.0, 1, {**_EXACT, "star_noise_model": "tangent"}
    ),
    CalibrationSetting("bias · 60 s", ("bias",), 60.0, 1, _EXACT),
    CalibrationSetting("prior scale · 60 s", ("prior_scale",), 60.0, 1, _EXACT),
    CalibrationSetting("σ_s, σ_v · 10 s · gyro 1 Hz", ("sigma_s", "sigma_v"), 10.0, 1, _ONE_HZ),
    CalibrationSetting("σ_s, σ_v · 60 s · gyro 1 Hz", ("sigma_s", "sigma_v"), 60.0, 1, _ONE_HZ),
    CalibrationSetting("σ_s, σ_v · 600 s · gyro 1 Hz", ("sigma_s", "sigma_v"), 600.0, 1, _ONE_HZ),
    CalibrationSetting("σ_s, σ_v · 10 s × 4 · gyro 1 Hz", ("sigma_s", "sigma_v"), 10.0, 4, _ONE_HZ),
    CalibrationSetting("σ_s, σ_v · 10 s × 16 · gyro 1 Hz", ("sigma_s", "sigma_v"), 10.0, 16, _ONE_HZ),
    CalibrationSetting(
        "σ_u · 300 s · 6 states · gyro 1 Hz",
        ("sigma_u",),
        300.0,
        1,
        {"estimate_bias": True, "update_iterations": 3, "dt": 1.0},
    ),
)
#: A few seconds' version for the tests.
QUICK_STUDY = (
    CalibrationSetting("σ_s, σ_v · 10 s", ("sigma_s", "sigma_v"), 10.0, 1, _EXACT),
    CalibrationSetting("bias · 30 s", ("bias",), 30.0, 1, _EXACT),
)


def _rate(flags: torch.Tensor) -> dict:
    """A rate over data sets with its counts and Clopper–Pearson interval."""
    k, n = int(flags.sum()), int(flags.numel())
    low, high = (float(v) for v in clopper_pearson(k, n))
    return {"rate": k / n if n else math.nan, "count": k, "datasets": n, "low": low, "high": high}


def calibrate_setting(base: ExperimentConfig, setting: CalibrationSetting, datasets: int, seed: int) -> dict:
    """Simulate ``datasets`` data sets of ``setting`` from ``base`` (filter EKF, configured at the truth), fit
    them, and measure the calibration (module docstring).

    Returns:
        a JSON-able dict: the setting, the fit's convergence, per coordinate the error statistics, coverage,
        false-alarm and detection rates, the joint verdict's false-alarm rate and, for the 3-state σ_s/σ_v
        settings, the autocovariance least-squares baseline's errors on the same data.
    """
    cfg = base.replace(
        runs=datasets * setting.trajectories,
        duration=setting.duration,
        seed=seed,
        filters=["EKF"],
        filter_sigma_s_scale=1.0,
        filter_sigma_v_scale=1.0,
        faults=[],
        **setting.overrides,
    )
    rec = record_environment(make_env(cfg), cfg.num_steps, cfg.seed)
    configured, kwargs = learning_problem(cfg, rec)
    chunk = max(1, GRAPH_BUDGET // (setting.trajectories * cfg.num_steps * (6 if cfg.estimate_bias else 1)))
    factors = _factors()
    # one parameter: its verdict is the likelihood ratio, judged at each mis-scaling by one pass of the filter
    alternatives = (
        [{setting.learn[0]: [float(v) * f for v in np.atleast_1d(configured[setting.learn[0]])]} for f in factors]
        if len(setting.learn) == 1
        else []
    )
    fits = fit_datasets(
        rec,
        configured,
        list(setting.learn),
        datasets=datasets,
        tolerance=TOLERANCE,
        chunk=chunk,
        alternatives=alternatives,
        **kwargs,
    )
    result = {
        "label": setting.label,
        "learn": list(setting.learn),
        "duration_s": setting.duration,
        "trajectories": setting.trajectories,
        "datasets": datasets,
        "seed": seed,
        "star_noise_model": cfg.star_noise_model,
        "gyro_dt_s": cfg.dt,
        "estimate_bias": cfg.estimate_bias,
        "converged": _rate(fits.converged),
        "iterations_max": int(fits.iterations.max()),
        "coordinates": _coordinates(fits),
    }
    judged_joint = fits.converged & (fits.joint_dof > 0)
    result["joint_false_alarm"] = _rate(~fits.joint_consistent[judged_joint])
    result["any_parameter_false_alarm"] = _rate(
        torch.stack([~fits.inside[k] & fits.judged[k] for k in fits.names]).any(0)[judged_joint]
    )
    if set(setting.learn) <= {"sigma_s", "sigma_v"} and not cfg.estimate_bias:
        result["baseline"] = _baseline(rec, datasets, configured)
    return result


def _factors() -> list[float]:
    """The mis-scalings judged: :data:`MIS_SCALINGS` and their inverses."""
    return [f for c in MIS_SCALINGS for f in (c, 1.0 / c)]


def _coordinates(fits: DatasetFits) -> list[dict]:
    """Per fitted coordinate: identification, error statistics, coverage, false alarm and detection (the
    likelihood ratio's for a single parameter, Wald's on the coordinate among several)."""
    out, i = [], 0
    for name in fits.names:
        size = fits.sizes[name]
        positive = name != "bias"
        truth = fits.configured[name].reshape(fits.fitted.shape[0], size)
        x_true = truth.log() if positive else truth
        for axis in range(size):
            j = i + axis
            judged = fits.judged[name]
            x_hat, se = fits.fitted[judged, j], fits.half_width[judged, j] / _Z95
            err = x_hat - x_true[judged, axis]
            n = int(judged.sum())
            sd = float(err.std()) if n > 1 else math.nan
            entry = {
                "name": name if size == 1 else f"{name}[{axis}]",
                "coordinate": f"log {name}" if positive else f"{name} (rad/s)",
                "truth": float(truth[0, axis]),
                "identified": _rate(fits.identified[name]),
                "judged": n,
                "mean_error": float(err.mean()) if n else math.nan,
                "bias_over_se": float(err.mean()) / (sd / math.sqrt(n)) if n > 1 and sd > 0 else math.nan,
                "rms_error": float(err.square().mean().sqrt()) if n else math.nan,
                "mean_standard_error": float(se.mean()) if n else math.nan,
                "coverage": _rate(err.abs() <= _Z95 * se),
            }
            if size == 1:
                entry["false_alarm"] = _rate(~fits.inside[name][judged])
                entry["detection"] = _detection(fits, name, judged, x_hat, se, x_true[judged, axis], positive)
            out.append(entry)
        if size > 1:  # the parameter's verdict is its block's test
            judged = fits.judged[name]
            out[-1]["block_false_alarm"] = _rate(~fits.inside[name][judged])
            out[-1]["detection"] = _detection(fits, name, judged, None, None, None, positive)
        i += size
    return out


def _detection(fits: DatasetFits, name: str, judged, x_hat, se, x_true, positive: bool) -> dict:
    """The share of judged data sets whose verdict flags a filter configured at each of :func:`_factors` × the
    truth: the likelihood ratio at that value (a single parameter: :attr:`DatasetFits.alternative_ratio`), or Wald's
    on the coordinate (``x_hat``, ``se``, ``x_true`` of the judged data sets)."""
    out = {}
    for a, factor in enumerate(_factors()):
        if len(fits.names) == 1:
            flagged = fits.alternative_ratio[a, judged] > chi2_quantile(0.95, fits.sizes[name])
        else:
            wrong = x_true + math.log(factor) if positive else x_true * factor
            flagged = (x_hat - wrong).abs() > _Z95 * se
        out[f"{factor:.4g}"] = _rate(flagged)
    return out


def _baseline(rec, datasets: int, configured: dict) -> dict:
    """The autocovariance least-squares estimates of ``σ_s`` and ``σ_v`` on the same data: their errors in
    ``log σ`` (mean, RMS) over the data sets it gives a positive estimate for, and that share."""
    from ...attitude.autocovariance import autocovariance_least_squares

    est = autocovariance_least_squares(rec, datasets=datasets)
    out = {}
    for name in ("sigma_s", "sigma_v"):
        values = torch.as_tensor(np.asarray(getattr(est, name)), dtype=torch.float64)
        ok = torch.isfinite(values) & (values > 0)
        err = values[ok].log() - math.log(float(configured[name]))
        out[name] = {
            "positive": _rate(ok),
            "mean_error": float(err.mean()) if ok.any() else math.nan,
            "rms_error": float(err.square().mean().sqrt()) if ok.any() else math.nan,
        }
    return out


def settings_named(labels: Sequence[str] | None, study: Sequence[CalibrationSetting] = STUDY) -> list:
    """The study's settings, or those whose labels are given (``ValueError`` naming an unknown one)."""
    if labels is None:
        return list(study)
    known = {s.label: s for s in study}
    unknown = [label for label in labels if label not in known]
    if unknown:
        raise ValueError(f"unknown calibration setting(s) {unknown}; known: {list(known)}")
    return [known[label] for label in labels]


def _cost(setting: CalibrationSetting) -> float:
    """Trajectory-steps of a data set, the measure of a setting's time (its gyro steps × trajectories)."""
    dt = setting.overrides.get("dt", 0.1)
    return setting.duration / dt * setting.trajectories * (2.0 if setting.overrides.get("estimate_bias") else 1.0)


def _calibrate_in_worker(base: dict, setting: CalibrationSetting, datasets: int, seed: int) -> dict:
    """:func:`calibrate_setting` in a worker process: one torch thread (the settings run side by side)."""
    from ..config.loader import ExperimentConfig as Config

    torch.set_num_threads(1)
    return calibrate_setting(Config(**base), setting, datasets, seed)


def run_study(
    base: ExperimentConfig,
    settings: Sequence[CalibrationSetting],
    *,
    datasets: int,
    seed: int,
    workers: int = 1,
    progress: bool = True,
) -> list[dict]:
    """:func:`calibrate_setting` for every setting, ``workers`` at a time in worker processes
    (:class:`concurrent.futures.ProcessPoolExecutor`, spawned, the longest first) or here (``workers = 1``); setting ``k`` draws
    its data from ``seed + k·datasets·16`` (disjoint trajectory seeds).  Results in the settings' order."""
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from multiprocessing import get_context

    from ..run.progress import progress_bar

    if isinstance(datasets, bool) or not isinstance(datasets, int) or datasets < 2:
        raise ValueError(f"datasets must be an integer ≥ 2 (rates over data sets), got {datasets!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    seeds = [seed + k * datasets * 16 for k in range(len(settings))]
    bar = progress_bar(total=len(settings), desc="calibrating", unit="setting", disable=not progress, leave=False)
    results: list[dict | None] = [None] * len(settings)
    with bar:
        if workers == 1:
            for k, s in enumerate(settings):
                results[k] = calibrate_setting(base, s, datasets, seeds[k])
                bar.update()
        else:
            with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
                longest_first = sorted(range(len(settings)), key=lambda k: -_cost(settings[k]))
                jobs = {
                    pool.submit(_calibrate_in_worker, base.to_dict(), settings[k], datasets, seeds[k]): k
                    for k in longest_first
                }
                for job in as_completed(jobs):
                    results[jobs[job]] = job.result()
                    bar.update()
    return [r for r in results if r is not None]


#: The settings of ``agsf diagnose``'s verdicts (:func:`verdict_study`): label, trajectories per data set and
#: seconds; the EKF of the base configuration with the iterated update, as the learning settings.
VERDICT_SETTINGS = (("1 trajectory × 30 s", 1, 30.0), ("16 trajectories × 20 s", 16, 20.0))


def verdict_study(base: ExperimentConfig, *, datasets: int, seed: int, quick: bool = False) -> list[dict]:
    """``agsf diagnose``'s false-alarm and detection rates (:func:`agsf_torch.experiments.studies.verdict_calibration.diagnose_verdict_rates`) in
    each of :data:`VERDICT_SETTINGS` (``quick``: the first, 5 s): the EKF with the iterated update, σ_s and σ_v
    mis-scaled by :data:`MIS_SCALINGS`.  JSON-able records: the label, the levels and the table's rows."""
    from .verdict_calibration import diagnose_verdict_rates

    out = []
    for label, trajectories, seconds in VERDICT_SETTINGS[:1] if quick else VERDICT_SETTINGS:
        cfg = base.replace(filters=["EKF"], update_iterations=3, duration=5.0 if quick else seconds, faults=[])
        rates = diagnose_verdict_rates(
            cfg, datasets=datasets, trajectories=trajectories, scales=(1.0, *MIS_SCALINGS), seed=seed, force=True
        )
        out.append(
            {
                "label": label,
                "datasets": datasets,
                "checks": list(rates.checks),
                "level": rates.level,
                "familywise_level": rates.familywise_level,
                "whiteness_level": rates.whiteness_level.tolist(),
                "rows": rates.rows(),
            }
        )
    return out
