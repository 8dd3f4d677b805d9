"""Quantiles of the χ² and Student-t distributions: the consistency bands, the innovation gate, the confidence
intervals of the summaries.

The inverse functions of :mod:`scipy.special` that ``scipy.stats.chi2.ppf`` and ``scipy.stats.t.ppf`` evaluate,
without importing :mod:`scipy.stats`, whose import is a noticeable part of every ``agsf`` command's start.
"""

from __future__ import annotations

import math

__all__ = ["chi2_quantile", "student_t_quantile"]


def _check(p: float, dof: float, what: str) -> tuple[float, float]:
    p, dof = float(p), float(dof)
    if not 0.0 < p < 1.0:
        raise ValueError(f"{what} quantile: the probability must lie in (0, 1), got {p}")
    if not (math.isfinite(dof) and dof > 0.0):
        raise ValueError(f"{what} quantile: the degrees of freedom must be finite and positive, got {dof}")
    return p, dof


def chi2_quantile(p: float, dof: float) -> float:
    """``χ²_dof(p)``, the value a χ² variable with ``dof`` degrees of freedom stays below with probability ``p``:
    ``2·P⁻¹(dof/2, p)``, ``P`` the regularised lower incomplete gamma function.

    Raises:
        ValueError: ``p`` outside (0, 1), or ``dof`` not finite and positive.
    """
    from scipy.special import gammaincinv

    p, dof = _check(p, dof, "χ²")
    return float(2.0 * gammaincinv(dof / 2.0, p))


def student_t_quantile(p: float, dof: float) -> float:
    """``t_dof(p)``, the value a Student-t variable with ``dof`` degrees of freedom stays below with probability
    ``p`` (``scipy.special.stdtrit``).

    Raises:
        ValueError: ``p`` outside (0, 1), or ``dof`` not finite and positive.
    """
    from scipy.special import stdtrit

    p, dof = _check(p, dof, "Student-t")
    return float(stdtrit(dof, p))
