"""The χ² and Student-t quantiles (agsf_torch.quantiles) against scipy.stats and printed tables."""

from __future__ import annotations

import math

import mpmath as mp
import pytest
import scipy.stats
from hypothesis import given
from hypothesis import strategies as st

from agsf_torch.quantiles import chi2_quantile, student_t_quantile
from tests.helpers import assert_within

probabilities = st.floats(min_value=1e-6, max_value=1.0 - 1e-6)
dofs = st.floats(min_value=0.5, max_value=1e5)


def _chi2_reference(p: str, dof: float):
    """χ²_dof(p) from the definition, in 40-digit arithmetic (mpmath, independent of scipy)."""
    mp.mp.dps = 40
    return mp.findroot(lambda x: mp.gammainc(mp.mpf(dof) / 2, 0, x / 2, regularized=True) - mp.mpf(p), mp.mpf(dof))


def _student_t_reference(p: str, dof: float):
    """t_dof(p) for p > ½ from the definition (the regularised incomplete beta function), in 40-digit arithmetic."""
    mp.mp.dps = 40
    n = mp.mpf(dof)
    tail = lambda t: mp.betainc(n / 2, mp.mpf(1) / 2, 0, n / (n + t * t), regularized=True) / 2  # noqa: E731
    return mp.findroot(lambda t: 1 - tail(t) - mp.mpf(p), mp.mpf(2))


# each function evaluates its quantile to a few units in the last place (the inverse functions' accuracy), and
# these quantiles are well conditioned (p away from 0 and 1): 1e-13 relative is ~500 units in the last place
@pytest.mark.parametrize(("p", "dof"), [("0.95", 1), ("0.975", 3), ("0.025", 300), ("0.5", 7.5)])
def test_chi2_quantiles_match_the_definition(p, dof):
    ref = float(_chi2_reference(p, dof))
    assert_within(chi2_quantile(float(p), dof), ref, 1e-13 * ref, "χ² quantile against the definition")


@pytest.mark.parametrize(("p", "dof"), [("0.975", 9), ("0.975", 99), ("0.9", 2.5)])
def test_student_t_quantiles_match_the_definition(p, dof):
    ref = float(_student_t_reference(p, dof))
    assert_within(student_t_quantile(float(p), dof), ref, 1e-13 * ref, "Student-t quantile against the definition")


@given(probabilities, dofs)
def test_the_quantiles_are_scipy_stats(p, dof):
    # the same inverse functions scipy.stats evaluates; the bound allows another scipy's rounding of them
    chi2 = scipy.stats.chi2.ppf(p, dof)
    assert_within(chi2_quantile(p, dof), chi2, 1e-12 * chi2, "χ² quantile against scipy.stats")
    # the t quantile is 0 at p = ½ (both sides exactly, by symmetry): the floor admits that one point
    t = scipy.stats.t.ppf(p, dof)
    assert_within(student_t_quantile(p, dof), t, 1e-12 * abs(t) + 1e-300, "Student-t quantile against scipy.stats")


@pytest.mark.parametrize("quantile", [chi2_quantile, student_t_quantile])
@pytest.mark.parametrize(
    ("p", "dof", "what"),
    [
        (0.0, 3, "probability"),
        (1.0, 3, "probability"),
        (math.nan, 3, "probability"),
        (0.5, 0, "degrees of freedom"),
        (0.5, math.inf, "degrees of freedom"),
        (0.5, -2, "degrees of freedom"),
    ],
)
def test_bad_arguments_are_refused_naming_them(quantile, p, dof, what):
    with pytest.raises(ValueError, match=what):
        quantile(p, dof)


def test_importing_the_package_leaves_scipy_stats_unloaded():
    import subprocess
    import sys

    code = "import sys, agsf_torch.experiments.cli.main; print('scipy.stats' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout == "False\n"
