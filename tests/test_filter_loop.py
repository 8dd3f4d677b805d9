"""The filter loop's first step: the fused kernels it needs compiled side by side (prepare_fused_kernels)."""

from __future__ import annotations

import torch

import agsf_torch.filter_loop as filter_loop
from agsf_torch.filter_loop import StepInput, filter_steps, prepare_fused_kernels
from agsf_torch.filters.registry import make_filter
from agsf_torch.fused import lanes
from agsf_torch.mixture import GaussianMixture
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from tests.helpers import F64, random_mrps, random_spd, random_unit_vectors


def _first_step(gen, B=256, N=2):
    model = AttitudeModel(estimate_bias=True)
    means = torch.cat((0.2 * random_mrps(B * N, gen).reshape(B, N, 3), torch.zeros(B, N, 3, dtype=F64)), -1)
    mixture = GaussianMixture(
        means=means, covs=random_spd(gen, B, N, n=6, scale=1e-4), weights=torch.ones(B, N, dtype=F64)
    )
    r = random_unit_vectors(gen, 4)
    y = (r.reshape(-1) + 1e-3 * torch.randn(B, 12, generator=gen, dtype=F64)).reshape(B, 4, 3)
    y = (y / y.norm(dim=-1, keepdim=True)).reshape(B, 12)
    u = torch.full((B, 3), 0.01, dtype=F64)
    return model, mixture, StepInput(0.1, u, (y, StarVectorMeasurement(r, None, 1e-3)))


def test_the_rehearsal_notes_the_kernels_of_predict_and_update_and_leaves_the_filters_untouched(
    gen, monkeypatch, tmp_path
):
    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(lanes, "_COMPILED", {})
    batches = []
    monkeypatch.setattr(lanes, "_compile_pending", lambda jobs, processes: batches.append(dict(jobs)))
    model, mixture, step = _first_step(gen)
    filters = {"GSF": make_filter("GSF", model, compile_fused=True), "EKF": make_filter("EKF", model)}
    before = {name: dict(f.diagnostics) for name, f in filters.items()}
    single = GaussianMixture(
        means=mixture.means[:, :1], covs=mixture.covs[:, :1], weights=torch.ones(256, 1, dtype=F64)
    )
    prepare_fused_kernels(filters, {"GSF": mixture, "EKF": single}, step)
    (jobs,) = batches
    names = sorted(job[0] for job in jobs.values())
    assert names == ["attitude_propagation_kernel (serial)", "star_kernel (serial)"]  # 512 lanes: serial variants
    assert {name: dict(f.diagnostics) for name, f in filters.items()} == before


def test_without_a_compiling_filter_nothing_is_rehearsed(gen, monkeypatch):
    monkeypatch.setattr(filter_loop, "compiling_in_parallel", lambda: (_ for _ in ()).throw(AssertionError("entered")))
    model, mixture, step = _first_step(gen, B=4)
    prepare_fused_kernels({"GSF": make_filter("GSF", model)}, {"GSF": mixture}, step)


def test_the_loop_prepares_before_its_first_step_only(gen, monkeypatch):
    calls = []
    monkeypatch.setattr(filter_loop, "prepare_fused_kernels", lambda f, m, s: calls.append(s))
    model, mixture, step = _first_step(gen, B=4)
    steps = [step, StepInput(0.1, step.u)]
    out = list(filter_steps({"GSF": make_filter("GSF", model)}, {"GSF": mixture}, iter(steps)))
    assert calls == [step] and len(out) == 2
    assert list(filter_steps({"GSF": make_filter("GSF", model)}, {"GSF": mixture}, [])) == []


def test_a_rehearsal_that_fails_is_announced_and_the_loop_goes_on(gen, monkeypatch, caplog):
    """A filter that cannot be copied (e.g. holding tensors of an autograd graph): one warning, then the real
    steps run (their kernels compile when first called; here the eager path of a filter that compiles nothing
    is forced to look like one that does)."""
    import copy
    import logging

    monkeypatch.setattr(copy, "deepcopy", lambda x: (_ for _ in ()).throw(RuntimeError("cannot copy")))
    monkeypatch.setattr(filter_loop, "_compiles", lambda filt: True)
    caplog.set_level(logging.WARNING, logger="agsf_torch")
    model, mixture, step = _first_step(gen, B=4)
    out = list(filter_steps({"GSF": make_filter("GSF", model)}, {"GSF": mixture}, [step]))
    assert len(out) == 1 and bool(torch.isfinite(out[0].filters["GSF"].mixture.means).all())
    (warning,) = [r.getMessage() for r in caplog.records]
    assert warning.startswith("could not rehearse the first step") and "RuntimeError: cannot copy" in warning
