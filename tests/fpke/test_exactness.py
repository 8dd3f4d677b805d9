"""Both weight-update matrices for the attitude models equal a dense tensor Gauss–Hermite reference.

The fast paths — the paper's ``L`` by the interpolatory product rule (840 / 84 nodes) and the Galerkin
``K`` in closed form from Gaussian moments — against quadrature with more points per axis than the
degree of the integrand needs, on random mixtures whose covariance eigenvalues span 1e-4 to 1e-2.

Below that the comparison cannot be made to 1e-10: evaluating ``ℓ`` in float64 loses digits in every
method when a covariance has eigenvalues 1e-10 and 1e-2, and two dense rules then disagree with each
other by up to 1e-2 norm-wise (measured: see the issue note).
"""

from __future__ import annotations

import pytest
import torch

from agsf_torch.fpke import ComponentRates, fpke_matrix, galerkin_matrices, residual_rule
from agsf_torch.models import AttitudeModel
from agsf_torch.propagation import moment_derivatives
from agsf_torch.quadrature import ProductRule, gauss_hermite
from tests.fused.test_galerkin import _term_scale
from tests.helpers import F64, assert_within


def _random_rates(model: AttitudeModel, B: int, N: int, gen: torch.Generator, log_eig: tuple[float, float]):
    n = model.state_dim
    Q, _ = torch.linalg.qr(torch.randn(B, N, n, n, generator=gen, dtype=F64))
    lo, hi = log_eig
    eig = 10.0 ** (lo + (hi - lo) * torch.rand(B, N, n, generator=gen, dtype=F64))
    P = Q @ torch.diag_embed(eig) @ Q.transpose(-1, -2)
    P = 0.5 * (P + P.transpose(-1, -2))
    centre = 0.3 * torch.randn(B, 1, n, generator=gen, dtype=F64)
    spread = torch.sqrt(eig.amax(-1, keepdim=True))  # components a few σ apart, so every pair overlaps
    mu = centre + spread * torch.randn(B, N, n, generator=gen, dtype=F64)
    u = 0.1 * torch.randn(B, 3, generator=gen, dtype=F64)
    r = moment_derivatives(model, mu, P, u.unsqueeze(-2))
    return ComponentRates(mu, torch.linalg.cholesky(P), r.mean_rate, r.cov_rate), u


def _within(A: torch.Tensor, ref: torch.Tensor, tol: float, what: str) -> None:
    """``A`` equals ``ref`` entry by entry to ``tol`` of the largest entry of its matrix (the integrand's scale)."""
    assert_within(A, ref, tol * ref.abs().amax((-2, -1), keepdim=True), what)


def _fast_and_dense(model, rates, u):
    """(fast L̃, dense L̃, denser L̃, fast K̃, dense K̃, denser K̃) — the dense rules exceed the integrands' degrees."""
    eb = model.estimate_bias
    rule, _ = residual_rule(model, None, 2)
    assert isinstance(rule, ProductRule)
    L = fpke_matrix(model, u, rates, rule, None)
    L1 = fpke_matrix(model, u, rates, *gauss_hermite((9, 9, 9, 4, 4, 4) if eb else (9, 9, 9)))  # degree 17 / 7 ≥ 12 / 4
    L2 = fpke_matrix(model, u, rates, *gauss_hermite((11, 11, 11, 5, 5, 5) if eb else (11, 11, 11)))
    assert torch.equal(L.log_scale, L1.log_scale)  # the same product Gaussians: the same largest log z
    G = galerkin_matrices(model, u, rates)  # closed form
    G1 = galerkin_matrices(
        model, u, rates, *gauss_hermite((6, 6, 6, 3, 3, 3) if eb else (6, 6, 6))
    )  # degree 11 / 5 ≥ 6 / 2
    G2 = galerkin_matrices(model, u, rates, *gauss_hermite((8, 8, 8, 4, 4, 4) if eb else (8, 8, 8)))
    assert torch.equal(G.mass, G1.mass)  # the mass matrix is closed-form on both routes: the same code
    return L.scaled, L1.scaled, L2.scaled, G.drift, G1.drift, G2.drift


def _rounding(points: tuple[int, ...], factors: int) -> float:
    """The worst-case rounding (relative to the integrand's scale) of a dense Gauss–Hermite rule's sum over its
    ``K`` nodes of a product of ``factors`` residual factors: each ``ℓ`` at ``x = m + Lξ`` sums terms of size
    ``‖Π‖‖Ṗ‖ |ξ|²`` (the scale of the matrix), so a node contributes up to ``(|ξ|²_max)^factors`` of it, each
    rounded to a few ε; 64× ``K (|ξ|²_max)^factors ε``."""
    nodes, _ = gauss_hermite(points)
    return 64 * nodes.shape[0] * float((nodes * nodes).sum(-1).max()) ** factors * torch.finfo(F64).eps


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_fast_matrices_equal_dense_gauss_hermite(gen, estimate_bias):
    """Covariance eigenvalues 1e-4 … 1e-2: both fast matrices equal the dense reference to the dense rule's own
    rounding (:func:`_rounding`; the fast routes round far less), whatever the draw."""
    model = AttitudeModel(estimate_bias=estimate_bias)
    eb = estimate_bias
    tol_L = _rounding((9, 9, 9, 4, 4, 4) if eb else (9, 9, 9), 2)
    tol_K = _rounding((6, 6, 6, 3, 3, 3) if eb else (6, 6, 6), 1)
    for _ in range(3):
        rates, u = _random_rates(model, 3, 3, gen, (-4.0, -2.0))
        L, L1, _, K, K1, _ = _fast_and_dense(model, rates, u)
        _within(L, L1, tol_L, "FPKE matrix L̃ against the dense rule")
        # K̃ entry by entry: its integrand E[ℓ] cancels among terms far larger than itself, so the rounding
        # scales with the terms' magnitudes T (tests.fused.test_galerkin._term_scale), not with max |K̃|
        scale, prod = _term_scale(model, u, rates)
        z = torch.exp(prod.log_z - prod.log_z.amax(-1, keepdim=True))
        i, j = prod.index
        for side, (a, b) in enumerate(((j, i), (i, j))):
            # (a z̃ in the subnormal range rounds to the absolute spacing 2⁻¹⁰⁷⁴, where tol_K·T·z̃ underflows)
            bound = tol_K * scale[side] * z + 16 * 2.0**-1074
            assert_within(K[..., a, b], K1[..., a, b], bound, f"Galerkin drift K̃ against the dense rule (side {side})")
