"""Consistency of a filter: its errors and innovations against its own covariances.

The metrics: RMS, NEES ``eᵀP⁻¹e`` (Cholesky solve) and the χ² band of an averaged NEES or NIS
(the NIS itself comes with each measurement update, ``filt.diagnostics``; the weight
entropy is :meth:`agsf_torch.GaussianMixture.entropy_of_weights`).  The checks, each
saying in words whether it passes and what a failure suggests:

* **NEES** (needs the truth): the run- and time-averaged ``eᵀP⁻¹e`` against the
  two-sided χ² band of the run average (``n`` degrees of freedom per run).
* **NIS** (always): ``νᵀS⁻¹ν`` at star frames divided by its expected value,
  against the χ² band of the average.  For star unit vectors under the model
  ``σ_s²I₃`` the noise has 2 degrees of freedom per star, not 3 (it lies across
  the star vector), so the expected NIS is ``tangent_fraction · d`` with
  ``tangent_fraction = 2/3`` for ``d`` valid entries.
* **Whiteness**: the lag-1 autocorrelation of the standardised NIS sequence of
  each run about its expected mean 0, averaged over runs, against ``±Φ⁻¹(1 − α_c/2)/√(count)``.
* **FPKE error**: reported (mean before/after the weight update), not judged.

A filter passes if every check passes, and the bands are simultaneous (Bonferroni): with ``m`` checks in the
family — 3 with the truth (NEES, NIS, whiteness), 2 without — each band is two-sided at level ``α_c = α/m``
(confidence ``1 − α/m``, ``α = 1 − confidence``, 5 % by default), so a consistent filter fails some check with
probability at most ``Σ α_c = α``, however the checks depend on each other.  ``familywise=False`` makes each band
at level ``α`` instead (the overall verdict then flags a consistent filter up to ``m·α`` of the time).

:func:`consistency_checks` judges one data set in words; :func:`consistency_check_arrays` judges many at once
(batched over leading dims), the same arithmetic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from .quantiles import chi2_quantile

__all__ = [
    "nees",
    "rms",
    "chi2_band",
    "nis_per_expected",
    "check_level",
    "Check",
    "CheckArrays",
    "consistency_checks",
    "consistency_check_arrays",
    "format_report",
]


def nees(error: Tensor, cov: Tensor) -> Tensor:
    """Normalised estimation error squared ``eᵀ P⁻¹ e`` (Cholesky solve).

    Args:
        error: ``[..., n]``; cov: ``[..., n, n]``.

    Returns:
        ``[...]``.
    """
    L = torch.linalg.cholesky(cov)
    z = torch.linalg.solve_triangular(L, error.unsqueeze(-1), upper=False).squeeze(-1)
    return (z * z).sum(-1)


def rms(values, dim: int = 0):
    """Root mean square along ``dim``: ``sqrt(mean(v²))``, of a tensor or a NumPy array (same type back)."""
    if torch.is_tensor(values):
        return torch.sqrt((values * values).mean(dim))
    values = np.asarray(values)
    return np.sqrt((values * values).mean(dim))


def chi2_band(dof: float, num_samples: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band for the average of ``num_samples`` independent χ²(dof) values.

    The sum is χ²(dof·num_samples), so the average lies in
    ``[χ²_{α/2}, χ²_{1−α/2}] / num_samples`` with probability ``confidence``.
    """
    a = (1.0 - confidence) / 2.0
    k = dof * num_samples
    return chi2_quantile(a, k) / num_samples, chi2_quantile(1.0 - a, k) / num_samples


def nis_per_expected(
    nis: np.ndarray, nis_dof: np.ndarray, tangent_fraction: float = 2.0 / 3.0, confidence: float = 0.95
) -> tuple[float, tuple[float, float]] | None:
    """The pooled NIS ratio ``Σ NIS / Σ E[NIS]`` over every valid update and its χ² band.

    ``E[NIS] = tangent_fraction · d`` for ``d`` valid measurement entries (2 per star for star unit
    vectors, module docstring); every update with ``d > 0`` counts, so a non-finite NIS there (a filter that
    diverged) makes the ratio non-finite (``inf``, or NaN) instead of being left out.  A consistent
    filter's ratio is 1 and lies, with probability ``confidence``, in the band: the average of
    ``count`` χ² values of ``k`` (the mean expectation) degrees of freedom, divided by ``k``
    (:func:`chi2_band`).

    Args:
        nis: ``[...]`` NIS, NaN where there was no update; nis_dof: ``[...]`` its valid entries.

    Returns:
        ``(ratio, (low, high))``, or ``None`` when no update has a valid NIS.
    """
    nis, nis_dof = np.asarray(nis, dtype=np.float64), np.asarray(nis_dof, dtype=np.float64)
    ratio, low, high, count = _pooled_nis(nis.reshape(1, -1), nis_dof.reshape(1, -1), tangent_fraction, confidence)
    if not count:
        return None
    return float(ratio), (float(low), float(high))


def _pooled_nis(
    nis: np.ndarray, nis_dof: np.ndarray, tangent_fraction: float, confidence: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`nis_per_expected` of each data set, pooled over the last two axes of ``nis [..., T, B]`` and
    ``nis_dof [..., T, B]`` (float64).

    Returns:
        ``(ratio, low, high, count)``, each ``[...]``: ``count`` the updates with a valid NIS; where it is 0 the
        ratio and the band are NaN.
    """
    updates = nis_dof > 0  # the NIS is NaN where there was no update (d = 0)
    count = updates.sum((-2, -1))
    expected = np.where(updates, tangent_fraction * nis_dof, 0.0).sum((-2, -1))
    with np.errstate(divide="ignore", invalid="ignore"):
        k = expected / count  # the mean expectation
        ratio = np.where(updates, nis, 0.0).sum((-2, -1)) / expected
        lo, hi = _chi2_bands(k, count, confidence)
        return np.where(count > 0, ratio, np.nan), lo / k, hi / k, count


def _chi2_bands(dof: np.ndarray, num_samples: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`chi2_band` elementwise over arrays ``dof [...]``, ``num_samples [...]`` (NaN where
    ``num_samples`` is 0): :func:`~agsf_torch.quantiles.chi2_quantile`'s ``2·P⁻¹(k/2, p)`` on arrays."""
    from scipy.special import gammaincinv

    a = (1.0 - confidence) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        half = np.where(num_samples > 0, dof * num_samples, np.nan) / 2.0
        return 2.0 * gammaincinv(half, a) / num_samples, 2.0 * gammaincinv(half, 1.0 - a) / num_samples


def check_level(confidence: float, checks: int, familywise: bool = True) -> float:
    """The false-alarm level ``α_c`` of each of ``checks`` bands for a family of ``confidence``: ``α/checks``
    (Bonferroni, ``α = 1 − confidence``), so that all ``checks`` hold together with probability at least
    ``confidence``; ``α`` itself when not ``familywise``."""
    alpha = 1.0 - confidence
    return alpha / checks if familywise else alpha


@dataclass(frozen=True)
class Check:
    """One check of :func:`consistency_checks`: its statistic, the band it must lie in (at false-alarm level
    ``level``, :func:`check_level`), whether it does, and the sentence saying so."""

    name: str
    value: float
    band: tuple[float, float]
    passed: bool
    text: str
    level: float = math.nan


@dataclass(frozen=True)
class CheckArrays:
    """One check of :func:`consistency_checks` judged for many data sets at once, ``[...]`` their shape.

    Attributes:
        name: the check's :attr:`Check.name` (``"nees"``, ``"nis"``, ``"whiteness"``).
        value: the statistic ``[...]``, NaN where the check is not made.
        low, high: the band ``[...]`` it must lie in.
        passed: ``[...]`` bool: made and inside the band (:attr:`Check.passed`).
        made: ``[...]`` bool: whether :func:`consistency_checks` makes the check for that data set (the NIS needs
            an update; the whiteness a finite NIS ratio and a pair of consecutive updates of a run).
        level: the band's false-alarm level ``α_c`` (:func:`check_level`): ``1 −`` its confidence.
    """

    name: str
    value: np.ndarray
    low: np.ndarray
    high: np.ndarray
    passed: np.ndarray
    made: np.ndarray
    level: float


def consistency_check_arrays(
    *,
    nees: np.ndarray | None,
    state_dim: int,
    nis: np.ndarray,
    nis_dof: np.ndarray,
    tangent_fraction: float = 2.0 / 3.0,
    confidence: float = 0.95,
    familywise: bool = True,
) -> dict[str, CheckArrays]:
    """The checks of :func:`consistency_checks` for many data sets at once (batched over leading dims).

    Args:
        nees: ``[..., T, B]`` or ``None`` (no truth): data set ``i`` is ``nees[i]``, ``T`` steps of ``B`` runs.
        state_dim: ``n``.
        nis: ``[..., T, B]`` NIS at star frames, NaN elsewhere.
        nis_dof: ``[..., T, B]`` valid measurement entries at each NIS.
        tangent_fraction: expected NIS per valid entry (2/3 for star unit vectors).
        confidence: with ``familywise``, the probability that a consistent filter passes every check (each band
            at level ``(1 − confidence)/m``, ``m`` = 3 with ``nees``, 2 without: the module docstring);
            otherwise each band's own confidence.
        familywise: make the bands simultaneous (Bonferroni).

    Returns:
        name → :class:`CheckArrays` of shape ``[...]``, in :func:`consistency_checks`' order: ``"nees"`` (with
        ``nees``), ``"nis"`` and ``"whiteness"`` (always; their ``made`` says where they are made).
    """
    nis, nis_dof = np.asarray(nis, dtype=np.float64), np.asarray(nis_dof, dtype=np.float64)
    level = check_level(confidence, 3 if nees is not None else 2, familywise)
    checks: dict[str, CheckArrays] = {}
    if nees is not None:
        nees = np.asarray(nees, dtype=np.float64)
        lo, hi = chi2_band(state_dim, nees.shape[-1], 1.0 - level)
        value = nees.mean((-2, -1))
        low, high = np.full(value.shape, lo), np.full(value.shape, hi)
        checks["nees"] = CheckArrays(
            "nees", value, low, high, (lo <= value) & (value <= hi), np.ones(value.shape, bool), level
        )
    ratio, low, high, count = _pooled_nis(nis, nis_dof, tangent_fraction, 1.0 - level)
    made = count > 0
    checks["nis"] = CheckArrays("nis", ratio, low, high, made & (low <= ratio) & (ratio <= high), made, level)
    checks["whiteness"] = _whiteness(nis, nis_dof, tangent_fraction, made & np.isfinite(ratio), level)
    return checks


def _whiteness(
    nis: np.ndarray, nis_dof: np.ndarray, tangent_fraction: float, judged: np.ndarray, level: float
) -> CheckArrays:
    """The whiteness check of each data set ``[...]`` (made where ``judged`` and some run has two updates in a
    row): the lag-1 autocorrelation about 0 of the standardised NIS of each run, over the star frames at which some run
    of the data set has a valid NIS, averaged over runs weighted by their pairs, against ``±Φ⁻¹(1 − level/2)/√(pairs)``
    (for white innovations it has mean 0 and tends to a normal of variance ``1/pairs`` as the runs' frames grow;
    with a few tens of frames per run the check is conservative, :mod:`agsf_torch.experiments.studies.verdict_calibration`)."""
    from scipy.special import ndtri

    valid = np.isfinite(nis) & (nis_dof > 0)
    with np.errstate(invalid="ignore"):
        scale = np.sqrt(2.0 * np.maximum(tangent_fraction * nis_dof, 1e-300))
        z = np.where(valid, (nis - tangent_fraction * nis_dof) / scale, np.nan)
    # the frames of each data set first, in time order (the others hold no valid NIS and add nothing)
    order = np.argsort(~valid.any(-1), axis=-1, kind="stable")[..., None]
    Z, V = np.take_along_axis(z, order, -2), np.take_along_axis(valid, order, -2)  # [..., T, B]
    count_b = V.sum(-2)
    # about the known mean 0 of a consistent filter's standardised NIS, not each run's own: a run's own mean
    # biases its autocorrelation by −1/n_b, a bias that does not shrink with more runs while the band does; a NIS
    # of another mean (a mis-scaled noise) shows as correlation too
    Zc = np.where(V, Z, 0.0)
    den_b = (Zc * Zc).sum(-2)
    pairs_b = (V[..., 1:, :] & V[..., :-1, :]).sum(-2)
    use = (count_b > 2) & (den_b > 0)
    lag_b = (Zc[..., 1:, :] * Zc[..., :-1, :]).sum(-2)
    num = np.where(use, lag_b / np.where(use, den_b, 1.0) * pairs_b, 0.0).sum(-1)
    n_pairs = np.where(use, pairs_b, 0).sum(-1)
    made = judged & (n_pairs > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(made, num / n_pairs, np.nan)
        bound = np.where(made, ndtri(1.0 - level / 2.0) / np.sqrt(n_pairs), np.nan)
    return CheckArrays("whiteness", rho, -bound, bound, made & (np.abs(rho) <= bound), made, level)


def consistency_checks(
    *,
    nees: np.ndarray | None,
    state_dim: int,
    nis: np.ndarray,
    nis_dof: np.ndarray,
    tangent_fraction: float = 2.0 / 3.0,
    confidence: float = 0.95,
    familywise: bool = True,
) -> list[Check]:
    """The checks of the module docstring (one data set of :func:`consistency_check_arrays`, in words).

    Args:
        nees: ``[T, B]`` or ``None`` (no truth).
        state_dim: ``n``.
        nis: ``[T, B]`` NIS at star frames, NaN elsewhere.
        nis_dof: ``[T, B]`` valid measurement entries at each NIS.
        tangent_fraction: expected NIS per valid entry (2/3 for star unit vectors).
        confidence, familywise: as in :func:`consistency_check_arrays` (by default a consistent filter passes
            every check with probability at least 95 %).
    """
    arrays = consistency_check_arrays(
        nees=nees,
        state_dim=state_dim,
        nis=nis,
        nis_dof=nis_dof,
        tangent_fraction=tangent_fraction,
        confidence=confidence,
        familywise=familywise,
    )
    checks: list[Check] = []
    for name, c in arrays.items():
        if not bool(c.made):
            continue
        v, lo, hi = float(c.value), float(c.low), float(c.high)
        if name == "nees":
            check = _band_check(
                "nees",
                "NEES",
                v,
                lo,
                hi,
                "the covariance matches the errors",
                "the filter is over-confident (errors larger than its covariance)",
                "the filter is under-confident (covariance too large)",
            )
        elif name == "nis" and not math.isfinite(v):
            text = f"NIS / expected {v}: an update's NIS is not finite — the filter diverged"
            check = Check("nis", v, (lo, hi), False, text)
        elif name == "nis":
            check = _band_check(
                "nis",
                "NIS / expected",
                v,
                lo,
                hi,
                "innovations match the measurement model",
                "innovations are larger than the filter expects — measurement or process noise under-modelled",
                "innovations are smaller than the filter expects — noise over-modelled",
            )
        else:
            ok, bound = bool(c.passed), hi
            text = (
                f"innovation lag-1 autocorrelation {v:.3g} within ±{bound:.3g}: white"
                if ok
                else f"innovation lag-1 autocorrelation {v:.3g} outside ±{bound:.3g}: correlated innovations — unmodelled dynamics or bias"
            )
            check = Check("whiteness", v, (-bound, bound), ok, text)
        checks.append(replace(check, level=c.level))
    return checks


def _band_check(key: str, label: str, v: float, lo: float, hi: float, inside: str, above: str, below: str) -> Check:
    """A value judged against ``[lo, hi]``, with the sentence for each outcome."""
    if lo <= v <= hi:
        return Check(key, v, (lo, hi), True, f"{label} {v:.4g} inside [{lo:.4g}, {hi:.4g}]: {inside}")
    where, meaning = ("above", above) if v > hi else ("below", below)
    return Check(key, v, (lo, hi), False, f"{label} {v:.4g} {where} [{lo:.4g}, {hi:.4g}]: {meaning}")


def format_report(name: str, checks: list[Check], fpke: tuple[float, float] | None = None) -> str:
    """A filter's verdict and its checks, one line each; then, for checks with a level, what the verdict's bands
    promise together (Bonferroni: a consistent filter fails some check at most ``Σ level`` of the time) and, if
    given, the FPKE error (mean before and after the weight update)."""
    lines = [
        f"{name}: "
        + (
            "all checks pass"
            if all(c.passed for c in checks)
            else "FAILED: " + ", ".join(c.name for c in checks if not c.passed)
        )
    ]
    lines += [f"  [{'pass' if c.passed else 'FAIL'}] {c.text}" for c in checks]
    levels = {c.level for c in checks}
    if len(levels) == 1 and math.isfinite(level := levels.pop()):
        lines.append(
            f"  [info] the {len(checks)} bands are simultaneous, each at level {100 * level:.3g} % (Bonferroni): "
            f"a consistent filter fails some check at most {100 * level * len(checks):.3g} % of the time"
        )
    if fpke is not None:
        lines.append(f"  [info] FPKE error wᵀLw (mean): {fpke[0]:.4g} before, {fpke[1]:.4g} after the weight update")
    return "\n".join(lines)
