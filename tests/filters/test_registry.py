"""The filter registry builds every filter by name; each filter's diagnostics are the keys it declares."""

from __future__ import annotations

import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.filters import (
    USQUE,
    AdaptiveGaussianSumFilter,
    Filter,
    GaussianSumFilter,
    MultiplicativeEKF,
    ParticleFilter,
)
from agsf_torch.filters.registry import ADAPTIVE_FILTERS, FILTER_NAMES, FILTERS, make_filter
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from tests.helpers import F64, assert_within, relative_bound


def test_registry_names_and_kinds():
    model = AttitudeModel(estimate_bias=True)
    kinds = {
        "EKF": GaussianSumFilter,
        "GSF": GaussianSumFilter,
        "AGSF": AdaptiveGaussianSumFilter,
        "AGSF-galerkin": AdaptiveGaussianSumFilter,
        "GSF-managed": GaussianSumFilter,
        "AGSF-managed": AdaptiveGaussianSumFilter,
        "AGSF-galerkin-managed": AdaptiveGaussianSumFilter,
        "MEKF": MultiplicativeEKF,
        "MEKF-fix": MultiplicativeEKF,
        "USQUE": USQUE,
        "PF": ParticleFilter,
    }
    assert set(FILTER_NAMES) == set(kinds)  # every registered filter is checked here
    for name in FILTER_NAMES:
        filt = make_filter(name, model, update_iterations=2)
        assert isinstance(filt, kinds[name]) and filt.update_iterations == 2
        assert isinstance(filt, Filter)
    adaptive = tuple(n for n in FILTER_NAMES if isinstance(make_filter(n, model), AdaptiveGaussianSumFilter))
    assert ADAPTIVE_FILTERS == adaptive
    assert make_filter("AGSF-galerkin", model).weight_update.name == "galerkin"
    assert make_filter("AGSF", model, reg=3.0).weight_update.reg == 3.0
    assert [n for n in FILTER_NAMES if FILTERS[n].mixture] == [
        "GSF",
        "AGSF",
        "AGSF-galerkin",
        "GSF-managed",
        "AGSF-managed",
        "AGSF-galerkin-managed",
    ]
    assert [n for n in FILTER_NAMES if make_filter(n, model).__dict__.get("management") is not None] == [
        "GSF-managed",
        "AGSF-managed",
        "AGSF-galerkin-managed",
    ]


def test_registry_refuses_unknown_names_and_options():
    model = AttitudeModel()
    with pytest.raises(ValueError, match="unknown filter 'UKF'; known: EKF, GSF"):
        make_filter("UKF", model)
    with pytest.raises(ValueError, match=r"unknown filter option\(s\) \['regularisation'\]"):
        make_filter("AGSF", model, regularisation=1.0)


@pytest.mark.parametrize("name", FILTER_NAMES)
@pytest.mark.parametrize("gate", [None, 0.9999])
def test_diagnostics_are_the_declared_keys(name, gate):
    model = AttitudeModel(estimate_bias=False)
    filt = make_filter(name, model, gate_probability=gate)
    N = 3 if FILTERS[name].mixture else 1
    g = torch.Generator().manual_seed(0)
    mix = GaussianMixture.from_gaussian(
        0.01 * torch.randn(2, 3, generator=g, dtype=F64), 1e-4 * torch.eye(3, dtype=F64).expand(2, 3, 3), N
    )
    mix = filt.predict(mix, torch.full((2, 3), 1e-3, dtype=F64), 0.1)
    assert set(filt.diagnostics) == set(filt.diagnostic_keys("predict"))
    r = torch.nn.functional.normalize(torch.randn(2, 4, 3, generator=g, dtype=F64), dim=-1)
    meas = StarVectorMeasurement(r, torch.ones(2, 4, dtype=torch.bool), 1e-4)
    filt.update(mix, meas.predict(filt.estimate(mix)[0]), meas)
    assert set(filt.diagnostics) == set(filt.diagnostic_keys("update"))
    with pytest.raises(ValueError, match="step must be 'predict' or 'update'"):
        filt.diagnostic_keys("estimate")


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_one_dt_check_for_every_filter(name):
    """dt = True is refused by every filter alike (the MEKF alone refused it), and 1e39 is a finite positive
    number (a float32 conversion used to overflow it), checked before anything changes."""
    from agsf_torch.filters.base import check_interval

    assert check_interval(1e39) == 1e39
    # a float32 0.1 is 0.1 to float32's rounding, 2⁻²⁴ relative (pytest.approx's default 1e-6 had allowed more)
    dt32 = check_interval(torch.tensor(0.1, dtype=torch.float32))
    assert_within(dt32, 0.1, relative_bound(0.1, 2.0**-24, 0.0), "a float32 interval of 0.1 s")
    model = AttitudeModel(estimate_bias=False)
    filt = make_filter(name, model)
    N = 3 if FILTERS[name].mixture else 1
    mix = GaussianMixture.from_gaussian(
        torch.zeros(2, 3, dtype=torch.float64), 1e-4 * torch.eye(3, dtype=torch.float64).expand(2, 3, 3), N
    )
    for bad in (True, 0.0, -1.0, float("inf"), float("nan"), "0.1"):
        with pytest.raises(ValueError, match="dt must be"):
            filt.predict(mix, torch.zeros(2, 3, dtype=torch.float64), bad)
