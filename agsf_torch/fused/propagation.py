"""The attitude model's moment propagation on lanes: RK4 of ``(μ, Φ, S)`` and the congruence, unrolled.

The same mathematics as :func:`agsf_torch.propagation.propagate_moments` for
:class:`~agsf_torch.models.AttitudeModel` (method.md §1–2): per RK4 step, from ``Φ = I``, ``S = 0``,

.. math:: \\dot μ = f(μ, ω̃),\\quad \\dot Φ = A(μ) Φ,\\quad \\dot S = A S + S A^T + g Q g^T,
          \\qquad P ← Φ P Φ^T + S,

with ``f = [¼B(p)ω; 0]``, ``A = [[F, −¼B(p)], [0, 0]]``, ``F = ½(pωᵀ − ωpᵀ − [ω×] + (ωᵀp)I)``,
``ω = ω̃ − b`` and ``gQgᵀ = diag((σ_v²/16)(1+s)² I₃, σ_u² I₃)``.  Written on entries
(:mod:`agsf_torch.fused.algebra`), the structure is known when the kernel is traced: ``A``'s bias
rows are zero, so ``Φ`` keeps its ``[0, I]`` bias rows and no arithmetic is emitted for them;
``gQgᵀ`` is diagonal.  ``P ← ΦPΦᵀ + S`` is formed on the lower triangle (symmetric by
construction, positive definite as a congruence plus a positive semi-definite ``S``), and the
kernel also returns whether every pivot of its Cholesky factorisation is positive, so the
filter checks definiteness without a factorisation of its own.
"""

from __future__ import annotations

import functools

from torch import Tensor

from .algebra import Entry, add, cholesky, dot, identity, matmul, matmul_t, mul, sub, zeros
from .lanes import entries, stack_entries

__all__ = ["attitude_propagation_kernel", "attitude_rates", "positive_pivots", "propagation_kernel"]

Mat = list[list[Entry]]


def attitude_rates(m: list[Entry], Phi: Mat, S: Mat, u: list[Tensor], sv2: Tensor, su2: Tensor, n: int):
    """``(μ̇, Φ̇, Ṡ)`` at ``(m, Φ, S)`` (module docstring); ``u`` the gyro rate (3-state: bias removed)."""
    p = m[:3]
    w = [sub(u[k], m[3 + k]) for k in range(3)] if n == 6 else list(u)
    s = add(add(mul(p[0], p[0]), mul(p[1], p[1])), mul(p[2], p[2]))
    pw = add(add(mul(p[0], w[0]), mul(p[1], w[1])), mul(p[2], w[2]))
    one_s = sub(1.0, s)
    x, y, z = p
    B = [
        [add(one_s, mul(2.0, mul(x, x))), mul(2.0, sub(mul(x, y), z)), mul(2.0, add(mul(x, z), y))],
        [mul(2.0, add(mul(x, y), z)), add(one_s, mul(2.0, mul(y, y))), mul(2.0, sub(mul(y, z), x))],
        [mul(2.0, sub(mul(x, z), y)), mul(2.0, add(mul(y, z), x)), add(one_s, mul(2.0, mul(z, z)))],
    ]
    f = [mul(0.25, add(add(mul(B[i][0], w[0]), mul(B[i][1], w[1])), mul(B[i][2], w[2]))) for i in range(3)]
    wx = [[None, mul(-1.0, w[2]), w[1]], [w[2], None, mul(-1.0, w[0])], [mul(-1.0, w[1]), w[0], None]]
    F = [
        [mul(0.5, add(sub(sub(mul(p[i], w[j]), mul(w[i], p[j])), wx[i][j]), pw if i == j else None)) for j in range(3)]
        for i in range(3)
    ]
    if n == 6:
        A = [F[i] + [mul(-0.25, B[i][j]) for j in range(3)] for i in range(3)] + zeros(3, 6)
        f = f + [None, None, None]
    else:
        A = F
    g_p = mul(sv2 / 16.0, mul(add(1.0, s), add(1.0, s)))
    G = [[(g_p if i < 3 else su2) if i == j else None for j in range(n)] for i in range(n)]
    AS = matmul(A, S)
    Sdot = [[add(add(AS[i][j], AS[j][i]), G[i][j]) if j <= i else None for j in range(n)] for i in range(n)]
    Sdot = [[Sdot[i][j] if j <= i else Sdot[j][i] for j in range(n)] for i in range(n)]
    return f, matmul(A, Phi), Sdot


def _stage(x, k, c):
    if isinstance(x, list):
        return [_stage(a, b, c) for a, b in zip(x, k)]
    return add(x, mul(c, k))


def _combine(x, k1, k2, k3, k4, h):
    if isinstance(x, list):
        return [_combine(*args, h) for args in zip(x, k1, k2, k3, k4)]
    inner = add(add(k1, mul(2.0, add(k2, k3))), k4)
    return add(x, mul(h / 6.0, inner))


def positive_pivots(P: Mat) -> Tensor:
    """Whether every pivot of the Cholesky factorisation of ``P`` (lower triangle read) is positive
    and finite: ``P`` is numerically positive definite (``[C]`` bool)."""
    return cholesky(P)[2]


def attitude_propagation_kernel(
    mean: Tensor, cov: Tensor, u: Tensor, dt: Tensor, sv2: Tensor, su2: Tensor, substeps: int = 1
) -> tuple[Tensor, Tensor, Tensor]:
    """Propagate every lane over ``dt`` (module docstring), batch-first in and out.

    Args:
        mean: ``[c, n]`` (``n`` = 3: MRP; 6: MRP and bias, rad/s); cov: ``[c, n, n]``;
        u: the gyro rate ``[c, 3]`` (rad/s; the 3-state model's known bias already removed);
        dt: the interval (s), a 0-d tensor; sv2, su2: ``σ_v²``, ``σ_u²`` (0-d tensors);
        substeps: RK4 steps in the interval (static).

    Returns:
        ``(mean [c, n], cov [c, n, n], positive_definite [c] bool)``.
    """
    c, n = mean.shape
    m = entries(mean, (n,))
    P = entries(cov, (n, n))
    ue = entries(u, (3,))
    h = dt / substeps
    for _ in range(substeps):
        Phi, S = identity(n), zeros(n)
        k1 = attitude_rates(m, Phi, S, ue, sv2, su2, n)
        k2 = attitude_rates(*_stage([m, Phi, S], k1, 0.5 * h), ue, sv2, su2, n)
        k3 = attitude_rates(*_stage([m, Phi, S], k2, 0.5 * h), ue, sv2, su2, n)
        k4 = attitude_rates(*_stage([m, Phi, S], k3, h), ue, sv2, su2, n)
        m, Phi, S = _combine([m, Phi, S], k1, k2, k3, k4, h)
        PPhiT = matmul_t(P, Phi)
        low = [[add(dot((Phi[i][t], PPhiT[t][j]) for t in range(n)), S[i][j]) for j in range(i + 1)] for i in range(n)]
        P = [[low[i][j] if j <= i else low[j][i] for j in range(n)] for i in range(n)]
    ok = positive_pivots(P)
    return stack_entries(m, c), stack_entries(P, c), ok


_KERNELS: dict[int, object] = {}


def propagation_kernel(substeps: int):
    """:func:`attitude_propagation_kernel` with ``substeps`` fixed: one object per value, so that the
    compiled kernel is reused (:func:`~agsf_torch.fused.lanes.run_in_chunks` caches by kernel)."""
    if substeps not in _KERNELS:
        _KERNELS[substeps] = functools.partial(attitude_propagation_kernel, substeps=substeps)
    return _KERNELS[substeps]
