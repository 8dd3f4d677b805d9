"""Gyro-driven MRP attitude kinematics (method.md §1).

State ``x = p`` (3-state, gyro bias known) or ``x = [p; b]`` (6-state), input the
measured body rate ``ω̃`` (rad/s):

.. math::

    \\dot p = \\tfrac14 B(p)(\\tilde ω - b - η_v),\\qquad \\dot b = η_u,

so ``f = [¼B(p)(ω̃ − b); 0]``, ``g = [[−¼B(p), 0], [0, I₃]]`` and
``Q = diag(σ_v² I₃, σ_u² I₃)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..constants import DEFAULT_SIGMA_U, DEFAULT_SIGMA_V
from ..rotations import cross_matrix, mrp_kinematics_matrix, mrp_shadow_jacobian
from .attitude_fused import ATTITUDE_DYNAMICS, FusedAttitudePaths
from .base import ContinuousModel, FokkerPlanckMoments, FokkerPlanckTerms, check_nonnegative, sum_last
from .derived import derived_from

__all__ = ["AttitudeModel", "DEFAULT_SIGMA_V", "DEFAULT_SIGMA_U"]


class AttitudeModel(FusedAttitudePaths, ContinuousModel):
    """MRP attitude driven by a rate gyro, with or without bias estimation.

    Args:
        estimate_bias: ``False`` → 3-state ``x = p`` with the gyro bias known
            (``bias``); ``True`` → 6-state ``x = [p; b]``.
        sigma_v: angle random walk σ_v (rad/s^½).
        sigma_u: rate random walk σ_u (rad/s^{3/2}); used by the 6-state model.
        bias: known constant gyro bias (rad/s), ``[3]``; subtracted from ``ω̃`` in
            the 3-state model, ignored by the 6-state one.  Known biases that
            differ between trajectories are subtracted from the gyro input instead.

    **Noise per trajectory.**  ``sigma_v`` and ``sigma_u`` may be a number or a tensor of batch dims that
    broadcast against the states' ``[B, N]`` from the right, ``[B, 1]`` for one value per trajectory; ``bias``
    likewise ``[B, 1, 3]``.  Learning fits independent data sets this way in one program
    (:func:`~agsf_torch.attitude.learning.fit_datasets`).  Propagation and the single-Gaussian and Gaussian sum
    updates take such a model (the generic path: the fused kernels take one value for all); the FPKE terms of the
    adaptive filters refuse it (:meth:`per_trajectory_noise`).

    The input ``u = ω̃`` must have shape ``[..., 3]`` (one rate per body axis): any other
    last dimension, ``[..., 1]`` included, is a ``ValueError`` (:meth:`check_input`), never a
    rate broadcast over the three axes.

    The closed forms and the fused kernels hold for these dynamics (``drift``, ``noise_gain``, ``noise_psd``):
    a subclass that overrides any of them gets ``torch.func`` derivatives, the generic quadrature and the
    unfused path (:mod:`~agsf_torch.models.derived`), unless it overrides the derivations too.
    """

    input_dim = 3
    input_description = "the gyro reading ω̃, rad/s"

    def __init__(
        self,
        estimate_bias: bool = False,
        sigma_v: float = DEFAULT_SIGMA_V,
        sigma_u: float = DEFAULT_SIGMA_U,
        bias: Tensor | float = 0.0,
    ) -> None:
        super().__init__()
        self.estimate_bias = bool(estimate_bias)
        self.state_dim = 6 if self.estimate_bias else 3
        self.register_buffer("sigma_v", check_nonnegative("sigma_v", sigma_v))
        self.register_buffer("sigma_u", check_nonnegative("sigma_u", sigma_u))
        b = torch.as_tensor(bias, dtype=torch.float64) if not isinstance(bias, Tensor) else bias
        if b.dim() == 0:
            b = b.expand(3).clone()
        if b.shape[-1] != 3:
            raise ValueError(f"bias must be a scalar, [3] or [..., 3] per trajectory ([B, 1, 3]), got {tuple(b.shape)}")
        if not bool(torch.isfinite(b).all()):
            raise ValueError("bias must be finite")
        self.register_buffer("bias", b)

    # ------------------------------------------------------------- helpers
    @property
    def per_trajectory_noise(self) -> bool:
        """Whether ``sigma_v``, ``sigma_u`` or ``bias`` holds one value per trajectory (class docstring)."""
        return self.sigma_v.dim() > 0 or self.sigma_u.dim() > 0 or self.bias.dim() > 1

    def _refuse_per_trajectory(self, what: str) -> None:
        """``ValueError`` naming ``what`` when the noise is per trajectory: the FPKE terms integrate one density
        over states whose batch dims are not the trajectories'."""
        if self.per_trajectory_noise:
            raise ValueError(
                f"{what} take one sigma_v, sigma_u and bias for all trajectories; this model has them per trajectory "
                f"(sigma_v {tuple(self.sigma_v.shape)}, sigma_u {tuple(self.sigma_u.shape)}, bias "
                f"{tuple(self.bias.shape)}): use the EKF, MEKF or GSF, or one value"
            )

    def _rate(self, x: Tensor, u: Tensor) -> Tensor:
        """Bias-corrected body rate ``ω = ω̃ − b`` (``[..., 3]``); ``u`` is checked to be ``[..., 3]``."""
        self.check_input(u)
        if self.estimate_bias:
            return u - x[..., 3:]
        return u - self.bias.to(u)

    @staticmethod
    def _mrp_rate(p: Tensor, w: Tensor) -> Tensor:
        """``¼B(p)ω = ¼[(1 − s)ω + 2 p×ω + 2p(pᵀω)]`` without forming ``B``."""
        s = sum_last(p * p, keepdim=True)
        pw = sum_last(p * w.expand_as(p) if w.dim() < p.dim() else p * w, keepdim=True)
        return 0.25 * (
            (1.0 - s) * w
            + 2.0 * torch.linalg.cross(p, w.expand_as(p) if w.dim() < p.dim() else w, dim=-1)
            + 2.0 * pw * p
        )

    # ------------------------------------------------------------ protocol
    def drift(self, x: Tensor, u: Tensor) -> Tensor:
        """``f(x, ω̃) = [¼B(p)(ω̃ − b); 0₃]``: ``x [..., n]``, ``u = ω̃ [..., 3]``."""
        p = x[..., :3]
        w = self._rate(x, u)
        pdot = self._mrp_rate(p, w)
        if self.estimate_bias:
            return torch.cat((pdot, torch.zeros_like(pdot)), -1)
        return pdot

    def noise_gain(self, x: Tensor) -> Tensor:
        """``g(x) = −¼B(p)`` (3-state) or ``[[−¼B(p), 0], [0, I₃]]`` (6-state)."""
        gp = -0.25 * mrp_kinematics_matrix(x[..., :3])
        if not self.estimate_bias:
            return gp
        z = torch.zeros_like(gp)
        eye = torch.eye(3, dtype=x.dtype, device=x.device).expand_as(gp)
        return torch.cat((torch.cat((gp, z), -1), torch.cat((z, eye), -1)), -2)

    def noise_psd(self) -> Tensor:
        """``Q = σ_v² I₃`` or ``diag(σ_v² I₃, σ_u² I₃)``."""
        one = torch.ones(3, dtype=self.sigma_v.dtype, device=self.sigma_v.device)
        sv2 = self.sigma_v[..., None] ** 2 * one
        if not self.estimate_bias:
            return torch.diag_embed(sv2)
        sv2, su2 = torch.broadcast_tensors(sv2, self.sigma_u[..., None] ** 2 * one)
        return torch.diag_embed(torch.cat((sv2, su2), -1))

    @derived_from("drift", "_rate", "_mrp_rate", generic=ContinuousModel.drift_jacobian)
    def drift_jacobian(self, x: Tensor, u: Tensor) -> Tensor:
        """Closed form ``A = [[F, −¼B(p)], [0, 0]]`` with ``ω = ω̃ − b``.

        .. math:: F = \\tfrac12 \\left(p ω^T - ω p^T - [ω×] + (ω^T p) I_3\\right)
        """
        p = x[..., :3]
        w = self._rate(x, u)
        p, w = torch.broadcast_tensors(p, w)
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        F = 0.5 * (
            p[..., :, None] * w[..., None, :]
            - w[..., :, None] * p[..., None, :]
            - cross_matrix(w)
            + sum_last(w * p)[..., None, None] * eye
        )
        if not self.estimate_bias:
            return F
        top = torch.cat((F, -0.25 * mrp_kinematics_matrix(p)), -1)
        return torch.cat((top, torch.zeros_like(top)), -2)

    @derived_from("noise_gain", "noise_psd", generic=ContinuousModel.process_noise)
    def process_noise(self, x: Tensor) -> Tensor:
        """Closed form ``g Q gᵀ``: ``(σ_v²/16)(1 + s)² I₃`` on the MRP block (``B Bᵀ = (1+s)² I``)."""
        p = x[..., :3]
        s = sum_last(p * p)[..., None, None]
        eye3 = torch.eye(3, dtype=x.dtype, device=x.device)
        # in x's dtype: a per-trajectory value has dims, which would take part in type promotion
        Gp = (self.sigma_v.to(x)[..., None, None] ** 2 / 16.0) * (1.0 + s) ** 2 * eye3
        if not self.estimate_bias:
            return Gp
        Gp, Gb = torch.broadcast_tensors(Gp, self.sigma_u.to(x)[..., None, None] ** 2 * eye3)
        z = torch.zeros_like(Gp)
        return torch.cat((torch.cat((Gp, z), -1), torch.cat((z, Gb), -1)), -2)

    def _diffusion_diagonal(self, x: Tensor) -> Tensor:
        """Diagonal of ``D = ½gQgᵀ``: ``(σ_v²/32)(1+s)²`` on the MRP axes, ``σ_u²/2`` on the bias axes."""
        p = x[..., :3]
        self._refuse_per_trajectory("the FPKE diffusion terms")
        s = sum_last(p * p, keepdim=True)
        dp = (self.sigma_v**2 / 32.0) * (1.0 + s) ** 2 * torch.ones_like(p)
        if not self.estimate_bias:
            return dp
        return torch.cat((dp, (0.5 * self.sigma_u**2) * torch.ones_like(p)), -1)

    @derived_from(*ATTITUDE_DYNAMICS, generic=ContinuousModel.fokker_planck_terms)
    def fokker_planck_terms(self, x: Tensor, u: Tensor) -> FokkerPlanckTerms:
        """Closed forms (method.md §3), with ``c = σ_v²/32``, ``s = pᵀp``, ``ω = ω̃ − b``:

        ``div f = (3/2) pᵀω``, ``D_pp = c(1+s)² I₃`` (``D_bb = (σ_u²/2) I₃``),
        ``aₖ = 4c(1+s) pₖ`` on the MRP entries (0 on the bias), ``Σ∂²D = 4c(3 + 5s)``.
        ``D`` is diagonal and is returned as its diagonal ``[..., n]``.
        """
        self._refuse_per_trajectory("the Fokker–Planck terms")
        p = x[..., :3]
        p_b, w_b = torch.broadcast_tensors(p, self._rate(x, u))
        s = sum_last(p_b * p_b, keepdim=True)
        pw = sum_last(p_b * w_b, keepdim=True)
        c = self.sigma_v**2 / 32.0
        pdot = 0.25 * ((1.0 - s) * w_b + 2.0 * torch.linalg.cross(p_b, w_b, dim=-1) + 2.0 * pw * p_b)
        a = (4.0 * c) * (1.0 + s) * p_b
        d = c * (1.0 + s) ** 2 * torch.ones_like(p_b)
        if self.estimate_bias:
            zero = torch.zeros_like(p_b)
            pdot = torch.cat((pdot, zero), -1)
            a = torch.cat((a, zero), -1)
            d = torch.cat((d, (0.5 * self.sigma_u**2) * torch.ones_like(p_b)), -1)
        return FokkerPlanckTerms(
            drift=pdot,
            drift_divergence=1.5 * pw.squeeze(-1),
            diffusion=d,
            diffusion_divergence=a,
            diffusion_second_divergence=(4.0 * c) * (3.0 + 5.0 * s.squeeze(-1)),
        )

    @derived_from(*ATTITUDE_DYNAMICS, generic=ContinuousModel.fpke_quadrature_points)
    def fpke_quadrature_points(self, factors: int = 2) -> tuple[int, ...]:
        """Exact rule for ``ℓⱼ`` (``factors = 1``: 4 points per MRP axis, 2 per bias axis)
        or ``ℓᵢℓⱼ`` (``factors = 2``: 7 and 3).

        ``ℓ`` is a polynomial of total degree 6 in ``p`` (the term ``zᵀDz`` with
        ``D ∝ (1+s)²``), so ``ℓⱼ`` needs 4 Gauss–Hermite points per MRP axis
        (degree 7 ≥ 6) and ``ℓᵢℓⱼ``, of degree 12, needs 7 (degree 13).  In
        the 6-state model ``ℓ`` is at most quadratic in the bias for fixed ``p``
        (``fᵀz`` and ``zᵀDz``); with the quadrature points ``x = m + Lξ`` (``L``
        lower-triangular, MRP first) the bias coordinates are linear in ``ξ_b`` and
        the MRP coordinates do not depend on ``ξ_b``, so ``ℓⱼ`` has degree ≤ 2 in
        each ``ξ_b`` axis (2 points) and ``ℓᵢℓⱼ`` degree ≤ 4 (3 points).  The 6-D
        rules have 4³·2³ = 512 and 7³·3³ = 9261 nodes and are exact.
        """
        if factors not in (1, 2):
            raise ValueError(f"factors must be 1 or 2, got {factors}")
        p, b = (4, 2) if factors == 1 else (7, 3)
        return (p, p, p, b, b, b) if self.estimate_bias else (p, p, p)

    @derived_from(*ATTITUDE_DYNAMICS, generic=ContinuousModel.fokker_planck_moments)
    def fokker_planck_moments(self, mean: Tensor, cov: Tensor, u: Tensor) -> FokkerPlanckMoments:
        """Exact Gaussian expectations of the Fokker–Planck terms under ``x ~ N(mean, cov)``.

        With ``m, M`` the MRP mean and covariance, ``ω = ω̃ − b`` (mean ``m_ω``),
        ``C = Cov(p, ω) = −S_pb`` (0 in the 3-state model), ``c = σ_v²/32`` and
        ``s = pᵀp``, the Gaussian moments are ``E[s] = mᵀm + tr M``,
        ``E[ppᵀ] = mmᵀ + M``, ``E[sp] = E[s]m + 2Mm``,
        ``E[s²] = E[s]² + 2tr M² + 4mᵀMm``, ``E[sω] = E[s]m_ω + 2Cᵀm``,
        ``E[p×ω] = m×m_ω + ε:C``, ``E[(pᵀω)p] = m(mᵀm_ω + tr C) + Cm + Mm_ω``.  The
        diffusion is ``D = φ D₁ + D₀`` with ``φ = (1+s)²``, ``D₁ = c`` on the MRP axes and
        ``D₀ = σ_u²/2`` on the bias axes; ``v = f − 2a`` with ``v_p = ¼B(p)ω − 8c(1+s)p``,
        ``∂v_p/∂p = F − 8c((1+s)I + 2ppᵀ)`` (``F`` of :meth:`drift_jacobian`) and
        ``∂v_p/∂b = −¼B(p)``.

        Args:
            mean: ``[..., n]``; cov: ``[..., n, n]``; u: ``ω̃`` ``[..., 3]``.
        """
        self.check_input(u)
        self._refuse_per_trajectory("the Fokker–Planck moments")
        n = self.state_dim
        m = mean[..., :3]
        M = cov[..., :3, :3]
        eye = torch.eye(3, dtype=mean.dtype, device=mean.device)
        if self.estimate_bias:
            m_w = u - mean[..., 3:]
            C = -cov[..., :3, 3:]
        else:
            m_w = (u - self.bias.to(u)).expand_as(m)
            C = torch.zeros_like(M)
        c = self.sigma_v.to(mean) ** 2 / 32.0

        def dot(a: Tensor, b: Tensor) -> Tensor:
            return sum_last(a * b, keepdim=True)

        Mm = (M @ m.unsqueeze(-1)).squeeze(-1)
        Es = dot(m, m) + M.diagonal(dim1=-2, dim2=-1).sum(-1, keepdim=True)  # [..., 1]
        Epp = m.unsqueeze(-1) * m.unsqueeze(-2) + M
        Esp = Es * m + 2.0 * Mm
        Es2 = Es * Es + 2.0 * sum_last((M * M).flatten(-2), keepdim=True) + 4.0 * dot(m, Mm)
        trC = C.diagonal(dim1=-2, dim2=-1).sum(-1, keepdim=True)
        Cm = (C @ m.unsqueeze(-1)).squeeze(-1)
        CTm = (C.transpose(-1, -2) @ m.unsqueeze(-1)).squeeze(-1)
        eps_C = torch.stack((C[..., 1, 2] - C[..., 2, 1], C[..., 2, 0] - C[..., 0, 2], C[..., 0, 1] - C[..., 1, 0]), -1)
        E_sw = Es * m_w + 2.0 * CTm
        E_cross = torch.linalg.cross(m, m_w, dim=-1) + eps_C
        E_pwp = m * (dot(m, m_w) + trC) + Cm + (M @ m_w.unsqueeze(-1)).squeeze(-1)
        E_pw = dot(m, m_w) + trC
        v_p = 0.25 * (m_w - E_sw + 2.0 * E_cross + 2.0 * E_pwp) - 8.0 * c * (m + Esp)
        E_pwT = m.unsqueeze(-1) * m_w.unsqueeze(-2) + C  # E[p ωᵀ]
        F = 0.5 * (E_pwT - E_pwT.transpose(-1, -2) - cross_matrix(m_w) + E_pw.unsqueeze(-1) * eye)
        J_pp = F - 8.0 * c * ((1.0 + Es).unsqueeze(-1) * eye + 2.0 * Epp)
        field_grad = 4.0 * (m + Esp)
        field_hess = 4.0 * (1.0 + Es).unsqueeze(-1) * eye + 8.0 * Epp
        scalar = (1.5 * E_pw - 4.0 * c * (3.0 + 5.0 * Es)).squeeze(-1)
        pattern = torch.cat((c.expand(3), torch.zeros(n - 3, dtype=mean.dtype, device=mean.device)))
        constant = torch.zeros(n, dtype=mean.dtype, device=mean.device)
        if self.estimate_bias:
            E_B = (1.0 - Es).unsqueeze(-1) * eye + 2.0 * cross_matrix(m) + 2.0 * Epp
            zero = torch.zeros_like(J_pp)
            J = torch.cat((torch.cat((J_pp, -0.25 * E_B), -1), torch.cat((zero, zero), -1)), -2)
            v = torch.cat((v_p, torch.zeros_like(v_p)), -1)
            field_grad = torch.cat((field_grad, torch.zeros_like(field_grad)), -1)
            field_hess = torch.cat((torch.cat((field_hess, zero), -1), torch.cat((zero, zero), -1)), -2)
            constant[3:] = 0.5 * self.sigma_u.to(mean) ** 2
        else:
            J, v = J_pp, v_p
        return FokkerPlanckMoments(
            scalar=scalar,
            transport=v,
            transport_jacobian=J,
            field=(1.0 + 2.0 * Es + Es2).squeeze(-1),
            field_gradient=field_grad,
            field_hessian=field_hess,
            pattern=pattern,
            constant=constant,
        )

    @derived_from(*ATTITUDE_DYNAMICS, generic=ContinuousModel.fpke_polynomial_space)
    def fpke_polynomial_space(self) -> tuple[tuple[tuple[int, ...], int], ...]:
        """``ℓ`` has total degree 6 in the MRP coordinates ``ξ_p`` and, for fixed ``ξ_p``, at most
        2 in the bias coordinates ``ξ_b`` (see :meth:`fpke_quadrature_points`):
        ``P₆(ξ_p) ⊗ P₂(ξ_b)``, 84 · 10 = 840 interpolation nodes (84 in the 3-state model)
        instead of the 9261 (343) of the tensor Gauss–Hermite rule for ``ℓᵢℓⱼ``."""
        p = ((0, 1, 2), 6)
        return (p, ((3, 4, 5), 2)) if self.estimate_bias else (p,)

    #: The largest rotation (rad) the moment equations are asked to follow over one interval: the MRP chart
    #: is switched between intervals only (``canonicalize``), and within one the MRP runs to ``tan(θ/4)``,
    #: singular at θ = 2π; a radian keeps ``|p| ≤ tan((π + 1)/4) ≈ 1.7`` and RK4's error small.
    MAX_ROTATION_PER_INTERVAL = 1.0

    def check_step(self, mean: Tensor, u: Tensor | None, step: float) -> None:
        """Refuse an interval ``h`` in which the body turns more than :attr:`MAX_ROTATION_PER_INTERVAL` rad,
        ``|ω̃ − b| h`` (``b`` each component's bias, or the known one), naming the angle, the rate and how many
        intervals would do (substeps do not help: the chart is switched between intervals)."""
        if u is None:
            return
        bias = mean[..., 3:] if self.estimate_bias else self.bias.to(u)
        omega = u.detach().unsqueeze(-2) - bias.detach()
        rate = float(torch.linalg.vector_norm(omega, dim=-1).max()) if omega.numel() else 0.0
        turn = rate * step
        limit = self.MAX_ROTATION_PER_INTERVAL
        if not math.isfinite(turn) or turn > limit:
            hint = (
                f"split it into at least {math.ceil(turn / limit)} intervals"
                if math.isfinite(turn)
                else "check dt and the gyro rates"
            )
            raise ValueError(
                f"an interval of {step:g} s at a body rate of {rate:g} rad/s turns {turn:g} rad, more than the "
                f"{limit:g} rad the MRP moment equations follow in one interval (the chart is switched between "
                f"intervals): {hint}"
            )

    # ------------------------------------------------------- MRP manifold
    def _switch(self, mean: Tensor, cov: Tensor, switch: Tensor) -> tuple[Tensor, Tensor]:
        """Map the components flagged in ``switch [...]`` to the other MRP set.

        ``p ← −p/s`` and ``P ← T P Tᵀ`` with ``T = blockdiag(J, I)``,
        ``J = (2ppᵀ − sI₃)/s²``; bias rows and columns are unchanged.  Only the flagged
        components are transformed (the others are returned as they are).
        """
        if not bool(switch.any()):
            return mean, cov
        if mean.shape[:-1] == cov.shape[:-2] == switch.shape and not bool(switch.all()):
            at = switch.nonzero(as_tuple=True)
            m, P = self._switch(mean[at], cov[at], torch.ones(len(at[0]), dtype=torch.bool, device=switch.device))
            return mean.index_put(at, m), cov.index_put(at, P)
        p = mean[..., :3]
        safe_p = torch.where(switch[..., None], p, torch.ones_like(p))
        J = mrp_shadow_jacobian(safe_p)
        eye = torch.eye(self.state_dim, dtype=mean.dtype, device=mean.device)
        T = eye.expand(*J.shape[:-2], self.state_dim, self.state_dim).clone()
        T[..., :3, :3] = J
        T = torch.where(switch[..., None, None], T, eye)
        new_p = torch.where(switch[..., None], -safe_p / (safe_p * safe_p).sum(-1, keepdim=True), p)
        new_mean = torch.cat((new_p, mean[..., 3:]), -1)
        new_cov = T @ cov @ T.transpose(-1, -2)
        return new_mean, 0.5 * (new_cov + new_cov.transpose(-1, -2))

    def canonicalize(self, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
        """Switch every component with ``|p| > 1`` to the shadow set (see :meth:`_switch`).

        Args:
            mean: ``[..., n]``; cov: ``[..., n, n]``.
        """
        p = mean[..., :3]
        return self._switch(mean, cov, (p * p).sum(-1) > 1.0)

    def align(self, mean: Tensor, cov: Tensor, reference: Tensor) -> tuple[Tensor, Tensor]:
        """Express each component in the MRP set (itself or its shadow) nearer to ``reference``.

        Components on different sides of ``|p| = 1`` describe nearby attitudes with
        far-apart MRPs; their moments are meaningful only in one chart.

        Args:
            mean: ``[..., N, n]``; cov: ``[..., N, n, n]``; reference: broadcastable to ``mean``.
        """
        p = mean[..., :3]
        s = (p * p).sum(-1, keepdim=True)
        shadow = -p / s.clamp_min(torch.finfo(p.dtype).tiny)
        ref = reference[..., :3]
        switch = ((shadow - ref) ** 2).sum(-1) < ((p - ref) ** 2).sum(-1)
        return self._switch(mean, cov, switch)

    def state_error(self, x_est: Tensor, x_true: Tensor) -> Tensor:
        """``x_est − x_true`` with the true MRP taken in whichever set (itself or
        its shadow) lies closer to the estimate."""
        p_e, p_t = torch.broadcast_tensors(x_est[..., :3], x_true[..., :3])
        s_t = (p_t * p_t).sum(-1, keepdim=True)
        shadow = -p_t / s_t.clamp_min(torch.finfo(p_t.dtype).tiny)
        d_direct = p_e - p_t
        d_shadow = p_e - shadow
        use_shadow = (d_shadow * d_shadow).sum(-1, keepdim=True) < (d_direct * d_direct).sum(-1, keepdim=True)
        dp = torch.where(use_shadow, d_shadow, d_direct)
        if not self.estimate_bias:
            return dp
        return torch.cat((dp, x_est[..., 3:] - x_true[..., 3:]), -1)
