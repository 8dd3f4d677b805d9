"""Moment propagation of Gaussian components between measurements (method.md §2).

Every component follows the extended-Kalman moment equations

.. math::

    \\dot μ = f(μ, u),\\qquad \\dot P = A P + P A^T + g(μ) Q g(μ)^T,\\quad A = ∂f/∂x|_μ,

integrated with classic fourth-order Runge–Kutta over the interval ``dt`` (in
the transition-matrix form of :func:`propagate_moments`), the input ``u`` held
constant (zero-order hold).  All trajectories and
components advance in one batched call.

A step ``h = dt / substeps`` that RK4 cannot follow is refused (``ValueError``), not integrated: when a mode of
the moment equations at a component's mean has ``|λ|h`` beyond :data:`RK4_STABILITY_LIMIT` (a stiff model, or a
component far out where the drift is steep), RK4 amplifies a mode the dynamics damp and the moments run off to
1e45 and beyond within a few steps, finite and wrong.  The modes are the eigenvalues ``λᵢ`` of the drift's
Jacobian ``A`` for the mean and ``Φ``, and their sums ``λᵢ + λⱼ`` for the noise integral ``Ṡ = AS + SAᵀ + gQgᵀ``:
up to twice the largest, so a stiff model needs twice the substeps its mean alone would.  (``S`` restarts from 0
each step; its one-step increment ``h φ₁(h(λᵢ + λⱼ)) gQgᵀ``, ``φ₁(z) = 1 + z/2 + z²/6 + z³/24``, turns indefinite
where ``φ₁`` changes sign, at exactly ``z = −2.785`` on the real axis: the same limit.)  The check costs one
``‖A‖∞`` per RK4 step (``2‖A‖∞`` bounds every ``|λᵢ + λⱼ|``); the eigenvalues are computed only where that bound
exceeds the limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .models.base import ContinuousModel
from .shapes import broadcast_shapes

__all__ = ["moment_derivatives", "propagate_moments", "MomentRates", "RK4_STABILITY_LIMIT"]

#: ``|λ|h`` beyond which an RK4 step leaves its stability region on a decaying mode (the region meets the
#: negative real axis at −2.785); well before it the step's local error is already of the order of the solution.
RK4_STABILITY_LIMIT = 2.785
#: ``|λ|h`` the substeps suggested in the error message aim at (inside the region in every direction).
_SUGGESTED = 2.0


@dataclass(frozen=True)
class MomentRates:
    """Time derivatives of the moments at a point of the trajectory.

    Attributes:
        mean_rate: ``μ̇`` ``[..., n]``.
        cov_rate: ``Ṗ`` ``[..., n, n]``.
    """

    mean_rate: Tensor
    cov_rate: Tensor


def moment_derivatives(model: ContinuousModel, mean: Tensor, cov: Tensor, u: Tensor | None) -> MomentRates:
    """Right-hand side of the moment ODE: ``μ̇ = f(μ, u)``, ``Ṗ = AP + PAᵀ + gQgᵀ``.

    Args:
        model: the continuous-time model.
        mean: ``[..., n]``; cov: ``[..., n, n]``; u: input broadcastable to ``[..., m]``.
    """
    A = model.drift_jacobian(mean, u)
    AP = A @ cov
    Pdot = AP + AP.transpose(-1, -2) + model.process_noise(mean)
    return MomentRates(model.drift(mean, u), Pdot)


#: Components propagated per batched pass: the RK4 step is memory-bound, and chunks of this size keep its
#: [chunk, n, n] intermediates in cache.
PROPAGATION_CHUNK = 8192


def propagate_moments(
    model: ContinuousModel, mean: Tensor, cov: Tensor, u: Tensor | None, dt: float, substeps: int = 1
) -> tuple[Tensor, Tensor]:
    r"""Advance ``(μ, P)`` by ``dt`` with ``substeps`` RK4 steps.

    Each RK4 step integrates, from ``Φ = I`` and ``S = 0``,

    .. math:: \dot μ = f(μ, u),\quad \dot Φ = A(μ) Φ,\quad \dot S = A S + S A^T + g Q g^T

    and sets ``P ← Φ P Φᵀ + S``.  For the moment ODE this is the same solution as
    RK4 on ``Ṗ`` directly, to the same order, but the congruence ``ΦPΦᵀ``
    keeps ``P`` positive definite however ill-conditioned it is (a covariance
    with eigenvalues 1e-3 and 1e-14 after a single precise star, say), where
    truncation errors of a direct RK4 step on ``P`` can push the small
    eigenvalues negative.

    Args:
        model: the continuous-time model.
        mean: ``[..., n]``.
        cov: ``[..., n, n]`` symmetric.
        u: input ``[..., m]`` (broadcast against ``mean``'s leading dims) or ``None``.
        dt: interval (s), > 0.
        substeps: RK4 steps in the interval (≥ 1).

    Returns:
        ``(mean [..., n], cov [..., n, n])`` at ``t + dt``, covariance symmetrised.

    Batches of more than :data:`PROPAGATION_CHUNK` components are propagated in chunks of
    that many (the same arithmetic per component).
    """
    lead = broadcast_shapes(mean.shape[:-1], cov.shape[:-2], *(() if u is None else (u.shape[:-1],)))
    count = math.prod(lead)
    if count > PROPAGATION_CHUNK:
        n = mean.shape[-1]
        mf = mean.expand(*lead, n).reshape(-1, n)
        Pf = cov.expand(*lead, n, n).reshape(-1, n, n)
        uf = None if u is None else u.expand(*lead, u.shape[-1]).reshape(-1, u.shape[-1])
        parts = [
            _propagate(
                model,
                mf[a : a + PROPAGATION_CHUNK],
                Pf[a : a + PROPAGATION_CHUNK],
                None if uf is None else uf[a : a + PROPAGATION_CHUNK],
                dt,
                substeps,
                (lead, a),
            )
            for a in range(0, count, PROPAGATION_CHUNK)
        ]
        return torch.cat([q[0] for q in parts]).reshape(*lead, n), torch.cat([q[1] for q in parts]).reshape(*lead, n, n)
    return _propagate(model, mean, cov, u, dt, substeps, (None, 0))


def _check_step(A: Tensor, h: float, dt: float, where: tuple[tuple[int, ...] | None, int]) -> None:
    """Refuse the RK4 step ``h`` where the Jacobian ``A [..., n, n]`` has an eigenvalue with ``|λ|h`` beyond
    :data:`RK4_STABILITY_LIMIT` (module docstring); ``where``: ``(the call's batch shape, this chunk's offset in it)``
    for a chunk of the flattened batch, ``(None, 0)`` for the whole call (indices in ``A``'s batch dims)."""
    bound = 2.0 * A.abs().sum(-1).amax(-1) * h  # 2‖A‖∞ h ≥ |λᵢ + λⱼ| h
    if not bool((bound > RK4_STABILITY_LIMIT).any()):
        return
    flagged = (bound > RK4_STABILITY_LIMIT).reshape(-1).nonzero().squeeze(-1)
    lam = torch.linalg.eigvals(A.reshape(-1, *A.shape[-2:])[flagged])  # [k, n]
    modes = (lam[:, :, None] + lam[:, None, :]).flatten(-2)  # [k, n²]: the noise integral's λᵢ + λⱼ (2λᵢ among them)
    radius = modes.abs().amax(-1)
    beyond = (radius * h > RK4_STABILITY_LIMIT).nonzero().squeeze(-1)
    if beyond.numel() == 0:
        return
    k = int(beyond[0])
    worst = modes[k, modes[k].abs().argmax()]
    lead, offset = where  # a chunk of the flattened batch ``lead``, or (None, 0): A's own batch dims
    shape = A.shape[:-2] if lead is None else lead
    index = tuple(int(i) for i in torch.unravel_index(torch.tensor(offset + int(flagged[k])), shape)) if shape else ()
    needed = math.ceil(float(radius[k]) * dt / _SUGGESTED)
    raise ValueError(
        f"the RK4 step of {h:g} s (dt / substeps) cannot follow the model's drift at batch index {index}: the "
        f"covariance's mode λᵢ + λⱼ = {complex(worst):.4g} 1/s there (λ: eigenvalues of the drift's Jacobian) has "
        f"|λᵢ + λⱼ|·step = {float(radius[k]) * h:.3g}, beyond RK4's stability limit {RK4_STABILITY_LIMIT} (the "
        f"moments would run off, finite and wrong); use at least substeps={needed} for dt={dt:g} s (stable; more for "
        "accuracy: RK4's error falls as the step⁴)"
    )


def _propagate(
    model: ContinuousModel,
    mean: Tensor,
    cov: Tensor,
    u: Tensor | None,
    dt: float,
    substeps: int,
    where: tuple[tuple[int, ...] | None, int],
) -> tuple[Tensor, Tensor]:
    h = dt / substeps
    n = mean.shape[-1]
    eye = torch.eye(n, dtype=mean.dtype, device=mean.device)

    def rates(m: Tensor, Phi: Tensor, S: Tensor, A: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        A = model.drift_jacobian(m, u) if A is None else A
        AS = A @ S
        return model.drift(m, u), A @ Phi, AS + AS.transpose(-1, -2) + model.process_noise(m)

    for _ in range(substeps):
        Phi = eye.expand_as(cov)
        S = torch.zeros_like(cov)
        A = model.drift_jacobian(mean, u)
        _check_step(A, h, dt, where)
        k1 = rates(mean, Phi, S, A)
        k2 = rates(mean + 0.5 * h * k1[0], Phi + 0.5 * h * k1[1], S + 0.5 * h * k1[2])
        k3 = rates(mean + 0.5 * h * k2[0], Phi + 0.5 * h * k2[1], S + 0.5 * h * k2[2])
        k4 = rates(mean + h * k3[0], Phi + h * k3[1], S + h * k3[2])
        mean = mean + (h / 6.0) * (k1[0] + 2.0 * (k2[0] + k3[0]) + k4[0])
        Phi = Phi + (h / 6.0) * (k1[1] + 2.0 * (k2[1] + k3[1]) + k4[1])
        S = S + (h / 6.0) * (k1[2] + 2.0 * (k2[2] + k3[2]) + k4[2])
        cov = Phi @ cov @ Phi.transpose(-1, -2) + 0.5 * (S + S.transpose(-1, -2))
        cov = 0.5 * (cov + cov.transpose(-1, -2))
    return mean, cov
