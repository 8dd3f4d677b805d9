"""The penalty update's ``E[ℓᵢℓⱼ]`` on lanes (:mod:`agsf_torch.fused.pair_products`) against the batched routes.

Both routes evaluate the same values at the same 84 MRP nodes per pair (6 states: the ten Hermite
coefficients in ``ξ_b`` of the closed-form bias block, :mod:`agsf_torch.fpke.bias_block`; 3 states: ``ℓ``
itself, the generic interpolatory rule) in a different order, and contract them as ``Σ_c vᵢ,cᵀWvⱼ,c``
(``W = TᵀT``).  A value sums at most ``k = 2n² + 4n + 8`` rounded products, each no larger than ``T``, the sum
of the magnitudes of ``ℓ``'s terms at the node (:func:`_node_term_scale`; 6 states: three times its largest
value over the 3³ Gauss–Hermite bias nodes, the coefficients being combinations of ``ℓ`` there with weights
≤ 3), so it rounds by ``≤ kεT``; the two routes' contractions then differ by at most
``(4kε + Kε)·C·Tᵢᵀ|W|Tⱼ`` (``K = 84`` nodes, ``C`` channels), times ``z̃_ij`` as ``L̃`` is scaled.  At
covariance conditions of 10¹² ``ℓ``'s terms are 10¹² times ``L̃``'s entries: the bound follows them.
"""

from __future__ import annotations

import math

import pytest
import torch

import agsf_torch.fused.pair_products as pair_products
from agsf_torch.fpke import fpke_matrix, fused_fpke_matrix
from agsf_torch.fpke.pairs import product_gaussians
from agsf_torch.fpke.rules import residual_rule
from agsf_torch.models import AttitudeModel
from agsf_torch.quadrature import gauss_hermite
from tests.fused.test_galerkin import _components

EPS = torch.finfo(torch.float64).eps


def _node_term_scale(model, u, comp) -> tuple[torch.Tensor, torch.Tensor]:
    """``T`` of both sides at the 84 MRP nodes ``[2, B, P, 84]`` (module docstring) and ``z̃_ij`` ``[B, P]``."""
    prod = product_gaussians(comp.with_precision())
    nodes, _ = pair_products._mrp_nodes_and_weights(torch.float64, torch.device("cpu"))
    if model.estimate_bias:
        xb, _ = gauss_hermite(3, 3)
        xi = torch.cat((nodes[:, None, :].expand(-1, 27, 3), xb[None].expand(84, -1, 3)), -1)  # [84, 27, 6]
    else:
        xi = nodes[:, None, :]
    x = prod.mean[..., None, None, :] + xi @ prod.chol[..., None, :, :].transpose(-1, -2)  # [B, P, 84, G, n]
    t = model.fokker_planck_terms(x, u[:, None, None, None, :])
    a = torch.abs
    out = []
    for s in (prod.first, prod.second):
        z = a((x - s.means[..., None, None, :]) @ s.precision[..., None, :, :])
        per_axis = a(s.mean_rates)[..., None, None, :] + a(t.drift) + 2 * a(t.diffusion_divergence)
        per_axis = per_axis + 0.5 * z @ a(s.cov_rates)[..., None, :, :] + a(t.diffusion) * z
        T = (z * per_axis).sum(-1) + (
            a(t.diffusion) * a(s.precision.diagonal(dim1=-2, dim2=-1))[..., None, None, :]
        ).sum(-1)
        T = T + a(t.drift_divergence) + a(t.diffusion_second_divergence)
        T = T + 0.5 * (a(s.precision) * a(s.cov_rates)).sum((-1, -2))[..., None, None]
        out.append(T.amax(-1) * (3.0 if model.estimate_bias else 1.0))
    return torch.stack(out), torch.exp(prod.log_z - prod.log_z.amax(-1, keepdim=True))


def _assert_agree(got, want, model, u, comp):
    """``L̃`` of two routes agree entry by entry to the bound of the module docstring."""
    n = model.state_dim
    T, z = _node_term_scale(model, u, comp)
    _, W = pair_products._mrp_nodes_and_weights(torch.float64, torch.device("cpu"))
    channels = 10 if n == 6 else 1
    k = 2 * n * n + 4 * n + 8
    # z̃ last (it may be subnormal), and the subnormals' absolute spacing 2⁻¹⁰⁷⁴ for the product z̃·E itself
    bound = ((4 * k + 84) * EPS * channels * ((T[0] @ W.abs()) * T[1]).sum(-1)) * z + 16 * 2.0**-1074  # [B, P]
    i, j = torch.triu_indices(comp.means.shape[-2], comp.means.shape[-2])
    torch.testing.assert_close(got.log_scale, want.log_scale, rtol=0, atol=0)  # the same product Gaussians
    assert bool(((got.scaled - want.scaled)[..., i, j].abs() <= bound).all())


def _assert_agree_from_components(got, want, model, u, comp):
    """``L̃`` of :func:`fused_fpke_matrix` (product Gaussians, rates and precisions formed on lanes) and of a route
    given the batched product Gaussians agree to the bound of the module docstring widened by the conditioning of
    what the first forms itself: the solves with ``Σ = Pᵢ + Pⱼ`` and the factorisations of ``Pᵢ``, ``Pⱼ`` and ``S``
    are backward stable, so ``m``, ``S`` and its factor, the rates and ``Π`` agree to ``O(κε)`` relative and every
    term of ``ℓ`` at a node to ``O(κε)`` of the terms' magnitudes ``T``; ``log z`` as in :mod:`tests.fused.test_galerkin`
    (``dᵀΣ⁻¹d`` to ``κ(Σ)ε`` of itself, ``log det Σ`` to ``nκ(Σ)ε``), which scales ``L̃`` by ``z̃ = exp(log z − max)``."""
    n = model.state_dim
    T, z = _node_term_scale(model, u, comp)
    _, W = pair_products._mrp_nodes_and_weights(torch.float64, torch.device("cpu"))
    prod = product_gaussians(comp.with_precision())
    Sigma = prod.first.covs + prod.second.covs
    kappa = torch.linalg.cond(Sigma) + torch.linalg.cond(prod.first.covs) + torch.linalg.cond(prod.second.covs)
    kappa = kappa + torch.linalg.cond(prod.cov)
    maha = (prod.y * (prod.first.means - prod.second.means)).sum(-1).abs()
    log_det = torch.linalg.slogdet(Sigma)[1].abs()
    tol_log_z = 64 * EPS * (n * kappa + log_det + kappa * maha + n * math.log(2 * math.pi))  # [B, P]
    tol_scale = tol_log_z.amax(-1)
    assert bool(((got.log_scale - want.log_scale).abs() <= tol_scale).all())
    channels = 10 if n == 6 else 1
    k = 2 * n * n + 4 * n + 8
    terms = (4 * k + 84 + 64 * kappa) * EPS * channels * ((T[0] @ W.abs()) * T[1]).sum(-1)
    i, j = torch.triu_indices(comp.means.shape[-2], comp.means.shape[-2])
    ref = want.scaled[..., i, j]
    bound = terms * z + 2 * ref.abs() * (tol_log_z + tol_scale[..., None]) + 16 * 2.0**-1074
    assert bool(((got.scaled - want.scaled)[..., i, j].abs() <= bound).all())


def _batched(model, u, comp):
    """``L̃`` by the batched route: the closed-form bias block (6 states) or the 84-node rule (3 states)."""
    rule, _ = residual_rule(model, None, 2)
    if model.estimate_bias:
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(model, "EAGER_MIN_PAIRS", {6: 10**12})
            return fpke_matrix(model, u, comp, rule, None)
    return fpke_matrix(model, u, comp, rule, None, pair_products=False)


def _on_lanes(model, u, comp, compile: bool = False):
    rule, _ = residual_rule(model, None, 2)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(model, "EAGER_MIN_PAIRS", {3: 0, 6: 0})
        return fpke_matrix(model, u, comp, rule, None, compile=compile)


_BIG = pytest.mark.slow  # the 6-state bound's term scale at 2,268 points per pair takes 10–40 s there
_CASES = [(3, B, N, c) for B, N, c in ((1, 1, 10.0), (3, 5, 1e3), (2, 64, 1e6), (667, 5, 1e12), (4, 7, 1e12))] + [
    (6, 1, 1, 10.0),
    (6, 3, 5, 1e3),
    (6, 4, 7, 1e12),
    (6, 40, 5, 1e9),
    pytest.param(6, 2, 64, 1e6, marks=_BIG),
    pytest.param(6, 667, 5, 1e12, marks=_BIG),  # 667 · 15 = 10,005 pairs
]


@pytest.mark.parametrize(("n", "B", "N", "condition"), _CASES)
def test_lanes_equal_the_batched_route(gen, n, B, N, condition):
    model, u, comp = _components(gen, B, N, n, condition)
    _assert_agree(_on_lanes(model, u, comp), _batched(model, u, comp), model, u, comp)


@pytest.mark.parametrize("n", [3, 6])
def test_eager_chunks_give_the_numbers_of_one_call(gen, n):
    """Lanes are independent, so the node values are the same; only the contraction with ``W`` (a BLAS
    product, blocked by its size) may round differently: by ≤ 2Kε·C·Tᵢᵀ|W|Tⱼ."""
    model, u, comp = _components(gen, 5, 4, n, 1e4)
    prod = product_gaussians(comp.with_precision())
    rate = u if n == 6 else u - model.bias
    whole = pair_products.attitude_pair_products(prod, rate, model.sigma_v, model.sigma_u)
    chunked = pair_products.attitude_pair_products(prod, rate, model.sigma_v, model.sigma_u, chunk=3)
    T, _ = _node_term_scale(model, u, comp)
    _, W = pair_products._mrp_nodes_and_weights(torch.float64, torch.device("cpu"))
    bound = 2 * 84 * EPS * (10 if n == 6 else 1) * ((T[0] @ W.abs()) * T[1]).sum(-1)
    assert bool(((whole - chunked).abs() <= bound).all())
    empty = product_gaussians(comp.with_precision().map(lambda t, dim: t[:0]))
    assert pair_products.attitude_pair_products(empty, rate[:0], model.sigma_v, model.sigma_u).shape == (0, 10)


@pytest.mark.parametrize("n", [3, 6])
def test_the_model_takes_the_lanes_route_from_its_crossover_on(gen, monkeypatch, n):
    """Below :attr:`AttitudeModel.EAGER_MIN_PAIRS` the batched route runs (6 states) or the generic rule
    (3 states: ``None``); from it on, and whenever compiled, the lanes route."""
    calls = []
    real = pair_products.attitude_pair_products
    monkeypatch.setattr(
        pair_products, "attitude_pair_products", lambda *a, **k: calls.append(k["compile"]) or real(*a, **k)
    )
    model, u, comp = _components(gen, 2, 5, n, 10.0)  # 30 pairs
    prod = product_gaussians(comp.with_precision())
    small = model.fpke_pair_products(u, prod)
    assert calls == [] and ((small is None) == (n == 3))
    monkeypatch.setattr(model, "EAGER_MIN_PAIRS", {n: 30})
    assert model.fpke_pair_products(u, prod).shape == (2, 15)
    assert calls == [False]


def test_the_penalty_filter_chooses_the_same_weights_on_either_route(gen, monkeypatch):
    """The adaptive filter's weights from ``L`` on lanes equal those from the batched route to the QP's
    sensitivity: with the default trace scaling its matrix is ``H = N·L̃/tr L̃ + λI`` (λ = 0.1) and its linear
    term does not depend on ``L``, so the minimiser moves by ≤ ‖ΔH‖₂‖w‖/λ_min(H), plus the QP's own rounding
    ``κ(H)ε`` (8× headroom on both)."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import AdaptiveGaussianSumFilter
    from agsf_torch.filters.weight_updates.base import component_rates

    N, lam = 5, 0.1
    model, u, comp = _components(gen, 6, N, 6, 1e4)
    log_w = torch.log_softmax(torch.randn(6, N, generator=gen, dtype=torch.float64), -1)
    mix = GaussianMixture(log_weights=log_w, means=comp.means, covs=comp.covs)
    out, H = {}, {}
    rates = component_rates(model, mix, u)
    for pairs in (0, 10**12):
        monkeypatch.setattr(AttitudeModel, "EAGER_MIN_PAIRS", {3: pairs, 6: pairs})
        agsf = AdaptiveGaussianSumFilter(model, weight_update="penalty")
        out[pairs] = agsf.predict(mix, u, 1.0).weights
        assert agsf.diagnostics["weights_adapted"]
        L = fpke_matrix(model, u, rates, residual_rule(model, None, 2)[0], None).scaled
        trace = L.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
        H[pairs] = N * L / trace + lam * torch.eye(N, dtype=torch.float64)
    dH = torch.linalg.matrix_norm(H[0] - H[10**12], ord=2)
    eig = torch.linalg.eigvalsh(H[10**12])
    bound = 8 * (dH * out[0].norm(dim=-1) / eig[..., 0] + eig[..., -1] / eig[..., 0] * EPS)
    assert bool(((out[0] - out[10**12]).norm(dim=-1) <= bound).all())


def _from_components(model, u, comp, compile: bool = False):
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(model, "EAGER_MIN_PAIRS", {3: 0, 6: 0})
        return fused_fpke_matrix(model, u, comp.means, comp.covs, compile=compile)


@pytest.mark.parametrize(("n", "B", "N", "condition"), _CASES)
def test_the_pairs_formed_on_lanes_give_the_batched_route(gen, n, B, N, condition):
    """:func:`fused_fpke_matrix` (product Gaussians, moment rates and ``E[ℓᵢℓⱼ]`` on lanes) against the batched
    route of :func:`fpke_matrix` on the generic product Gaussians and rates."""
    model, u, comp = _components(gen, B, N, n, condition)
    _assert_agree_from_components(_from_components(model, u, comp), _batched(model, u, comp), model, u, comp)


def test_the_model_declines_small_eager_batches_of_components(gen):
    """Below :attr:`EAGER_MIN_PAIRS` eagerly (and without a gyro rate) the model has no fused route: the penalty
    update then takes :func:`fpke_matrix`'s."""
    model, u, comp = _components(gen, 3, 5, 6, 1e3)  # 45 pairs
    assert model.fused_penalty_pairs(comp.means, comp.covs, u) is None
    assert fused_fpke_matrix(model, u, comp.means, comp.covs) is None
    assert model.fused_penalty_pairs(comp.means, comp.covs, None, compile=True) is None


def test_a_pair_whose_factorisation_fails_gives_a_non_finite_log_z(gen):
    """A factorisation on lanes that meets a non-positive pivot (``Σ = Pᵢ + Pⱼ`` not positive definite) makes
    ``log z`` NaN on that pair, never a finite wrong number: the penalty update then refuses ``L`` as not finite."""
    model, u, comp = _components(gen, 4, 1, 6, 1e3)
    mu, P = comp.means[:, 0], comp.covs[:, 0]
    Pj = P.clone()
    Pj[2] = -2.0 * P[2]  # pair 2: Σ = −P
    sv2, su2 = model.sigma_v**2, model.sigma_u**2
    out = pair_products.attitude_pair_moments_kernel(mu, P, mu, Pj, u, sv2, su2)
    log_z = out[-1]
    assert bool(torch.isnan(log_z[2])) and bool(torch.isfinite(log_z[[0, 1, 3]]).all())


def test_the_penalty_update_takes_the_fused_route_with_the_same_weights(gen, monkeypatch):
    """The penalty update forms its pairs on lanes when the model offers it; the weights agree with those of
    :func:`fpke_matrix`'s route (the model's hook declined) to the QP's sensitivity, bounded as in
    :func:`test_the_penalty_filter_chooses_the_same_weights_on_either_route` from the two ``L̃`` of the
    propagated mixture (the same propagation on both sides)."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import AdaptiveGaussianSumFilter, GaussianSumFilter
    from agsf_torch.filters.weight_updates.base import component_rates

    N, lam = 5, 0.1
    model, u, comp = _components(gen, 40, N, 6, 1e4)  # 600 pairs: the eager lanes routes
    log_w = torch.log_softmax(torch.randn(40, N, generator=gen, dtype=torch.float64), -1)
    mix = GaussianMixture(log_weights=log_w, means=comp.means, covs=comp.covs)
    prop = GaussianSumFilter(model).predict(mix, u, 1.0)
    calls, out = [], {}
    real = pair_products.attitude_penalty_pairs
    monkeypatch.setattr(pair_products, "attitude_penalty_pairs", lambda *a, **k: calls.append(1) or real(*a, **k))
    for fused in (True, False):
        calls.clear()
        with pytest.MonkeyPatch.context() as mp:
            if not fused:
                mp.setattr(AttitudeModel, "fused_penalty_pairs", lambda self, *a, **k: None)
            out[fused] = AdaptiveGaussianSumFilter(model, weight_update="penalty").predict(mix, u, 1.0).weights
        assert bool(calls) == fused
    rule = residual_rule(model, None, 2)[0]
    H = {}
    for fused, L in (
        (True, fused_fpke_matrix(model, u, prop.means, prop.covs)),
        (False, fpke_matrix(model, u, component_rates(model, prop, u), rule, None)),
    ):
        trace = L.scaled.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
        H[fused] = N * L.scaled / trace + lam * torch.eye(N, dtype=torch.float64)
    dH = torch.linalg.matrix_norm(H[True] - H[False], ord=2)
    eig = torch.linalg.eigvalsh(H[False])
    bound = 8 * (dH * out[True].norm(dim=-1) / eig[..., 0] + eig[..., -1] / eig[..., 0] * EPS)
    assert bool(((out[True] - out[False]).norm(dim=-1) <= bound).all())


@pytest.mark.parametrize("n", [3, 6])
def test_compiled_calls_take_chunks_of_compiled_pairs(gen, monkeypatch, n):
    """The compiled kernel's threaded variant sees only chunks of ``COMPILED_PAIRS`` pairs (the tail padded; its
    temporaries ``[pairs, 84]`` kept small), fewer pairs one serial call; the numbers are the eager kernel's."""
    from agsf_torch.fused import lanes

    seen = []

    def recording(kernel, key, inputs, shared, serial):
        def run(*args):
            seen.append((args[0].shape[0], serial))
            return kernel(*args)

        return run

    monkeypatch.setattr(lanes, "_load", recording)
    monkeypatch.setattr(lanes, "_COMPILED", {})
    chunk = pair_products.COMPILED_PAIRS
    for B, calls in ((2, [(30, True)]), (20, [(chunk, False)] * -(-300 // chunk))):
        seen.clear()
        model, u, comp = _components(gen, B, 5, n, 1e3)  # 15 pairs per trajectory
        _assert_agree(_on_lanes(model, u, comp, compile=True), _on_lanes(model, u, comp), model, u, comp)
        assert seen == calls


@pytest.mark.slow
@pytest.mark.parametrize("n", [3, 6])
def test_the_compiled_kernel_equals_the_eager_one(gen, n):
    model, u, comp = _components(gen, 300, 5, n, 1e6)  # 4500 pairs: 35 chunks of COMPILED_PAIRS = 128, a padded one
    _assert_agree(_on_lanes(model, u, comp, compile=True), _on_lanes(model, u, comp), model, u, comp)


@pytest.mark.slow
@pytest.mark.parametrize("n", [3, 6])
def test_the_compiled_pairs_from_components_equal_the_eager_ones(gen, n):
    model, u, comp = _components(gen, 300, 5, n, 1e6)
    eager = _from_components(model, u, comp)
    _assert_agree_from_components(_from_components(model, u, comp, compile=True), eager, model, u, comp)
