"""Every tensor the filters, the loop and the runner create follows its inputs' device and dtype.

A float32 run through the filter loop stays float32 (a hard-coded float64 constant would
promote it), and no tensor factory in the core is called without ``device=`` (a hard-coded CPU
tensor would break a CUDA run; this machine has no GPU, so the rule is checked in the source).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

import agsf_torch
from agsf_torch import GaussianMixture
from agsf_torch.filter_loop import StepInput, filter_steps
from agsf_torch.filters.registry import FILTER_NAMES, filter_spec, make_filter
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.rotations import mrp_to_dcm
from tests.helpers import random_mrps, random_unit_vectors

#: Modules of the estimator core whose tensors must follow their inputs.
CORE = [
    "filters",
    "filter_loop.py",
    "experiments/run/runner.py",
    "propagation.py",
    "update.py",
    "gating.py",
    "mixture.py",
    "fpke",
    "qp.py",
    "consistency.py",
]
#: Factories that create a tensor from nothing (their device must be given).
FACTORIES = {"zeros", "ones", "eye", "full", "empty", "arange", "linspace", "randn", "rand"}


@pytest.mark.parametrize("estimate_bias", [False, True])
@pytest.mark.parametrize("name", FILTER_NAMES)
def test_a_float32_run_through_the_loop_stays_float32(gen, name, estimate_bias):
    dtype = torch.float32
    model = AttitudeModel(estimate_bias=estimate_bias)
    filt = make_filter(name, model, gate_probability=0.9999)
    B, n = 4, model.state_dim
    p = random_mrps(B, gen, max_norm=0.5)
    mean = torch.cat((p, torch.zeros(B, 3, dtype=p.dtype)), -1)[:, :n].to(dtype)
    cov = torch.diag(torch.tensor([1e-4] * 3 + [1e-10] * 3)[:n]).to(dtype).expand(B, n, n)
    mixture = GaussianMixture.from_gaussian(mean, cov, 3 if filter_spec(name).mixture else 1)
    r = random_unit_vectors(gen, B, 5).to(dtype)
    y = (mrp_to_dcm(p).to(dtype).unsqueeze(1) @ r.unsqueeze(-1)).squeeze(-1).reshape(B, 15)
    u = torch.full((B, 3), 0.01, dtype=dtype)
    steps = [StepInput(0.1, u), StepInput(0.1, u, (y, StarVectorMeasurement(r, None, 1e-3)))]
    for step in filter_steps({name: filt}, {name: mixture}, steps):
        out = step.filters[name]
        tensors = {
            "means": out.mixture.means,
            "covs": out.mixture.covs,
            "log_weights": out.mixture.log_weights,
            "mean": out.mean,
            "cov": out.cov,
            "nis": out.nis,
            "dof": out.dof,
            **out.extra,
        }
        tensors.update({f"diagnostics/{k}": v for k, v in filt.diagnostics.items() if torch.is_tensor(v)})
        wrong = {k: v.dtype for k, v in tensors.items() if v.is_floating_point() and v.dtype != dtype}
        assert not wrong, wrong


def _factory_calls_without_device(path: Path) -> list[str]:
    source = path.read_text()
    found = []
    for node in ast.walk(ast.parse(source)):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in FACTORIES
            and isinstance(node.func.value, ast.Name)
            and node.func.value.id == "torch"
            and "device" not in {k.arg for k in node.keywords}
        ):
            found.append(f"{path}:{node.lineno}: {ast.get_source_segment(source, node)}")
    return found


def test_no_tensor_factory_in_the_core_is_called_without_a_device():
    root = Path(agsf_torch.__file__).parent
    files = [f for entry in CORE for f in ((root / entry).rglob("*.py") if (root / entry).is_dir() else [root / entry])]
    assert len(files) > len(CORE)  # the entries exist (a renamed module must be renamed here too)
    offenders = [line for f in files for line in _factory_calls_without_device(f)]
    assert not offenders, "\n".join(offenders)
