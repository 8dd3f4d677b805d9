"""Convex quadratic programs on the probability simplex.

.. math:: \\min_w \\; ½ w^T H w + c^T w \\quad\\text{s.t.}\\quad 1^T w = 1,\\; w ≥ 0

:func:`solve_simplex_qp` solves a whole batch exactly in torch: a batched
primal–dual active-set iteration settles most problems in a few KKT solves, and
any it has not settled is solved by *support enumeration*: the minimiser of a convex QP lies in the relative interior of one
face of the simplex, where it solves the equality-constrained KKT system

.. math:: \\begin{bmatrix} H_{SS} & -1 \\\\ 1^T & 0 \\end{bmatrix}
          \\begin{bmatrix} w_S \\\\ ν \\end{bmatrix} = \\begin{bmatrix} -c_S \\\\ 1 \\end{bmatrix}

for its support ``S``.  All ``2^N − 1`` supports are solved at once as one
batched linear solve, the KKT conditions (``w_S ≥ 0``; multipliers
``μᵢ = (Hw + c)ᵢ − ν ≥ 0`` off the support) select the solution, and ties are
broken by the objective.  The method is finite by construction — no iteration
count can stop it early — and exact to the conditioning of the selected KKT
system.  Its cost grows as ``2^N``: it is meant for mixtures of up to
``MAX_COMPONENTS`` components.  When the minimiser is unique (always, for
``H ≻ 0`` on the simplex, e.g. the filter's ``L + λI``) the selected support's
KKT matrix is nonsingular.

Convexity is a precondition, checked on every call (:data:`PSD_TOLERANCE`, one batched
Cholesky factorisation of the ``N × N`` matrices): for a concave or indefinite ``H`` the
KKT conditions also hold at maximisers and saddle points, which the solver would return
with a zero residual.  The filters' matrices are PSD by construction only up to their
quadrature: ``L = Σₖ wₖ ℓ(xₖ)ℓ(xₖ)ᵀ`` and the Galerkin ``M`` are Gram matrices, PSD for a
rule with positive weights, but a sparse grid (negative weights) or rounding can break it.

Reference back ends, for validation and the benchmark (the filters always use
:func:`solve_simplex_qp`): Clarabel called directly (:func:`solve_simplex_qp_clarabel`)
and through cvxpy (:func:`solve_simplex_qp_cvxpy`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from .chunks import check_chunk_size
from .shapes import broadcast_shapes

__all__ = [
    "MAX_COMPONENTS",
    "QPResult",
    "solve_simplex_qp",
    "kkt_residual",
    "hold_at_zero",
    "bounded_below",
    "solve_simplex_qp_clarabel",
    "solve_simplex_qp_cvxpy",
]

#: Largest problem size :func:`solve_simplex_qp` accepts.
MAX_COMPONENTS = 64
#: Largest problem size settled by support enumeration (``2^N − 1`` supports); above it, an interior-point method.
MAX_ENUMERATION = 12
#: Convexity tolerance (float64): ``H`` is accepted as positive semidefinite when ``H + τ·max|Hᵢⱼ|·I``
#: is positive definite, i.e. its smallest eigenvalue is ≥ about ``−τ·max|Hᵢⱼ|``, with
#: ``τ = max(PSD_TOLERANCE, 100 ε)`` for the dtype's ε (1.2e-5 in float32).
PSD_TOLERANCE = 1e-10


@dataclass(frozen=True)
class QPResult:
    """Solution of a batch of simplex QPs.

    Attributes:
        w: ``[..., N]`` on the simplex (``w ≥ 0``, ``Σw = 1`` to rounding).
        kkt_residual: ``[...]`` scaled KKT residual (see :func:`kkt_residual`).
        iterations: active-set iterations run (batch-wide, not per problem), plus the
            ``2^N − 1`` candidate supports if any problem needed the support enumeration
            (N ≤ ``MAX_ENUMERATION``), or plus the interior-point iterations if any needed those.
    """

    w: Tensor
    kkt_residual: Tensor
    iterations: int


@lru_cache(maxsize=16)
def _supports(N: int) -> np.ndarray:
    return np.array([[(s >> i) & 1 for i in range(N)] for s in range(1, 2**N)], dtype=bool)


def _check_inputs(H: Tensor, c: Tensor) -> None:
    if H.dim() < 2 or H.shape[-1] != H.shape[-2]:
        raise ValueError(f"H must have shape [..., N, N], got {tuple(H.shape)}")
    if c.shape[-1] != H.shape[-1]:
        raise ValueError(f"c must have shape [..., {H.shape[-1]}], got {tuple(c.shape)}")
    for name, t in (("H", H), ("c", c)):
        if not bool(torch.isfinite(t).all()):
            bad = (~torch.isfinite(t)).nonzero()[0].tolist()
            raise ValueError(f"{name} has a non-finite entry at index {tuple(bad)} (batch index first)")
    if H.shape[-1] > MAX_COMPONENTS:
        raise ValueError(f"solve_simplex_qp handles N ≤ {MAX_COMPONENTS} components, got {H.shape[-1]}")


def _check_convex(H: Tensor, batch: tuple[int, ...]) -> None:
    """Raise ``ValueError`` naming the first batch index (in ``batch``) of the symmetric ``H [P, N, N]``
    that is not positive semidefinite to :data:`PSD_TOLERANCE`: the solver's optimality
    certificate (the KKT conditions) characterises the minimiser of a *convex* problem only —
    for a concave one it selects a stationary point, e.g. the maximiser.

    One batched Cholesky factorisation of ``H + PSD_TOLERANCE·max|Hᵢᵢ|·I`` (for a PSD matrix
    ``max|Hᵢⱼ| = max Hᵢᵢ``); the eigenvalue for the message is computed only on failure.
    """
    Hd = H.detach()
    scale = Hd.diagonal(dim1=-2, dim2=-1).abs().amax(-1)
    shift = max(PSD_TOLERANCE, 100.0 * torch.finfo(Hd.dtype).eps) * scale + torch.finfo(Hd.dtype).tiny
    eye = torch.eye(Hd.shape[-1], dtype=Hd.dtype, device=Hd.device)
    bad = torch.linalg.cholesky_ex(Hd + shift[:, None, None] * eye).info != 0
    if bool(bad.any()):
        k = int(bad.nonzero()[0])
        idx = tuple(int(i) for i in np.unravel_index(k, batch)) if batch else ()
        lam = float(torch.linalg.eigvalsh(Hd[k])[0])
        raise ValueError(
            f"H is not positive semidefinite at batch index {idx} (smallest eigenvalue {lam:.3g}, "
            f"largest |diagonal| {float(scale[k]):.3g}): solve_simplex_qp solves convex problems only"
        )


def kkt_residual(H: Tensor, c: Tensor, w: Tensor) -> Tensor:
    """Scaled KKT residual of a simplex-QP point, ``[...]``.

    With ``g = Hw + c`` and the equality multiplier estimated as ``ν = Σwᵢgᵢ / Σwᵢ``
    (exact at a KKT point), the residual is the largest of: primal
    infeasibility (``max(−wᵢ, 0)``, ``|Σw − 1|``), and, relative to
    ``1 + max|H| + max|c|``, dual infeasibility ``max(ν − gᵢ, 0)`` and
    complementarity ``|wᵢ (gᵢ − ν)|``.
    """
    g = (H @ w.unsqueeze(-1)).squeeze(-1) + c
    nu = (w * g).sum(-1, keepdim=True) / w.sum(-1, keepdim=True)
    mu = g - nu
    primal = torch.maximum((-w).clamp_min(0).amax(-1), (w.sum(-1) - 1).abs())
    dual = (-mu).clamp_min(0).amax(-1)
    comp = (w.clamp_min(0) * mu).abs().amax(-1)
    scale = 1.0 + H.abs().flatten(-2).amax(-1) + c.abs().amax(-1)
    return torch.maximum(primal, torch.maximum(dual, comp) / scale)


def hold_at_zero(H: Tensor, c: Tensor, active: Tensor) -> tuple[Tensor, Tensor]:
    """The simplex QP ``(H, c)`` with ``wᵢ`` held at zero wherever ``active [..., N]`` is ``False``.

    Row and column ``i`` of ``H`` become ``hᵢ eᵢ`` (``h`` the largest active diagonal entry) and ``cᵢ`` becomes
    ``2(max|H| + max|c|)`` over the active entries, above any value of the equality multiplier
    ``ν = (Hw + c)ⱼ`` (``|ν| ≤ max|H| + max|c|`` for ``w`` on the simplex): the KKT point of the new problem has
    ``wᵢ = 0`` and, on the active entries, is the KKT point of the problem restricted to them.  Each problem needs
    one active entry.

    Args:
        H: ``[..., N, N]``; c: ``[..., N]``; active: ``[..., N]`` bool.

    Returns:
        ``(H', c')``.
    """
    both = active[..., :, None] & active[..., None, :]
    H_act = torch.where(both, H, torch.zeros_like(H))
    c_act = torch.where(active, c, torch.zeros_like(c))
    scale = H_act.abs().flatten(-2).amax(-1) + c_act.abs().amax(-1)
    h = H_act.diagonal(dim1=-2, dim2=-1).amax(-1)
    h = torch.where(h > 0, h, torch.ones_like(h))
    eye = torch.eye(H.shape[-1], dtype=torch.bool, device=H.device)
    held = torch.where(eye & ~active[..., None, :], h[..., None, None], torch.zeros_like(H))
    return torch.where(both, H, held), torch.where(active, c, (2.0 * scale + h)[..., None].expand_as(c))


def bounded_below(H: Tensor, c: Tensor, lower: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The simplex QP ``(H, c)`` with ``w ≥ ℓ`` as a simplex QP in ``v``.

    With ``w = ℓ + s·v``, ``s = 1 − Σℓ``, the set ``{w ≥ ℓ, Σw = 1}`` is the simplex in ``v``, and
    ``½wᵀHw + cᵀw = s·(½ vᵀ(sH)v + (c + Hℓ)ᵀv) + const``: the problem in ``v`` is ``(sH, c + Hℓ)``, convex with
    ``H``, so :func:`solve_simplex_qp` solves it exactly and ``w = ℓ + s·v``.

    Args:
        H: ``[..., N, N]``; c: ``[..., N]``; lower: ``ℓ [..., N]``, finite, ``≥ 0``, ``Σℓ < 1``.

    Returns:
        ``(sH [..., N, N], c + Hℓ [..., N], s [...])``.

    Raises:
        ValueError: ``ℓ`` negative or not finite, or ``Σℓ ≥ 1`` (no room left on the simplex).
    """
    if not bool(torch.isfinite(lower).all()) or bool((lower < 0).any()):
        raise ValueError("lower bounds must be finite and ≥ 0")
    s = 1.0 - lower.sum(-1)
    if not bool((s > 0).all()):
        raise ValueError(f"lower bounds must sum to less than 1, got a sum of {float(lower.sum(-1).max())}")
    return s[..., None, None] * H, c + (H @ lower.unsqueeze(-1)).squeeze(-1), s


def solve_simplex_qp(H: Tensor, c: Tensor | None = None, *, chunk_size: int | None = 4096) -> QPResult:
    """Solve ``min ½wᵀHw + cᵀw`` on the simplex for a batch, exactly.

    A batched primal–dual active-set iteration runs first: solve the KKT system
    on the current support, keep the entries with ``wᵢ > 0``, add those whose
    multiplier ``μᵢ`` is negative, stop when the KKT conditions hold (typically
    1–3 iterations for the filter's ``L + λI``).  Problems it has not settled
    after ``2N + 2`` iterations — it may cycle on hard problems — are solved by
    support enumeration (module docstring) for ``N ≤ MAX_ENUMERATION``, exact by
    construction, and above by a batched Mehrotra interior-point method whose
    support is then polished by active-set iterations started from it (:func:`_interior_point`).

    Args:
        H: ``[..., N, N]`` symmetric positive semidefinite (only the symmetric part is used;
            checked to :data:`PSD_TOLERANCE` by one batched Cholesky factorisation).
        c: ``[..., N]`` (default zero).
        chunk_size: problems per batched enumeration call (bounds memory), a positive integer
            (``None``: all in one call).

    Returns:
        :class:`QPResult` (its ``iterations`` counts the work of all three stages, see there).

    Raises:
        ValueError: non-finite entries (naming the batch index), bad shapes, ``N > MAX_COMPONENTS`` (64),
            an ``H`` that is not positive semidefinite (naming the batch index), or a ``chunk_size``
            that is not a positive integer.
    """
    H = torch.as_tensor(H)
    if not H.is_floating_point():
        H = H.to(torch.float64)
    if c is None:
        c = torch.zeros(H.shape[:-1], dtype=H.dtype, device=H.device)
    c = torch.as_tensor(c, dtype=H.dtype, device=H.device)
    _check_inputs(H, c)
    chunk_size = check_chunk_size(chunk_size)
    try:
        batch = broadcast_shapes(H.shape[:-2], c.shape[:-1])
    except RuntimeError:
        raise ValueError(f"the batch dims of H {tuple(H.shape)} and c {tuple(c.shape)} do not broadcast") from None
    N = H.shape[-1]
    Hf = H.expand(*batch, N, N).reshape(-1, N, N)
    cf = c.expand(*batch, N).reshape(-1, N)
    Hf = 0.5 * (Hf + Hf.transpose(-1, -2))
    _check_convex(Hf, tuple(batch))
    w, done, iterations = _active_set(Hf, cf)
    if not bool(done.all()):
        idx = (~done).nonzero().squeeze(-1)
        Hr, cr = Hf[idx], cf[idx]
        if N <= MAX_ENUMERATION:
            S = torch.as_tensor(_supports(N), device=H.device)  # [K, N]
            chunk_size = chunk_size or idx.numel()
            out = [
                _solve_chunk(Hr[i : i + chunk_size], cr[i : i + chunk_size], S)
                for i in range(0, idx.numel(), chunk_size)
            ]
            w = w.index_copy(0, idx, torch.cat(out))
            iterations += S.shape[0]
        else:
            w_ip, ip_iterations = _interior_point(Hr, cr)
            w = w.index_copy(0, idx, w_ip)
            iterations += ip_iterations
    w = w.reshape(*batch, N)
    return QPResult(w, kkt_residual(H.expand(*batch, N, N), c.expand(*batch, N), w), iterations)


_KKT_TOL = 1e-12


def _support_solve(H: Tensor, c: Tensor, m: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """KKT solutions with the entries outside the support mask ``m`` pinned to 0.

    Args:
        H: ``[B, N, N]``; c: ``[B, N]``; m: ``[B, K, N]`` (1.0 on the support).

    Returns:
        ``w [B, K, N]`` (zero where singular), the scaled KKT violation ``[B, K]``
        (inf where singular), and the multipliers ``μ [B, K, N]``.
    """
    N = H.shape[-1]
    # KKT matrix per (problem, support); variables off the support are pinned to 0 by identity rows
    top = torch.cat(
        (H.unsqueeze(1) * (m.unsqueeze(-1) * m.unsqueeze(-2)) + torch.diag_embed(1.0 - m), -m.unsqueeze(-1)), -1
    )
    bottom = torch.cat((m, torch.zeros_like(m[..., :1])), -1).unsqueeze(-2)
    A = torch.cat((top, bottom), -2)
    rhs = torch.cat((-c.unsqueeze(1) * m, torch.ones_like(m[..., :1])), -1)
    sol, info = torch.linalg.solve_ex(A, rhs.unsqueeze(-1))
    sol = sol.squeeze(-1)
    singular = info != 0
    w = torch.where(singular.unsqueeze(-1), torch.zeros_like(m), sol[..., :N] * m)
    g = (H.unsqueeze(1) @ w.unsqueeze(-1)).squeeze(-1) + c.unsqueeze(1)
    mu = (g - sol[..., N:]) * (1.0 - m)
    scale = (1.0 + H.abs().flatten(-2).amax(-1) + c.abs().amax(-1)).unsqueeze(-1)
    violation = torch.maximum((-w).clamp_min(0).amax(-1), (-mu).clamp_min(0).amax(-1) / scale)
    violation = torch.where(singular | ~torch.isfinite(violation), torch.full_like(violation, float("inf")), violation)
    return w, violation, mu


def _active_set(H: Tensor, c: Tensor, support: Tensor | None = None) -> tuple[Tensor, Tensor, int]:
    """Batched primal–dual active-set iterations from the ``support [B, N]`` (bool; default: every
    component); returns ``(w [B, N], settled [B], iterations)``."""
    B, N = c.shape
    if support is None:
        m = torch.ones(B, 1, N, dtype=H.dtype, device=H.device)
    else:
        m = support.to(H.dtype).unsqueeze(1)
    w_out = torch.zeros(B, N, dtype=H.dtype, device=H.device)
    done = torch.zeros(B, dtype=torch.bool, device=H.device)
    active = torch.arange(B, device=H.device)
    it = 0
    for it in range(1, 2 * N + 3):
        w, violation, mu = _support_solve(H[active], c[active], m)
        ok = violation[:, 0] <= _KKT_TOL
        w_ok = w[ok, 0].clamp_min(0.0)
        w_out[active[ok]] = w_ok / w_ok.sum(-1, keepdim=True)
        done[active[ok]] = True
        keep = ~ok
        if not bool(keep.any()):
            break
        support = m[keep, 0] > 0
        new = (support & (w[keep, 0] > 0)) | (~support & (mu[keep, 0] < 0))
        empty = ~new.any(-1)
        if bool(empty.any()):  # keep one entry: the lowest gradient
            g = (H[active[keep]] @ w[keep, 0].unsqueeze(-1)).squeeze(-1) + c[active[keep]]
            new[empty] = torch.nn.functional.one_hot(g[empty].argmin(-1), N).bool()
        m = new.to(H.dtype).unsqueeze(1)
        active = active[keep]
    return w_out, done, it


def _interior_point(H: Tensor, c: Tensor, max_iterations: int = 60, tol: float = 1e-13) -> tuple[Tensor, int]:
    """Batched Mehrotra predictor–corrector for ``[B, N]`` simplex QPs, then active-set iterations
    started from the identified support (their solution kept where it satisfies the KKT conditions).

    With slacks ``s`` (the multipliers of ``w ≥ 0``), ``ν`` (of ``Σw = 1``) and
    ``D = diag(s/w)``, each Newton step solves ``(H + D)Δw − 1Δν = r`` with
    ``1ᵀΔw = −r_p`` by one Cholesky factorisation per problem and iteration, shared
    by the predictor and the corrector.  Returns ``(w [B, N], iterations)``.
    """
    B, N = c.shape
    one = torch.ones(B, N, 1, dtype=H.dtype, device=H.device)
    w = torch.full((B, N), 1.0 / N, dtype=H.dtype, device=H.device)
    g = (H @ w.unsqueeze(-1)).squeeze(-1) + c
    nu = g.amin(-1, keepdim=True) - 1.0
    s = g - nu  # ≥ 1
    scale = 1.0 + H.abs().flatten(-2).amax(-1, keepdim=True) + c.abs().amax(-1, keepdim=True)
    it = 0
    for it in range(1, max_iterations + 1):
        r_d = (H @ w.unsqueeze(-1)).squeeze(-1) + c - nu - s
        r_p = w.sum(-1, keepdim=True) - 1.0
        mu = (w * s).mean(-1, keepdim=True)
        if bool(((r_d.abs().amax(-1, keepdim=True) / scale <= tol) & (r_p.abs() <= tol) & (mu / scale <= tol)).all()):
            break
        L, info = torch.linalg.cholesky_ex(H + torch.diag_embed(s / w))
        bad = info != 0
        if bool(bad.any()):  # H + D lost definiteness to rounding: regularise those problems
            L2 = torch.linalg.cholesky(
                H[bad]
                + torch.diag_embed(s[bad] / w[bad])
                + 1e-12 * scale[bad, :, None] * torch.eye(N, dtype=H.dtype, device=H.device)
            )
            L = L.index_put((bad.nonzero().squeeze(-1),), L2)
        Kone = torch.cholesky_solve(one, L).squeeze(-1)  # K⁻¹1

        def newton(r_c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            rhs = -r_d - r_c / w
            Kr = torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1)
            dnu = (-r_p - Kr.sum(-1, keepdim=True)) / Kone.sum(-1, keepdim=True)
            dw = Kr + dnu * Kone
            ds = -(r_c + s * dw) / w
            return dw, dnu, ds

        def step_length(v: Tensor, dv: Tensor) -> Tensor:
            ratio = torch.where(dv < 0, -v / dv, torch.full_like(v, float("inf")))
            return ratio.amin(-1, keepdim=True)  # largest step keeping v + α dv ≥ 0

        dw, dnu, ds = newton(w * s)  # affine scaling (predictor)
        a_aff = torch.minimum(step_length(w, dw), step_length(s, ds)).clamp(max=1.0)
        mu_aff = ((w + a_aff * dw) * (s + a_aff * ds)).mean(-1, keepdim=True)
        sigma = (mu_aff / mu).clamp(0.0, 1.0) ** 3
        dw, dnu, ds = newton(w * s + dw * ds - sigma * mu)  # corrector
        alpha = (0.995 * torch.minimum(step_length(w, dw), step_length(s, ds))).clamp(max=1.0)
        w, nu, s = w + alpha * dw, nu + alpha * dnu, s + alpha * ds
    # polish: active-set iterations from the support {w > 1e-9·max w}: a weight whose bound's multiplier is
    # nearly zero leaves the iterations only slowly (still ~1e-6 when they stop), and the first KKT solve on
    # the support then shows it negative and drops it
    support = w > 1e-9 * w.amax(-1, keepdim=True)
    polished, ok, _ = _active_set(H, c, support)
    w_final = torch.where(ok.unsqueeze(-1), polished, w.clamp_min(0.0))
    return w_final / w_final.sum(-1, keepdim=True), it


def _solve_chunk(H: Tensor, c: Tensor, S: Tensor) -> Tensor:
    """Support enumeration for ``[B, N]`` problems over the supports ``S [K, N]``."""
    B, N = c.shape
    m = S.to(H.dtype).unsqueeze(0).expand(B, -1, -1)
    w, violation, _ = _support_solve(H, c, m)
    # among supports meeting KKT to tolerance pick the lowest objective; if none does (numerical
    # trouble), the smallest violation
    wc = w.clamp_min(0)
    wc = wc / wc.sum(-1, keepdim=True).clamp_min(torch.finfo(H.dtype).tiny)
    obj = 0.5 * (wc.unsqueeze(-2) @ H[:, None] @ wc.unsqueeze(-1)).squeeze(-1).squeeze(-1) + (c[:, None] * wc).sum(-1)
    ok = violation <= _KKT_TOL
    key = torch.where(ok, obj, torch.full_like(obj, float("inf")))
    best = torch.where(ok.any(-1), key.argmin(-1), violation.argmin(-1))
    return wc.gather(1, best[:, None, None].expand(B, 1, N)).squeeze(1)


def _polish(H: np.ndarray, c: np.ndarray, w: np.ndarray, threshold: float = 1e-6) -> np.ndarray:
    """Re-solve the KKT system on the support an interior-point solution identifies.

    Interior-point iterates approach a face only as fast as the duality gap
    closes; where a multiplier is (nearly) zero the error in ``w`` is of order
    ``sqrt(gap)``.  Polishing — as in OSQP — fixes the identified inactive
    entries at zero and solves the equality-constrained problem exactly; the
    result is kept only if it is feasible and does not raise the objective.
    """
    S = w > threshold * w.max()
    k = int(S.sum())
    A = np.zeros((k + 1, k + 1))
    A[:k, :k] = H[np.ix_(S, S)]
    A[:k, k] = -1.0
    A[k, :k] = 1.0
    rhs = np.concatenate((-c[S], [1.0]))
    try:
        sol = np.linalg.solve(A, rhs)
    except np.linalg.LinAlgError:
        return w
    out = np.zeros_like(w)
    out[S] = sol[:k]
    obj = lambda v: 0.5 * v @ H @ v + c @ v  # noqa: E731
    if out.min() < 0 or obj(out) > obj(w) + 1e-15 * (1 + abs(obj(w))):
        return w
    return out


def _flat_problems(H, c) -> tuple[tuple[int, ...], np.ndarray, np.ndarray]:
    """``(batch shape, H [P, N, N], c [P, N])`` as float64 numpy, broadcast and flattened."""
    H = np.asarray(H, dtype=np.float64)
    N = H.shape[-1]
    c = np.zeros(H.shape[:-1]) if c is None else np.asarray(c, dtype=np.float64)
    batch = np.broadcast_shapes(H.shape[:-2], c.shape[:-1])
    return batch, np.broadcast_to(H, (*batch, N, N)).reshape(-1, N, N), np.broadcast_to(c, (*batch, N)).reshape(-1, N)


def solve_simplex_qp_clarabel(
    H: Tensor | np.ndarray, c: Tensor | np.ndarray | None = None, polish: bool = True, **settings
) -> np.ndarray:
    """Reference: Clarabel's interior-point solver called directly, one problem at a time.

    Args:
        H: ``[..., N, N]``; c: ``[..., N]``;
        polish: re-solve on the identified support (see :func:`_polish`) — needed
            for 1e-8 accuracy on degenerate problems (a zero multiplier);
        settings: ``clarabel.DefaultSettings`` fields
           (defaults: ``tol_gap_abs = tol_gap_rel = tol_feas = 1e-12``, quiet).

    Returns:
        ``w`` as a numpy array ``[..., N]``.
    """
    import clarabel
    import scipy.sparse as sp

    batch, Hf, cf = _flat_problems(H, c)
    N = Hf.shape[-1]
    A = sp.csc_matrix(np.vstack((np.ones((1, N)), -np.eye(N))))
    b = np.concatenate(([1.0], np.zeros(N)))
    cones = [clarabel.ZeroConeT(1), clarabel.NonnegativeConeT(N)]
    opts = clarabel.DefaultSettings()
    opts.verbose = False
    for key, value in {"tol_gap_abs": 1e-12, "tol_gap_rel": 1e-12, "tol_feas": 1e-12, **settings}.items():
        setattr(opts, key, value)
    out = np.empty_like(cf)
    for k in range(Hf.shape[0]):
        P = sp.csc_matrix(np.triu(0.5 * (Hf[k] + Hf[k].T)))
        sol = clarabel.DefaultSolver(P, cf[k], A, b, cones, opts).solve()
        out[k] = np.asarray(sol.x)
        if polish:
            out[k] = _polish(0.5 * (Hf[k] + Hf[k].T), cf[k], out[k])
    return out.reshape(*batch, N)


def solve_simplex_qp_cvxpy(H: Tensor | np.ndarray, c: Tensor | np.ndarray | None = None) -> np.ndarray:
    """Reference: the same problem through cvxpy with the CLARABEL solver (tolerances 1e-12), one problem at a time."""
    import cvxpy as cp

    batch, Hf, cf = _flat_problems(H, c)
    N = Hf.shape[-1]
    out = np.empty_like(cf)
    for k in range(Hf.shape[0]):
        w = cp.Variable(N)
        Hs = cp.psd_wrap(0.5 * (Hf[k] + Hf[k].T))
        prob = cp.Problem(cp.Minimize(0.5 * cp.quad_form(w, Hs) + cf[k] @ w), [cp.sum(w) == 1, w >= 0])
        prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12)
        out[k] = w.value
    return out.reshape(*batch, N)
