"""The attitude model's Galerkin pair integrals on lanes: ``log z_ij``, ``E[ℓᵢ]`` and ``E[ℓⱼ]`` per pair.

The same mathematics as :func:`agsf_torch.fpke.galerkin_matrices` on its closed-form route
(method.md §3b) for :class:`~agsf_torch.models.AttitudeModel`, one lane per pair ``(i, j)`` of
components: with ``Σ = Pᵢ + Pⱼ`` (Cholesky factor ``L_Σ``), ``d = μᵢ − μⱼ`` and
``[Kᵀ | y | Σ⁻¹] = Σ⁻¹[Pᵢ | d | I]`` (:func:`~agsf_torch.fpke.pairs.product_gaussians`),

.. math:: m = μ_i − P_i y,\\quad S = P_i − P_i K^T,\\quad
          \\log z = −½\\big(d^Ty + \\log\\det Σ + n\\log 2π\\big),

the model's Gaussian moments under ``N(m, S)``
(:func:`~agsf_torch.attitude.physics.fokker_planck_moments`) and ``E[ℓ]`` of each side
(:func:`~agsf_torch.fpke.moments.residual_mean`) from ``Πδ = ∓y``, ``ΠS = I − Kᵀ`` or ``Kᵀ`` and
``ΠSΠ − Π = −Σ⁻¹``; the components' moment rates ``μ̇ᵢ, Ṗᵢ`` are formed in the kernel, once per
component.  Written on entries (:mod:`agsf_torch.fused.algebra`): every solve is a
6×6 (3×3) triangular sweep on lanes, the bias rows of the moments' Jacobian and the MRP-only
diffusion pattern are structural zeros, and one pass over memory replaces the generic path's
hundreds of batched kernels.
"""

from __future__ import annotations

import math

from torch import Tensor

from ..attitude import physics
from .algebra import Entry, add, cholesky, cholesky_solve, dot, mul, neg, sub, symmetric_part, zeros
from .lanes import entries, pair_index, symmetric_to_pairs, to_pairs
from .propagation import attitude_rates

__all__ = ["attitude_pair_kernel", "residual_mean", "product_gaussian"]

Mat = list[list[Entry]]


def residual_mean(
    mom: dict,
    D1: list[Entry],
    D0: list[Entry],
    mean_rate: list[Entry],
    cov_rate: Mat,
    wbar: list[Entry],
    PiS: Mat,
    Q: Mat,
) -> Entry:
    """``E[ℓ]`` of one side of a pair (:func:`agsf_torch.fpke.moments.residual_mean` for a diagonal
    ``D = φD₁ + D₀``, on entries): ``wbar = Πδ``, ``PiS = ΠS``, ``Q = ΠSΠ − Π``."""
    n = len(wbar)
    rate_terms = add(
        dot((wbar[k], mean_rate[k]) for k in range(n)),
        mul(
            0.5,
            add(
                dot((cov_rate[a][b], mul(wbar[a], wbar[b])) for a in range(n) for b in range(n)),
                dot((cov_rate[a][b], Q[a][b]) for a in range(n) for b in range(n)),
            ),
        ),
    )
    J = mom["transport_jacobian"]
    transport = add(
        dot((mom["transport"][k], wbar[k]) for k in range(n)),
        dot((J[a][b], PiS[a][b]) for a in range(n) for b in range(n)),
    )
    grad, hess = mom["gradient"], mom["hessian"]
    g = [dot((PiS[a][b], grad[b]) for b in range(n)) for a in range(n)]
    Y = [[dot((PiS[a][t], hess[t][b]) for t in range(n)) for b in range(n)] for a in range(n)]
    base = [add(mul(wbar[k], wbar[k]), Q[k][k]) for k in range(n)]
    field_part = dot((D1[k], base[k]) for k in range(n))
    field_extra = add(
        mul(2.0, dot((D1[k], mul(wbar[k], g[k])) for k in range(n))),
        dot((D1[a], mul(Y[a][b], PiS[a][b])) for a in range(n) for b in range(n)),
    )
    constant_part = dot((D0[k], base[k]) for k in range(n))
    diffusion = add(add(mul(mom["field"], field_part), field_extra), constant_part)
    return sub(add(rate_terms, mom["scalar"]), add(transport, diffusion))


def product_gaussian(mi: list[Entry], Pi: Mat, mj: list[Entry], Pj: Mat) -> dict:
    """``pᵢpⱼ = z N(m, S)`` on entries (:func:`~agsf_torch.fpke.pairs.product_gaussians`, module docstring):
    ``mean`` ``m``, ``cov`` ``S`` (symmetrised), ``log_z``, ``gain`` ``Kᵀ = Σ⁻¹Pᵢ``, ``y = Σ⁻¹(μᵢ − μⱼ)``,
    ``sum_precision`` ``Σ⁻¹`` (symmetrised) and ``ok`` (``[C]`` bool: every pivot of ``Σ = Pᵢ + Pⱼ`` positive)."""
    n = len(mi)
    Sigma = [[add(Pi[a][b], Pj[a][b]) for b in range(n)] for a in range(n)]
    L, inv, ok = cholesky(Sigma)
    d = [sub(mi[k], mj[k]) for k in range(n)]
    Kt_cols = [cholesky_solve(L, inv, [Pi[a][b] for a in range(n)]) for b in range(n)]  # column b of Σ⁻¹Pᵢ
    Kt = [[Kt_cols[b][a] for b in range(n)] for a in range(n)]
    y = cholesky_solve(L, inv, d)
    inv_cols = [cholesky_solve(L, inv, [1.0 if a == b else None for a in range(n)]) for b in range(n)]
    Sinv = symmetric_part([[inv_cols[b][a] for b in range(n)] for a in range(n)])
    mean = [sub(mi[a], dot((Pi[a][k], y[k]) for k in range(n))) for a in range(n)]
    S = symmetric_part(
        [[sub(Pi[a][b], dot((Pi[a][k], Kt[k][b]) for k in range(n))) for b in range(n)] for a in range(n)]
    )
    log_det = 2.0 * sum(L[k][k].log() for k in range(n))
    log_z = mul(-0.5, add(add(dot((d[k], y[k]) for k in range(n)), log_det), n * math.log(2.0 * math.pi)))
    return {"mean": mean, "cov": S, "log_z": log_z, "gain": Kt, "y": y, "sum_precision": Sinv, "ok": ok}


def attitude_pair_kernel(
    means: Tensor, covs: Tensor, u: Tensor, c: Tensor, sv2: Tensor, su2: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """``(log z_ij, E[ℓᵢ], E[ℓⱼ])`` ``[T, P]`` for the ``P = N(N+1)/2`` pairs ``i ≤ j`` of every
    trajectory (module docstring; pairs in the order of ``torch.triu_indices``).  The components' moment
    rates ``μ̇ = f(μ)``, ``Ṗ = AP + PAᵀ + gQgᵀ`` are formed here, once per component
    (:func:`~agsf_torch.fused.propagation.attitude_rates`), and gathered to the pairs with ``μ`` and ``P``.

    Args:
        means: ``μ`` ``[T, N, n]``; covs: ``P`` ``[T, N, n, n]``; u: the gyro rate ``[T, 3]`` (rad/s; the
        3-state model's known bias removed); c: ``σ_v²/32``; sv2, su2: ``σ_v²``, ``σ_u²`` (0-d tensors).
    """
    T, N, n = means.shape
    m_c = entries(means.reshape(T * N, n), (n,))
    P_c = entries(covs.reshape(T * N, n, n), (n, n))
    u_c = list(u.t().repeat_interleave(N, dim=1).unbind(0))  # the gyro rate on every component lane
    f_c, _, Pdot_c = attitude_rates(m_c, zeros(n), P_c, u_c, sv2, su2)
    first, second = pair_index(N)
    P = len(first)
    (mi, Pi, rate_i, cov_rate_i), (mj, Pj, rate_j, cov_rate_j) = (
        (
            [to_pairs(v, T, N, index) for v in m_c],
            symmetric_to_pairs(P_c, T, N, index),
            [to_pairs(v, T, N, index) for v in f_c],
            symmetric_to_pairs(Pdot_c, T, N, index),
        )
        for index in (first, second)
    )
    ue = [to_pairs(v, T, N, first) for v in u_c]
    g = product_gaussian(mi, Pi, mj, Pj)
    Kt, y, Sinv, mean, S, log_z = (g[k] for k in ("gain", "y", "sum_precision", "mean", "cov", "log_z"))
    mom = physics.fokker_planck_moments(mean, S, ue, c)
    D1 = [c] * 3 + [None] * (n - 3)
    D0 = [None] * 3 + [mul(0.5, su2)] * (n - 3)
    Q = [[neg(v) for v in row] for row in Sinv]
    I_minus_Kt = [[sub(1.0 if a == b else None, Kt[a][b]) for b in range(n)] for a in range(n)]
    e_i = residual_mean(mom, D1, D0, rate_i, cov_rate_i, [neg(v) for v in y], I_minus_Kt, Q)
    e_j = residual_mean(mom, D1, D0, rate_j, cov_rate_j, y, Kt, Q)
    return tuple(v.reshape(T, P) for v in (log_z, e_i, e_j))
