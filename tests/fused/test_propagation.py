"""The fused attitude propagation against the generic one (:func:`agsf_torch.propagation.propagate_moments`).

Both evaluate the same RK4 (μ, Φ, S) step and congruence in a different order, so they agree to
the rounding of that arithmetic: an entry of ``ΦPΦᵀ`` is a sum of ``n²`` products, which rounds to
``γ = (2n² + 8)ε`` of ``‖Φ‖²‖P‖`` (``‖Φ‖ ≤ e^{dt‖A‖}``), and RK4 on ``μ`` to a few tens of ε of
``‖μ‖``; the tolerances below are 8× those bounds, whatever the conditioning of ``P``.
"""

from __future__ import annotations

import math

import pytest
import torch

from agsf_torch.fused.lanes import run_in_chunks
from agsf_torch.fused.propagation import propagation_kernel
from agsf_torch.models import AttitudeModel
from agsf_torch.propagation import propagate_moments
from tests.helpers import F64, assert_within, random_mrps

EPS = torch.finfo(F64).eps


def _problem(gen, C, n, condition, rate):
    p = random_mrps(C, gen, max_norm=1.0)
    mean = torch.cat((p, 1e-5 * torch.randn(C, 3, generator=gen, dtype=F64)), -1)[:, :n]
    Q, _ = torch.linalg.qr(torch.randn(C, n, n, generator=gen, dtype=F64))
    eig = torch.logspace(0, -math.log10(condition), n, dtype=F64) * 1e-3  # spread `condition`
    cov = Q @ torch.diag_embed(eig.expand(C, n)) @ Q.transpose(-1, -2)
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    u = rate * torch.randn(C, 3, generator=gen, dtype=F64) / math.sqrt(3.0)
    return mean, cov, u


@pytest.mark.parametrize("n", [3, 6])
@pytest.mark.parametrize("substeps", [1, 3])
@pytest.mark.parametrize(
    ("C", "condition", "dt", "rate"),
    [(1, 1e3, 0.1, 0.1), (5, 1e12, 1e-3, 1.0), (4097, 1e6, 1.0, 0.5), (10_001, 1e12, 0.1, 1.0)],
)
def test_fused_propagation_equals_the_generic_one(gen, n, substeps, C, condition, dt, rate):
    model = AttitudeModel(estimate_bias=n == 6, bias=torch.tensor([1e-6, -2e-6, 3e-6]))
    mean, cov, u = _problem(gen, C, n, condition, rate)
    want_m, want_P = propagate_moments(model, mean, cov, u, dt, substeps)
    rate_u = u if n == 6 else u - model.bias
    shared = (torch.tensor(dt, dtype=F64), model.sigma_v**2, model.sigma_u**2)
    got_m, got_P, ok = run_in_chunks(propagation_kernel(substeps), (mean, cov, rate_u), shared=shared)
    phi = math.exp(dt * (rate + 1.0))  # ‖Φ‖ ≤ e^{dt‖A‖}, ‖A‖ ≤ |ω| + ½|B| with |p| ≤ 1
    tol_P = 8 * (2 * n * n + 8) * EPS * phi**2
    assert_within(got_P, want_P, tol_P * want_P.abs().amax((-1, -2), keepdim=True), "propagated covariance")
    tol_m = 8 * 64 * EPS * substeps
    assert_within(got_m, want_m, tol_m * want_m.abs().amax(-1, keepdim=True), "propagated mean")
    assert torch.equal(got_P, got_P.transpose(-1, -2)) and bool(ok.all())


def test_the_model_declares_its_fused_path_and_declines_small_eager_batches(gen):
    model = AttitudeModel(estimate_bias=True)
    mean, cov, u = _problem(gen, 2000, 6, 1e6, 0.1)
    fused = model.fused_propagation(mean, cov, u, 0.1)
    want = propagate_moments(model, mean, cov, u, 0.1)
    assert fused is not None
    # the module docstring's bound (|ω| ≈ 0.1 rad/s here), not the 1e-15·max|P| one machine met
    tol_P = 8 * (2 * 6 * 6 + 8) * EPS * math.exp(0.1 * (0.1 + 1.0)) ** 2
    assert_within(fused[1], want[1], tol_P * want[1].abs().amax((-1, -2), keepdim=True), "covariance on the fused path")
    assert model.fused_propagation(mean[:5], cov[:5], u[:5], 0.1) is None  # eager and small: generic is faster


def test_the_definiteness_flag_marks_a_covariance_that_is_not_positive_definite(gen):
    model = AttitudeModel(estimate_bias=False)
    mean, cov, u = _problem(gen, 3, 3, 1e3, 0.1)
    cov[1] = -cov[1]
    shared = (torch.tensor(0.1, dtype=F64), model.sigma_v**2, model.sigma_u**2)
    _, _, ok = run_in_chunks(propagation_kernel(1), (mean, cov, u), shared=shared)
    assert ok.tolist() == [True, False, True]


@pytest.mark.slow
@pytest.mark.parametrize("n", [3, 6])
def test_the_compiled_kernel_equals_the_eager_one(gen, n):
    """torch.compile of the same kernel (fixed chunk sizes, the tail padded): the same numbers to rounding."""
    model = AttitudeModel(estimate_bias=n == 6)
    mean, cov, u = _problem(gen, 4096 + 70, n, 1e9, 0.5)
    shared = (torch.tensor(0.1, dtype=F64), model.sigma_v**2, model.sigma_u**2)
    eager = run_in_chunks(propagation_kernel(1), (mean, cov, u), shared=shared)
    compiled = run_in_chunks(propagation_kernel(1), (mean, cov, u), shared=shared, compile=True)
    tol = 8 * (2 * n * n + 8) * EPS * math.exp(0.2) ** 2
    for a, b, what in zip(compiled[:2], eager[:2], ("mean", "covariance")):
        scale = b.abs().flatten(1).amax(-1).reshape(-1, *[1] * (b.dim() - 1))
        assert_within(a, b, tol * scale, f"compiled propagation's {what}")
    assert torch.equal(compiled[2], eager[2])
