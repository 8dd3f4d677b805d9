"""Batched simplex QP against Clarabel (direct and through cvxpy)."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.qp import (
    MAX_COMPONENTS,
    bounded_below,
    kkt_residual,
    solve_simplex_qp,
    solve_simplex_qp_clarabel,
    solve_simplex_qp_cvxpy,
)
from tests.helpers import F64, assert_within, relative_bound

#: Clarabel's answers are accurate to its interior-point tolerances (~1e-8 in the weights, which lie in [0, 1]).
CLARABEL = 1e-8


def _random_problems(gen, B, N, rank=None):
    A = torch.randn(B, N, rank or N, generator=gen, dtype=F64)
    H = A @ A.transpose(-1, -2)
    c = torch.randn(B, N, generator=gen, dtype=F64)
    return H, c


@pytest.mark.parametrize("N", [1, 2, 3, 5, 9])
def test_random_problems_match_clarabel(gen, N):
    H, c = _random_problems(gen, 60, N)
    res = solve_simplex_qp(H, c)
    ref = solve_simplex_qp_clarabel(H, c)
    assert_within(res.w, ref, CLARABEL, "weights against Clarabel")
    assert_within(res.kkt_residual, 0.0, 1e-12, "KKT residual")
    assert_within(res.w.sum(-1), 1.0, 1e-12, "sum of the weights")
    assert bool((res.w >= 0).all())


@pytest.mark.parametrize("N", [13, 32, 64])
def test_large_problems_match_clarabel(gen, N):
    """Above the enumeration limit: active set, then interior point with a polished support."""
    H, c = _random_problems(gen, 20, N, rank=N // 2)  # singular H: a face of the simplex, ties possible
    H = H + 1e-6 * torch.eye(N, dtype=F64)
    res = solve_simplex_qp(H, c)
    # singular H + 1e-6 I: along its nearly flat directions Clarabel's answer is less accurate than its 1e-8
    assert_within(res.w, solve_simplex_qp_clarabel(H, c), 10 * CLARABEL, "weights against Clarabel")
    assert_within(res.kkt_residual, 0.0, 1e-12, "KKT residual")


@pytest.mark.parametrize("N", [5, 13, 40])
def test_interior_point_alone_matches_clarabel(gen, N):
    """The interior-point fallback on its own (the active set settles most problems before it runs)."""
    from agsf_torch.qp import _interior_point

    H, c = _random_problems(gen, 30, N)
    H = H / N + 1e-3 * torch.eye(N, dtype=F64)
    w, iterations = _interior_point(H, c)
    assert_within(w, solve_simplex_qp_clarabel(H, c), CLARABEL, "interior-point weights against Clarabel")
    assert_within(kkt_residual(H, c, w), 0.0, 1e-10, "KKT residual")
    assert iterations < 60


@pytest.mark.parametrize("multiplier", [1e-5, 1e-7, 1e-9])
def test_interior_point_settles_bounds_whose_multipliers_are_nearly_zero(gen, multiplier):
    """A weight at its bound with a multiplier near zero leaves the interior-point iterations only slowly
    (~1e-6 when they stop); the polish must still find the exact support.  Problems are built around a
    known minimiser: ``w*`` zero on half the components, bound multipliers ``multiplier`` there, so
    ``c = ν1 + s − Hw*``.  The polished solution is the KKT solution on the support: error ≤ 64 κ(H) ε."""
    from agsf_torch.qp import _KKT_TOL, _interior_point

    B, N = 50, 8
    A = torch.randn(B, N, N, generator=gen, dtype=F64)
    H = A @ A.transpose(-1, -2) / N + 1e-3 * torch.eye(N, dtype=F64)
    w_star = torch.rand(B, N, generator=gen, dtype=F64)
    w_star[:, N // 2 :] = 0.0
    w_star = w_star / w_star.sum(-1, keepdim=True)
    s = torch.zeros(B, N, dtype=F64)
    s[:, N // 2 :] = multiplier
    nu = torch.randn(B, 1, generator=gen, dtype=F64)
    c = nu + s - (H @ w_star.unsqueeze(-1)).squeeze(-1)
    w, _ = _interior_point(H, c)
    bound = 64 * torch.linalg.cond(H) * torch.finfo(F64).eps
    assert_within(w, w_star, bound[:, None], "polished weights against the known minimiser")
    assert_within(kkt_residual(H, c, w), 0.0, _KKT_TOL, "KKT residual")


def test_matches_cvxpy(gen):
    H, c = _random_problems(gen, 10, 5)
    assert_within(solve_simplex_qp(H, c).w, solve_simplex_qp_cvxpy(H, c), CLARABEL, "weights against cvxpy")


def test_ill_conditioned_problems(gen):
    """cond(H) ≥ 1e12: eigenvalues spread over twelve decades."""
    B, N = 40, 5
    Q, _ = torch.linalg.qr(torch.randn(B, N, N, generator=gen, dtype=F64))
    lam = torch.logspace(0, -12, N, dtype=F64)
    H = Q @ torch.diag_embed(lam) @ Q.transpose(-1, -2)
    c = 0.1 * torch.randn(B, N, generator=gen, dtype=F64)
    assert float(torch.linalg.cond(H).min()) >= 1e12 * 0.99
    res = solve_simplex_qp(H, c)
    ref = solve_simplex_qp_clarabel(H, c)
    assert_within(res.w, ref, CLARABEL, "weights of an ill-conditioned problem against Clarabel")
    # the filter's unscaled problem: an astronomically large L plus the unit penalty (Hessian L + I).
    # Clarabel does not converge at this scale; the torch solver's KKT certificate still holds.
    L = 1e30 * H
    w_ref = torch.softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    res = solve_simplex_qp(L + torch.eye(N, dtype=F64), -w_ref)
    assert_within(res.kkt_residual, 0.0, 1e-12, "KKT residual")
    assert_within(res.w.sum(-1), 1.0, 1e-12, "sum of the weights")


def test_degenerate_problems():
    # ties: identical components → the unique minimiser splits evenly
    H = torch.ones(3, 3, dtype=F64) + torch.eye(3, dtype=F64)
    res = solve_simplex_qp(H, torch.zeros(3, dtype=F64))
    assert_within(res.w, 1 / 3, 1e-14, "tied weights")  # κ(H) = 4: a few roundings of 1/3
    # H with a zero direction on the simplex (rank one, H = aaᵀ), made unique by a linear term;
    # the first c also leaves a zero multiplier at the solution (Clarabel alone is off by 4e-7 there,
    # its polished answer agrees)
    a = torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=F64)
    H = torch.outer(a, a)
    for c in ([0.0, -1.0, 0.5, 0.2], [0.3, -2.5, 0.5, 0.2], [0.0, -0.7, 0.5, 0.2]):
        c = torch.tensor(c, dtype=F64)
        res = solve_simplex_qp(H, c)
        assert_within(res.w, solve_simplex_qp_clarabel(H, c), CLARABEL, "weights of a rank-one H against Clarabel")
        assert_within(res.kkt_residual, 0.0, 1e-12, "KKT residual")
    # H = 0: a linear program with a unique vertex solution
    res = solve_simplex_qp(torch.zeros(4, 4, dtype=F64), c)
    vertex = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=F64)
    assert_within(res.w, vertex, relative_bound(vertex, 1e-7, 1e-7), "the linear program's vertex")
    # the minimiser on an edge, with a zero multiplier at the vertex that is not in the support
    H = torch.diag(torch.tensor([1.0, 1.0, 1.0], dtype=F64))
    c = torch.tensor([-0.5, -0.5, 0.0], dtype=F64)
    res = solve_simplex_qp(H, c)
    assert_within(res.w, solve_simplex_qp_clarabel(H, c), CLARABEL, "weights on an edge against Clarabel")


def test_batched_over_leading_dims(gen):
    H, c = _random_problems(gen, 12, 4)
    res = solve_simplex_qp(H.reshape(3, 4, 4, 4), c.reshape(3, 4, 4), chunk_size=5)
    assert torch.equal(res.w.reshape(12, 4), solve_simplex_qp(H, c).w)
    assert 1 <= res.iterations <= 2 * 4 + 2  # settled by the active-set phase, no enumeration needed


def test_enumeration_path_matches_clarabel(gen):
    """The exact fallback (support enumeration) on its own, on random and degenerate problems."""
    from agsf_torch.qp import _solve_chunk, _supports

    H, c = _random_problems(gen, 40, 5)
    S = torch.as_tensor(_supports(5))
    assert_within(_solve_chunk(H, c, S), solve_simplex_qp_clarabel(H, c), CLARABEL, "enumerated weights")
    H0 = torch.zeros(1, 4, 4, dtype=F64)
    c0 = torch.tensor([[0.0, -1.0, 0.5, 0.2]], dtype=F64)
    vertex = torch.tensor([[0.0, 1.0, 0.0, 0.0]], dtype=F64)
    assert_within(
        _solve_chunk(H0, c0, torch.as_tensor(_supports(4))),
        vertex,
        relative_bound(vertex, 1e-7, 1e-7),
        "the enumerated vertex of a linear program",
    )


def test_active_set_settles_the_filters_problems_quickly(gen):
    """The filter's form L̃ + λI, −λ w_ref: the active-set phase settles every problem (no enumeration)."""
    from agsf_torch.qp import _active_set

    A = torch.randn(500, 5, 5, generator=gen, dtype=F64)
    H = A @ A.transpose(-1, -2) / 5 + torch.eye(5, dtype=F64)
    c = -torch.softmax(torch.randn(500, 5, generator=gen, dtype=F64), -1)
    w, done, iterations = _active_set(H, c)
    assert bool(done.all()) and iterations <= 12
    assert_within(w, solve_simplex_qp_clarabel(H, c), CLARABEL, "active-set weights against Clarabel")


def test_kkt_residual_detects_non_optimal_points(gen):
    H, c = _random_problems(gen, 5, 4)
    w = torch.full((5, 4), 0.25, dtype=F64)
    opt = solve_simplex_qp(H, c).w
    assert_within(kkt_residual(H, c, opt), 0.0, 1e-12, "KKT residual")
    assert float(kkt_residual(H, c, w).min()) > 1e-3


@pytest.mark.parametrize("where", ["H", "c"])
def test_non_finite_input_names_the_problem(where):
    H = torch.eye(3, dtype=F64).repeat(4, 1, 1)
    c = torch.zeros(4, 3, dtype=F64)
    (H if where == "H" else c)[2, 1] = float("nan")
    with pytest.raises(ValueError, match=rf"{where} has a non-finite entry at index \(2, 1"):
        solve_simplex_qp(H, c)


def test_shape_errors():
    with pytest.raises(ValueError, match="H must have shape"):
        solve_simplex_qp(torch.ones(3, 2, dtype=F64), torch.ones(3, dtype=F64))
    with pytest.raises(ValueError, match="c must have shape"):
        solve_simplex_qp(torch.eye(3, dtype=F64), torch.ones(2, dtype=F64))
    N = MAX_COMPONENTS + 1
    with pytest.raises(ValueError, match=f"N ≤ {MAX_COMPONENTS}"):
        solve_simplex_qp(torch.eye(N, dtype=F64), torch.zeros(N, dtype=F64))


def test_non_convex_problems_are_refused_naming_the_batch_index(gen):
    """Concave or indefinite H: the KKT certificate would hold at the maximiser (residual 0), so it is refused."""
    H, c = _random_problems(gen, 12, 3)
    H = H.reshape(3, 4, 3, 3).clone()
    H[1, 2] = torch.diag(torch.tensor([1.0, -1e-3, 2.0], dtype=F64))  # indefinite
    with pytest.raises(
        ValueError, match=r"H is not positive semidefinite at batch index \(1, 2\) \(smallest eigenvalue -0\.001"
    ):
        solve_simplex_qp(H, c.reshape(3, 4, 3))
    with pytest.raises(ValueError, match=r"not positive semidefinite at batch index \(\)"):
        solve_simplex_qp(-torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64))  # the maximiser of a concave QP
    # an H shared by a batch of c is checked once, named in the broadcast batch
    with pytest.raises(ValueError, match=r"at batch index \(0,\)"):
        solve_simplex_qp(-torch.eye(3, dtype=F64), torch.zeros(5, 3, dtype=F64))


def test_positive_semidefinite_up_to_rounding_is_accepted(gen):
    """Singular PSD H (rank one, zero, a Gram matrix with eigenvalues at the rounding level) still solve."""
    a = torch.randn(6, generator=gen, dtype=F64)
    X = torch.randn(6, 2, generator=gen, dtype=F64)
    for H in (torch.outer(a, a), torch.zeros(6, 6, dtype=F64), X @ X.T * 1e8):
        assert float(torch.linalg.eigvalsh(H).min()) <= 1e-6 * float(H.abs().max() + 1)  # singular
        res = solve_simplex_qp(H, torch.linspace(0.0, 1.0, 6, dtype=F64))
        assert_within(res.kkt_residual, 0.0, 1e-12, "KKT residual")


@pytest.mark.parametrize("bad", [0, -4, 2.5, True, "8"])
def test_bad_chunk_size_is_refused(gen, bad):
    H, c = _random_problems(gen, 3, 3)
    with pytest.raises(ValueError, match="chunk_size must be a positive integer"):
        solve_simplex_qp(H, c, chunk_size=bad)


def test_singular_gram_matrices_in_float32_are_convex_to_float32_rounding():
    """Rank-deficient Gram matrices rounded to float32 have eigenvalues down to about −ε·max Hᵢᵢ: accepted."""
    gen = torch.Generator().manual_seed(11)
    G = torch.randn(200, 5, 3, generator=gen, dtype=torch.float64)
    H = (G @ G.transpose(-1, -2)).to(torch.float32)
    assert float(torch.linalg.eigvalsh(H.double()).min()) < 0  # the rounding made some indefinite
    res = solve_simplex_qp(H)
    assert torch.isfinite(res.w).all()
    assert_within(res.w.sum(-1), 1.0, relative_bound(1.0, 1e-5, 1e-5), "sum of float32 weights")


@pytest.mark.parametrize("N", [2, 5, 9, 16])
def test_bounded_below_gives_the_kkt_point_of_the_bounded_problem(gen, N):
    # min ½wᵀHw + cᵀw over {w ≥ ℓ, Σw = 1}: at the minimiser, with g = Hw + c and ν its multiplier, gᵢ = ν where
    # wᵢ > ℓᵢ and gᵢ ≥ ν where wᵢ = ℓᵢ (checked here directly, not through the transformed problem)
    H, c = _random_problems(gen, 60, N)
    c = 5.0 * c  # far from the centre: many bounds active
    lower = 0.5 / N * torch.rand(60, N, generator=gen, dtype=F64)
    Hv, cv, s = bounded_below(H, c, lower)
    w = lower + s[..., None] * solve_simplex_qp(Hv, cv).w
    g = (H @ w.unsqueeze(-1)).squeeze(-1) + c
    free = w - lower
    nu = (free * g).sum(-1, keepdim=True) / free.sum(-1, keepdim=True)
    scale = 1.0 + H.abs().flatten(-2).amax(-1) + c.abs().amax(-1)
    tol = 1e-12 * scale[:, None]
    assert bool((free >= -1e-15).all())
    assert_within(w.sum(-1), 1.0, 1e-12, "sum of the weights")
    assert bool(((g - nu) >= -tol).all()), "dual feasibility"
    assert_within(free * (g - nu), 0.0, tol, "complementarity")
    assert bool(((w - lower) < 1e-15).any(-1).float().mean() > 0.5), "most problems should have a bound active"


def test_bounded_below_without_bounds_is_the_simplex_problem(gen):
    H, c = _random_problems(gen, 20, 5)
    Hv, cv, s = bounded_below(H, c, torch.zeros(20, 5, dtype=F64))
    assert torch.equal(Hv, H) and torch.equal(cv, c) and torch.equal(s, torch.ones(20, dtype=F64))


@pytest.mark.parametrize(
    ("lower", "match"), [([-0.1, 0.2], "≥ 0"), ([0.5, 0.5], "less than 1"), ([0.1, float("nan")], "finite")]
)
def test_bounded_below_refuses_bounds_that_leave_no_simplex(lower, match):
    with pytest.raises(ValueError, match=match):
        bounded_below(torch.eye(2, dtype=F64), torch.zeros(2, dtype=F64), torch.tensor(lower, dtype=F64))
