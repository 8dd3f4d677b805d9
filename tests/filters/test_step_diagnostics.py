"""The filters' step diagnostics: a dict that prints one summary line per key."""

from __future__ import annotations

import json

import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.filters import GaussianSumFilter, MultiplicativeEKF
from agsf_torch.filters.step_diagnostics import StepDiagnostics, summarize_value
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.rotations import mrp_to_dcm
from tests.helpers import assert_within


def _line(diag: StepDiagnostics, key: str) -> list[str]:
    """The words of ``key``'s line in ``repr(diag)``."""
    lines = [line for line in repr(diag).splitlines() if line.split()[0] == key]
    assert len(lines) == 1, repr(diag)
    return lines[0].split()


def test_numeric_tensor_line_has_shape_dtype_and_nan_aware_statistics():
    x = torch.tensor([[1.0, 2.0, float("nan")], [3.0, 4.0, 5.0]], dtype=torch.float64)
    words = _line(StepDiagnostics(nis=x), "nis")
    assert words[:3] == ["nis", "[2,", "3]"] and words[3] == "float64"
    assert words[4:10] == ["min", "1", "mean", "3", "max", "5"]  # the NaN is ignored ...
    assert words[10:] == ["(1", "NaN)"]  # ... and counted


def test_one_line_per_key_and_nothing_printed_whole():
    d = StepDiagnostics(
        fpke_error_before=torch.linspace(1.2e-3, 9.9e-3, 256, dtype=torch.float64),
        dof=torch.tensor([15, 15, 12]),
        weights_adapted=True,
        covariance_repairs=0,
    )
    text = repr(d)
    assert str(d) == text
    assert len(text.splitlines()) == 4
    assert _line(d, "fpke_error_before") == [
        "fpke_error_before",
        "[256]",
        "float64",
        "min",
        "0.0012",
        "mean",
        "0.00555",
        "max",
        "0.0099",
    ]
    assert _line(d, "dof") == ["dof", "[3]", "int64", "min", "12", "mean", "14", "max", "15"]
    assert _line(d, "weights_adapted") == ["weights_adapted", "bool", "True"]
    assert _line(d, "covariance_repairs") == ["covariance_repairs", "int", "0"]
    # columns aligned: every line's dtype starts at the same column
    starts = {line.index(word) for line, word in zip(text.splitlines(), ("float64", "int64", "bool", "int"))}
    assert len(starts) == 1


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (torch.tensor(-3.25, dtype=torch.float64), ("", "float64", "-3.25")),
        (torch.tensor(7), ("", "int64", "7")),
        (torch.tensor(True), ("", "bool", "True")),
        (torch.tensor([True, False, True]), ("[3]", "bool", "true 2/3")),
        (torch.zeros(0, 5), ("[0, 5]", "float32", "empty")),
        (torch.full((4,), float("nan")), ("[4]", "float32", "all NaN")),
        (torch.tensor([1.0, float("inf")]), ("[2]", "float32", "min 1  mean inf  max inf")),
        (torch.tensor([3 + 4j, 0j]), ("[2]", "complex64 |·|", "min 0  mean 2.5  max 5")),
        (2.5, ("", "float", "2.5")),
        ("text", ("", "str", "'text'")),
    ],
)
def test_summarize_value(value, expected):
    assert summarize_value(value) == expected


def test_tensor_requiring_grad_is_summarised_without_touching_the_graph():
    x = torch.tensor([1.0, 3.0], requires_grad=True)
    y = 2 * x
    assert summarize_value(y) == ("[2]", "float32", "min 2  mean 4  max 6")
    y.sum().backward()  # the graph is intact
    assert x.grad.tolist() == [2.0, 2.0]


def test_it_is_still_a_dict():
    t = torch.arange(3.0)
    d = StepDiagnostics({"a": t, "b": 1})
    assert isinstance(d, dict)
    assert d == {"a": t, "b": 1} and list(d) == ["a", "b"] and d["a"] is t
    assert dict(**d) == {"a": t, "b": 1}
    d["c"] = 2
    assert json.dumps({k: v for k, v in d.items() if not torch.is_tensor(v)}) == '{"b": 1, "c": 2}'
    assert repr(StepDiagnostics()) == "StepDiagnostics({})"


def _filters_and_belief():
    B = 4
    gen = torch.Generator().manual_seed(0)
    p = 0.1 * torch.randn(B, 3, generator=gen, dtype=torch.float64)
    model = AttitudeModel(estimate_bias=False)
    r = torch.nn.functional.normalize(torch.randn(B, 3, 3, generator=gen, dtype=torch.float64), dim=-1)
    body = (mrp_to_dcm(p).unsqueeze(-3) @ r.unsqueeze(-1)).squeeze(-1)
    frame = {"star_body": body, "star_inertial": r, "star_mask": torch.ones(B, 3, dtype=torch.bool)}
    y, meas = StarVectorMeasurement.from_observation(frame, sigma=1e-5)
    eye = 1e-4 * torch.eye(3, dtype=torch.float64).expand(B, 3, 3)
    return model, GaussianMixture.from_gaussian(p, eye, 3), GaussianMixture.from_gaussian(p, eye, 1), y, meas


@pytest.mark.parametrize("kind", ["GSF", "MEKF"])
def test_filters_hold_their_diagnostics_in_the_view(kind):
    model, mix3, mix1, y, meas = _filters_and_belief()
    filt, mix = (GaussianSumFilter(model), mix3) if kind == "GSF" else (MultiplicativeEKF(model), mix1)
    assert isinstance(filt.diagnostics, StepDiagnostics) and not filt.diagnostics
    u = torch.zeros(mix.batch_shape + (3,), dtype=torch.float64)
    mix = filt.predict(mix, u, 0.1)
    assert isinstance(filt.diagnostics, StepDiagnostics)
    assert set(filt.diagnostics) == set(filt.diagnostic_keys("predict"))
    filt.update(mix, y, meas)
    d = filt.diagnostics
    assert isinstance(d, StepDiagnostics) and set(d) == set(filt.diagnostic_keys("update"))
    assert len(repr(d).splitlines()) == len(d)
    words = _line(d, "log_likelihood")
    assert words[1:3] == ["[4]", "float64"]
    # printed to 3 significant digits (`.3g`): off by at most half a unit of the third, 5e-3 of the value
    mean = float(d["log_likelihood"].mean())
    assert_within(float(words[6]), mean, 5e-3 * abs(mean), "printed mean of the log-likelihood")
