"""The attitude model's moment propagation on lanes: RK4 of ``(μ, Φ, S)`` and the congruence, unrolled.

The same mathematics as :func:`agsf_torch.propagation.propagate_moments` for
:class:`~agsf_torch.models.AttitudeModel` (method.md §1–2): per RK4 step, from ``Φ = I``, ``S = 0``,

.. math:: \\dot μ = f(μ, ω̃),\\quad \\dot Φ = A(μ) Φ,\\quad \\dot S = A S + S A^T + g Q g^T,
          \\qquad P ← Φ P Φ^T + S,

with ``f = [¼B(p)ω; 0]``, ``A = [[F, −¼B(p)], [0, 0]]``, ``F = ½(pωᵀ − ωpᵀ − [ω×] + (ωᵀp)I)``,
``ω = ω̃ − b`` and ``gQgᵀ = diag((σ_v²/16)(1+s)² I₃, σ_u² I₃)``, the functions of
:mod:`agsf_torch.attitude.physics` applied to lanes.  Written on entries
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

from ..attitude import physics
from .algebra import Entry, add, cholesky, dot, identity, matmul, matmul_t, mul, zeros
from .lanes import entries, stack_entries

__all__ = ["attitude_propagation_kernel", "attitude_rates", "positive_pivots", "propagation_kernel"]

Mat = list[list[Entry]]


def attitude_rates(m: list[Entry], Phi: Mat, S: Mat, u: list[Tensor], sv2: Tensor, su2: Tensor):
    """``(μ̇, Φ̇, Ṡ) = (f, AΦ, AS + SAᵀ + gQgᵀ)`` at ``(m, Φ, S)`` (module docstring), ``f``, ``A`` and ``gQgᵀ``
    from :mod:`agsf_torch.attitude.physics`; ``u`` the gyro rate (3-state: bias removed)."""
    n = len(m)
    s = physics.mrp_norm2(m[:3])
    A = physics.drift_jacobian(m, u, s)
    G = physics.process_noise(m, sv2, su2, s)
    AS = matmul(A, S)
    low = [[add(add(AS[i][j], AS[j][i]), G[i][j]) for j in range(i + 1)] for i in range(n)]
    Sdot = [[low[i][j] if j <= i else low[j][i] for j in range(n)] for i in range(n)]
    return physics.drift(m, u, s), matmul(A, Phi), Sdot


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
        k1 = attitude_rates(m, Phi, S, ue, sv2, su2)
        k2 = attitude_rates(*_stage([m, Phi, S], k1, 0.5 * h), ue, sv2, su2)
        k3 = attitude_rates(*_stage([m, Phi, S], k2, 0.5 * h), ue, sv2, su2)
        k4 = attitude_rates(*_stage([m, Phi, S], k3, h), ue, sv2, su2)
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
