"""Summary statistics of an experiment, from its per-run data alone (``runs.npz``)."""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from ...consistency import chi2_band, nis_per_expected, rms
from ...filters.registry import ADAPTIVE_FILTERS, FILTER_NAMES
from ...quantiles import student_t_quantile
from ..config.loader import ExperimentConfig

__all__ = [
    "summarize",
    "mean_ci95",
    "clopper_pearson",
    "paired_difference",
    "minus_gsf_key",
    "mixture_life",
    "error_windows",
    "WINDOW_TEXT",
]

#: What each time window of the error statistics covers, in one sentence (printed under every table).
WINDOW_TEXT = {
    "before_first_frame": "before the first star frame: the prior's stretch, every step from t = dt (the first "
    "gyro period) up to that frame",
    "between_frames": "between frames: every step after the first star frame that is not itself a frame",
    "all": "all: every step of the run, t = dt to the end",
}


def error_windows(frames: np.ndarray) -> dict[str, np.ndarray]:
    """The time windows of the error statistics as boolean masks ``[T]`` over the steps, from the star-frame
    flags ``frames [T]``: ``before_first_frame`` (the prior's stretch), ``between_frames`` (after the first
    frame, off frames) and ``all`` (:data:`WINDOW_TEXT`).  Without any frame, every step is before the first."""
    frames = np.asarray(frames, dtype=bool)
    first = int(np.argmax(frames)) if frames.any() else len(frames)
    idx = np.arange(len(frames))
    return {
        "before_first_frame": idx < first,
        "between_frames": (~frames) & (idx > first),
        "all": np.ones(len(frames), dtype=bool),
    }


def minus_gsf_key(adaptive: str) -> str:
    """The summary key of an adaptive filter's paired difference against the GSF
    (``AGSF`` → ``agsf_minus_gsf``, ``AGSF-galerkin`` → ``agsf_galerkin_minus_gsf``)."""
    return adaptive.lower().replace("-", "_") + "_minus_gsf"


def summarize(data: dict[str, np.ndarray], cfg: ExperimentConfig) -> dict[str, Any]:
    """Summary statistics from the per-run data alone (``runs.npz``).

    * ``rms_deg [T]``: ``sqrt(mean_b θ_b(t)²)`` in degrees;
    * ``between_frames``: per run ``r_b = sqrt(mean_t θ_b(t)²)`` over the steps after the first
      star frame that are not frames (:func:`error_windows`); ``mean_rms_deg`` is ``mean_b r_b``;
    * ``before_first_frame``: the same over the prior's stretch, the steps before the first frame;
    * ``rms_error_axes_rad``, ``rms_sigma_axes_rad`` ``[T, n]``: per state axis (rotation about each true body
      axis, then the bias) the RMS over runs of the error and of the filter's 1σ;
    * ``agsf_minus_gsf`` (``agsf_galerkin_minus_gsf``): paired differences
      ``r_b(AGSF) − r_b(GSF)`` (the Galerkin filter's), mean and a Student-t 95 %
      confidence interval; every per-run mean above carries its own interval
      (``ci95_rms_deg``, ``time_averaged_nees_ci95``, over runs);
    * ``nis_per_expected``: ``Σ NIS / Σ E[NIS]`` over every star frame and run (``E[NIS]`` = 2 per valid star,
      :func:`~agsf_torch.consistency.nis_per_expected`), 1 for a consistent filter, with ``nis_band_95``, the
      95 % band a consistent filter's ratio lies in; the consistency measure that needs no truth.  Absent
      without a star frame;
    * managed filters (``active_components`` in ``data``): their mixture's life (:func:`mixture_life`).

    Without the truth (``runs.npz`` of a replay of flight data: no ``error_angle``) the scores against it
    (``rms_deg``, the windows, NEES, the errors, the paired differences) are absent, and ``scored_against_truth``
    says so; the 1σ, the weights, the NIS and the FPKE residual are there.
    """
    time = data["time"]
    frames = data["star_frame"].astype(bool)
    windows = {k: v for k, v in error_windows(frames).items() if k != "all"}
    names = [n for n in FILTER_NAMES if f"{n}/sigma" in data]
    n_state = data[f"{names[0]}/sigma"].shape[-1]
    runs = data[f"{names[0]}/sigma"].shape[0]
    truth = f"{names[0]}/error_angle" in data  # a replay of flight data has no truth: no errors, no NEES
    out: dict[str, Any] = {
        "config": cfg.to_dict(),
        "time_s": time.tolist(),
        "star_frame": frames.tolist(),
        "scored_against_truth": truth,
        "filters": {},
    }
    if truth:
        out["nees_band_95"] = list(chi2_band(n_state, runs))
    if "prior_error_angle" in data:  # every filter's estimate at t = 0: the prior mean
        out["prior_rms_deg"] = float(np.degrees(rms(np.asarray(data["prior_error_angle"]), 0)))
    per_run: dict[str, dict[str, np.ndarray]] = {}
    for name in names:
        entry: dict[str, Any] = {
            "weights_run0": data[f"{name}/weights"][0].tolist(),
            "sigma_run0_rad": data[f"{name}/sigma"][0].tolist(),
            "rms_sigma_axes_rad": np.sqrt(np.mean(data[f"{name}/sigma"] ** 2, axis=0)).tolist(),
            "mean_weight_entropy": float(data[f"{name}/weight_entropy"].mean()),
        }
        if f"{name}/estimate" in data:
            entry["estimate_run0"] = data[f"{name}/estimate"][0].tolist()
        if truth:
            entry.update(
                {
                    "rms_deg": np.degrees(rms(data[f"{name}/error_angle"], 0)).tolist(),
                    "nees_mean": data[f"{name}/nees"].mean(0).tolist(),
                    "time_averaged_nees": float(data[f"{name}/nees"].mean()),
                    "time_averaged_nees_ci95": list(mean_ci95(data[f"{name}/nees"].mean(1))[1:]),
                    "error_run0_rad": data[f"{name}/error"][0].tolist(),
                    "rms_error_axes_rad": np.sqrt(np.mean(data[f"{name}/error"] ** 2, axis=0)).tolist(),
                }
            )
        pooled = nis_per_expected(data[f"{name}/nis"], data[f"{name}/nis_dof"]) if f"{name}/nis" in data else None
        if pooled is not None:
            entry["nis_per_expected"], entry["nis_band_95"] = pooled[0], list(pooled[1])
        for key in ("fpke_error_before", "fpke_error_after"):
            if f"{name}/{key}" in data:
                entry[f"{key}_mean"] = data[f"{name}/{key}"].mean(0).tolist()
        if f"{name}/fpke_error_after" in data:
            entry.update(fpke_ratio(data[f"{name}/fpke_error_before"], data[f"{name}/fpke_error_after"]))
        if f"{name}/active_components" in data:  # a managed filter (agsf_torch.filters.management)
            entry.update(
                mixture_life(*(data[f"{name}/{k}"] for k in ("active_components", "splits", "merges", "prunes")))
            )
        for key in ("gate_rejected", "gyro_held"):
            if f"{name}/{key}" in data:
                entry[f"{key}_total"] = int(data[f"{name}/{key}"].sum())
        per_run[name] = {}
        for wname, mask in windows.items():
            if truth and mask.any():
                r = np.degrees(rms(data[f"{name}/error_angle"][:, mask], 1))  # [B]
                per_run[name][wname] = r
                entry[wname] = {
                    "mean_rms_deg": float(r.mean()),
                    "std_rms_deg": float(r.std(ddof=1)) if runs > 1 else 0.0,
                    "ci95_rms_deg": list(mean_ci95(r)[1:]),
                }
        out["filters"][name] = entry
    for adaptive in ADAPTIVE_FILTERS:
        key = minus_gsf_key(adaptive)
        if truth and "GSF" in per_run and adaptive in per_run:
            out[key] = {
                wname: paired_difference(per_run[adaptive][wname], per_run["GSF"][wname])
                for wname in windows
                if wname in per_run["GSF"]
            }
    return out


def fpke_ratio(before: np.ndarray, after: np.ndarray) -> dict[str, Any]:
    """The fraction of the FPKE residual the weight update leaves, ``after / before`` per run and step
    (``[B, T]``; NaN where ``before`` is 0 or not finite): ``fpke_ratio_mean`` ``[T]`` over the runs and
    ``fpke_ratio_p10_p90`` (two ``[T]`` lists), NaN-aware."""
    before, after = np.asarray(before, dtype=np.float64), np.asarray(after, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where((before > 0) & np.isfinite(before), after / before, np.nan)
    with warnings.catch_warnings():  # a step where no run has a ratio gives NaN, as said
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(ratio, 0)
        lo, hi = np.nanpercentile(ratio, [10.0, 90.0], axis=0)
    return {"fpke_ratio_mean": mean.tolist(), "fpke_ratio_p10_p90": [lo.tolist(), hi.tolist()]}


def mixture_life(active: np.ndarray, splits: np.ndarray, merges: np.ndarray, prunes: np.ndarray) -> dict[str, Any]:
    """A managed filter's mixture over the run from its per-step counts (``runs.npz``, each ``[B, T]``, integers).

    Args:
        active: components in use at the end of each step; splits, merges, prunes: the events of each step
            (its predict and its update together), counts.

    Returns:
        ``active_components_mean`` ``[T]`` (count, mean over the runs), ``active_components_min_max`` (two ``[T]``
        lists: the fewest and the most over the runs), and ``splits_cumulative_mean``, ``merges_cumulative_mean``,
        ``prunes_cumulative_mean`` ``[T]``: per run the events up to and including each step, mean over the runs
        (count per trajectory).
    """
    active = np.asarray(active, dtype=np.float64)
    out: dict[str, Any] = {
        "active_components_mean": active.mean(0).tolist(),
        "active_components_min_max": [active.min(0).tolist(), active.max(0).tolist()],
    }
    for key, counts in (("splits", splits), ("merges", merges), ("prunes", prunes)):
        out[f"{key}_cumulative_mean"] = np.cumsum(np.asarray(counts, dtype=np.float64), 1).mean(0).tolist()
    return out


def mean_ci95(values: np.ndarray) -> tuple[float, float, float]:
    """Mean of per-run values ``[B]`` and its Student-t 95 % interval ``(mean, low, high)``."""
    values = np.asarray(values, dtype=np.float64)
    m = float(values.mean())
    if values.size < 2:
        return m, float("nan"), float("nan")
    half = float(student_t_quantile(0.975, values.size - 1) * values.std(ddof=1) / math.sqrt(values.size))
    return m, m - half, m + half


def median_ci95(values: np.ndarray) -> tuple[float, float, float]:
    """Median of per-run values ``[B]`` and its distribution-free (sign-test) interval of at least 95 % coverage,
    ``(median, low, high)``: the order statistics ``x₍ₖ₎``, ``x₍B₋ₖ₊₁₎`` with ``k`` the largest integer such that
    ``P(Bin(B, ½) ≤ k − 1) ≤ 0.025`` (the interval holds whatever the values' distribution, heavy tails included);
    ``(median, −inf, inf)`` below six values, where no such ``k`` exists."""
    from scipy.stats import binom

    x = np.sort(np.asarray(values, dtype=np.float64))
    B = x.size
    med = float(np.median(x)) if B else float("nan")
    k = int((binom.cdf(np.arange(B), B, 0.5) <= 0.025).sum())  # P(Bin ≤ j) ≤ 0.025 for j < k
    if k < 1:
        return med, -math.inf, math.inf
    return med, float(x[k - 1]), float(x[B - k])


def paired_difference(a: np.ndarray, b: np.ndarray) -> dict[str, Any]:
    """Paired per-run difference ``a − b`` (deg): mean, Student-t 95 % interval and relative to ``mean(b)``."""
    m, lo, hi = mean_ci95(np.asarray(a) - np.asarray(b))
    return {"mean_deg": m, "ci95_deg": [lo, hi], "relative": float(m / np.mean(b))}


def clopper_pearson(successes: np.ndarray, trials: np.ndarray, confidence: float = 0.95) -> np.ndarray:
    """The Clopper–Pearson (exact) interval of a binomial proportion, elementwise.

    ``[B⁻¹(α/2; k, n − k + 1), B⁻¹(1 − α/2; k + 1, n − k)]`` with ``B⁻¹`` the inverse regularised incomplete beta
    function and ``α = 1 − confidence``; the low end is 0 at ``k = 0``, the high end 1 at ``k = n``.

    Args:
        successes: ``k [...]``; trials: ``n [...]`` (integers, ``0 ≤ k ≤ n``).

    Returns:
        ``[..., 2]`` (NaN where ``n = 0``).
    """
    from scipy.special import betaincinv

    k, n = np.broadcast_arrays(np.asarray(successes, np.float64), np.asarray(trials, np.float64))
    a = (1.0 - confidence) / 2.0
    with np.errstate(invalid="ignore", divide="ignore"):
        low = np.where(k > 0, betaincinv(np.maximum(k, 1.0), n - k + 1.0, a), 0.0)
        high = np.where(k < n, betaincinv(k + 1.0, np.maximum(n - k, 1.0), 1.0 - a), 1.0)
    return np.where((n > 0)[..., None], np.stack((low, high), -1), np.nan)
