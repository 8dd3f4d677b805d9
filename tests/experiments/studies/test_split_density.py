"""One wide Gaussian on the sine SDE that must become several (``experiments/studies/split_density.py``), at a
short horizon: mixture management against the exact (grid FPKE) density."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize
from scipy.stats import norm

from agsf_torch.experiments.studies.split_density import one_component_prior, run_split_density
from agsf_torch.filters import GaussianSumFilter
from agsf_torch.models.benchmarks import SineDriftModel
from tests.helpers import F64, assert_within, relative_bound

EPS = torch.finfo(F64).eps


@pytest.fixture(scope="module")
def short_run():
    """2 s (20 steps) from the default one-component prior N(0.16, 1.0144), the managed filters at capacity 16;
    densities kept at the horizon."""
    return run_split_density(horizon=2.0, report_times=(2.0,), benchmark_prior=False)


def _best_single_gaussian_ise(p: np.ndarray, grid: np.ndarray) -> float:
    """The least ISE against ``p`` found over single Gaussians ``N(m, s²)``: Nelder–Mead on ``(m, log s)`` from
    nine starts (modes at ±2.5 and the middle, three widths)."""

    def ise(z: np.ndarray) -> float:
        return float(np.trapezoid((norm.pdf(grid, z[0], math.exp(z[1])) - p) ** 2, grid))

    starts = [(m, math.log(s)) for m in (-2.5, 0.0, 2.5) for s in (0.7, 1.5, 3.0)]
    return min(minimize(ise, x0, method="Nelder-Mead", options={"xatol": 1e-8, "fatol": 1e-12}).fun for x0 in starts)


def test_one_wide_component_becomes_several(short_run):
    """(a) The managed GSF leaves the single component behind: more than one active component at the horizon,
    and no more than its capacity.

    (b) Its density is closer to the exact one than any single Gaussian by at least a factor 2 in ISE, hence
    than the unmanaged one-component GSF's.  Why the margin holds: by t = 2 s the exact density is bimodal
    (modes near ±2.7, trough at 0 about a third of the lower peak), which no single Gaussian can follow; the
    best one the search finds is a structural error (measured 0.039; the EKF's Gaussian, 0.073, is one of the
    candidates, so the search is also checked against it), whereas the managed mixture's error is set by the
    resolution of its splits (measured 0.0049, a factor 8 below the best single Gaussian).  A factor 2 leaves a
    factor 4 for changes in the management's choices or the propagation that do not break the mechanism.
    """
    r = short_run
    gsf, managed = r["filters"]["gsf"], r["filters"]["gsf_managed"]
    assert managed["active"][-1] > 1
    assert managed["active"].max() <= r["management"]["capacity"]
    assert gsf["active"][-1] == 1
    p = r["reference"]["one_component"]["density"][-1]
    best = _best_single_gaussian_ise(p, r["grid"])
    print(
        f"ISE at t = 2 s: one-component GSF {gsf['ise'][-1]:.4g}, best single Gaussian {best:.4g}, "
        f"managed GSF {managed['ise'][-1]:.4g} ({managed['active'][-1]} components)"
    )
    assert best <= gsf["ise"][-1], "the search missed a single Gaussian as good as the EKF's"
    assert 2.0 * managed["ise"][-1] <= best
    assert 2.0 * managed["ise"][-1] <= gsf["ise"][-1]


def test_the_first_split_preserves_mean_and_variance(short_run):
    """(c) The prior's entropy test fires at once (``|cos m|(1 − cos σ) ≈ 0.46 nats/s`` against 0.05), so the
    first management pass splits the prior itself, into the three DeMars–Bishop–Jah children; the mixture it
    leaves has the prior's mean and variance to rounding.

    Bound: each child's weight carries a few ulps (the log share, the logsumexp normalisation, exp), each child
    mean a few ulps of ``|m| + 1.06σ``, each child variance a few of ``σ²``; the weighted sums of three terms add a
    few more.  16 ulps of the moment's scale (``|m| + σ`` for the mean, ``σ²`` for the variance) covers them with
    room for the test run's jitter of up to 4 ulps.

    The reproduced pass is the filter's own: propagating it with the unmanaged GSF gives the managed filter's
    output of that step (the same RK4 on the same inputs; 16 ulps of each entry admit the jitter only).
    """
    fs = short_run["first_split"]
    assert fs is not None and fs["step"] == 0
    prior = one_component_prior()
    # the mixture entering the first step is the prior itself (the same numbers, not a computed copy)
    assert torch.equal(fs["before"].means, prior.means) and torch.equal(fs["before"].covs, prior.covs)
    after = fs["after"]
    assert int(torch.isfinite(after.log_weights).sum()) == 3
    m0, P0 = prior.moments()
    m1, P1 = after.moments()
    sigma = math.sqrt(float(P0[0, 0]))
    assert_within(m1, m0, 16 * EPS * (abs(float(m0[0])) + sigma), "mean after the first split")
    assert_within(P1, P0, 16 * EPS * sigma**2, "variance after the first split")

    propagated = GaussianSumFilter(SineDriftModel(), substeps=10).predict(after, None, 0.1)
    active = torch.isfinite(fs["propagated"].log_weights)
    assert torch.equal(active, torch.isfinite(propagated.log_weights))
    for name in ("log_weights", "means", "covs"):
        want = getattr(propagated, name)[active]
        assert_within(getattr(fs["propagated"], name)[active], want, relative_bound(want, 16 * EPS, 0.0), name)
