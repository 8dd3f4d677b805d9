"""Consistency of a filter: its errors and innovations against its own covariances.

The metrics: RMS, NEES ``eᵀP⁻¹e`` (Cholesky solve) and the χ² band of an averaged NEES or NIS
(the NIS itself comes with each measurement update, ``filt.diagnostics``; the weight
entropy is :meth:`agsf_torch.GaussianMixture.entropy_of_weights`).  The checks, each
saying in words whether it passes and what a failure suggests:

* **NEES** (needs the truth): the run- and time-averaged ``eᵀP⁻¹e`` against the
  two-sided 95 % χ² band of the run average (``n`` degrees of freedom per run).
* **NIS** (always): ``νᵀS⁻¹ν`` at star frames divided by its expected value,
  against the χ² band of the average.  For star unit vectors under the model
  ``σ_s²I₃`` the noise has 2 degrees of freedom per star, not 3 (it lies across
  the star vector), so the expected NIS is ``tangent_fraction · d`` with
  ``tangent_fraction = 2/3`` for ``d`` valid entries.
* **Whiteness**: the lag-1 autocorrelation of the standardised NIS sequence of
  each run, averaged over runs, against ``±1.96/√(count)``.
* **FPKE error**: reported (mean before/after the weight update), not judged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .quantiles import chi2_quantile

__all__ = ["nees", "rms", "chi2_band", "nis_per_expected", "Check", "consistency_checks", "format_report"]


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
    updates = nis_dof > 0  # the NIS is NaN where there was no update (d = 0)
    count = int(updates.sum())
    if not count:
        return None
    expected = tangent_fraction * nis_dof[updates]
    k = float(expected.mean())
    lo, hi = chi2_band(k, count, confidence)
    return float(nis[updates].sum() / expected.sum()), (lo / k, hi / k)


@dataclass(frozen=True)
class Check:
    name: str
    value: float
    band: tuple[float, float]
    passed: bool
    text: str


def consistency_checks(
    *,
    nees: np.ndarray | None,
    state_dim: int,
    nis: np.ndarray,
    nis_dof: np.ndarray,
    tangent_fraction: float = 2.0 / 3.0,
    confidence: float = 0.95,
) -> list[Check]:
    """The checks of the module docstring.

    Args:
        nees: ``[T, B]`` or ``None`` (no truth).
        state_dim: ``n``.
        nis: ``[T, B]`` NIS at star frames, NaN elsewhere.
        nis_dof: ``[T, B]`` valid measurement entries at each NIS.
        tangent_fraction: expected NIS per valid entry (2/3 for star unit vectors).
    """
    checks: list[Check] = []
    if nees is not None:
        B = nees.shape[1]
        lo, hi = chi2_band(state_dim, B, confidence)
        checks.append(
            _band_check(
                "nees",
                "NEES",
                float(np.mean(nees)),
                lo,
                hi,
                "the covariance matches the errors",
                "the filter is over-confident (errors larger than its covariance)",
                "the filter is under-confident (covariance too large)",
            )
        )
    pooled = nis_per_expected(nis, nis_dof, tangent_fraction, confidence)
    if pooled is not None and not math.isfinite(pooled[0]):
        text = f"NIS / expected {pooled[0]}: an update's NIS is not finite — the filter diverged"
        checks.append(Check("nis", pooled[0], pooled[1], False, text))
    elif pooled is not None:
        ratio, (lo, hi) = pooled
        checks.append(
            _band_check(
                "nis",
                "NIS / expected",
                ratio,
                lo,
                hi,
                "innovations match the measurement model",
                "innovations are larger than the filter expects — measurement or process noise under-modelled",
                "innovations are smaller than the filter expects — noise over-modelled",
            )
        )
        valid = np.isfinite(nis) & (nis_dof > 0)
        # whiteness: lag-1 autocorrelation of the standardised NIS per run
        z = np.where(
            valid,
            (nis - tangent_fraction * nis_dof) / np.sqrt(2.0 * np.maximum(tangent_fraction * nis_dof, 1e-300)),
            np.nan,
        )
        frames = valid.any(1)
        Z, V = z[frames], valid[frames]  # [F, B]
        count_b = V.sum(0)
        mean_b = np.where(V, Z, 0.0).sum(0) / np.maximum(count_b, 1)
        Zc = np.where(V, Z - mean_b, 0.0)
        den_b = (Zc * Zc).sum(0)
        pairs_b = (V[1:] & V[:-1]).sum(0)
        use = (count_b > 2) & (den_b > 0)
        num = float(((Zc[1:] * Zc[:-1]).sum(0)[use] / den_b[use] * pairs_b[use]).sum())
        n_pairs = int(pairs_b[use].sum())
        if n_pairs:
            rho = num / n_pairs
            bound = 1.959963984540054 / math.sqrt(n_pairs)
            ok = abs(rho) <= bound
            text = (
                f"innovation lag-1 autocorrelation {rho:.3g} within ±{bound:.3g}: white"
                if ok
                else f"innovation lag-1 autocorrelation {rho:.3g} outside ±{bound:.3g}: correlated innovations — unmodelled dynamics or bias"
            )
            checks.append(Check("whiteness", rho, (-bound, bound), ok, text))
    return checks


def _band_check(key: str, label: str, v: float, lo: float, hi: float, inside: str, above: str, below: str) -> Check:
    """A value judged against ``[lo, hi]``, with the sentence for each outcome."""
    if lo <= v <= hi:
        return Check(key, v, (lo, hi), True, f"{label} {v:.4g} inside [{lo:.4g}, {hi:.4g}]: {inside}")
    where, meaning = ("above", above) if v > hi else ("below", below)
    return Check(key, v, (lo, hi), False, f"{label} {v:.4g} {where} [{lo:.4g}, {hi:.4g}]: {meaning}")


def format_report(name: str, checks: list[Check], fpke: tuple[float, float] | None = None) -> str:
    lines = [
        f"{name}: "
        + (
            "all checks pass"
            if all(c.passed for c in checks)
            else "FAILED: " + ", ".join(c.name for c in checks if not c.passed)
        )
    ]
    lines += [f"  [{'pass' if c.passed else 'FAIL'}] {c.text}" for c in checks]
    if fpke is not None:
        lines.append(f"  [info] FPKE error wᵀLw (mean): {fpke[0]:.4g} before, {fpke[1]:.4g} after the weight update")
    return "\n".join(lines)
