"""USQUE, the unscented quaternion estimator, and the unscented core it is built on.

Crassidis & Markley, "Unscented filtering for spacecraft attitude estimation", JGCD 26(4), 2003
(the filter); Julier & Uhlmann, "A new extension of the Kalman filter to nonlinear systems", 1997
(the unscented transformation); Lefebvre, Bruyninckx & De Schutter, "Comment on 'A new method for the
nonlinear transformation of means and covariances in filters and estimators'", IEEE TAC 47(8), 2002
(the unscented update as a statistical linear regression); García-Fernández, Svensson, Morelande &
Särkkä, "Posterior linearization filter: principles and implementation using sigma points",
IEEE TSP 63(20), 2015 (its iterated form).

**The unscented core** works on a plain vector state ``x [..., n]`` with covariance ``P [..., n, n]``;
the ``2n + 1`` sigma points are a tensor dimension (``[..., 2n+1, n]``), never a Python loop.  With
``P = L Lᵀ`` (Cholesky) and the spread ``λ`` (Crassidis & Markley's, the scaled unscented
transformation's ``λ = α²(n + κ) − n``):

.. math::

    χ_0 = \\hat x,\\quad χ_i = \\hat x + \\sqrt{n+λ}\\, L e_i,\\quad χ_{n+i} = \\hat x - \\sqrt{n+λ}\\, L e_i
    \\quad (i = 1..n),

    W_0 = \\frac{λ}{n+λ},\\quad W_i = \\frac{1}{2(n+λ)},\\qquad
    \\bar y = \\sum_i W_i\\, γ_i,\\quad P_{yy} = \\sum_i W_i (γ_i - \\bar y)(γ_i - \\bar y)^T,\\quad
    P_{xy} = \\sum_i W_i (χ_i - \\hat x)(γ_i - \\bar y)^T

(:func:`sigma_points`, :func:`unscented_weights`, :func:`unscented_moments`,
:func:`unscented_cross_covariance`; the mean and the covariance share the weights, as in the paper).

**The unscented measurement update** (:func:`unscented_update`) is the Kalman step with ``Pνν = Pyy + R``
and ``K = Pxy Pνν⁻¹``:

.. math:: \\hat x^+ = \\hat x + K(\\tilde y - \\bar y),\\qquad P^+ = P - K P_{νν} K^T .

``P − K Pνν Kᵀ`` subtracts two nearly equal matrices after an informative measurement (a star camera after
a wide prior) and loses positive definiteness to rounding; the Joseph form, a sum of positive semidefinite
terms, does not, but needs an ``H``.  The unscented update *is* the Kalman update of the statistical
linear regression of ``h`` on the sigma points (Lefebvre et al.):

.. math::

    \\tilde H = P_{xy}^T P^{-1},\\qquad Ω = \\sum_i W_i\\, r_i r_i^T,\\quad
    r_i = γ_i - \\bar y - \\tilde H (χ_i - \\hat x)\\quad (= P_{yy} - \\tilde H P \\tilde H^T),

    y = \\bar y + \\tilde H (x - \\hat x) + e,\\qquad e \\sim N(0, R + Ω),

for which ``H̃ P H̃ᵀ + R + Ω = Pyy + R`` and ``P H̃ᵀ = Pxy``: the same gain and mean, and the Joseph form
``(I − KH̃) P (I − KH̃)ᵀ + K(R + Ω)Kᵀ`` equals ``P − K Pνν Kᵀ`` algebraically.  So the update hands this
linear model to the project's Kalman step (:func:`~agsf_torch.update.kalman_update`: Cholesky solves,
information form where ``Pνν`` is too ill-conditioned, masks, the Joseph form, symmetrisation,
``log N(ỹ; ȳ, Pνν)``).  ``H̃`` comes from two triangular solves with ``L`` (no inverse), and ``Ω`` is a
weighted sum of outer products, positive semidefinite by construction for ``λ ≥ 0`` (a negative ``λ``
gives the centre point a negative weight; then ``R + Ω`` may be indefinite).  ``iterations > 1`` is the
iterated posterior linearisation of García-Fernández et al.: the regression is redone on sigma points of
the current posterior and the prior updated again with it (the first iteration is the unscented update).

**USQUE** (:class:`USQUE`) puts the core on the attitude: its error state is the generalised Rodrigues
parameters (GRP) of the error quaternion, its reference a quaternion (:mod:`~agsf_torch.filters.multiplicative`
states the conventions, which are the project's: scalar-last, ``q = δq ⊗ q̂`` with a body-frame error).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from ..mixture import GaussianMixture
from ..models.attitude import AttitudeModel
from ..models.base import MeasurementModel
from ..rotations import quat_conjugate, quat_multiply, quat_to_mrp, rotvec_to_quat
from ..update import ComponentUpdate, kalman_update
from .base import BaseFilter, UpdateFrame
from .error_state import error_state_to_mrp, mrp_to_error_state, symmetric_part

__all__ = [
    "USQUE",
    "GRPErrorMeasurement",
    "grp_to_quat",
    "quat_to_grp",
    "sigma_points",
    "unscented_weights",
    "unscented_moments",
    "unscented_cross_covariance",
    "statistical_linearisation",
    "unscented_update",
]


# ============================================================================ the unscented core
def _cholesky(cov: Tensor, what: str) -> Tensor:
    """Lower Cholesky factor of ``cov [..., n, n]``; ``ValueError`` naming ``what`` and the first trajectory
    where it is not positive definite."""
    L, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        idx = (info != 0).nonzero()[0].tolist()
        raise ValueError(f"{what} is not positive definite at trajectory index {tuple(idx)}: no sigma points")
    return L


def _check_spread(n: int, lam: float) -> float:
    lam = float(lam)
    if not (math.isfinite(lam) and n + lam > 0.0):
        raise ValueError(f"the sigma-point spread λ must be finite with n + λ > 0 (n = {n}), got λ = {lam}")
    return lam


def unscented_weights(n: int, lam: float, *, like: Tensor) -> Tensor:
    """The weights of the ``2n + 1`` sigma points, ``[2n+1]``, in ``like``'s dtype and device:

    .. math:: W_0 = λ/(n+λ),\\qquad W_i = 1/(2(n+λ))\\quad (i = 1..2n),

    for the mean and the covariance alike (Crassidis & Markley; they sum to 1).

    Args:
        n: the state dimension; lam: the spread ``λ`` (``n + λ > 0``).
    """
    lam = _check_spread(n, lam)
    w = torch.full((2 * n + 1,), 0.5 / (n + lam), dtype=like.dtype, device=like.device)
    w[0] = lam / (n + lam)
    return w


def _points_from_factor(mean: Tensor, L: Tensor, lam: float) -> Tensor:
    """``[x̂, x̂ + √(n+λ) L e_i, x̂ − √(n+λ) L e_i]`` ``[..., 2n+1, n]`` from ``mean [..., n]`` and ``L [..., n, n]``."""
    n = L.shape[-1]
    spread = math.sqrt(n + lam) * L.transpose(-1, -2)  # row i: √(n+λ) L e_i
    mean = mean.unsqueeze(-2)
    batch = torch.broadcast_shapes(mean.shape[:-2], spread.shape[:-2])
    center = mean.expand(*batch, 1, n)
    return torch.cat((center, center + spread, center - spread), -2)


def sigma_points(mean: Tensor, cov: Tensor, lam: float = 1.0) -> Tensor:
    """The ``2n + 1`` symmetric sigma points of ``N(mean, cov)`` (module docstring), from the Cholesky factor.

    Args:
        mean: ``[..., n]``; cov: ``[..., n, n]`` symmetric positive definite (leading dims broadcast).
        lam: the spread ``λ``, ``n + λ > 0`` (default 1, USQUE's).

    Returns:
        ``χ [..., 2n+1, n]``: ``χ_0 = mean``, then ``mean + √(n+λ) L e_i`` for ``i = 1..n``, then the ``n``
        opposite points.

    Raises:
        ValueError: ``cov`` not positive definite (naming the trajectory), or ``n + λ ≤ 0``.
    """
    lam = _check_spread(mean.shape[-1], lam)
    return _points_from_factor(mean, _cholesky(cov, "the covariance"), lam)


def unscented_moments(points: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """The weighted mean and covariance of transformed sigma points:

    .. math:: \\bar y = \\sum_i W_i γ_i,\\qquad P_{yy} = \\sum_i W_i (γ_i - \\bar y)(γ_i - \\bar y)^T

    (symmetrised).

    Args:
        points: ``γ [..., S, d]`` (``S = 2n + 1`` sigma points); weights: ``[S]`` (:func:`unscented_weights`).

    Returns:
        ``(ȳ [..., d], P_yy [..., d, d])``.
    """
    mean = weights @ points
    dev = points - mean.unsqueeze(-2)
    return mean, symmetric_part((weights[:, None] * dev).transpose(-1, -2) @ dev)


def unscented_cross_covariance(
    points_x: Tensor, mean_x: Tensor, points_y: Tensor, mean_y: Tensor, weights: Tensor
) -> Tensor:
    """``P_xy = Σᵢ Wᵢ (χᵢ − x̂)(γᵢ − ȳ)ᵀ``.

    Args:
        points_x: ``χ [..., S, n]``; mean_x: ``[..., n]``; points_y: ``γ [..., S, d]``; mean_y: ``[..., d]``;
        weights: ``[S]``.

    Returns:
        ``[..., n, d]``.
    """
    dx = (points_x - mean_x.unsqueeze(-2)) * weights[:, None]
    return dx.transpose(-1, -2) @ (points_y - mean_y.unsqueeze(-2))


def _evaluate(h: Callable[[Tensor], Tensor], points: Tensor) -> Tensor:
    """``h`` on ``points [..., S, n]``, called with the sigma-point dim first (``[S, ..., n]``, as
    :func:`~agsf_torch.update.evaluate_measurement` calls a measurement with the component dim first, so that a
    measurement whose tensors carry only the trajectory dims broadcasts); returns ``[..., S, d]``."""
    return h(points.movedim(-2, 0)).movedim(0, -2)


def statistical_linearisation(
    mean: Tensor, cov: Tensor, h: Callable[[Tensor], Tensor], lam: float = 1.0
) -> tuple[Tensor, Tensor, Tensor]:
    """The statistical linear regression of ``h`` on the sigma points of ``N(mean, cov)`` (module docstring):
    ``h(x) ≈ ȳ + H̃ (x − mean) + e``, ``e ~ N(0, Ω)``.

    .. math:: \\tilde H = P_{xy}^T P^{-1} = (L^{-T} L^{-1} P_{xy})^T,\\qquad
              Ω = \\sum_i W_i\\, r_i r_i^T,\\quad r_i = γ_i - \\bar y - \\tilde H (χ_i - \\hat x)

    ``H̃`` by two triangular solves with ``L`` (``P = LLᵀ``), never an inverse; ``Ω = P_yy − H̃ P H̃ᵀ`` is summed
    from the residuals, so it is positive semidefinite for ``λ ≥ 0``.

    Args:
        mean: ``[..., n]``; cov: ``[..., n, n]`` positive definite.
        h: ``[S, ..., n]`` → ``[S, ..., d]``, elementwise over leading dims (called once, on all sigma points).
        lam: the spread ``λ``.

    Returns:
        ``(ȳ [..., d], H̃ [..., d, n], Ω [..., d, d])``.
    """
    n = mean.shape[-1]
    lam = _check_spread(n, lam)
    L = _cholesky(cov, "the covariance")
    X = _points_from_factor(mean, L, lam)
    Y = _evaluate(h, X)
    weights = unscented_weights(n, lam, like=mean)
    y_mean, _ = unscented_moments(Y, weights)
    Pxy = unscented_cross_covariance(X, mean, Y, y_mean, weights)
    A = torch.linalg.solve_triangular(L, Pxy, upper=False)  # L⁻¹ Pxy
    H = torch.linalg.solve_triangular(L.transpose(-1, -2), A, upper=True).transpose(-1, -2)  # Pxyᵀ L⁻ᵀ L⁻¹
    resid = Y - y_mean.unsqueeze(-2) - (X - mean.unsqueeze(-2)) @ H.transpose(-1, -2)
    Omega = symmetric_part((weights[:, None] * resid).transpose(-1, -2) @ resid)
    return y_mean, H, Omega


class _RegressionMeasurement(MeasurementModel):
    """The linear measurement ``h(x) = ȳ + H̃ (x − x_c)`` with noise ``R + Ω`` of a statistical linearisation about
    ``x_c`` (what :func:`~agsf_torch.update.kalman_update` updates with in :func:`unscented_update`)."""

    elementwise_checked = True

    def __init__(self, center: Tensor, y_mean: Tensor, H: Tensor, noise: Tensor, mask: Tensor | None) -> None:
        super().__init__()
        self.center, self.y_mean, self.H, self.noise, self._mask = center, y_mean, H, noise, mask

    def predict(self, x: Tensor) -> Tensor:
        return self.y_mean + (self.H @ (x - self.center).unsqueeze(-1)).squeeze(-1)

    def jacobian(self, x: Tensor) -> Tensor:
        return self.H.expand(*torch.broadcast_shapes(x.shape[:-1], self.H.shape[:-2]), *self.H.shape[-2:])

    def noise_cov(self) -> Tensor:
        return self.noise

    def mask(self) -> Tensor | None:
        return self._mask


def unscented_update(
    mean: Tensor,
    cov: Tensor,
    y: Tensor,
    h: Callable[[Tensor], Tensor],
    noise_cov: Tensor,
    *,
    lam: float = 1.0,
    mask: Tensor | None = None,
    iterations: int = 1,
) -> ComponentUpdate:
    """The unscented Kalman update of ``N(mean, cov)`` with ``ỹ = h(x) + v``, ``v ~ N(0, R)`` (module docstring).

    .. math::

        P_{νν} = P_{yy} + R,\\quad K = P_{xy} P_{νν}^{-1},\\quad \\hat x^+ = \\hat x + K(\\tilde y - \\bar y),\\quad
        P^+ = (I - K\\tilde H) P (I - K\\tilde H)^T + K (R + Ω) K^T \\;(= P - K P_{νν} K^T),

    by :func:`statistical_linearisation` and :func:`~agsf_torch.update.kalman_update` (Cholesky solves, Joseph
    form, symmetrised).  Masked entries are removed exactly as there (they change neither the state nor the
    likelihood; a trajectory without a valid entry is returned unchanged).  With ``iterations = j > 1`` the
    regression is redone about the ``(j−1)``-th posterior and the prior updated with it (iterated posterior
    linearisation); on a linear ``h`` every iteration gives the Kalman update.

    Args:
        mean: ``[..., n]``; cov: ``[..., n, n]`` positive definite.
        y: ``[..., d]``.
        h: the measurement function, ``[S, ..., n]`` → ``[S, ..., d]`` (sigma-point dim first; e.g. a
            :class:`~agsf_torch.models.MeasurementModel`'s ``predict``).
        noise_cov: ``R``, ``[d, d]`` or ``[..., d, d]``.
        lam: the spread ``λ`` (``n + λ > 0``).
        mask: entry validity ``[..., d]`` bool, or ``None`` (all valid).
        iterations: regressions (≥ 1).

    Returns:
        The :class:`~agsf_torch.update.ComponentUpdate` of one component: ``means [..., 1, n]``,
        ``covs [..., 1, n, n]``, ``log_likelihood [...]`` (``log N(ỹ; ȳ, Pνν)`` over the valid entries),
        ``nis [..., 1]`` (``νᵀPνν⁻¹ν``), ``dof [...]``, ``innovation`` ``ỹ − ȳ`` and ``innovation_cov`` ``Pνν``
        of the last regression.
    """
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
    batch = torch.broadcast_shapes(mean.shape[:-1], cov.shape[:-2])
    n = mean.shape[-1]
    mean, cov = mean.expand(*batch, n), cov.expand(*batch, n, n)
    log_w = torch.zeros(batch + (1,), dtype=mean.dtype, device=mean.device)
    R = noise_cov.to(mean)
    center, spread = mean, cov
    for _ in range(iterations):
        y_mean, H, Omega = statistical_linearisation(center, spread, h, lam)
        linear = _RegressionMeasurement(center, y_mean, H, R + Omega, mask)
        result = kalman_update(log_w, mean.unsqueeze(-2), cov.unsqueeze(-3), y, linear, 1, mask=mask, mixture_nis=False)
        center, spread = result.means[..., 0, :], result.covs[..., 0, :, :]
    return result


# ============================================================================ the GRP chart
def _grp_scale(a: float, f: float | None) -> tuple[float, float]:
    a = float(a)
    if not (math.isfinite(a) and 0.0 <= a <= 1.0):
        raise ValueError(f"the GRP parameter a must lie in [0, 1], got {a}")
    f = 2.0 * (a + 1.0) if f is None else float(f)
    if not (math.isfinite(f) and f > 0.0):
        raise ValueError(f"the GRP scale f must be finite and > 0, got {f}")
    return a, f


def quat_to_grp(dq: Tensor, a: float = 1.0, f: float | None = None) -> Tensor:
    """Generalised Rodrigues parameters of an error quaternion (Crassidis & Markley):

    .. math:: δp = f\\, \\frac{δq_{1:3}}{a + δq_4},

    with the sign of ``δq`` chosen so that ``δq_4 ≥ 0`` (the rotation of at most π; ``q`` and ``−q`` are one
    attitude).  ``a = 0, f = 1``: the Gibbs vector; ``a = 1, f = 1``: the MRP; the default ``f = 2(a+1)``
    makes ``δp`` equal the rotation vector to third order (``a = 1, f = 4``: ``δp = 4 tan(θ/4) e``).

    Args:
        dq: ``[..., 4]`` unit, scalar-last; a: in ``[0, 1]``; f: ``> 0`` (``None``: ``2(a+1)``).

    Returns:
        ``[..., 3]`` (rad for the default ``f``).
    """
    a, f = _grp_scale(a, f)
    dq = dq * torch.where(dq[..., 3:] < 0, -1.0, 1.0).to(dq)
    return f * dq[..., :3] / (a + dq[..., 3:])


def grp_to_quat(dp: Tensor, a: float = 1.0, f: float | None = None) -> Tensor:
    """The error quaternion of generalised Rodrigues parameters (the inverse of :func:`quat_to_grp`):

    .. math:: δq_4 = \\frac{-a|δp|^2 + f\\sqrt{f^2 + (1 - a^2)|δp|^2}}{f^2 + |δp|^2},\\qquad
              δq_{1:3} = \\frac{a + δq_4}{f}\\, δp .

    Args:
        dp: ``[..., 3]``; a, f: as :func:`quat_to_grp`.

    Returns:
        Unit quaternion ``[..., 4]``, scalar-last.
    """
    a, f = _grp_scale(a, f)
    s = (dp * dp).sum(-1, keepdim=True)
    q4 = (f * torch.sqrt(f * f + (1.0 - a * a) * s) - a * s) / (f * f + s)
    return torch.cat(((a + q4) * dp / f, q4), -1)


class GRPErrorMeasurement(MeasurementModel):
    """A measurement model seen from USQUE's error state about a fixed reference:
    ``h_δ(δx) = h(x(δx))`` with the chart

    .. math:: x(δx) = \\left[p\\big(δq(δp) ⊗ \\hat q\\big);\\; \\hat b + δb\\right],\\qquad δx = [δp; δb],

    ``δq(δp)`` of :func:`grp_to_quat` and ``p(·)`` the short-set MRP.  Noise, mask and block size are the wrapped
    model's; the Jacobian (used only by the innovation gate) is ``torch.func``'s.

    Args:
        measurement: any :class:`~agsf_torch.models.MeasurementModel` of the MRP state ``[p]`` or ``[p; b]``.
        quat: the reference ``q̂ [..., 4]``; bias: ``b̂ [..., 3]`` (``[..., 0]`` in the 3-state model).
        a, f: the GRP parameters.
    """

    #: Not probed by :func:`~agsf_torch.models.contract.check_measurement_elementwise` (the wrapped model is).
    elementwise_checked = True

    def __init__(
        self, measurement: MeasurementModel, quat: Tensor, bias: Tensor, a: float = 1.0, f: float | None = None
    ) -> None:
        super().__init__()
        self.inner = measurement
        self.quat = quat
        self.bias = bias
        self.a, self.f = _grp_scale(a, f)
        self.block_size = measurement.block_size

    def state(self, dx: Tensor) -> Tensor:
        """``x(δx)`` ``[..., n]`` of ``δx [..., n]`` (class docstring)."""
        dq, q = torch.broadcast_tensors(grp_to_quat(dx[..., :3], self.a, self.f), self.quat)
        p = quat_to_mrp(quat_multiply(dq, q))
        if dx.shape[-1] == 3:
            return p
        return torch.cat((p, self.bias + dx[..., 3:]), -1)

    def predict(self, x: Tensor) -> Tensor:
        return self.inner.predict(self.state(x))

    def noise_cov(self) -> Tensor:
        return self.inner.noise_cov()

    def mask(self) -> Tensor | None:
        return self.inner.mask()


# ============================================================================ USQUE
def _per_trajectory(name: str, value: Tensor, like: Tensor, entries: int = 0) -> Tensor:
    """A model parameter as one value per trajectory: a number stays one; the model's per-trajectory form
    ``[..., 1]`` (``[..., 1, 3]`` for ``entries = 3``: it broadcasts against the states' ``[..., N]``) loses its
    component dim, which a one-component filter has once."""
    v = value.to(like)
    if v.dim() <= (1 if entries else 0):
        return v
    dim = -2 if entries else -1
    if v.shape[dim] != 1:
        raise ValueError(
            f"the model's {name} has shape {tuple(v.shape)}: a one-component filter takes a number or one value per "
            f"trajectory, [..., 1{', 3' if entries else ''}]"
        )
    return v.squeeze(dim)


class USQUE(BaseFilter):
    """Batched unscented quaternion estimator (USQUE) on an :class:`~agsf_torch.models.AttitudeModel` (3- or
    6-state), after Crassidis & Markley (2003).

    Same contract as :class:`~agsf_torch.filters.MultiplicativeEKF`: the belief outside is a one-component
    :class:`~agsf_torch.mixture.GaussianMixture` in the global MRP chart, mean ``[p(q̂); b̂]`` and covariance
    ``T P Tᵀ`` (:func:`~agsf_torch.filters.error_state.error_state_to_mrp`); every call converts to the reference
    ``(q̂, b̂)`` and the error covariance ``P``, works there and converts back.  All leading dims are
    trajectories; float64 unless the belief is another dtype.

    **Error state** ``δx = [δp; δb]`` (``[δp]`` in the 3-state model): ``δp`` the generalised Rodrigues parameters
    (:func:`quat_to_grp`) of the body-frame error ``δq``, ``q = δq ⊗ q̂``, with the paper's ``a = 1`` and
    ``f = 2(a + 1)``, for which ``δp`` is the MEKF's rotation-vector error to third order (the covariance is read
    in both charts alike; another ``f`` scales the attitude rows by ``f/(2(a+1))``).

    **Spread** ``λ = 1``, the value of the paper's simulations (its general form is the scaled unscented
    transformation's ``λ = α²(n + κ) − n``): the points lie ``√(n+λ) = 2`` (3-state) or ``√7`` (6-state)
    standard deviations out and every weight is positive (``W₀ = λ/(n+λ)``, ``Wᵢ = 1/(2(n+λ))``), so the
    covariances summed from the points stay positive semidefinite.

    **Propagation** over ``Δt`` with the gyro reading ``ω̃`` held (the paper's time update; sigma points are a
    tensor dim ``[..., 2n+1, n]``):

    .. math::

        χ = \\text{sigma points of } N(0,\\, P^+ + \\bar Q),\\qquad
        q_i = δq(χ_i^{δp}) ⊗ \\hat q,\\quad \\hat ω_i = \\tilde ω - \\hat b - χ_i^{δb},

        q_i ← δq(\\hat ω_i Δt) ⊗ q_i \\quad\\text{(exact for a constant rate, as the MEKF's reference)},

        χ_i^{δp} ← p_{GRP}(q_i ⊗ q_0^{-1}),\\quad χ_i^{δb} \\text{ unchanged},\\qquad
        δ\\hat x^- = \\sum_i W_i χ_i,\\quad P^- = \\sum_i W_i (χ_i - δ\\hat x^-)(χ_i - δ\\hat x^-)^T + \\bar Q,

    (3-state: ``ω̂ = ω̃ − b`` with the model's known bias, the same for every point), with the paper's process noise

    .. math:: \\bar Q = \\frac{Δt}{2}\\begin{bmatrix} (σ_v^2 - \\tfrac16 σ_u^2 Δt^2) I_3 & 0 \\\\ 0 & σ_u^2 I_3
              \\end{bmatrix}\\quad(\\tfrac{Δt}{2}σ_v^2 I_3 \\text{ in the 3-state model}),

    added before the sigma points and after (``ΦQ̄Φᵀ + Q̄`` is the MEKF's Farrenkopf ``Q_d`` for ``ω̂ = 0``;
    σ_v, σ_u the model's ``sigma_v``, ``sigma_u``).  The predicted reference is ``q̂⁻ = δq(δp̂⁻) ⊗ q_0`` and
    ``b̂⁻ = b̂ + δb̂⁻``: the belief outside has its mean at the reference, so the mean of the propagated points
    (second order in the spread) moves into it, ``P⁻`` kept (as the MEKF's reset keeps its covariance).

    **Update** (unscented, :func:`unscented_update`) with any :class:`~agsf_torch.models.MeasurementModel` of the
    MRP state (masks honoured): sigma points of ``N(0, P⁻)`` in the error chart, each mapped to its MRP state
    ``[p(δq(δp_i) ⊗ q̂⁻); b̂⁻ + δb_i]`` and through the model's ``predict`` (:class:`GRPErrorMeasurement`); then
    ``Pνν = Pyy + R``, ``K = Pxy Pνν⁻¹`` by Cholesky solves and the covariance in Joseph form on the statistical
    linearisation, equal to the paper's ``P⁺ = P⁻ − K Pνν Kᵀ`` (module docstring: why).  The paper's update reuses
    the propagated sigma points; here they are drawn afresh from ``P⁻``, because predict and update exchange a
    Gaussian (which also lets the update see ``Q̄``).  ``update_iterations > 1`` iterates the regression in the
    prior's error chart (posterior linearisation; 1 is the paper's update).  The gate (``gate_probability``) is
    the base filter's, on the linearisation of :class:`GRPErrorMeasurement` at the prediction.

    **Reset**: ``q̂⁺ = δq(δp̂⁺) ⊗ q̂⁻``, ``b̂⁺ = b̂⁻ + δb̂⁺``, ``P⁺`` kept (the paper's).

    **A wide prior and a precise sensor.**  The regression slope ``H̃`` is a secant through points ``√(n+λ)``
    standard deviations out.  Where the measurement is odd in the error (a star direction across the line of
    sight), the symmetric points lie on that secant exactly, ``Ω`` vanishes along it, and with ``R`` far below
    the spread the single update returns the secant's mean (off by ``O(θ²)`` of the spread ``θ``) with a
    covariance of ``R``'s size: overconfident, the EKF's failure in another form.  The paper's sensor (a
    magnetometer) was coarse; after a 30° prior a star camera of 10 µrad leaves the single update degrees off,
    while ``update_iterations = 3`` to ``5`` (the update relinearised at its posterior) converges, as the
    iterated MEKF does (tests/filters/test_unscented_quaternion.py).  With unit vectors, ``ȳ`` lies inside the
    sphere by about ``½ tr P_θ`` (the mean of rotated unit vectors): that radial innovation enters the NIS
    and the likelihood, which the MEKF evaluates at ``h(x̂)`` on the sphere, but not the state (it is even in
    the error, so uncorrelated with it).

    Args:
        model: the attitude model (``estimate_bias``, ``sigma_v``, ``sigma_u``, known ``bias``).
        a: the GRP parameter, in ``[0, 1]`` (default 1, the paper's).
        f: the GRP scale, ``> 0`` (default ``None``: ``2(a + 1)``, the paper's).
        lam: the sigma-point spread ``λ``, ``n + λ > 0`` (default 1, the paper's).
        **options: ``update_iterations``, ``gate_probability``, ``repair_covariance``, ``min_eigenvalue``
            (:class:`~agsf_torch.filters.base.BaseFilter`; ``fused`` and ``compile_fused`` are accepted and have
            no effect: there is no fused path).

    Diagnostics (``.diagnostics``, as the MEKF's): predict — ``weight_entropy [...]`` (zeros),
    ``covariance_repairs``; update — ``log_likelihood [...]``, ``nis [..., 1]``, ``nis_mixture [...]``,
    ``dof [...]``, ``weight_entropy``, ``covariance_repairs`` and, with gating, ``gate_*``.

    Example::

        usque = USQUE(AttitudeModel(estimate_bias=True))
        belief = GaussianMixture.from_gaussian(mean0, P0)         # [B, 6], [B, 6, 6]
        belief = usque.predict(belief, gyro, 0.1)                  # gyro [B, 3] rad/s
        belief = usque.update(belief, y, StarVectorMeasurement(r, mask, 1e-5))
        mean, cov = usque.estimate(belief)
    """

    model_type = AttitudeModel
    num_components = 1
    mixture_nis = False  # one component: the mixture NIS is the component's

    def __init__(
        self, model: AttitudeModel, *, a: float = 1.0, f: float | None = None, lam: float = 1.0, **options: Any
    ) -> None:
        super().__init__(model, **options)
        self.a, self.f = _grp_scale(a, f)
        self.lam = _check_spread(model.state_dim, lam)

    def checkpoint_options(self) -> dict[str, Any]:
        """The base filter's options, ``a``, ``f`` and ``lam``
        (:meth:`~agsf_torch.filters.base.BaseFilter.checkpoint_options`)."""
        return {**super().checkpoint_options(), "a": self.a, "f": self.f, "lam": self.lam}

    # ------------------------------------------------------------ error state
    def _chart_scale(self, like: Tensor) -> Tensor:
        """``∂δp/∂δθ`` at 0 per error-state entry, ``[n]``: ``f/(2(a+1))`` on the attitude, 1 on the bias."""
        n = self.model.state_dim
        s = torch.ones(n, dtype=like.dtype, device=like.device)
        s[:3] = self.f / (2.0 * (self.a + 1.0))
        return s

    def _to_error_state(self, mixture: GaussianMixture) -> tuple[Tensor, Tensor, Tensor, int]:
        """``(q̂ [..., 4], b̂ [..., 3 or 0], P [..., n, n] in the GRP chart, repairs)`` of a one-component belief."""
        q, b, P = mrp_to_error_state(mixture.means[..., 0, :], mixture.covs[..., 0, :, :])
        P, repairs = self._checked(P, "in the input belief")
        s = self._chart_scale(P)
        return q, b, P * s[:, None] * s[None, :], repairs

    def _checked(self, P: Tensor, where: str) -> tuple[Tensor, int]:
        P, repairs = self._ensure_positive_definite(P.unsqueeze(-3), where, "the error-state covariance")
        return P[..., 0, :, :], repairs

    def _to_mixture(self, mixture: GaussianMixture, q: Tensor, b: Tensor, P: Tensor) -> GaussianMixture:
        s = self._chart_scale(P)
        mean, cov = error_state_to_mrp(q, b, P / s[:, None] / s[None, :])
        log_w = torch.zeros(mean.shape[:-1] + (1,), dtype=mean.dtype, device=mean.device)
        # the filter's own output (a sum of outer products plus Q̄, or a checked posterior): no per-step validation
        return mixture.replace(log_weights=log_w, means=mean.unsqueeze(-2), covs=cov.unsqueeze(-3), validate=False)

    def q_bar(self, dt: float, like: Tensor) -> Tensor:
        """The paper's ``Q̄`` (class docstring), ``[n, n]``, or ``[..., n, n]`` for a model with per-trajectory noise.

        Args:
            dt: interval (s); like: a tensor whose dtype and device ``Q̄`` takes.
        """
        sv2 = _per_trajectory("sigma_v", self.model.sigma_v, like) ** 2
        attitude = (0.5 * dt) * sv2
        if self.model.estimate_bias:
            su2 = _per_trajectory("sigma_u", self.model.sigma_u, like) ** 2
            attitude, bias = torch.broadcast_tensors(attitude - (0.5 * dt) * su2 * dt**2 / 6.0, (0.5 * dt) * su2)
            diagonal = torch.stack((attitude,) * 3 + (bias,) * 3, -1)
        else:
            diagonal = torch.stack((attitude,) * 3, -1)
        return torch.diag_embed(diagonal)

    # ------------------------------------------------------------- the steps
    def _propagate(self, mixture: GaussianMixture, u: Tensor | None, dt: float) -> tuple[GaussianMixture, int]:
        """The paper's time update (class docstring); ``u = ω̃ [..., 3]`` (rad/s), held over the interval."""
        q, b, P, repairs = self._to_error_state(mixture)
        n = P.shape[-1]
        Qbar = self.q_bar(dt, P)
        weights = unscented_weights(n, self.lam, like=P)
        zero = torch.zeros(P.shape[:-1], dtype=P.dtype, device=P.device)
        L = _cholesky(symmetric_part(P + Qbar), "the error-state covariance plus Q̄")
        X = _points_from_factor(zero, L, self.lam)  # [..., 2n+1, n]
        points = quat_multiply(grp_to_quat(X[..., :3], self.a, self.f), q.unsqueeze(-2))
        if self.model.estimate_bias:
            rate = u.unsqueeze(-2) - b.unsqueeze(-2) - X[..., 3:]
        else:
            rate = (u - _per_trajectory("bias", self.model.bias, u, entries=3)).unsqueeze(-2)
        points = quat_multiply(*torch.broadcast_tensors(rotvec_to_quat(rate * dt), points))
        points = points / torch.linalg.vector_norm(points, dim=-1, keepdim=True)
        q0 = points[..., 0, :]
        errors = quat_to_grp(quat_multiply(points, quat_conjugate(q0).unsqueeze(-2)), self.a, self.f)
        mean, P = unscented_moments(torch.cat((errors, X[..., 3:]), -1), weights)
        P = symmetric_part(P + Qbar)
        q = quat_multiply(grp_to_quat(mean[..., :3], self.a, self.f), q0)
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        b = b.expand(*q.shape[:-1], n - 3) + mean[..., 3:]
        return self._to_mixture(mixture, q, b, P), repairs

    def _update_frame(self, mixture: GaussianMixture, measurement: MeasurementModel) -> UpdateFrame:
        """The error state about the reference ``(q̂, b̂)``: zero mean, ``P`` (GRP chart), the measurement seen from
        it (:class:`GRPErrorMeasurement`)."""
        q, b, P, _ = self._to_error_state(mixture)
        n = mixture.state_dim
        zero_w = torch.zeros(P.shape[:-2] + (1,), dtype=P.dtype, device=P.device)
        zero_x = torch.zeros(P.shape[:-2] + (1, n), dtype=P.dtype, device=P.device)
        seen = GRPErrorMeasurement(measurement, q, b, self.a, self.f)
        return UpdateFrame(zero_w, zero_x, P.unsqueeze(-3), seen, context=(q, b))

    def _kalman_step(self, frame: UpdateFrame, y: Tensor, mask: Tensor | None) -> ComponentUpdate:
        """The unscented update in the error chart (:func:`unscented_update`), ``mask`` the gate's or the model's."""
        measurement = frame.measurement
        return unscented_update(
            frame.means[..., 0, :],
            frame.covs[..., 0, :, :],
            y,
            measurement.predict,
            measurement.noise_cov(),
            lam=self.lam,
            mask=measurement.mask() if mask is None else mask,
            iterations=self.update_iterations,
        )

    def _posterior(
        self, prior: GaussianMixture, frame: UpdateFrame, result: ComponentUpdate
    ) -> tuple[GaussianMixture, int]:
        """The reset (class docstring); trajectories without a valid entry keep their belief exactly."""
        q, b = frame.context
        n = prior.state_dim
        dx, P_post = result.means[..., 0, :], result.covs[..., 0, :, :]
        batch = dx.shape[:-1]
        q_post = quat_multiply(grp_to_quat(dx[..., :3], self.a, self.f), q.expand(*batch, 4))
        q_post = q_post / torch.linalg.vector_norm(q_post, dim=-1, keepdim=True)
        b_post = b.expand(*batch, n - 3) + dx[..., 3:]
        P_post, repairs = self._checked(P_post, "after the measurement update")
        out = self._to_mixture(prior, q_post, b_post, P_post)
        keep = (result.dof == 0)[..., None, None]
        means = torch.where(keep, prior.means.expand_as(out.means), out.means)
        covs = torch.where(keep[..., None], prior.covs.expand_as(out.covs), out.covs)
        means, covs = self.model.canonicalize(means, covs)
        return out.replace(means=means, covs=covs, validate=False), repairs  # checked above; kept entries the input's

    def estimate(self, mixture: GaussianMixture) -> tuple[Tensor, Tensor]:
        """Point estimate and covariance in MRP coordinates: the one component.

        Returns:
            ``(mean [..., n], cov [..., n, n])``.
        """
        self.check_mixture(mixture)
        return mixture.means[..., 0, :], mixture.covs[..., 0, :, :]
