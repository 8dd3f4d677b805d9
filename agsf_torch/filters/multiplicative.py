"""Multiplicative extended Kalman filter (MEKF): the attitude filter GNC engineers fly.

Lefferts, Markley & Shuster, "Kalman filtering for spacecraft attitude estimation",
JGCD 5(5), 1982; Crassidis & Junkins, *Optimal Estimation of Dynamic Systems* (attitude
estimation chapter); Markley & Crassidis, *Fundamentals of Spacecraft Attitude
Determination and Control* (attitude filtering chapter).
An industry baseline next to the Gaussian sum filters, with the same contract.

**Conventions** (the project's, :mod:`agsf_torch.rotations`): quaternions are
scalar-last ``[x, y, z, w]``; ``C(q)`` maps inertial to body (``b = C r``);
``C(q_a ⊗ q_b) = C(q_a) C(q_b)``; ``δq(φ) = rotvec_to_quat(φ) = [sin(|φ|/2) φ/|φ|; cos(|φ|/2)]``
with ``C(δq(φ)) = exp(−[φ×])``.  The error state ``δθ`` is a small rotation in the
body frame, so with this product the truth is the *left* product

.. math:: q = δq(δθ) ⊗ \\hat q,\\qquad C(q) = \\exp(-[δθ×])\\, C(\\hat q) ≈ (I - [δθ×])\\, C(\\hat q),

(the ``δq ⊗ q̂`` of Markley's and Crassidis' texts; the reverse order would be an
inertial-frame error).  6-state: ``δx = [δθ; δb]`` with ``δb = b − b̂``.

**The belief outside** is a one-component :class:`~agsf_torch.mixture.GaussianMixture`
in the global MRP chart: mean ``[p(q̂); b̂]`` and covariance ``T P_δ Tᵀ`` with

.. math:: T = \\operatorname{blockdiag}\\left(\\frac{∂p(δq(δθ) ⊗ \\hat q)}{∂δθ}\\Big|_0 = \\tfrac14 B(p),\\; I_3\\right),
          \\qquad T^{-1} = \\operatorname{blockdiag}\\left(\\frac{4 B(p)^T}{(1+s)^2},\\; I_3\\right)

(``B Bᵀ = (1+s)² I``), so the conversion in both directions is a closed form, no
inverse of a covariance.  Every call converts to ``(q̂, b̂, P_δ)``, works there and
converts back; the returned MRP is always the short set ``|p| ≤ 1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..attitude.star_fix import star_fix
from ..mixture import GaussianMixture
from ..models.attitude import AttitudeModel
from ..models.base import MeasurementModel
from ..models.star_vectors import StarVectorMeasurement
from ..rotations import (
    cross_matrix,
    mrp_to_quat,
    quat_multiply,
    rotvec_to_quat,
)
from ..update import ComponentUpdate
from .base import BaseFilter, UpdateFrame
from .error_state import (
    ErrorStateMeasurement,
    error_state_to_mrp,
    exp_and_right_jacobian,
    mrp_to_error_state,
    rotation_series,
    symmetric_part,
)

__all__ = [
    "MultiplicativeEKF",
    "mrp_to_error_state",
    "error_state_to_mrp",
    "rotation_series",
]  # helpers from error_state


class MultiplicativeEKF(BaseFilter):
    """Batched multiplicative EKF on an :class:`~agsf_torch.models.AttitudeModel` (3- or 6-state).

    Same contract as :class:`~agsf_torch.filters.GaussianSumFilter` (the Monte Carlo
    runner drives it unchanged); the belief is a one-component mixture in MRP
    coordinates (module docstring).  All leading dims are trajectories; float64.

    **Propagation** over ``Δt`` with the gyro reading ``ω̃`` held, ``ω̂ = ω̃ − b̂``
    (``b̂`` = the model's known ``bias`` in the 3-state model, the estimate in the
    6-state one), ``φ = ω̂Δt``, ``K = [φ×]``, ``θ = |φ|`` and ``f₁…f₅`` of
    :func:`rotation_series`:

    .. math::

        \\hat q_{k+1} = δq(ω̂Δt) ⊗ \\hat q_k \\quad\\text{(exact for a constant rate)},

        Φ = \\begin{bmatrix} e^{-[ω̂×]Δt} & -\\int_0^{Δt} e^{-[ω̂×]τ}dτ \\\\ 0 & I \\end{bmatrix}
          = \\begin{bmatrix} I - f_1K + f_2K^2 & -Δt\\,(I - f_2K + f_3K^2) \\\\ 0 & I \\end{bmatrix},

        P_δ ← Φ P_δ Φ^T + Q_d,

    from the error dynamics ``δθ̇ = −[ω̂×]δθ − δb − η_v``, ``δḃ = η_u`` (σ_v in rad/s^½,
    σ_u in rad/s^{3/2}: the model's ``sigma_v``, ``sigma_u``).  ``Q_d`` (``discrete_noise``):

    * ``"farrenkopf"`` (default, the flight-standard form of Farrenkopf / Crassidis & Junkins):

      .. math:: Q_d = \\begin{bmatrix} (σ_v^2Δt + \\tfrac13σ_u^2Δt^3) I & -\\tfrac12σ_u^2Δt^2 I \\\\
                -\\tfrac12σ_u^2Δt^2 I & σ_u^2Δt\\, I \\end{bmatrix}

      exact for ``ω̂ = 0``; for ``ω̂ ≠ 0`` its σ_u terms are off by ``O(θ)`` relative
      (the σ_v term is exact, rotations keep ``σ_v² I`` isotropic).
    * ``"exact"``: ``Q_d = ∫₀^Δt Φ(τ) diag(σ_v²I, σ_u²I) Φ(τ)ᵀ dτ`` in closed form,

      .. math:: Q_{11} = σ_v^2Δt I + σ_u^2Δt^3(\\tfrac13 I + 2f_5K^2),\\;
                Q_{12} = -σ_u^2Δt^2(\\tfrac12 I - f_3K + f_4K^2),\\; Q_{22} = σ_u^2Δt I.

    The 3-state model keeps the attitude blocks: ``Φ = e^{-[ω̂×]Δt}``, ``Q_d = σ_v²Δt I``.

    **Update** with any :class:`~agsf_torch.models.MeasurementModel` ``h`` of the MRP
    state (masks honoured): ``H_δ = H(x̂) blockdiag(¼B(p̂), I)`` (for star vectors
    this is the textbook ``[(C r)×]``), then the project's Joseph-form Kalman step
    (:func:`~agsf_torch.update.kalman_update`: Cholesky solves, masked entries removed
    exactly, ``log N(ỹ; h, S)``).  With ``update_iterations > 1`` it is Gauss–Newton in
    the prior's error chart, relinearised at the updated reference
    ``x(δx̂ⱼ) = [p(δq(δθ̂ⱼ) ⊗ q̂⁻); b̂⁻ + δb̂ⱼ]`` with the exact chart Jacobian
    ``blockdiag(¼B(p)J(δθ̂ⱼ), I)``.

    **Reset** (the error state returns to zero):

    .. math::

        \\hat q^+ = δq(δθ̂) ⊗ \\hat q^-,\\qquad \\hat b^+ = \\hat b^- + δ\\hat b,

        P_δ^+ ← P_δ^+ \\;(\\text{classic})\\quad\\text{or}\\quad Γ P_δ^+ Γ^T,\\; Γ = \\operatorname{blockdiag}(J(δθ̂), I)

    (``covariance_reset=True``: the covariance is carried to the chart of the new
    reference to first order; the classic MEKF leaves it, an ``O(|δθ̂|)`` relative difference).

    **Start** (``start``): ``"prior"`` (default) runs from the belief it is given.  ``"star_fix"`` starts as flight
    software does: each trajectory runs from its prior (Kalman updates included) until its first frame whose valid
    stars (after the gate, if any) determine an attitude (≥ 2 non-parallel ones,
    :func:`~agsf_torch.attitude.star_fix.star_fix`); at that frame its attitude is replaced by the frame's Wahba
    solution ``q_fix`` (measured directions ``b̃_j = y_j/|y_j|``, catalogue vectors ``r_j``) with Shuster's QUEST
    covariance

    .. math:: P_{θθ} = \\Big(\\sum_j \\frac{I - b̃_j b̃_j^T}{σ_j^2}\\Big)^{-1}

    (by a Cholesky solve; the information of the star update ``H_j = [b×]``, whatever the noise model), its bias
    estimate and bias covariance are kept and the attitude–bias covariance is zeroed.  That frame is not used again
    in a Kalman update (its stars are masked out for that trajectory: the fix has already used them, and using them
    twice would count their information twice); its update diagnostics show no entries (``dof`` 0).  Which
    trajectories have been fixed is the filter's run state (:attr:`initialised`; :meth:`state_dict`,
    :meth:`load_state_dict`, :meth:`reset`): a trajectory whose frames never fix an attitude stays on its prior.
    The measurement must then be a :class:`~agsf_torch.models.StarVectorMeasurement` (``ValueError`` at the update
    otherwise).

    Args:
        model: the attitude model (``estimate_bias``, ``sigma_v``, ``sigma_u``, known ``bias``).
        discrete_noise: ``"farrenkopf"`` (default) or ``"exact"`` (above).
        covariance_reset: also transport the covariance in the reset (default ``False``).
        start: ``"prior"`` (default) or ``"star_fix"`` (above; the registry's ``MEKF-fix``).
        **options: ``update_iterations`` (≥ 1; 1 is the classic MEKF), ``gate_probability``
            (the per-block χ² innovation gate of :mod:`agsf_torch.gating`, as in the GSF)
            (:class:`~agsf_torch.filters.base.BaseFilter`).

    Diagnostics (``.diagnostics`` after each call, as the GSF's): predict —
    ``weight_entropy [...]`` (zeros), ``covariance_repairs`` (0 unless ``repair_covariance``); update —
    ``log_likelihood [...]``, ``nis [..., 1]``, ``nis_mixture [...]``, ``dof [...]``,
    ``weight_entropy``, ``covariance_repairs`` and, with gating, ``gate_*``.

    Example::

        mekf = MultiplicativeEKF(AttitudeModel(estimate_bias=True))
        belief = GaussianMixture.from_gaussian(mean0, P0)         # [B, 6], [B, 6, 6]
        belief = mekf.predict(belief, gyro, 0.1)                   # gyro [B, 3] rad/s
        belief = mekf.update(belief, y, StarVectorMeasurement(r, mask, 1e-5))
        mean, cov = mekf.estimate(belief)
    """

    model_type = AttitudeModel
    num_components = 1
    mixture_nis = False  # one component: the mixture NIS is the component's
    #: The starts the MEKF implements (``start``).
    STARTS = ("prior", "star_fix")

    def __init__(
        self,
        model: AttitudeModel,
        *,
        discrete_noise: str = "farrenkopf",
        covariance_reset: bool = False,
        start: str = "prior",
        **options: Any,
    ) -> None:
        if start not in self.STARTS:
            raise ValueError(f"start must be one of {', '.join(map(repr, self.STARTS))}, got {start!r}")
        super().__init__(model, **options)
        if discrete_noise not in ("farrenkopf", "exact"):
            raise ValueError(f"discrete_noise must be 'farrenkopf' or 'exact', got {discrete_noise!r}")
        self.start = start
        self.discrete_noise = discrete_noise
        self.covariance_reset = bool(covariance_reset)
        self._initialised: Tensor | None = None  # [...] bool: trajectories started from a star fix
        self._fix: _FrameFix | None = None  # the star fix of the update under way (_kalman_step → _after_update)

    def checkpoint_options(self) -> dict[str, Any]:
        """The base filter's options, ``discrete_noise``, ``covariance_reset`` and, unless it is the default
        ``"prior"`` (so that checkpoints written before the option still load), ``start``
        (:meth:`~agsf_torch.filters.base.BaseFilter.checkpoint_options`)."""
        options = {
            **super().checkpoint_options(),
            "discrete_noise": self.discrete_noise,
            "covariance_reset": self.covariance_reset,
        }
        if self.start != "prior":
            options["start"] = self.start
        return options

    # ------------------------------------------------------------ error state
    def _to_error_state(self, mixture: GaussianMixture) -> tuple[Tensor, Tensor, Tensor, int]:
        """``(q̂ [..., 4], b̂ [..., 3 or 0], P_δ [..., n, n], repairs)`` of a one-component belief."""
        q, b, P = mrp_to_error_state(mixture.means[..., 0, :], mixture.covs[..., 0, :, :])
        P, repairs = self._checked(P, "in the input belief")
        return q, b, P, repairs

    def _checked(self, P: Tensor, where: str) -> tuple[Tensor, int]:
        P, repairs = self._ensure_positive_definite(P.unsqueeze(-3), where, "the error-state covariance")
        return P[..., 0, :, :], repairs

    def _to_mixture(self, mixture: GaussianMixture, q: Tensor, b: Tensor, P: Tensor) -> GaussianMixture:
        mean, cov = error_state_to_mrp(q, b, P)
        log_w = torch.zeros(mean.shape[:-1] + (1,), dtype=mean.dtype, device=mean.device)
        # the filter's own output (Φ P Φᵀ + Q of a checked P, or a checked posterior): no per-step validation
        return mixture.replace(log_weights=log_w, means=mean.unsqueeze(-2), covs=cov.unsqueeze(-3), validate=False)

    # ------------------------------------------------------------ transition
    def transition(self, omega: Tensor, dt: float) -> tuple[Tensor, Tensor]:
        """Error-state transition ``Φ`` and discrete process noise ``Q_d`` (class docstring).

        Args:
            omega: bias-corrected rate ``ω̂`` ``[..., 3]`` (rad/s), held over ``dt``.
            dt: interval (s).

        Returns:
            ``(Φ [..., n, n], Q_d [..., n, n])``, ``n`` the model's state dimension.
        """
        R, J, f = exp_and_right_jacobian(omega * dt)
        eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
        sv2 = self.model.sigma_v.to(omega) ** 2
        if not self.model.estimate_bias:
            return R, (sv2 * dt) * eye.expand_as(R)
        su2 = self.model.sigma_u.to(omega) ** 2
        if self.discrete_noise == "farrenkopf":
            Q11 = (sv2 * dt + su2 * dt**3 / 3.0) * eye.expand_as(R)
            Q12 = (-0.5 * su2 * dt**2) * eye.expand_as(R)
        else:
            K = cross_matrix(omega * dt)
            K2 = K @ K
            Q11 = sv2 * dt * eye + su2 * dt**3 * (eye / 3.0 + 2.0 * f[4] * K2)
            Q12 = -su2 * dt**2 * (0.5 * eye - f[2] * K + f[3] * K2)
        Q22 = (su2 * dt) * eye.expand_as(R)
        zero = torch.zeros_like(R)
        Phi = torch.cat((torch.cat((R, -dt * J), -1), torch.cat((zero, eye.expand_as(R)), -1)), -2)
        Q = torch.cat((torch.cat((Q11, Q12), -1), torch.cat((Q12.transpose(-1, -2), Q22), -1)), -2)
        return Phi, Q

    # ------------------------------------------------------------- the steps
    def _propagate(self, mixture: GaussianMixture, u: Tensor | None, dt: float) -> tuple[GaussianMixture, int]:
        """The reference quaternion exactly, the error covariance by ``Φ P Φᵀ + Q_d`` (class docstring);
        ``u = ω̃ [..., 3]`` (rad/s), held over the interval."""
        q, b, P, repairs = self._to_error_state(mixture)
        omega = u - (b if self.model.estimate_bias else self.model.bias.to(u))
        q = quat_multiply(*torch.broadcast_tensors(rotvec_to_quat(omega * dt), q))
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        Phi, Q = self.transition(omega, dt)
        P = symmetric_part(Phi @ P @ Phi.transpose(-1, -2) + Q)
        b = b.expand(*q.shape[:-1], b.shape[-1])
        return self._to_mixture(mixture, q, b, P), repairs

    def _update_frame(self, mixture: GaussianMixture, measurement: MeasurementModel) -> UpdateFrame:
        """The error state about the reference ``(q̂, b̂)``: zero mean, ``P_δ``, the measurement seen from it."""
        q, b, P, _ = self._to_error_state(mixture)
        n = mixture.state_dim
        zero_w = torch.zeros(P.shape[:-2] + (1,), dtype=P.dtype, device=P.device)
        zero_x = torch.zeros(P.shape[:-2] + (1, n), dtype=P.dtype, device=P.device)
        return UpdateFrame(zero_w, zero_x, P.unsqueeze(-3), ErrorStateMeasurement(measurement, q, b), context=(q, b))

    def _posterior(
        self, prior: GaussianMixture, frame: UpdateFrame, result: ComponentUpdate
    ) -> tuple[GaussianMixture, int]:
        """The reset (class docstring); trajectories without a valid entry keep their belief exactly."""
        q, b = frame.context
        n = prior.state_dim
        dx, P_post = result.means[..., 0, :], result.covs[..., 0, :, :]
        batch = dx.shape[:-1]
        q_post = quat_multiply(rotvec_to_quat(dx[..., :3]), q.expand(*batch, 4))
        q_post = q_post / torch.linalg.vector_norm(q_post, dim=-1, keepdim=True)
        b_post = b.expand(*batch, n - 3) + dx[..., 3:]
        if self.covariance_reset:
            _, J, _ = exp_and_right_jacobian(dx[..., :3])
            Gam = torch.eye(n, dtype=P_post.dtype, device=P_post.device).expand(*batch, n, n).clone()
            Gam[..., :3, :3] = J
            P_post = symmetric_part(Gam @ P_post @ Gam.transpose(-1, -2))
        P_post, repairs = self._checked(P_post, "after the measurement update")
        out = self._to_mixture(prior, q_post, b_post, P_post)
        keep = (result.dof == 0)[..., None, None]
        means = torch.where(keep, prior.means.expand_as(out.means), out.means)
        cov_out = torch.where(keep[..., None], prior.covs.expand_as(out.covs), out.covs)
        means, cov_out = self.model.canonicalize(means, cov_out)
        if self._fix is not None and bool(self._fix.now.any()):
            means, cov_out, fixed = self._fixed_belief(frame, self._fix, means, cov_out)
            repairs += fixed
        return out.replace(
            means=means, covs=cov_out, validate=False
        ), repairs  # checked above; kept entries are the input's

    # ------------------------------------------------------------ star-fix start
    def _validate_update(self, mixture: GaussianMixture, y: Any, measurement: MeasurementModel) -> Tensor:
        """As the base class's; with ``start="star_fix"`` the measurement must be a star-vector one and the run
        state must cover the belief's trajectories."""
        y = super()._validate_update(mixture, y, measurement)
        if self.start == "star_fix":
            if not isinstance(measurement, StarVectorMeasurement):
                raise ValueError(
                    f"start='star_fix' fixes the attitude from star vectors: the measurement must be a "
                    f"StarVectorMeasurement, got {type(measurement).__name__} (use start='prior')"
                )
            if self._initialised is not None and tuple(self._initialised.shape) != tuple(mixture.batch_shape):
                raise ValueError(
                    f"the star-fix run state covers trajectories of shape {tuple(self._initialised.shape)}, the belief "
                    f"has batch shape {tuple(mixture.batch_shape)}: reset() the filter for a new run"
                )
        return y

    def _kalman_step(self, frame: UpdateFrame, y: Tensor, mask: Tensor | None) -> ComponentUpdate:
        """The base class's Kalman step; with ``start="star_fix"`` the trajectories this frame fixes first
        (:meth:`_frame_fix`) take no part in it (their entries are masked out; class docstring)."""
        if self.start != "star_fix":
            return super()._kalman_step(frame, y, mask)
        self._fix = self._frame_fix(frame, y, mask)
        if bool(self._fix.now.any()):
            keep = (~self._fix.now).unsqueeze(-1).expand(y.shape)
            mask = frame.measurement.mask() if mask is None else mask  # the entry mask replaces the model's
            mask = keep if mask is None else mask & keep
        return super()._kalman_step(frame, y, mask)

    def _frame_fix(self, frame: UpdateFrame, y: Tensor, mask: Tensor | None) -> _FrameFix:
        """The star fix of this frame for the trajectories not yet started from one (class docstring).

        The valid stars are the measurement's, less the gate's rejections (``mask [..., 3M]``); ``y [..., 3M]``
        holds their measured directions (normalised here).  Trajectories that cannot be fixed get the identity in
        place of the information, so that one batched Cholesky factorisation serves all."""
        measurement = frame.measurement.inner
        batch = frame.covs.shape[:-3]
        M = measurement.num_stars
        valid = torch.ones(M, dtype=torch.bool, device=y.device)
        if measurement.star_mask is not None:
            valid = valid & measurement.star_mask
        if mask is not None:
            valid = valid & mask.unflatten(-1, (M, 3)).all(-1)
        valid = valid.expand(*batch, M)
        body = y.unflatten(-1, (M, 3))
        norm = torch.linalg.vector_norm(body, dim=-1, keepdim=True)
        body = torch.where(valid.unsqueeze(-1), body / norm.clamp_min(torch.finfo(y.dtype).tiny), 0.0)
        inertial = measurement.r_inertial.to(y).expand(*batch, M, 3)
        mrp, ok = star_fix(body, inertial, valid)
        before = (
            torch.zeros(batch, dtype=torch.bool, device=y.device) if self._initialised is None else self._initialised
        )
        now = ok & ~before
        eye = torch.eye(3, dtype=y.dtype, device=y.device)
        weight = valid.to(y.dtype) / measurement.sigma.to(y)[..., None] ** 2  # 1/σ_j², 0 off the valid stars
        J = ((eye - body.unsqueeze(-1) * body.unsqueeze(-2)) * weight[..., None, None]).sum(-3)
        J = torch.where(now[..., None, None], J, eye)
        P = torch.cholesky_solve(eye.expand_as(J), torch.linalg.cholesky(J))
        return _FrameFix(now=now, quat=mrp_to_quat(mrp), cov=symmetric_part(P), initialised=before | ok)

    def _fixed_belief(
        self, frame: UpdateFrame, fix: _FrameFix, means: Tensor, covs: Tensor
    ) -> tuple[Tensor, Tensor, int]:
        """The posterior ``(means [..., 1, n], covs [..., 1, n, n], repairs)`` with the trajectories ``fix.now``
        started from the fix: attitude ``q_fix`` with the QUEST covariance, bias and its covariance from the prior
        (``frame``), attitude–bias covariance zero."""
        _, b = frame.context
        P = frame.covs[..., 0, :, :].clone()
        P[..., :3, :] = 0.0
        P[..., :, :3] = 0.0
        P[..., :3, :3] = fix.cov
        P, repairs = self._checked(P, "after the star fix")
        mean, cov = error_state_to_mrp(fix.quat, b.expand(*fix.quat.shape[:-1], b.shape[-1]), P)
        now = fix.now[..., None, None]
        means = torch.where(now, mean.unsqueeze(-2), means)
        covs = torch.where(now.unsqueeze(-1), cov.unsqueeze(-3), covs)
        return means, covs, repairs

    def _after_update(self, posterior: GaussianMixture) -> None:
        """Commit the star-fix run state of the update just made (last: a failed update changes nothing)."""
        if self._fix is not None:
            self._initialised, self._fix = self._fix.initialised, None

    @property
    def initialised(self) -> Tensor | None:
        """``[...]`` bool: the trajectories started from a star fix (``start="star_fix"``), or ``None`` before the
        first update of a run."""
        return None if self._initialised is None else self._initialised.clone()

    def reset(self) -> None:
        """Start a new run: no trajectory has been started from a star fix."""
        self._initialised, self._fix = None, None

    def state_dict(self) -> dict[str, Any]:
        """The run state: ``{}`` with ``start="prior"``; ``{"initialised": [...] bool tensor or None}`` with
        ``start="star_fix"``."""
        if self.start != "star_fix":
            return super().state_dict()
        return {"initialised": None if self._initialised is None else self._initialised.clone()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (validated before anything changes)."""
        if self.start != "star_fix":
            super().load_state_dict(state)
            return
        if not isinstance(state, dict) or set(state) != {"initialised"}:
            got = sorted(state) if isinstance(state, dict) else state
            raise ValueError(f"the star-fix MEKF's state must be {{'initialised': ...}}, got {got!r}")
        flag = state["initialised"]
        if flag is not None and not (torch.is_tensor(flag) and flag.dtype == torch.bool):
            raise ValueError(f"state 'initialised' must be a bool tensor or None, got {flag!r}")
        self._initialised, self._fix = None if flag is None else flag.clone(), None

    def estimate(self, mixture: GaussianMixture) -> tuple[Tensor, Tensor]:
        """Point estimate and covariance in MRP coordinates: the one component.

        Returns:
            ``(mean [..., n], cov [..., n, n])``.
        """
        self.check_mixture(mixture)
        return mixture.means[..., 0, :], mixture.covs[..., 0, :, :]


@dataclass(frozen=True)
class _FrameFix:
    """The star fix of one frame (:meth:`MultiplicativeEKF._frame_fix`).

    Attributes:
        now: ``[...]`` bool, the trajectories this frame fixes first.
        quat: ``[..., 4]``, the fix's attitude (meaningful where ``now``).
        cov: ``[..., 3, 3]``, its QUEST covariance (rad²; the identity where not ``now``).
        initialised: ``[...]`` bool, the trajectories started from a fix once this frame is done.
    """

    now: Tensor
    quat: Tensor
    cov: Tensor
    initialised: Tensor
