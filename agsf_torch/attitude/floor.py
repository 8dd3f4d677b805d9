"""The physical floor: the steady-state attitude (and bias) error covariance of a gyro and a star camera.

The multiplicative EKF (:class:`~agsf_torch.filters.MultiplicativeEKF`) linearised about a constant attitude
(``ω̂ = 0``) is a linear time-invariant Kalman filter, and its covariance recursion is the Riccati recursion;
its limit, the solution of the discrete algebraic Riccati equation (DARE), is the accuracy no filter on the same
sensors can beat (the filter is optimal for the linear model).  The scenario: a gyro with angle random walk
``σ_v`` (rad/s^½) and, in the 6-state model, rate random walk ``σ_u`` (rad/s^{3/2}), propagated in steps of
``Δt``; a star frame every ``T = kΔt`` with ``m`` stars of noise ``σ`` (rad per axis across each direction).

**Between frames** the MEKF's own error-state transition and Farrenkopf discrete noise at ``ω̂ = 0``
(:meth:`MultiplicativeEKF.transition`, ``discrete_noise="farrenkopf"``), composed over the ``k`` steps (for a
body turning at a constant rate ``ω``, ``rate=``: the transition at that rate with the exact discrete noise, a
time-invariant model all the same):

.. math::

    Φ_T = Φ(Δt)^k = \\begin{bmatrix} I & -T I \\\\ 0 & I \\end{bmatrix},\\qquad
    Q_T = \\sum_{i=0}^{k-1} Φ(Δt)^i Q_d(Δt) Φ(Δt)^{iT}
        = \\begin{bmatrix} (σ_v^2T + \\tfrac13σ_u^2T^3) I & -\\tfrac12σ_u^2T^2 I \\\\
                           -\\tfrac12σ_u^2T^2 I & σ_u^2T\\, I \\end{bmatrix}

(Farrenkopf's ``Q_d`` is exact at ``ω̂ = 0``, so the composition equals the one-step form over ``T``; the
3-state model keeps the attitude blocks, ``Φ_T = I``, ``Q_T = σ_v²T I``).

**At a frame** the star-vector update (:class:`~agsf_torch.models.StarVectorMeasurement`, ``H_j = [(C r_j)×]``)
adds the information

.. math:: J = \\sum_{j=1}^{m} \\frac{I - b_j b_j^T}{σ^2}

on the attitude block (``[b×]ᵀ[b×] = I − bbᵀ``; the same for the ``"tangent"`` noise model, whose radial
variance the rows across ``b`` never see).  Without star directions the per-star information is averaged over
isotropically distributed directions, ``E[I − bbᵀ] = I − ⅓I = ⅔I``, so ``J = (2m/3σ²) I``: **an assumption**,
optimistic about the roll axis of a narrow-field camera, whose stars lie close to its boresight.  With
``directions`` (body frame) the average is taken over them instead.  The update is written as the
pseudo-measurement ``H = [Lᵀ 0]``, ``R = I₃`` with ``L Lᵀ = J`` (Cholesky), which carries the same information.

**The floor.**  The a-priori covariance just before a frame solves the DARE (``scipy.linalg.solve_discrete_are``)

.. math:: P^- = Φ_T P^- Φ_T^T - Φ_T P^- H^T (H P^- H^T + R)^{-1} H P^- Φ_T^T + Q_T,

the a-posteriori one just after it is the Joseph-form update (``S = H P⁻ Hᵀ + R`` by Cholesky,
``K = P⁻ Hᵀ S⁻¹``),

.. math:: P^+ = (I - KH) P^- (I - KH)^T + K R K^T,

and between frames ``P(jΔt) = Φ(Δt)^j P⁺ Φ(Δt)^{jT} + Σ_{i<j} Φ(Δt)^i Q_d Φ(Δt)^{iT}`` grows back to ``P⁻`` at
``j = k``.  With isotropic information each axis is Farrenkopf's single-axis problem with the measurement noise
``σ_n² = 3σ²/(2m)`` (Farrenkopf, *Analytic steady-state accuracy solutions for two common spacecraft attitude
estimators*, J. Guidance and Control 1(4), 1978; Crassidis & Junkins, *Optimal Estimation of Dynamic Systems*,
attitude estimation chapter): with ``S_u = σ_u T^{3/2}/σ_n``, ``S_v = σ_v T^{1/2}/σ_n``,

.. math::

    γ = \\tfrac12 S_u + \\sqrt{4 + S_v^2 + S_u^2/12},\\qquad ξ = \\tfrac12\\left(γ + \\sqrt{γ^2 - 4}\\right),

    P^+_{θθ} = σ_n^2 (1 - ξ^{-2}),\\quad P^-_{θθ} = σ_n^2 (ξ^2 - 1),\\quad
    P^+_{bb} = \\frac{σ_n^2}{T^2}\\left(S_u (ξ - ξ^{-1}) - \\tfrac12 S_u^2\\right),

which the tests hold the DARE solution to (``tests/attitude/test_floor.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import torch
from torch import Tensor

from ..filters.multiplicative import MultiplicativeEKF
from ..filters.options import positive_int
from ..models.attitude import AttitudeModel
from ..models.star_vectors import unit_vectors

__all__ = ["Floor", "riccati_floor", "frame_information", "ARCSEC_PER_RAD"]

#: Seconds of arc in a radian (180·3600/π).
ARCSEC_PER_RAD = 180.0 * 3600.0 / math.pi

#: The largest relative distance of ``frame_interval / dt`` from an integer taken as that integer.
_STEP_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Floor:
    """The steady-state error covariance of the MEKF's linearised model (module docstring).

    Covariances are of the error state ``δx = [δθ; δb]`` (body-frame rotation in rad, bias in rad/s) or ``δθ``
    (3-state), float64 ``[n, n]``; the axes are the body axes the star directions are given in.

    Attributes:
        P_before: ``P⁻``, just before a frame (the DARE solution).
        P_after: ``P⁺``, just after a frame.
        P_mean: the mean of ``P(t)`` over the ``k`` instants ``t = 0, Δt, …, T − Δt`` after a frame
            (``P(0) = P⁺``): what a root-mean-square error over every gyro step of a long run measures.
        information: ``J`` ``[3, 3]`` (rad⁻²), the information of one frame on the attitude.
        frame_interval: ``T`` (s).
        dt: ``Δt`` (s), the propagation step.
    """

    P_before: Tensor
    P_after: Tensor
    P_mean: Tensor
    information: Tensor
    frame_interval: float
    dt: float

    @property
    def steps_per_frame(self) -> int:
        """``k = T/Δt``."""
        return round(self.frame_interval / self.dt)

    @property
    def arcsec_before(self) -> Tensor:
        """Per-axis attitude standard deviation just before a frame, ``sqrt(diag P⁻_θθ)`` (arcsec), ``[3]``."""
        return _attitude_sigma(self.P_before)

    @property
    def arcsec_after(self) -> Tensor:
        """Per-axis attitude standard deviation just after a frame, ``sqrt(diag P⁺_θθ)`` (arcsec), ``[3]``."""
        return _attitude_sigma(self.P_after)

    @property
    def arcsec_mean(self) -> Tensor:
        """Per-axis root-mean-square over time of the attitude error between frames, ``sqrt(diag P̄_θθ)``
        (arcsec), ``[3]`` (:attr:`P_mean`; the root of the mean variance, not the mean of the deviations)."""
        return _attitude_sigma(self.P_mean)

    @property
    def bias_before(self) -> Tensor | None:
        """Per-axis bias standard deviation just before a frame (rad/s), ``[3]``; ``None`` in the 3-state model."""
        return _bias_sigma(self.P_before)

    @property
    def bias_after(self) -> Tensor | None:
        """Per-axis bias standard deviation just after a frame (rad/s), ``[3]``; ``None`` in the 3-state model."""
        return _bias_sigma(self.P_after)


def _attitude_sigma(P: Tensor) -> Tensor:
    return P.diagonal()[:3].sqrt() * ARCSEC_PER_RAD


def _bias_sigma(P: Tensor) -> Tensor | None:
    return P.diagonal()[3:].sqrt() if P.shape[-1] == 6 else None


def _positive(name: str, value: Any, unit: str) -> float:
    """``value`` as a finite float > 0; ``ValueError`` naming ``name`` otherwise (``bool`` refused)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ValueError(f"{name} must be a finite number > 0 ({unit}), got {value!r}")
    if not (math.isfinite(float(value)) and float(value) > 0.0):
        raise ValueError(f"{name} must be a finite number > 0 ({unit}), got {value!r}")
    return float(value)


def frame_information(stars_per_frame: int, sigma_star: float, directions: Any = None) -> Tensor:
    """The information of one star frame on the body-frame attitude error, ``J`` ``[3, 3]`` (rad⁻²):

    .. math:: J = \\frac{m}{σ^2} \\frac{1}{K} \\sum_{j=1}^{K} (I - b_j b_j^T)
              \\quad\\text{or, without directions,}\\quad J = \\frac{2m}{3σ^2} I

    (``m`` stars per frame, each with the per-star information averaged over the ``K`` given directions or
    over isotropic ones).  With ``K = m`` directions this is exactly the information of that frame.

    Args:
        stars_per_frame: ``m`` ≥ 1.
        sigma_star: ``σ`` (rad per axis across the direction), > 0.
        directions: unit vectors ``[K, 3]`` (body frame), or ``None`` (isotropic).

    Raises:
        ValueError: naming the argument; also when the directions are all parallel (the rotation about them
            unobserved: ``J`` singular).
    """
    m = positive_int("stars_per_frame", stars_per_frame)
    sigma = _positive("sigma_star", sigma_star, "rad")
    eye = torch.eye(3, dtype=torch.float64)
    if directions is None:
        return (2.0 * m / (3.0 * sigma**2)) * eye
    b = torch.as_tensor(directions, dtype=torch.float64)
    if b.dim() != 2 or b.shape[-1] != 3 or b.shape[0] < 1:
        raise ValueError(f"directions must be unit vectors [K, 3] (body frame), got shape {tuple(b.shape)}")
    if not bool(torch.isfinite(b).all()):
        raise ValueError("directions must be finite")
    b = unit_vectors("directions", b)
    J = (m / sigma**2) * (eye - b.transpose(0, 1) @ b / b.shape[0])
    J = 0.5 * (J + J.transpose(0, 1))
    if int(torch.linalg.cholesky_ex(J).info) != 0 or float(torch.linalg.eigvalsh(J)[0]) <= 1e-12 * float(J.trace()):
        raise ValueError(
            "directions are all parallel: a frame of them leaves the rotation about them unobserved (no floor)"
        )
    return J


def riccati_floor(
    sigma_v: float,
    sigma_u: float | None,
    frame_interval: float,
    stars_per_frame: int,
    sigma_star: float,
    *,
    dt: float | None = None,
    directions: Any = None,
    rate: Any = None,
) -> Floor:
    """The steady-state error covariance of the MEKF on a gyro and a star camera (module docstring).

    Args:
        sigma_v: gyro angle random walk σ_v (rad/s^½), > 0.
        sigma_u: gyro rate random walk σ_u (rad/s^{3/2}), > 0, for the 6-state model (bias estimated); ``None``
            for the 3-state model (bias known).
        frame_interval: ``T`` (s), the time between star frames, > 0 (frames every ``k`` steps: ``T = k·dt``).
        stars_per_frame: ``m``, stars per frame, an integer ≥ 1.
        sigma_star: ``σ``, camera noise (rad per axis across each star direction), > 0.
        dt: the propagation (gyro) step Δt (s); ``T/Δt`` must be an integer.  Default ``T`` (one step per
            frame; at ``ω̂ = 0`` the floor does not depend on it, only :attr:`Floor.P_mean` does).
        directions: star directions ``[K, 3]`` (body frame) over which the per-star information is averaged
            (:func:`frame_information`), or ``None`` for isotropic directions.
        rate: a constant body rate ``ω`` ``[3]`` (rad/s), or ``None`` for ``ω = 0``.  A turning body carries its
            error, fixed in inertial space, past the camera's directions: the error-state transition
            ``Φ = e^{-[ω×]Δt}…`` (with the exact discrete noise, :meth:`MultiplicativeEKF.transition`) is then no
            longer the identity on the attitude, while the model stays time-invariant (the floor still solves a
            DARE); a narrow-field camera's boresight axis is observed through the other axes as the body turns.

    Returns:
        :class:`Floor` (``n = 6`` with ``sigma_u``, 3 without).

    Raises:
        ValueError: naming the argument: a non-positive or non-finite ``sigma_v``, ``sigma_u``,
            ``frame_interval``, ``dt`` or ``sigma_star``; ``stars_per_frame`` not a positive integer; ``T/Δt``
            not an integer; directions that are all parallel.

    Example::

        floor = riccati_floor(3.16e-7, None, 1.0, 5, 10e-6, dt=0.1)   # the paper's case 1
        floor.arcsec_before, floor.arcsec_after                         # σ per axis (arcsec), [3] each
    """
    sigma_v = _positive("sigma_v", sigma_v, "rad/s^½")
    if sigma_u is not None:
        sigma_u = _positive("sigma_u", sigma_u, "rad/s^{3/2}; None for the 3-state model")
    T = _positive("frame_interval", frame_interval, "s")
    dt = T if dt is None else _positive("dt", dt, "s")
    ratio = T / dt
    k = round(ratio)
    if k < 1 or abs(ratio - k) > _STEP_TOLERANCE * max(1.0, ratio):
        raise ValueError(f"frame_interval / dt must be a positive integer (steps per frame), got {T!r} / {dt!r}")
    J = frame_information(stars_per_frame, sigma_star, directions)

    omega = torch.zeros(3, dtype=torch.float64) if rate is None else torch.as_tensor(rate, dtype=torch.float64)
    if omega.shape != (3,) or not bool(torch.isfinite(omega).all()):
        raise ValueError(f"rate must be a finite body rate [3] (rad/s) or None, got {rate!r}")
    model = AttitudeModel(estimate_bias=sigma_u is not None, sigma_v=sigma_v, sigma_u=sigma_u or 0.0)
    noise = "farrenkopf" if rate is None else "exact"  # the same at ω = 0; exact for a turning body
    Phi, Q = MultiplicativeEKF(model, discrete_noise=noise).transition(omega, dt)
    n = Phi.shape[-1]
    eye = torch.eye(n, dtype=torch.float64)
    Phi_T, Q_T = eye, torch.zeros(n, n, dtype=torch.float64)
    for _ in range(k):
        Phi_T, Q_T = Phi @ Phi_T, Phi @ Q_T @ Phi.T + Q

    H = torch.zeros(3, n, dtype=torch.float64)
    H[:, :3] = torch.linalg.cholesky(J).T  # Hᵀ R⁻¹ H = blockdiag(J, 0) with R = I₃
    R = torch.eye(3, dtype=torch.float64)
    P_before = torch.from_numpy(scipy.linalg.solve_discrete_are(Phi_T.T.numpy(), H.T.numpy(), Q_T.numpy(), R.numpy()))
    P_before = 0.5 * (P_before + P_before.T)

    L = torch.linalg.cholesky(H @ P_before @ H.T + R)
    K = torch.cholesky_solve(H @ P_before, L).T  # P⁻Hᵀ S⁻¹ (S symmetric)
    I_KH = eye - K @ H
    P_after = I_KH @ P_before @ I_KH.T + K @ R @ K.T
    P_after = 0.5 * (P_after + P_after.T)

    P, total = P_after, torch.zeros_like(P_after)
    for _ in range(k):
        total = total + P
        P = Phi @ P @ Phi.T + Q
    return Floor(
        P_before=P_before,
        P_after=P_after,
        P_mean=total / k,
        information=J,
        frame_interval=T,
        dt=dt,
    )
