"""The error-state chart of the multiplicative EKF: quaternion reference and body-frame error.

Conventions (:mod:`agsf_torch.rotations`): scalar-last quaternions, ``C(q)`` maps
inertial to body, ``C(q_a ⊗ q_b) = C(q_a) C(q_b)``, ``δq(φ) = rotvec_to_quat(φ)``.  A
body-frame error ``δθ`` enters as ``q = δq(δθ) ⊗ q̂``; a belief in the global MRP chart
maps to ``(q̂, b̂, P_δ)`` by ``T = blockdiag(¼B(p), I)`` and back (see
:mod:`agsf_torch.filters.multiplicative`).  Also the coefficient series of
constant-rate rotation kinematics used by the discrete error dynamics.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..models.base import MeasurementModel
from ..rotations import (
    attitude_error_jacobian,
    cross_matrix,
    mrp_kinematics_matrix,
    mrp_to_quat,
    quat_multiply,
    quat_to_mrp,
    rotvec_to_quat,
)

__all__ = [
    "mrp_to_error_state",
    "error_state_to_mrp",
    "rotation_series",
    "exp_and_right_jacobian",
    "symmetric_part",
    "ErrorStateMeasurement",
]

_SERIES_TERMS = 10
_SERIES_BELOW = 1.0  # |φ| (rad) below which the coefficients come from their Taylor series


def rotation_series(theta: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The five coefficient functions of constant-rate rotation kinematics, ``f_m(θ) = Σ_k (−θ²)^k / (2k+m)!``:

    .. math::

        f_1 = \\frac{\\sin θ}{θ},\\; f_2 = \\frac{1 - \\cos θ}{θ^2},\\; f_3 = \\frac{θ - \\sin θ}{θ^3},\\;
        f_4 = \\frac{θ^2/2 - 1 + \\cos θ}{θ^4},\\; f_5 = \\frac{\\sin θ - θ + θ^3/6}{θ^5}

    Closed forms lose digits to cancellation for small θ (and are 0/0 at θ = 0), so
    below θ = 1 the series (10 terms, truncation < 1/21! ≈ 2e-20) is used.

    Args:
        theta: ``[...]`` ≥ 0 (rad).

    Returns:
        ``(f1, f2, f3, f4, f5)``, each ``[...]``.
    """
    small = theta < _SERIES_BELOW
    t = torch.where(small, torch.full_like(theta, 2.0 * _SERIES_BELOW), theta)  # safe argument of the closed forms
    s, c = torch.sin(t), torch.cos(t)
    closed = torch.stack(
        (s / t, (1.0 - c) / t**2, (t - s) / t**3, (0.5 * t**2 - 1.0 + c) / t**4, (s - t + t**3 / 6.0) / t**5), -1
    )
    k = torch.arange(_SERIES_TERMS, dtype=theta.dtype, device=theta.device)
    coeff = torch.tensor(
        [[(-1.0) ** j / math.factorial(2 * j + m) for m in range(1, 6)] for j in range(_SERIES_TERMS)],
        dtype=theta.dtype,
        device=theta.device,
    )  # [K, 5]
    series = (theta * theta).unsqueeze(-1) ** k @ coeff  # Σ_k θ^{2k} (−1)^k/(2k+m)!
    return tuple(torch.where(small.unsqueeze(-1), series, closed).unbind(-1))  # type: ignore[return-value]


def exp_and_right_jacobian(phi: Tensor) -> tuple[Tensor, Tensor, tuple[Tensor, ...]]:
    """``exp(−[φ×]) = I − f₁K + f₂K²`` and ``J(φ) = I − f₂K + f₃K²`` with ``K = [φ×]``.

    ``J`` is the Jacobian of the body-frame composition, ``δq(φ + ε) = δq(J(φ) ε) ⊗ δq(φ) + O(ε²)``
    (the SO(3) right Jacobian), and ``∫₀^Δt exp(−[ω×]τ) dτ = Δt J(ωΔt)``.

    Args:
        phi: ``[..., 3]`` (rad).

    Returns:
        ``(exp [..., 3, 3], J [..., 3, 3], (f1, …, f5) each [..., 1, 1])``.
    """
    K = cross_matrix(phi)
    K2 = K @ K
    f = tuple(v[..., None, None] for v in rotation_series(torch.linalg.vector_norm(phi, dim=-1)))
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    return eye - f[0] * K + f[1] * K2, eye - f[1] * K + f[2] * K2, f


def _mrp_map(p: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """``T = blockdiag(¼B(p), I)`` and its closed-form inverse ``blockdiag(4Bᵀ/(1+s)², I)``, ``[..., n, n]``."""
    G, G_inv = 0.25 * mrp_kinematics_matrix(p), attitude_error_jacobian(p)  # ¼B(p) and its inverse 4Bᵀ/(1+s)²
    if n == 3:
        return G, G_inv
    T = torch.eye(n, dtype=p.dtype, device=p.device).expand(*p.shape[:-1], n, n).clone()
    T_inv = T.clone()
    T[..., :3, :3] = G
    T_inv[..., :3, :3] = G_inv
    return T, T_inv


def symmetric_part(P: Tensor) -> Tensor:
    """``½(P + Pᵀ)`` of covariances ``P [..., n, n]``: the rounding of a congruence made symmetric again."""
    return 0.5 * (P + P.transpose(-1, -2))


def mrp_to_error_state(mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """MRP belief → MEKF state: ``(q̂, b̂, P_δ)``.

    .. math:: \\hat q = q(p),\\qquad P_δ = T^{-1} P\\, T^{-T},\\quad T^{-1} = \\operatorname{blockdiag}(4B(p)^T/(1+s)^2, I)

    Args:
        mean: ``[..., n]`` (``n`` = 3: ``p``; 6: ``[p; b]``, rad/s), any MRP set.
        cov: ``[..., n, n]`` (MRP², (rad/s)²).

    Returns:
        ``(q [..., 4], b [..., 3] (empty [..., 0] when n = 3), P_δ [..., n, n] (rad², (rad/s)²))``.
    """
    n = mean.shape[-1]
    p = mean[..., :3]
    _, T_inv = _mrp_map(p, n)
    return mrp_to_quat(p), mean[..., 3:], symmetric_part(T_inv @ cov @ T_inv.transpose(-1, -2))


def error_state_to_mrp(quat: Tensor, bias: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """MEKF state → MRP belief (short set ``|p| ≤ 1``): mean ``[p(q̂); b̂]``, cov ``T P_δ Tᵀ``.

    Args:
        quat: ``[..., 4]``; bias: ``[..., 3]`` or ``[..., 0]``; cov: ``[..., n, n]``.

    Returns:
        ``(mean [..., n], cov [..., n, n])``.
    """
    p = quat_to_mrp(quat)
    n = cov.shape[-1]
    T, _ = _mrp_map(p, n)
    mean = torch.cat((p, bias.expand(*p.shape[:-1], n - 3)), -1)
    return mean, symmetric_part(T @ cov @ T.transpose(-1, -2))


class ErrorStateMeasurement(MeasurementModel):
    """A measurement model seen from the MEKF's error state about a fixed reference.

    ``h_δ(δx) = h(x(δx))`` with the chart ``x(δx) = [p(δq(δθ) ⊗ q̂); b̂ + δb]`` and

    .. math:: H_δ(δx) = H(x)\\, \\operatorname{blockdiag}\\left(\\tfrac14 B(p(x))\\, J(δθ),\\; I\\right)

    (``J = I`` at ``δx = 0``; the iterated update relinearises at ``δx ≠ 0``).  Noise,
    mask and block size are the wrapped model's, so :func:`~agsf_torch.update.kalman_update`
    and :func:`~agsf_torch.gating.innovation_gate` run on it unchanged.
    """

    #: Not probed by :func:`~agsf_torch.models.contract.check_measurement_elementwise` (checked otherwise).
    elementwise_checked = True

    def __init__(self, measurement: MeasurementModel, quat: Tensor, bias: Tensor) -> None:
        super().__init__()
        self.inner = measurement
        self.quat = quat
        self.bias = bias
        self.block_size = measurement.block_size

    def state(self, dx: Tensor) -> Tensor:
        p = quat_to_mrp(quat_multiply(*torch.broadcast_tensors(rotvec_to_quat(dx[..., :3]), self.quat)))
        if dx.shape[-1] == 3:
            return p
        return torch.cat((p, self.bias + dx[..., 3:]), -1)

    def predict(self, x: Tensor) -> Tensor:
        return self.inner.predict(self.state(x))

    def jacobian(self, x: Tensor) -> Tensor:
        state = self.state(x)
        T, _ = _mrp_map(state[..., :3], x.shape[-1])
        _, J, _ = exp_and_right_jacobian(x[..., :3])
        T = T.clone()
        T[..., :3, :3] = T[..., :3, :3] @ J
        return self.inner.jacobian(state) @ T

    def noise_cov(self) -> Tensor:
        return self.inner.noise_cov()

    def mask(self) -> Tensor | None:
        return self.inner.mask()
