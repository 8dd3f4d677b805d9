"""A checkpoint records its filters' options: loaded into a filter whose options differ, it is refused naming the
option and both values, before any filter changes; only the options that choose how the same arithmetic runs (and a
diagnostics switch) may differ, and the refusal says which they are."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.filters import (
    AdaptiveGaussianSumFilter,
    ExtendedKalmanFilter,
    GalerkinWeightUpdate,
    GaussianSumFilter,
    MultiplicativeEKF,
    PenaltyWeightUpdate,
)
from agsf_torch.models import AttitudeModel
from agsf_torch.storage import checkpoint
from agsf_torch.storage.checkpoint import load_checkpoint, save_checkpoint
from tests.helpers import F64

MODEL = AttitudeModel(estimate_bias=False)
MAY_DIFFER = "fused, compile_fused, compile, chunk_size and residual_diagnostics may differ"


def _mixture(components: int) -> GaussianMixture:
    means = torch.tensor([[0.1, -0.2, 0.05], [0.0, 0.3, -0.1]], dtype=F64)
    return GaussianMixture.from_gaussian(means, 1e-6 * torch.eye(3, dtype=F64).expand(2, 3, 3), components)


def _adaptive(update_kind, model, **options):
    """An adaptive filter with ``options``, each given to its weight update or to the filter, whichever takes it."""
    fields = {f.name for f in dataclasses.fields(update_kind) if f.init}
    update = update_kind(**{k: v for k, v in options.items() if k in fields})
    return AdaptiveGaussianSumFilter(
        model, weight_update=update, **{k: v for k, v in options.items() if k not in fields}
    )


def _agsf(model, **options):
    return _adaptive(PenaltyWeightUpdate, model, **options)


def _galerkin(model, **options):
    return _adaptive(GalerkinWeightUpdate, model, **options)


#: (build a filter from options, the option, its value in the checkpoint, its value in the loading filter, how the
#: two are shown)
DIFFERENCES = [
    (_galerkin, "cadence", 2, 1, "2 in the checkpoint, 1 in this filter"),
    (_galerkin, "tikhonov", 1e-9, 1e-8, "1e-09 in the checkpoint, 1e-08 in this filter"),
    (_galerkin, "quadrature", None, 3, "None in the checkpoint, 3 in this filter"),
    (_agsf, "cadence", 1, 3, "1 in the checkpoint, 3 in this filter"),
    (_agsf, "reg", 1.0, 0.5, "1.0 in the checkpoint, 0.5 in this filter"),
    (_agsf, "scaling", "trace", "none", "'trace' in the checkpoint, 'none' in this filter"),
    (_agsf, "weight_ref", "update", "previous", "'update' in the checkpoint, 'previous' in this filter"),
    (_agsf, "quadrature", (3, 3, 3), (4, 4, 4), "(3, 3, 3) in the checkpoint, (4, 4, 4) in this filter"),
    (_agsf, "adapt", True, False, "True in the checkpoint, False in this filter"),
    (_agsf, "substeps", 1, 2, "1 in the checkpoint, 2 in this filter"),
    (_agsf, "update_iterations", 1, 3, "1 in the checkpoint, 3 in this filter"),
    (GaussianSumFilter, "gate_probability", None, 0.9999, "None in the checkpoint, 0.9999 in this filter"),
    (GaussianSumFilter, "repair_covariance", False, True, "False in the checkpoint, True in this filter"),
    (GaussianSumFilter, "min_eigenvalue", 1e-12, 1e-10, "1e-12 in the checkpoint, 1e-10 in this filter"),
    (GaussianSumFilter, "substeps", 2, 1, "2 in the checkpoint, 1 in this filter"),
    (ExtendedKalmanFilter, "update_iterations", 2, 1, "2 in the checkpoint, 1 in this filter"),
    (
        MultiplicativeEKF,
        "discrete_noise",
        "farrenkopf",
        "exact",
        "'farrenkopf' in the checkpoint, 'exact' in this filter",
    ),
    (MultiplicativeEKF, "covariance_reset", False, True, "False in the checkpoint, True in this filter"),
]


def _components(build) -> int:
    return 1 if build in (ExtendedKalmanFilter, MultiplicativeEKF) else 3


@pytest.mark.parametrize(
    ("build", "option", "saved", "loading", "shown"),
    DIFFERENCES,
    ids=[f"{getattr(b, '__name__', b)}-{o}" for b, o, *_ in DIFFERENCES],
)
def test_a_checkpoint_of_other_options_is_refused_naming_the_option_and_both_values(
    tmp_path, build, option, saved, loading, shown
):
    path = save_checkpoint(
        tmp_path / "ck.pt", {"f": _mixture(_components(build))}, {"f": build(MODEL, **{option: saved})}
    )
    target = build(MODEL, **{option: loading})
    if isinstance(target, AdaptiveGaussianSumFilter):  # a run under way: it must be left as it was
        target.weight_update.run.step, target.weight_update.run.elapsed = 5, 0.25
    before = target.state_dict()
    with pytest.raises(ValueError) as refused:
        load_checkpoint(path, {"f": target})
    message = str(refused.value)
    assert message.startswith(f"{path}: filter 'f': {option} is {shown}"), message
    assert MAY_DIFFER in message
    assert target.state_dict() == before


def test_every_difference_is_named(tmp_path):
    path = save_checkpoint(tmp_path / "ck.pt", {"f": _mixture(3)}, {"f": _galerkin(MODEL, cadence=2, tikhonov=1e-8)})
    with pytest.raises(ValueError, match=r"cadence is 2 in the checkpoint, 1 in this filter; tikhonov is 1e-08"):
        load_checkpoint(path, {"f": _galerkin(MODEL)})


def test_the_options_of_another_filter_kind_are_named(tmp_path):
    """A multiplicative EKF's checkpoint into an EKF (one component each, neither keeping run state)."""
    path = save_checkpoint(tmp_path / "ck.pt", {"f": _mixture(1)}, {"f": MultiplicativeEKF(MODEL)})
    with pytest.raises(ValueError) as refused:
        load_checkpoint(path, {"f": ExtendedKalmanFilter(MODEL)})
    message = str(refused.value)
    assert "filter 'f': discrete_noise is 'farrenkopf' in the checkpoint, absent in this filter; " in message
    assert "covariance_reset is False in the checkpoint, absent in this filter; " in message
    assert "substeps is absent in the checkpoint, 1 in this filter: " in message


@pytest.mark.parametrize(
    ("build", "saved", "loading"),
    [
        (_galerkin, {"compile": True, "chunk_size": 64}, {"compile": False, "chunk_size": None}),
        (_galerkin, {"residual_diagnostics": True}, {"residual_diagnostics": False}),
        (_agsf, {"fused": False, "compile_fused": True}, {"fused": True, "compile_fused": False}),
        (GaussianSumFilter, {"fused": True}, {"fused": False}),
    ],
)
def test_the_options_that_choose_how_the_arithmetic_runs_may_differ(tmp_path, build, saved, loading):
    """Compiled or eager, fused or generic, chunked or not: the same numbers to rounding (a resumed run is bit for bit
    only with the same options); the residual diagnostics change no number."""
    saving = build(MODEL, **saved)
    path = save_checkpoint(tmp_path / "ck.pt", {"f": _mixture(3)}, {"f": saving})
    target = build(MODEL, **loading)
    mixtures, _ = load_checkpoint(path, {"f": target})
    assert target.state_dict() == saving.state_dict() and torch.equal(mixtures["f"].means, _mixture(3).means)


def test_a_tensor_option_is_compared_by_value(tmp_path):
    """A learned λ is a 0-d tensor: the same value as a number is the same option; a quadrature rule given as nodes
    and weights is compared entry by entry."""
    nodes, weights = torch.zeros(1, 3, dtype=F64), torch.ones(1, dtype=F64)
    saving = _agsf(MODEL, reg=torch.tensor(0.5, dtype=F64, requires_grad=True), quadrature=(nodes, weights))
    path = save_checkpoint(tmp_path / "ck.pt", {"f": _mixture(3)}, {"f": saving})
    load_checkpoint(path, {"f": _agsf(MODEL, reg=0.5, quadrature=(nodes.clone(), weights.clone()))})
    shown = (
        r"quadrature is \(tensor\(\[\[0.0, 0.0, 0.0\]\]\), tensor\(\[1.0\]\)\) in the checkpoint, "
        r"\(tensor\(\[\[1.0, 1.0, 1.0\]\]\), tensor\(\[1.0\]\)\) in this filter"
    )
    with pytest.raises(ValueError, match=shown):
        load_checkpoint(path, {"f": _agsf(MODEL, reg=0.5, quadrature=(nodes + 1, weights))})


def test_a_checkpoint_of_the_format_before_options_loads_with_a_warning_naming_it(tmp_path):
    saving = _galerkin(MODEL, cadence=2)
    path = save_checkpoint(tmp_path / "old.pt", {"f": _mixture(3)}, {"f": saving})
    state = torch.load(path, weights_only=True)
    state["format"] = "agsf-checkpoint-2"
    del state["filters"]["f"]["options"]
    torch.save(state, path)
    target = _galerkin(MODEL, cadence=2)
    with pytest.warns(RuntimeWarning, match=r"old\.pt records no filter options .*agsf-checkpoint-2"):
        load_checkpoint(path, {"f": target})
    assert checkpoint.FORMAT != "agsf-checkpoint-2"
