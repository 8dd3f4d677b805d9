"""The proposal of a redraw for the initial state: the prior and t densities about Laplace modes.

In the MRP chart the t components live in the multiplicative chart ``x = μ ⊞ δ``
about their mode (:func:`_mrp_retract`, :func:`_mrp_local` and the Jacobian
:func:`_mrp_retract_jacobian`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..mixture import GaussianMixture
from ..rotations import mrp_to_quat, quat_conjugate, quat_multiply

__all__ = ["InitialStateProposal"]


def _mrp_retract(mode: Tensor, delta: Tensor) -> Tensor:
    """``x = mode ⊞ δ``: the MRP of ``q(mode) ⊗ q(δ)`` (``C(x) = C(mode) C(δ)``), bias added.

    Quaternions from MRPs by inverse stereographic projection, ``q(p) = [2p, 1 − s]/(1 + s)``,
    and back by ``p = q_v/(1 + q₄)`` with no sign normalisation, so that ``δ ↦ x`` is a
    bijection of ``R³`` (almost everywhere) that preserves the rotation group's Haar measure
    ``∝ (1 + |p|²)⁻³ dp``; hence ``|det ∂x/∂δ| = (1 + |x|²)³ / (1 + |δ|²)³``.
    """
    q = quat_multiply(mrp_to_quat(mode[..., :3]), mrp_to_quat(delta[..., :3]))
    p = q[..., :3] / (1.0 + q[..., 3:]).clamp_min(torch.finfo(q.dtype).tiny)
    return torch.cat((p, mode[..., 3:] + delta[..., 3:]), -1)


def _mrp_local(mode: Tensor, x: Tensor) -> Tensor:
    """Inverse of :func:`_mrp_retract`: ``δ`` with ``mode ⊞ δ = x``."""
    q = quat_multiply(quat_conjugate(mrp_to_quat(mode[..., :3])), mrp_to_quat(x[..., :3]))
    p = q[..., :3] / (1.0 + q[..., 3:]).clamp_min(torch.finfo(q.dtype).tiny)
    return torch.cat((p, x[..., 3:] - mode[..., 3:]), -1)


def _mrp_retract_jacobian(mode: Tensor) -> Tensor:
    """``J = ∂(mode ⊞ δ)/∂δ`` at ``δ = 0``, ``[..., n, n]`` (identity on the bias block).

    ``q(δ) ≈ [2δ, 1]``, so ``dq = q(mode) ⊗ [2dδ, 0]`` and ``dx = dq_v/(1 + q₄) − q_v dq₄/(1 + q₄)²``.
    """
    n = mode.shape[-1]
    q = mrp_to_quat(mode[..., :3])  # [..., 4]
    eye3 = torch.eye(3, dtype=mode.dtype, device=mode.device)
    basis = torch.cat((2.0 * eye3, torch.zeros(3, 1, dtype=mode.dtype, device=mode.device)), -1)  # [3, 4]
    dq = quat_multiply(q.unsqueeze(-2).expand(*q.shape[:-1], 3, 4), basis.expand(*q.shape[:-1], 3, 4))  # [..., i, 4]
    den = 1.0 + q[..., None, 3:]
    cols = dq[..., :3] / den - q[..., None, :3] * dq[..., 3:] / den**2  # [..., i, 3]: column i
    J = torch.eye(n, dtype=mode.dtype, device=mode.device).expand(*mode.shape[:-1], n, n).clone()
    J[..., :3, :3] = cols.transpose(-1, -2)
    return J


class InitialStateProposal:
    r"""The defensive proposal of a redraw for the initial state ``x₀`` (batched ``[B]``).

    .. math:: q(x) = α\,p_0(x) + (1 - α) Σ_m c_m\, t_ν\!\left(δ_m(x); 0, s^2 C^δ_m\right)
              \left|\det ∂δ_m/∂x\right|

    ``p₀`` is the prior (so ``p₀/q ≤ 1/α``: importance weights stay bounded), and each
    multivariate-t component lives in local coordinates ``δ`` about a Laplace mode
    ``μ_m``: ``x = μ_m + δ`` in the Euclidean chart; in the MRP chart
    ``x = μ_m ⊞ δ`` (``C(x) = C(μ_m) C(δ)``, :func:`_mrp_retract`), in which the set of
    attitudes consistent with a single star direction is a straight line, so a
    one-star posterior is a thin *straight* ridge rather than a curved ring.
    ``C^δ_m = J⁻¹ C_m J⁻ᵀ`` with ``J = ∂x/∂δ`` at ``δ = 0`` carries the Laplace
    covariance ``C_m`` of ``x₀``.

    Args:
        prior: mixture ``[B]``.
        modes: ``[B, M, n]``; covs: Laplace covariances ``[B, M, n, n]``.
        shares: ``c_m`` ``[B, M]`` summing to 1.
        defensive_weight: ``α``; t_dof: ``ν`` (integer); t_scale: ``s``; chart: as everywhere.
    """

    def __init__(
        self,
        prior: GaussianMixture,
        modes: Tensor,
        covs: Tensor,
        shares: Tensor,
        *,
        defensive_weight: float,
        t_dof: int,
        t_scale: float,
        chart: str,
    ) -> None:
        self.prior, self.modes, self.chart = prior, modes, chart
        self.alpha, self.nu = float(defensive_weight), int(t_dof)
        self.log_shares = torch.log(shares)
        if chart == "mrp":
            J = _mrp_retract_jacobian(modes)
            Y = torch.linalg.solve(J, covs)
            covs = torch.linalg.solve(J, Y.transpose(-1, -2))
            covs = 0.5 * (covs + covs.transpose(-1, -2))
        self.chol = torch.linalg.cholesky(covs) * float(t_scale)  # [B, M, n, n]

    def _to_x(self, modes: Tensor, delta: Tensor) -> Tensor:
        return _mrp_retract(modes, delta) if self.chart == "mrp" else modes + delta

    def sample(self, K: int, generator: torch.Generator) -> Tensor:
        """``K`` draws per trajectory, ``[B, K, n]``."""
        B, M, n = self.modes.shape
        dtype, device = self.modes.dtype, self.modes.device
        probs = torch.cat(
            (torch.full((B, 1), self.alpha, dtype=dtype, device=device), (1.0 - self.alpha) * self.log_shares.exp()), -1
        )
        comp = torch.multinomial(probs, K, replacement=True, generator=generator)  # [B, K]
        idx = (comp - 1).clamp_min(0)
        mu = torch.gather(self.modes, 1, idx[..., None].expand(-1, -1, n))
        L = torch.gather(self.chol, 1, idx[..., None, None].expand(-1, -1, n, n))
        z = torch.randn(B, K, n, generator=generator, dtype=dtype, device=device)
        chi2 = (torch.randn(B, K, self.nu, generator=generator, dtype=dtype, device=device) ** 2).sum(-1)
        delta = (L @ z.unsqueeze(-1)).squeeze(-1) * torch.sqrt(self.nu / chi2)[..., None]  # t_ν(0, s²C^δ)
        x_t = self._to_x(mu, delta)
        pr = self.prior
        j = torch.multinomial(pr.weights, K, replacement=True, generator=generator)
        Lp = torch.gather(torch.linalg.cholesky(pr.covs), 1, j[..., None, None].expand(-1, -1, n, n))
        zp = torch.randn(B, K, n, generator=generator, dtype=dtype, device=device)
        x_p = torch.gather(pr.means, 1, j[..., None].expand(-1, -1, n)) + (Lp @ zp.unsqueeze(-1)).squeeze(-1)
        return torch.where((comp == 0)[..., None], x_p, x_t)

    def log_prob(self, x: Tensor) -> Tensor:
        """``log q(x)`` for ``x [B, K, n]`` → ``[B, K]``."""
        n = x.shape[-1]
        nu = self.nu
        xm = x.unsqueeze(1)  # [B, 1, K, n]
        modes = self.modes.unsqueeze(2)  # [B, M, 1, n]
        if self.chart == "mrp":
            delta = _mrp_local(modes.expand(-1, -1, x.shape[1], -1), xm.expand(-1, modes.shape[1], -1, -1))
            s_d = (delta[..., :3] ** 2).sum(-1)
            s_x = (x[..., :3] ** 2).sum(-1).unsqueeze(1)
            log_jac = 3.0 * torch.log1p(s_d) - 3.0 * torch.log1p(s_x)  # log |∂δ/∂x|
        else:
            delta = xm - modes
            log_jac = 0.0
        w = torch.linalg.solve_triangular(self.chol, delta.transpose(-1, -2), upper=False)  # [B, M, n, K]
        maha = (w * w).sum(-2)
        logdet = 2.0 * torch.log(self.chol.diagonal(dim1=-2, dim2=-1)).sum(-1, keepdim=True)
        log_t = (
            math.lgamma((nu + n) / 2)
            - math.lgamma(nu / 2)
            - 0.5 * n * math.log(nu * math.pi)
            - 0.5 * logdet
            - 0.5 * (nu + n) * torch.log1p(maha / nu)
        ) + log_jac  # [B, M, K]
        log_t = torch.where(torch.isnan(log_t), torch.full_like(log_t, -math.inf), log_t)
        parts = torch.cat(
            (
                (math.log(self.alpha) + self.prior.log_prob(x)).unsqueeze(1),
                math.log(1.0 - self.alpha) + self.log_shares.unsqueeze(-1) + log_t,
            ),
            1,
        )
        return torch.logsumexp(parts, 1)
