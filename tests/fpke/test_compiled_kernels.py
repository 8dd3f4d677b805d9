"""A generic model's FPKE node kernels compiled ahead of time (agsf_torch.fpke.matrices through
agsf_torch.compiled_kernels.compiled_function): keyed by the exported graph, exported once per process, model and
shape, announced, and eager where they cannot be compiled.

No test compiles: the package is stood in for by the exported program itself (``program.module()``), so these tests
check the export, the keys and the fallbacks, and the exported graph's numbers against the eager kernel's."""

from __future__ import annotations

import logging

import pytest
import torch

from agsf_torch import compiled_kernels
from agsf_torch.fpke import ComponentRates, fpke_matrix
from agsf_torch.models.benchmarks import LorenzModel
from agsf_torch.propagation import moment_derivatives
from agsf_torch.quadrature import gauss_hermite
from tests.helpers import F64, assert_within, relative_bound


@pytest.fixture
def packages(monkeypatch, tmp_path) -> dict:
    """A kernel cache in ``tmp_path`` whose "compiler" keeps the exported program (path → program) and whose loader
    runs it."""
    programs: dict = {}

    def package(program, path, threads):
        programs[path] = program
        path.write_bytes(b"package")

    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(compiled_kernels, "package_program", package)
    monkeypatch.setattr(compiled_kernels, "load_package", lambda path: lambda *t: tuple(programs[path].module()(*t)))
    monkeypatch.setattr(compiled_kernels, "_BY_GRAPH", {})
    return programs


def _problem(gen, model):
    N = 3
    mean = torch.randn(2, N, 3, generator=gen, dtype=F64)
    A = torch.randn(2, N, 3, 3, generator=gen, dtype=F64)
    cov = 0.1 * (A @ A.transpose(-1, -2) + torch.eye(3, dtype=F64))
    r = moment_derivatives(model, mean, cov, None)
    rates = ComponentRates(mean, torch.linalg.cholesky(cov), r.mean_rate, r.cov_rate)
    return rates, gauss_hermite(3, 3)  # 27 nodes: chunks of 10 leave a tail of 7, padded


def _matrix(model, rates, rule, compile):
    return fpke_matrix(model, None, rates, *rule, chunk_size=10, compile=compile).scaled


def test_the_exported_kernel_gives_the_eager_numbers_and_is_announced_once(gen, packages, caplog):
    model = LorenzModel()
    rates, rule = _problem(gen, model)
    eager = _matrix(model, rates, rule, False)
    caplog.set_level(logging.INFO, logger="agsf_torch")
    compiled = _matrix(model, rates, rule, True)
    messages = [r.getMessage() for r in caplog.records]
    assert len(packages) == 1 and len(messages) == 2, messages
    assert messages[0].startswith("compiling the kernel 'fpke_pair' ahead of time")
    assert messages[1].startswith("compiled the kernel 'fpke_pair' in ")
    # the same operations traced: rounding of the re-associated sums only, relative to each matrix's largest entry
    bound = relative_bound(eager, 64 * torch.finfo(F64).eps, 64 * torch.finfo(F64).eps * float(eager.abs().max()))
    assert_within(compiled, eager, bound, "exported pair kernel against eager")
    caplog.clear()
    _matrix(model, rates, rule, True)  # the same model and shapes: the process's memo, nothing exported again
    assert caplog.records == [] and len(packages) == 1


def test_the_package_follows_the_graph_not_the_models_tensor_values(gen, packages, monkeypatch):
    """The model's tensors are inputs of the compiled kernel: new noise values reuse its package and give their own
    numbers; a changed constant of the physics (a float attribute, baked into the graph) is a new package."""
    model = LorenzModel()
    rates, rule = _problem(gen, model)
    _matrix(model, rates, rule, True)
    louder = LorenzModel(Q=(2.0, 3.0, 5.0))
    monkeypatch.setattr(compiled_kernels, "_BY_GRAPH", {})  # a new process
    compiled = _matrix(louder, rates, rule, True)
    assert len(packages) == 1
    eager = _matrix(louder, rates, rule, False)
    bound = relative_bound(eager, 64 * torch.finfo(F64).eps, 64 * torch.finfo(F64).eps * float(eager.abs().max()))
    assert_within(compiled, eager, bound, "the package run with another model's noise")
    _matrix(LorenzModel(rho=20.0), rates, rule, True)
    assert len(packages) == 2


def test_a_kernel_that_cannot_be_exported_runs_eagerly_after_one_warning(gen, packages):
    class Branching(LorenzModel):
        def fokker_planck_terms(self, x, u):
            if bool((x[..., 0] > 1e9).any()):  # data-dependent control flow: not exportable
                raise AssertionError("unreachable")
            return super().fokker_planck_terms(x, u)

    model = Branching()
    rates, rule = _problem(gen, model)
    with pytest.warns(RuntimeWarning, match="'pair' of Branching could not be compiled") as caught:
        compiled = _matrix(model, rates, rule, True)
    assert len(caught) == 1 and not packages
    eager = _matrix(model, rates, rule, False)  # the same kernel eagerly; its last chunk padded with zero weights
    bound = relative_bound(eager, 64 * torch.finfo(F64).eps, 64 * torch.finfo(F64).eps * float(eager.abs().max()))
    assert_within(compiled, eager, bound, "the declined kernel run eagerly")
    _matrix(model, rates, rule, True)  # declined from then on, without another warning


def test_a_call_that_needs_gradients_runs_eagerly(gen, packages):
    model = LorenzModel()
    rates, rule = _problem(gen, model)
    means = rates.means.clone().requires_grad_(True)
    rates = ComponentRates(means, rates.chol, rates.mean_rates, rates.cov_rates)
    _matrix(model, rates, rule, True).sum().backward()
    assert not packages and means.grad is not None
