"""The filter loop: its first step compiles the fused kernels it needs when first called, with no rehearsal."""

from __future__ import annotations

import torch

from agsf_torch.filter_loop import StepInput, filter_steps
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


def test_kernels_compile_when_first_called_in_the_real_step_and_never_again(gen, monkeypatch, tmp_path):
    """No rehearsal: a filter that compiles its fused kernels compiles each when the loop's first step first calls it
    (the propagation's, then the update's), in this process, and later steps load nothing again; the filter itself
    runs once per step (its diagnostics are the real step's)."""
    from agsf_torch import compiled_kernels

    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(lanes, "_COMPILED", {})
    compiled = []

    def fake_compile(kernel, inputs, shared, path, serial, threads=None):
        compiled.append(compiled_kernels.kernel_name(kernel) + (" (serial)" if serial else ""))
        path.write_bytes(b"package")
        fake_compile.kernels[path] = kernel

    fake_compile.kernels = {}
    monkeypatch.setattr(compiled_kernels, "compile_ahead_of_time", fake_compile)
    monkeypatch.setattr(compiled_kernels, "load_package", lambda path: fake_compile.kernels[path])
    model, mixture, step = _first_step(gen)
    filt = make_filter("GSF", model, compile_fused=True)
    steps = list(filter_steps({"GSF": filt}, {"GSF": mixture}, [step, step, StepInput(0.1, step.u)]))
    assert len(steps) == 3
    assert compiled == ["attitude_propagation_kernel (serial)", "star_kernel (serial)"]  # 512 lanes: serial variants
    assert bool(torch.isfinite(steps[-1].filters["GSF"].mixture.means).all())


def test_no_inputs_no_steps(gen):
    model, mixture, _ = _first_step(gen, B=4)
    assert list(filter_steps({"GSF": make_filter("GSF", model)}, {"GSF": mixture}, [])) == []
