"""Gyro-driven MRP attitude kinematics (method.md §1).

State ``x = p`` (3-state, gyro bias known) or ``x = [p; b]`` (6-state), input the
measured body rate ``ω̃`` (rad/s):

.. math::

    \\dot p = \\tfrac14 B(p)(\\tilde ω - b - η_v),\\qquad \\dot b = η_u,

so ``f = [¼B(p)(ω̃ − b); 0]``, ``g = [[−¼B(p), 0], [0, I₃]]`` and
``Q = diag(σ_v² I₃, σ_u² I₃)``.  Every equation is a function of :mod:`agsf_torch.attitude.physics`, which the
fused kernels (:mod:`.attitude_fused`) evaluate too; the methods here apply it to the entries of batched tensors.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..attitude import physics
from ..constants import DEFAULT_SIGMA_U, DEFAULT_SIGMA_V
from ..fused.algebra import as_entries, as_tensor
from .attitude_fused import ATTITUDE_DYNAMICS, FusedAttitudePaths
from .base import ContinuousModel, FokkerPlanckMoments, FokkerPlanckTerms, check_nonnegative
from .derived import derived_from

__all__ = ["AttitudeModel", "DEFAULT_SIGMA_V", "DEFAULT_SIGMA_U", "SHADOW_SPREAD", "SHADOW_FORCED"]

#: A component beyond ``|p| = 1`` moves to the shadow set only where its spread ``√tr P_pp`` is at most this
#: fraction of ``|p|``: the shadow map ``−p/|p|²`` bends by about that fraction over one standard deviation, so the
#: linearised switch (``P ← JPJᵀ``) keeps such a component; a wider one stays in its own set.
SHADOW_SPREAD = 0.1
#: ... and whatever its spread beyond ``|p| = 3`` (a rotation of 287°), well before the chart's singularity at 360°.
SHADOW_FORCED = 3.0


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

    The closed forms and the fused kernels are built from the same functions as these dynamics (``drift``,
    ``noise_gain``, ``noise_psd``, :mod:`agsf_torch.attitude.physics`) and hold for them only:
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

    def _gyro_rate(self, u: Tensor) -> Tensor:
        """The gyro rate the physics takes (:func:`~agsf_torch.attitude.physics.body_rate`): ``ω̃`` (6 states: each
        component's bias is a state), or ``ω̃ − b`` with the known bias (3 states), ``[..., 3]`` rad/s."""
        return u if self.estimate_bias else u - self.bias.to(u)

    def _entries(self, x: Tensor, u: Tensor) -> tuple[list, list]:
        """The entries of ``x [..., n]`` and of the gyro rate the physics takes (:meth:`_gyro_rate`; ``u`` checked to
        be ``[..., 3]``): views that broadcast as the tensors do (:func:`~agsf_torch.fused.algebra.as_entries`)."""
        self.check_input(u)
        return as_entries(x, (self.state_dim,)), as_entries(self._gyro_rate(u), (3,))

    # ------------------------------------------------------------ protocol
    def drift(self, x: Tensor, u: Tensor) -> Tensor:
        """``f(x, ω̃) = [¼B(p)(ω̃ − b); 0₃]`` (:func:`~agsf_torch.attitude.physics.drift`): ``x [..., n]``,
        ``u = ω̃ [..., 3]``."""
        return as_tensor(physics.drift(*self._entries(x, u)), like=x)

    def noise_gain(self, x: Tensor) -> Tensor:
        """``g(x) = −¼B(p)`` (3-state) or ``[[−¼B(p), 0], [0, I₃]]`` (6-state) (:func:`~agsf_torch.attitude.physics.noise_gain`)."""
        return as_tensor(physics.noise_gain(as_entries(x, (self.state_dim,))), like=x)

    def noise_psd(self) -> Tensor:
        """``Q = σ_v² I₃`` or ``diag(σ_v² I₃, σ_u² I₃)`` (:func:`~agsf_torch.attitude.physics.noise_psd`)."""
        return as_tensor(physics.noise_psd(self.sigma_v**2, self.sigma_u**2, self.state_dim))

    @derived_from("drift", "_gyro_rate", generic=ContinuousModel.drift_jacobian)
    def drift_jacobian(self, x: Tensor, u: Tensor) -> Tensor:
        """Closed form ``A = [[F, −¼B(p)], [0, 0]]`` with ``ω = ω̃ − b``
        (:func:`~agsf_torch.attitude.physics.drift_jacobian`).

        .. math:: F = \\tfrac12 \\left(p ω^T - ω p^T - [ω×] + (ω^T p) I_3\\right)
        """
        return as_tensor(physics.drift_jacobian(*self._entries(x, u)), like=x)

    @derived_from("drift", "_gyro_rate", generic=ContinuousModel.drift_divergence)
    def drift_divergence(self, x: Tensor, u: Tensor) -> Tensor:
        """Closed form ``∇·f = (3/2)pᵀω`` with ``ω = ω̃ − b`` (:func:`~agsf_torch.attitude.physics.drift_divergence`),
        ``[...]`` 1/s."""
        xe, ue = self._entries(x, u)
        return physics.drift_divergence(xe[:3], physics.body_rate(xe, ue))

    @derived_from("noise_gain", "noise_psd", generic=ContinuousModel.process_noise)
    def process_noise(self, x: Tensor) -> Tensor:
        """Closed form ``g Q gᵀ``: ``(σ_v²/16)(1 + s)² I₃`` on the MRP block (``B Bᵀ = (1+s)² I``;
        :func:`~agsf_torch.attitude.physics.process_noise`)."""
        # in x's dtype: a per-trajectory value has dims, which would take part in type promotion
        sv2, su2 = self.sigma_v.to(x) ** 2, self.sigma_u.to(x) ** 2
        return as_tensor(physics.process_noise(as_entries(x, (self.state_dim,)), sv2, su2), like=x)

    @derived_from(*ATTITUDE_DYNAMICS, generic=ContinuousModel.fokker_planck_terms)
    def fokker_planck_terms(self, x: Tensor, u: Tensor) -> FokkerPlanckTerms:
        """Closed forms (method.md §3; :func:`~agsf_torch.attitude.physics.fokker_planck_terms`), with
        ``c = σ_v²/32``, ``s = pᵀp``, ``ω = ω̃ − b``:

        ``div f = (3/2) pᵀω``, ``D_pp = c(1+s)² I₃`` (``D_bb = (σ_u²/2) I₃``),
        ``aₖ = 4c(1+s) pₖ`` on the MRP entries (0 on the bias), ``Σ∂²D = 4c(3 + 5s)``.
        ``D`` is diagonal and is returned as its diagonal ``[..., n]``.
        """
        self._refuse_per_trajectory("the Fokker–Planck terms")
        xe, ue = self._entries(x, u)
        t = physics.fokker_planck_terms(xe[:3], physics.body_rate(xe, ue), (self.sigma_v**2 / 32.0).to(x))
        bias = [None] * (self.state_dim - 3)
        d_b = [(0.5 * self.sigma_u**2).to(x)] * (self.state_dim - 3)
        return FokkerPlanckTerms(
            drift=as_tensor(t["rate"] + bias, like=x),
            drift_divergence=as_tensor([t["divergence"]], like=x)[..., 0],
            diffusion=as_tensor([t["diffusion"]] * 3 + d_b, like=x),
            diffusion_divergence=as_tensor(t["diffusion_divergence"] + bias, like=x),
            diffusion_second_divergence=as_tensor([t["second_divergence"]], like=x)[..., 0],
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
        """Exact Gaussian expectations of the Fokker–Planck terms under ``x ~ N(mean, cov)``
        (:func:`~agsf_torch.attitude.physics.fokker_planck_moments`, which states them).  The diffusion is
        ``D = φ D₁ + D₀`` with ``φ = (1+s)²``, ``D₁ = c = σ_v²/32`` on the MRP axes (``pattern``) and
        ``D₀ = σ_u²/2`` on the bias axes (``constant``).

        Args:
            mean: ``[..., n]``; cov: ``[..., n, n]``; u: ``ω̃`` ``[..., 3]``.
        """
        self._refuse_per_trajectory("the Fokker–Planck moments")
        n = self.state_dim
        me, ue = self._entries(mean, u)
        c = self.sigma_v.to(mean) ** 2 / 32.0
        mom = physics.fokker_planck_moments(me, as_entries(cov, (n, n)), ue, c)
        zeros = torch.zeros(n - 3, dtype=mean.dtype, device=mean.device)
        return FokkerPlanckMoments(
            scalar=as_tensor([mom["scalar"]], like=mean)[..., 0],
            transport=as_tensor(mom["transport"], like=mean),
            transport_jacobian=as_tensor(mom["transport_jacobian"], like=mean),
            field=as_tensor([mom["field"]], like=mean)[..., 0],
            field_gradient=as_tensor(mom["gradient"], like=mean),
            field_hessian=as_tensor(mom["hessian"], like=mean),
            pattern=torch.cat((c.expand(3), zeros)),
            constant=torch.cat(
                (torch.zeros(3, dtype=mean.dtype, device=mean.device), zeros + 0.5 * self.sigma_u.to(mean) ** 2)
            ),
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
        safe_p = as_entries(torch.where(switch[..., None], p, torch.ones_like(p)), (3,))
        J = as_tensor(physics.shadow_jacobian(safe_p))
        eye = torch.eye(self.state_dim, dtype=mean.dtype, device=mean.device)
        T = eye.expand(*J.shape[:-2], self.state_dim, self.state_dim).clone()
        T[..., :3, :3] = J
        T = torch.where(switch[..., None, None], T, eye)
        new_p = torch.where(switch[..., None], as_tensor(physics.shadow(safe_p)), p)
        new_mean = torch.cat((new_p, mean[..., 3:]), -1)
        new_cov = T @ cov @ T.transpose(-1, -2)
        return new_mean, 0.5 * (new_cov + new_cov.transpose(-1, -2))

    def canonicalize(self, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
        """Switch to the shadow set (see :meth:`_switch`) every component with ``|p| > 1`` that the linearised
        switch carries, ``√tr P_pp ≤`` :data:`SHADOW_SPREAD` ``·|p|``, and every one beyond
        :data:`SHADOW_FORCED` whatever its spread.

        A wider component stays in its own set: the shadow map ``−p/|p|²`` bends by about ``√tr P_pp / |p|`` over
        one standard deviation, and its linearisation ``P ← JPJᵀ`` would leave most of such a component's mass
        (e.g. a 90°-per-axis prior drawn around a mean in the shadow set) where the Gaussian no longer reaches: on
        ``agsf validate``'s one-star scenario from a 90° prior the truth then lay up to 266 (squared Mahalanobis)
        from every component of the initial mixture, against at most 36 where the mean was inside the unit ball.

        Args:
            mean: ``[..., n]``; cov: ``[..., n, n]``.
        """
        p = mean[..., :3]
        s = (p * p).sum(-1)
        spread = cov[..., :3, :3].diagonal(dim1=-2, dim2=-1).sum(-1)  # tr P_pp ≥ the largest variance
        accurate = spread <= SHADOW_SPREAD**2 * s
        return self._switch(mean, cov, (s > 1.0) & (accurate | (s > SHADOW_FORCED**2)))

    def align(self, mean: Tensor, cov: Tensor, reference: Tensor) -> tuple[Tensor, Tensor]:
        """Express each component in the MRP set (itself or its shadow) nearer to ``reference``.

        Components on different sides of ``|p| = 1`` describe nearby attitudes with
        far-apart MRPs; their moments are meaningful only in one chart.

        Args:
            mean: ``[..., N, n]``; cov: ``[..., N, n, n]``; reference: broadcastable to ``mean``.
        """
        return self._switch(mean, cov, _nearer_set(mean[..., :3], reference[..., :3])[1])

    def state_error(self, x_est: Tensor, x_true: Tensor) -> Tensor:
        """``x_est − x_true`` with the true MRP taken in whichever set (itself or
        its shadow) lies closer to the estimate."""
        p_e, p_t = torch.broadcast_tensors(x_est[..., :3], x_true[..., :3])
        dp = p_e - _nearer_set(p_t, p_e)[0]
        if not self.estimate_bias:
            return dp
        return torch.cat((dp, x_est[..., 3:] - x_true[..., 3:]), -1)


def _nearer_set(p: Tensor, ref: Tensor) -> tuple[Tensor, Tensor]:
    """``p [..., 3]`` or its shadow, whichever lies nearer to ``ref``, and where the shadow was taken ``[...]``
    (``p = 0`` stays: its shadow lies at infinity)."""
    shadow = -p / (p * p).sum(-1, keepdim=True).clamp_min(torch.finfo(p.dtype).tiny)
    switch = ((shadow - ref) ** 2).sum(-1) < ((p - ref) ** 2).sum(-1)
    return torch.where(switch[..., None], shadow, p), switch
