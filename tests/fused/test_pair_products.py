"""The penalty update's ``E[ℓᵢℓⱼ]`` on lanes (:mod:`agsf_torch.fused.pair_products`) against the batched routes.

Both routes evaluate the same values at the same 84 MRP nodes per pair (6 states: the ten Hermite
coefficients in ``ξ_b`` of the closed-form bias block, :mod:`agsf_torch.models.attitude_bias_block`; 3 states: ``ℓ``
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
from agsf_torch.rotations import cross_matrix
from tests.fused.test_galerkin import _components
from tests.helpers import assert_within

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


def _assert_agree(got, want, model, u, comp, log_z_ulps: int = 0):
    """``L̃`` of two routes agree entry by entry to the bound of the module docstring (with ``log_z_ulps``: their
    ``log z`` may differ by that many units in the last place, which moves ``z̃`` by as much relative)."""
    n = model.state_dim
    T, z = _node_term_scale(model, u, comp)
    _, W = pair_products._mrp_nodes_and_weights(torch.float64, torch.device("cpu"))
    channels = 10 if n == 6 else 1
    k = 2 * n * n + 4 * n + 8
    # z̃ last (it may be subnormal), and the subnormals' absolute spacing 2⁻¹⁰⁷⁴ for the product z̃·E itself
    bound = ((4 * k + 84) * EPS * channels * ((T[0] @ W.abs()) * T[1]).sum(-1)) * z + 16 * 2.0**-1074  # [B, P]
    i, j = torch.triu_indices(comp.means.shape[-2], comp.means.shape[-2])
    # [B]: ulps of log z's terms (the largest log z, and log det Σ's n terms 2 log L_kk, |…| ≤ 128 here)
    ulps = log_z_ulps * EPS * (want.log_scale.abs() + 128.0)
    if log_z_ulps:  # z̃ = exp(log z − log_scale), each of the two to that many ulps of itself
        assert_within(got.log_scale, want.log_scale, ulps, "log scale (the largest log z)")
        log_z = z.log().clamp_min(-745.0)  # an underflowed z̃ has no digits to lose
        bound = bound + 2 * want.scaled[..., i, j].abs() * (2 * ulps[..., None] + log_z_ulps * EPS * log_z.abs())
    else:  # the same product Gaussians by the same code: the same log z, bit for bit
        assert torch.equal(got.log_scale, want.log_scale)
    assert_within(got.scaled[..., i, j], want.scaled[..., i, j], bound, "scaled FPKE matrix L̃ (pairs i ≤ j)")


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
    tol_scale = tol_log_z.gather(-1, prod.log_z.argmax(-1, keepdim=True)).squeeze(-1)  # the largest z's own
    assert_within(got.log_scale, want.log_scale, tol_scale, "log scale (the largest log z)")
    channels = 10 if n == 6 else 1
    k = 2 * n * n + 4 * n + 8
    terms = (4 * k + 84 + 64 * kappa) * EPS * channels * ((T[0] @ W.abs()) * T[1]).sum(-1)
    i, j = torch.triu_indices(comp.means.shape[-2], comp.means.shape[-2])
    ref = want.scaled[..., i, j]
    bound = terms * z + 2 * ref.abs() * (tol_log_z + tol_scale[..., None]) + 16 * 2.0**-1074
    assert_within(got.scaled[..., i, j], ref, bound, "scaled FPKE matrix L̃ from the components (pairs i ≤ j)")


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
    assert_within(chunked, whole, bound, "E[ℓᵢℓⱼ] in chunks of 3 pairs")
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
    # every entry moves by at most the 2-norm of the move
    assert_within(out[0], out[10**12], bound[..., None], "penalty weights on lanes against the batched route")


def _from_components(model, u, comp, compile: bool = False):
    """``L̃`` from :func:`~agsf_torch.fused.pair_products.attitude_penalty_pairs` (eager, or compiled)."""
    from agsf_torch.fpke.matrices import _fpke_from_pairs

    rate = u if model.estimate_bias else u - model.bias.to(u)
    log_z, acc = pair_products.attitude_penalty_pairs(
        comp.means, comp.covs, rate, model.sigma_v, model.sigma_u, compile=compile
    )
    N = comp.means.shape[-2]
    return _fpke_from_pairs(log_z, log_z.amax(-1), acc, torch.triu_indices(N, N), N)


def _eager_as_compiled(monkeypatch, seen=None):
    """Compiled calls of :func:`~agsf_torch.fused.lanes.run_in_chunks` run the eager kernel (nothing compiles),
    each call's lanes and variant noted in ``seen``."""
    from agsf_torch.fused import lanes

    def load(kernel, key, inputs, shared, serial):
        def run(*args):
            if seen is not None:
                seen.append((kernel.__name__, args[0].shape[0], serial))
            return kernel(*args)

        return run

    monkeypatch.setattr(lanes, "_load", load)
    monkeypatch.setattr(lanes, "_COMPILED", {})


def _jacobian_term_scale(mu, u_p, n):
    """The sum of the magnitudes of the terms of each entry of ``A = ∂f/∂x`` ``[Q, n, n]`` as both routes form it
    (:meth:`AttitudeModel.drift_jacobian`, :func:`~agsf_torch.fused.propagation.attitude_rates`): with
    ``ω = ω̃ − b`` taken as ``|ω̃| + |b|`` (its own rounding), ``F = ½(pωᵀ − ωpᵀ − [ω×] + (ωᵀp)I)`` term by term,
    and ``−¼B(p)``, ``B = (1 − s)I + 2[p×] + 2ppᵀ``, as ``¼((1 + s)I + 2|[p×]| + 2|p||p|ᵀ)``; the bias rows are
    structural zeros on both routes.  An entry of ``A`` may cancel among its terms (``ωᵀp`` on the diagonal), so
    ``|A|`` itself does not bound its rounding; this does."""
    p = mu[:, :3].abs()
    w = u_p.abs() + (mu[:, 3:].abs() if n == 6 else 0.0)
    eye = torch.eye(3, dtype=mu.dtype)
    F = 0.5 * (
        p[:, :, None] * w[:, None, :]
        + w[:, :, None] * p[:, None, :]
        + cross_matrix(w).abs()
        + (p * w).sum(-1)[:, None, None] * eye
    )
    if n == 3:
        return F
    s = (p * p).sum(-1)[:, None, None]
    B = (1.0 + s) * eye + 2.0 * cross_matrix(p).abs() + 2.0 * p[:, :, None] * p[:, None, :]
    top = torch.cat((F, 0.25 * B), -1)
    return torch.cat((top, torch.zeros_like(top)), -2)


def _assert_moments_agree(model, u, comp, run=None):
    """The moments kernel's outputs (run by ``run(inputs, shared)``; default: eagerly) against
    :func:`product_gaussians` and :func:`moment_derivatives`, each to its own conditioning: the solves with
    ``Σ = Pᵢ + Pⱼ`` are backward stable, so ``m = μᵢ − Pᵢy`` and ``S = Pᵢ − PᵢΣ⁻¹Pᵢ`` agree to ``O(nκ(Σ)ε)`` of their
    terms, ``LLᵀ`` is ``S`` to ``O(nε‖S‖)`` (Cholesky), ``log z`` as in :mod:`tests.fused.test_galerkin`; the rates
    ``f(μ)``, ``AP + PAᵀ + gQgᵀ`` are short sums of products, a few ε of their terms' magnitudes.

    ``Ṗ``: each route forms ``A`` to ``c_A = 8`` roundings of its terms' magnitudes ``|A|ₜ``
    (:func:`_jacobian_term_scale`; ``ω`` one, a product one, the sums of up to four terms three, ``ωᵀp`` and
    ``s = pᵀp`` three more on the diagonals), sums ``n`` products for each entry of ``AP`` (``n`` roundings, in any
    order: BLAS or the kernel's unrolled sums) and adds ``(AP)ᵀ`` and ``gQgᵀ`` (2; ``gQgᵀ = (σ_v²/16)(1 + s)²`` to 7
    of its value), so each is within ``(n + c_A + 2)ε·(|A|ₜ|P| + |P||A|ₜᵀ + |gQgᵀ|)`` of the exact rate, and the two
    within twice that.  Every term counts: on the bias rows ``A`` is zero but ``PAᵀ`` is not
    (``Ṗ_bp = P_bb(−¼B)ᵀ + P_bp Fᵀ``), so a bound ``2|A||P|`` vanished there where the rates, rounded differently
    by another BLAS (MKL's AVX-512 path), differed by an ulp."""
    from agsf_torch.propagation import moment_derivatives

    n = model.state_dim
    B = comp.means.shape[0]
    rate = u if model.estimate_bias else u - model.bias.to(u)
    prod = product_gaussians(comp.with_precision())
    i, j = prod.index
    P = i.shape[0]
    flat = lambda t: t.reshape(B * P, *t.shape[2:])  # noqa: E731
    sides = [(flat(comp.means[:, k]), flat(comp.covs[:, k])) for k in (i, j)]
    u_p = rate.unsqueeze(1).expand(B, P, 3).reshape(-1, 3)  # the kernel's rate: the known bias removed
    gyro = u.unsqueeze(1).expand(B, P, 3).reshape(-1, 3)  # the model's input
    inputs, shared = (*sides[0], *sides[1], u_p), (model.sigma_v**2, model.sigma_u**2)
    run = run or (lambda inputs, shared: pair_products.attitude_pair_moments_kernel(*inputs, *shared))
    m, L, rate_i, Pdot_i, rate_j, Pdot_j, log_z = run(inputs, shared)
    norm = lambda t: torch.linalg.matrix_norm(t, ord=2) if t.dim() > 2 else t.norm(dim=-1)  # noqa: E731
    Sigma = flat(prod.first.covs + prod.second.covs)
    kappa = torch.linalg.cond(Sigma)
    Pi, y = flat(prod.first.covs), flat(prod.y)
    # the 2-norm bounds below bound every entry
    tol_m = 64 * n * kappa * EPS * (norm(sides[0][0]) + norm(Pi) * norm(y))
    assert_within(m, flat(prod.mean), tol_m[:, None], "product Gaussian mean m")
    tol_S = 64 * n * kappa * EPS * norm(Pi) * (1 + norm(flat(prod.gain)))
    S = flat(prod.cov)
    tol_LL = tol_S + 64 * n * EPS * norm(S)
    assert_within(L @ L.transpose(-1, -2), S, tol_LL[:, None, None], "product Gaussian covariance S as LLᵀ")
    assert bool((L.triu(1) == 0).all())
    d = sides[0][0] - sides[1][0]
    maha = (y * d).sum(-1).abs()
    log_det = torch.linalg.slogdet(Sigma)[1].abs()
    tol_z = 64 * EPS * (n * kappa + log_det + kappa * maha + n * math.log(2 * math.pi))
    assert_within(log_z, flat(prod.log_z), tol_z, "product Gaussian log z")
    for side, ((mu, cov), mean_rate, cov_rate) in enumerate(((sides[0], rate_i, Pdot_i), (sides[1], rate_j, Pdot_j))):
        want = moment_derivatives(model, mu, cov, gyro)
        A_t = _jacobian_term_scale(mu, u_p, n)
        scale_P = A_t @ cov.abs() + cov.abs() @ A_t.transpose(-1, -2) + model.process_noise(mu).abs()
        rounds = n + 8 + 2  # AP's n, A's c_A = 8, then (AP)ᵀ and gQgᵀ: each route's, to the two routes' twice
        assert_within(cov_rate, want.cov_rate, 2 * rounds * EPS * scale_P, f"covariance rate Ṗ of side {side}")
        # f = ¼B(p)ω: an entry of B sums terms of magnitude ≤ 3(1 + s) (the diagonal 1 + s + 2pₖ², the others
        # 2|pᵢpⱼ| + 2|pₖ| ≤ 2(1 + s)), to ~9 roundings a route with ω's; 64ε·(1 + s)Σ|ω| covers both routes'
        p = mu[:, :3]
        w = (u_p - mu[:, 3:]) if n == 6 else u_p
        scale_f = (1 + (p * p).sum(-1, keepdim=True)) * w.abs().sum(-1, keepdim=True)
        assert_within(mean_rate, want.mean_rate, 64 * EPS * scale_f, f"mean rate f(μ) of side {side}")


@pytest.mark.parametrize(
    ("n", "condition", "bias"), [(6, 1e3, 0.0), (6, 1e9, 0.0), (6, 1e12, 0.0), (3, 1e6, 0.02), (3, 1e12, 0.0)]
)
def test_the_moments_kernel_gives_the_generic_product_gaussians_and_rates(gen, n, condition, bias):
    """:func:`attitude_pair_moments_kernel` against the generic product Gaussians and rates
    (:func:`_assert_moments_agree`), the 3-state model with a known bias of 0.02 rad/s once."""
    model, u, comp = _components(gen, 30, 5, n, condition)
    if bias:
        model = AttitudeModel(estimate_bias=False, bias=torch.tensor([bias, -bias, 0.5 * bias]))
    _assert_moments_agree(model, u, comp)


@pytest.mark.parametrize(
    ("n", "B", "N", "condition"), [(3, 1, 1, 10.0), (3, 7, 5, 1e3), (6, 1, 1, 10.0), (6, 7, 5, 1e3)]
)
def test_the_pairs_formed_on_lanes_give_the_batched_route(gen, n, B, N, condition):
    """:func:`attitude_penalty_pairs` (product Gaussians, moment rates and ``E[ℓᵢℓⱼ]`` on lanes) against the
    batched route of :func:`fpke_matrix` on the generic product Gaussians and rates, end to end where the bound
    is tight enough to see a wrong entry (conditions ≤ 10³; above, the two kernels are checked one by one: the
    moments kernel above, the node kernel in :func:`test_lanes_equal_the_batched_route`)."""
    model, u, comp = _components(gen, B, N, n, condition)
    _assert_agree_from_components(_from_components(model, u, comp), _batched(model, u, comp), model, u, comp)


@pytest.mark.parametrize("n", [3, 6])
def test_the_end_to_end_bound_sees_a_wrong_entry(gen, n):
    """The bound of :func:`_assert_agree_from_components` is not empty: at condition 10 an off-diagonal entry 1 %
    off fails it.  (It is loose: the terms of ``ℓ`` at the nodes are far larger than ``L̃``'s entries, and at
    condition 10³ the 6-state bound admits errors of that size; the kernels are therefore also checked one by
    one, the moments kernel in :func:`test_the_moments_kernel_gives_the_generic_product_gaussians_and_rates`,
    the node kernel in :func:`test_lanes_equal_the_batched_route`.)"""
    model, u, comp = _components(gen, 3, 5, n, 10.0)
    got, want = _from_components(model, u, comp), _batched(model, u, comp)
    _assert_agree_from_components(got, want, model, u, comp)
    wrong = got.scaled.clone()
    wrong[..., 0, 1] *= 1.01
    wrong[..., 1, 0] = wrong[..., 0, 1]
    with pytest.raises(AssertionError):
        _assert_agree_from_components(type(got)(wrong, got.log_scale), want, model, u, comp)


def test_the_known_bias_reaches_the_pairs(gen):
    """The 3-state model's known gyro bias is removed from the rate: with a bias of 0.02 rad/s the lanes route agrees
    with the batched one, which it would not if the bias were dropped (L̃ moves far beyond the bound)."""
    _, u, comp = _components(gen, 4, 5, 3, 10.0)
    model = AttitudeModel(estimate_bias=False, bias=torch.tensor([0.02, -0.01, 0.015]))
    from agsf_torch.fpke.residual import ComponentRates
    from agsf_torch.propagation import moment_derivatives

    rates = moment_derivatives(model, comp.means, comp.covs, u.unsqueeze(-2))
    comp = ComponentRates(comp.means, comp.chol, rates.mean_rate, rates.cov_rate, covs=comp.covs)
    got, want = _from_components(model, u, comp), _batched(model, u, comp)
    _assert_agree_from_components(got, want, model, u, comp)
    unbiased = AttitudeModel(estimate_bias=False, bias=torch.zeros(3))
    with pytest.raises(AssertionError):
        _assert_agree_from_components(_from_components(unbiased, u, comp), want, model, u, comp)


def test_the_model_offers_the_route_only_compiled_and_without_gradients(gen):
    """Eagerly (its kernel of product Gaussians is slower than the batched LAPACK route below ~1,500 pairs), without
    a gyro rate or with gradients asked for, the model has no fused route: the penalty update then takes
    :func:`fpke_matrix`'s."""
    model, u, comp = _components(gen, 300, 5, 6, 1e3)  # 4,500 pairs
    assert model.fused_penalty_pairs(comp.means, comp.covs, u) is None
    assert fused_fpke_matrix(model, u, comp.means, comp.covs) is None
    assert model.fused_penalty_pairs(comp.means, comp.covs, None, compile=True) is None
    means = comp.means.clone().requires_grad_()
    assert model.fused_penalty_pairs(means, comp.covs, u, compile=True) is None


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
    Pj[2] = -0.5 * P[2]  # Σ = ½P is positive definite, S = P − 2P = −P is not: its own factor's pivots fail
    log_z = pair_products.attitude_pair_moments_kernel(mu, P, mu, Pj, u, sv2, su2)[-1]
    assert bool(torch.isnan(log_z[2])) and bool(torch.isfinite(log_z[[0, 1, 3]]).all())


def test_the_penalty_update_refuses_a_pair_that_could_not_be_factorised(gen, monkeypatch):
    """A NaN ``log z`` from the lanes route (a failed factorisation) makes the penalty update refuse ``L`` as not
    finite, naming the trajectory, before its state changes."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import AdaptiveGaussianSumFilter
    from agsf_torch.filters.weight_updates import PenaltyWeightUpdate

    _eager_as_compiled(monkeypatch)
    model, u, comp = _components(gen, 3, 5, 6, 1e3)
    real = pair_products.attitude_penalty_pairs

    def failing(*args, **kwargs):
        log_z, acc = real(*args, **kwargs)
        log_z = log_z.clone()
        log_z[1, 4] = torch.nan
        return log_z, acc

    monkeypatch.setattr(pair_products, "attitude_penalty_pairs", failing)
    log_w = torch.log_softmax(torch.randn(3, 5, generator=gen, dtype=torch.float64), -1)
    mix = GaussianMixture(log_weights=log_w, means=comp.means, covs=comp.covs)
    agsf = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(compile=True))
    before = agsf.state_dict()
    with pytest.raises(ValueError, match=r"FPKE matrix L is not finite at trajectory index \(1,\)"):
        agsf.predict(mix, u, 1.0)
    assert agsf.state_dict()["weight_update"] == before["weight_update"]


def test_the_penalty_update_takes_the_fused_route_with_the_same_weights(gen, monkeypatch):
    """The penalty update forms its pairs on lanes when the model offers it; the weights agree with those of
    :func:`fpke_matrix`'s route (the model's hook declined) to the QP's sensitivity, bounded as in
    :func:`test_the_penalty_filter_chooses_the_same_weights_on_either_route` from the two ``L̃`` of the
    propagated mixture (the same propagation on both sides)."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import AdaptiveGaussianSumFilter, GaussianSumFilter
    from agsf_torch.filters.weight_updates import PenaltyWeightUpdate
    from agsf_torch.filters.weight_updates.base import component_rates

    _eager_as_compiled(monkeypatch)  # the compiled routes, run eagerly: nothing is compiled here
    N, lam = 5, 0.1
    model, u, comp = _components(gen, 40, N, 6, 1e4)  # 600 pairs: the lanes routes
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
            agsf = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(compile=True))
            out[fused] = agsf.predict(mix, u, 1.0).weights
        assert bool(calls) == fused
    rule = residual_rule(model, None, 2)[0]
    H = {}
    for fused, L in (
        (True, fused_fpke_matrix(model, u, prop.means, prop.covs, compile=True)),
        (False, fpke_matrix(model, u, component_rates(model, prop, u), rule, None, compile=True)),
    ):
        trace = L.scaled.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
        H[fused] = N * L.scaled / trace + lam * torch.eye(N, dtype=torch.float64)
    dH = torch.linalg.matrix_norm(H[True] - H[False], ord=2)
    eig = torch.linalg.eigvalsh(H[False])
    bound = 8 * (dH * out[True].norm(dim=-1) / eig[..., 0] + eig[..., -1] / eig[..., 0] * EPS)
    # every entry moves by at most the 2-norm of the move
    assert_within(out[True], out[False], bound[..., None], "penalty weights on the fused route against fpke_matrix's")


@pytest.mark.parametrize("n", [3, 6])
def test_compiled_calls_take_chunks_of_compiled_pairs(gen, monkeypatch, n):
    """The compiled kernel's threaded variant sees only chunks of ``COMPILED_PAIRS`` pairs (the tail padded; its
    temporaries ``[pairs, 84]`` kept small), fewer pairs one serial call; the numbers are the eager kernel's."""
    seen = []
    _eager_as_compiled(monkeypatch, seen)
    chunk = pair_products.COMPILED_PAIRS[n]
    name = "attitude_pair_values_kernel"
    big = 2 * chunk // 15 + 1  # trajectories whose 15 pairs each fill two chunks and part of a third
    for B, calls in ((2, [(name, 30, True)]), (big, [(name, chunk, False)] * -(-15 * big // chunk))):
        seen.clear()
        model, u, comp = _components(gen, B, 5, n, 1e3)  # 15 pairs per trajectory
        _assert_agree(_on_lanes(model, u, comp, compile=True), _on_lanes(model, u, comp), model, u, comp)
        assert seen == calls


@pytest.mark.parametrize("n", [3, 6])
def test_compiled_pairs_from_components_take_their_chunks(gen, monkeypatch, n):
    """Compiled, the moments kernel takes chunks of the default 1,024 lanes and the node kernels (both sides for the
    pairs i < j, one for the pairs i = i) chunks of ``COMPILED_PAIRS`` (the tails padded, the padding dropped before
    the next kernel); the numbers are those of the eager route."""
    from agsf_torch.fused import lanes

    seen = []
    _eager_as_compiled(monkeypatch, seen)
    model, u, comp = _components(gen, 120, 5, n, 1e3)  # 1,800 pairs: more than a chunk of either kind
    got = _from_components(model, u, comp, compile=True)
    eager = _from_components(model, u, comp)
    # the same eager code on every lane, in other chunks: elementwise the same operations (a vectorised log may round
    # a tail lane differently, by an ulp of log z), and the node kernel's product with W in other blocks
    _assert_agree(got, eager, model, u, comp, log_z_ulps=16)
    chunk = pair_products.COMPILED_PAIRS[n]
    moments = [c for c in seen if c[0] == "attitude_pair_moments_kernel"]
    values = [c for c in seen if c[0] == "attitude_pair_values_kernel"]
    diagonal = [c for c in seen if c[0] == "attitude_diagonal_pair_values_kernel"]
    assert moments == [("attitude_pair_moments_kernel", lanes.COMPILED_CHUNK, False)] * 2
    assert values == [("attitude_pair_values_kernel", chunk, False)] * -(-1200 // chunk)  # 120 · 10 pairs i < j
    assert diagonal == [("attitude_diagonal_pair_values_kernel", chunk, False)] * -(-600 // chunk)  # 120 · 5


@pytest.mark.slow
@pytest.mark.parametrize("n", [3, 6])
def test_the_compiled_kernel_equals_the_eager_one(gen, n):
    model, u, comp = _components(gen, 300, 5, n, 1e6)  # 4500 pairs: chunks of COMPILED_PAIRS[n], a padded one
    _assert_agree(_on_lanes(model, u, comp, compile=True), _on_lanes(model, u, comp), model, u, comp)


@pytest.mark.slow
@pytest.mark.parametrize("n", [3, 6])
def test_the_compiled_pairs_from_components_equal_the_eager_ones(gen, n):
    """Compiled, the moments kernel meets the bounds of the eager one (:func:`_assert_moments_agree`; the node
    kernel compiled: :func:`test_the_compiled_kernel_equals_the_eager_one`), and the whole route agrees with the
    eager one end to end."""
    from agsf_torch.fused.lanes import run_in_chunks

    model, u, comp = _components(gen, 300, 5, n, 1e6)

    def compiled(inputs, shared):
        return run_in_chunks(
            pair_products.attitude_pair_moments_kernel,
            inputs,
            shared=shared,
            compile=True,
            key=("attitude pair moments", n),
        )

    _assert_moments_agree(model, u, comp, compiled)
    eager = _from_components(model, u, comp)
    _assert_agree_from_components(_from_components(model, u, comp, compile=True), eager, model, u, comp)


@pytest.mark.parametrize("N", [1, 3])
def test_fused_fpke_matrix_takes_any_batch_shape_and_a_shared_rate(gen, monkeypatch, N):
    """:func:`fused_fpke_matrix` on components ``[2, 3, N, n]`` with one gyro rate ``[3]`` for all equals the route
    on the flattened batch with the rate repeated, reshaped (the same lanes: the same numbers), and agrees with the
    batched route; ``N = 1`` has its single diagonal pair."""
    _eager_as_compiled(monkeypatch)
    model, u, comp = _components(gen, 6, N, 6, 10.0)
    rate = u[0]
    means, covs = comp.means.reshape(2, 3, N, 6), comp.covs.reshape(2, 3, N, 6, 6)
    got = fused_fpke_matrix(model, rate, means, covs, compile=True)
    flat = fused_fpke_matrix(model, rate.expand(6, 3), comp.means, comp.covs, compile=True)
    assert got.scaled.shape == (2, 3, N, N) and got.log_scale.shape == (2, 3)
    assert torch.equal(got.scaled.reshape(6, N, N), flat.scaled) and torch.equal(
        got.log_scale.reshape(6), flat.log_scale
    )
    from agsf_torch.fpke.residual import ComponentRates
    from agsf_torch.propagation import moment_derivatives

    rates = moment_derivatives(model, comp.means, comp.covs, rate.expand(6, 1, 3))
    comp = ComponentRates(comp.means, comp.chol, rates.mean_rate, rates.cov_rate, covs=comp.covs)
    _assert_agree_from_components(flat, _batched(model, rate.expand(6, 3), comp), model, rate.expand(6, 3), comp)
