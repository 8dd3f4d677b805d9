"""The attitude physics is written once (:mod:`agsf_torch.attitude.physics`): the generic model's methods, the
star-vector measurement, :mod:`agsf_torch.rotations` and the fused kernels all evaluate its functions."""

from __future__ import annotations

import pytest
import torch

from agsf_torch import rotations
from agsf_torch.attitude import physics
from agsf_torch.fused.algebra import as_entries, as_tensor
from agsf_torch.fused.lanes import run_in_chunks
from agsf_torch.fused.propagation import propagation_kernel
from agsf_torch.fused.star_update import fused_star_update
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from tests.helpers import F64, assert_within, random_mrps, random_spd, random_unit_vectors

EPS = torch.finfo(F64).eps


def _spy(monkeypatch, name: str) -> list:
    """Record every call of ``physics.<name>`` (the function stays what it is)."""
    calls, real = [], getattr(physics, name)
    monkeypatch.setattr(physics, name, lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


@pytest.mark.parametrize("n", [3, 6])
def test_the_model_and_its_kernel_evaluate_one_drift(gen, monkeypatch, n):
    calls = _spy(monkeypatch, "mrp_rate")
    model = AttitudeModel(estimate_bias=n == 6)
    x = torch.cat((random_mrps(4, gen), 1e-5 * torch.ones(4, 3, dtype=F64)), -1)[:, :n]
    u = 1e-2 * torch.randn(4, 3, generator=gen, dtype=F64)
    model.drift(x, u)
    assert calls, "the model's drift does not come from physics.mrp_rate"
    calls.clear()
    P = 1e-4 * random_spd(gen, 4, n=n)
    shared = (torch.tensor(0.1, dtype=F64), model.sigma_v**2, model.sigma_u**2)
    run_in_chunks(propagation_kernel(1), (x, P, u), shared=shared)
    assert calls, "the fused propagation does not come from physics.mrp_rate"


def test_the_measurement_its_kernel_and_rotations_evaluate_one_attitude_matrix(gen, monkeypatch):
    calls = _spy(monkeypatch, "attitude_matrix")
    p = random_mrps(8, gen)
    rotations.mrp_to_dcm(p)
    assert calls
    calls.clear()
    r = random_unit_vectors(gen, 8, 4)
    meas = StarVectorMeasurement(r, sigma=1e-4)
    y = meas.predict(p)
    assert calls
    calls.clear()
    fused_star_update(torch.zeros(8, 1, dtype=F64), p[:, None], 1e-4 * random_spd(gen, 8, 1), y, meas)
    assert calls


def test_the_closed_forms_hold_their_identities(gen):
    """``BBᵀ = (1 + s)²I``, ``gQgᵀ`` of the noise gain and density, ``E = 4Bᵀ/(1 + s)²`` and ``Hⱼ = [bⱼ×]E``
    against ``C(p + δ)r`` by central differences, on the entries of batched tensors (:func:`as_entries`)."""
    p = random_mrps(500, gen, max_norm=1.3)
    x = torch.cat((p, 1e-4 * torch.ones_like(p)), -1)
    s = (p * p).sum(-1)[:, None, None]
    B = as_tensor(physics.kinematics_matrix(as_entries(p, (3,))))
    eye = torch.eye(3, dtype=F64)
    assert_within(B @ B.transpose(-1, -2), (1 + s) ** 2 * eye, 32 * EPS * (1 + s) ** 2, "B Bᵀ")
    sv2, su2 = torch.tensor(4.0, dtype=F64), torch.tensor(9.0, dtype=F64)
    g = as_tensor(physics.noise_gain(as_entries(x, (6,))))
    Q = as_tensor(physics.noise_psd(sv2, su2, 6), like=x)
    G = as_tensor(physics.process_noise(as_entries(x, (6,)), sv2, su2))
    assert_within(G, g @ Q @ g.transpose(-1, -2), 64 * EPS * 9.0 * (1 + s.amax()) ** 2, "g Q gᵀ")
    E = as_tensor(physics.chart_map(as_entries(p, (3,))))
    assert_within(E, 4 * B.transpose(-1, -2) / (1 + s) ** 2, 32 * EPS * 4, "E = 4Bᵀ/(1 + s)²")
    r = as_entries(random_unit_vectors(gen, 500, 1)[:, 0], (3,))
    pe = as_entries(p, (3,))
    H = as_tensor(physics.star_jacobian(physics.star_vector(physics.attitude_matrix(pe), r), physics.chart_map(pe)))
    h = 1e-6
    for k in range(3):
        d = torch.zeros(3, dtype=F64)
        d[k] = h
        plus = as_tensor(physics.star_vector(physics.attitude_matrix(as_entries(p + d, (3,))), r))
        minus = as_tensor(physics.star_vector(physics.attitude_matrix(as_entries(p - d, (3,))), r))
        # central differences: truncation O(h²|∂³h|) with |∂³(Cr)/∂p³| ≤ 10³ here, rounding O(ε/h)
        assert_within(H[..., k], (plus - minus) / (2 * h), 1e3 * h * h + 1e2 * EPS / h, f"H column {k}")


def test_the_rate_derivatives_are_those_of_the_rate_and_the_divergence(gen):
    """``f_p = ¼B(p)ω`` and ``div f = (3/2)pᵀω`` are linear in ``ω``: :func:`physics.rate_derivatives` times ``ω``
    gives both, to a few roundings of terms of size ``(1 + |p|)²|ω|``."""
    p = random_mrps(500, gen, max_norm=1.3)
    w = torch.randn(500, 3, generator=gen, dtype=F64)
    pe, we = as_entries(p, (3,)), as_entries(w, (3,))
    B4, grad = (as_tensor(v) for v in physics.rate_derivatives(pe))
    terms = physics.fokker_planck_terms(pe, we, 1.0)
    scale = (1 + p.norm(dim=-1, keepdim=True)) ** 2 * w.norm(dim=-1, keepdim=True)
    assert_within((B4 @ w[..., None])[..., 0], as_tensor(terms["rate"]), 16 * EPS * scale, "¼B(p)ω")
    assert_within((grad * w).sum(-1), as_tensor(terms["divergence"]), 16 * EPS * scale[..., 0], "(3/2)pᵀω")


def test_both_bias_block_routes_evaluate_the_rate_derivatives(gen, monkeypatch):
    """The batched bias block (:mod:`agsf_torch.models.attitude_bias_block`) and the pair kernel on lanes take
    ``¼B(p)`` and ``(3/2)p`` from :func:`physics.rate_derivatives`, not a copy of their own."""
    from agsf_torch.fpke.pairs import product_gaussians
    from agsf_torch.fused.pair_products import attitude_pair_products as on_lanes
    from agsf_torch.models.attitude_bias_block import attitude_pair_products as batched
    from tests.fpke.test_exactness import _random_rates

    calls = _spy(monkeypatch, "rate_derivatives")
    model = AttitudeModel(estimate_bias=True)
    rates, u = _random_rates(model, 2, 3, gen, (-4.0, -2.0))
    prod = product_gaussians(rates.with_precision())
    batched(model, u, prod)
    assert calls, "the batched bias block does not come from physics.rate_derivatives"
    calls.clear()
    on_lanes(prod, u, model.sigma_v, model.sigma_u)
    assert calls, "the pair kernel on lanes does not come from physics.rate_derivatives"
