"""The path-space redraw of :class:`~agsf_torch.density.PosteriorReference`.

Where the bootstrap would collapse (``ESS/K < redraw_threshold``, e.g. the first
sharp star frame), or resampling has left fewer than ``redraw_threshold·K``
lineages, the trajectory's particles are **redrawn** by path-space importance
sampling: ``x₀ ~ q`` — a *defensive* mixture of the prior itself and multivariate-t
densities about Laplace (Gauss–Newton) fits of the posterior of ``x₀`` given all
frames so far (:class:`InitialStateProposal`) — and the noise path from its prior
(the SDE re-simulated from ``t₀``), with weight ``p₀(x₀) Πₖ p(yₖ | x_{tₖ}) / q(x₀)``.
Redraw weights are bounded, ``p₀/q ≤ 1/α``.

The Laplace fits only shape the proposal: their approximations (linearised
measurements and process noise, one RK4 step per interval, Gaussian shape) cost
efficiency, never correctness.  What limits the efficiency of a redraw is the noise
path drawn from its prior: its ESS falls roughly like ``Πⱼ (Rⱼ / (Rⱼ + Σⱼ))^{1/2}``
with ``Σⱼ`` the process-noise variance accumulated in the measured directions between
``t₀`` and frame ``j``, so redraws are efficient while that noise is small against the
measurement noise (attitude: σ_v √t ≪ σ_s, hundreds of seconds for the default gyro
and camera).  A redraw re-simulates from ``t₀``, so its cost grows with the elapsed
time.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .charts import canonical_points, switch_flow
from .frames import point_eval
from .proposal import InitialStateProposal

if TYPE_CHECKING:
    from .frames import Frame


class PathSpaceRedraw:
    """The redraw steps of :class:`~agsf_torch.density.PosteriorReference` (a mixin).

    They read the sampler's set-up (``model``, ``chart``, ``state_dim``,
    ``num_samples``, ``generator``, ``prior``, ``prior_mean``, ``prior_cov``, the
    proposal options), its state (``samples``, ``initial_samples``) and its record of
    inputs and frames (``_intervals``, ``_frames``), and call its ``_em_interval`` and
    ``_frame_log_likelihood``.
    """

    def _flow(self, x0: Tensor, with_tangents: bool):
        """Noise-free flow from ``t₀`` through every recorded interval (one RK4 step each).

        With tangents, also the flow Jacobian ``S = ∂x(t)/∂x₀`` and the linearised
        process-noise covariance ``Σ̇ = AΣ + ΣAᵀ + gQgᵀ`` (``Σ(t₀) = 0``).

        Returns:
            per frame (in order): ``(x, S, Σ)`` at the frame time (``S, Σ`` ``None`` without tangents).
        """
        model = self.model
        x = x0
        n = self.state_dim
        S = Sig = None
        if with_tangents:
            S = torch.eye(n, dtype=x.dtype, device=x.device).expand(*x.shape, n).clone()
            Sig = torch.zeros_like(S)
        out = []
        frames_at: dict[int, int] = {}
        for f in self._frames:
            frames_at[f.step] = frames_at.get(f.step, 0) + 1

        def collect(step):
            for _ in range(frames_at.get(step, 0)):
                out.append((x, S, Sig))

        def rhs(x, S, Sig, u):
            fx = model.drift(x, u)
            if S is None:
                return fx, None, None
            A = model.drift_jacobian(x, u)
            ASig = A @ Sig
            return fx, A @ S, ASig + ASig.transpose(-1, -2) + model.process_noise(x)

        collect(0)
        last = max(frames_at) if frames_at else 0
        for i, (u, dt) in enumerate(self._intervals[:last]):
            uu = None if u is None else u.unsqueeze(1)
            k1 = rhs(x, S, Sig, uu)
            k2 = rhs(*_axpy3((x, S, Sig), k1, dt / 2), uu)
            k3 = rhs(*_axpy3((x, S, Sig), k2, dt / 2), uu)
            k4 = rhs(*_axpy3((x, S, Sig), k3, dt), uu)
            x, S, Sig = (
                None if a is None else a + dt / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
                for a, b1, b2, b3, b4 in zip((x, S, Sig), k1, k2, k3, k4)
            )
            if self.chart == "mrp":
                x, S, Sig = switch_flow(x, S, Sig)
            collect(i + 1)
        return out

    def _map_back(self, pts: Tensor) -> Tensor:
        """Points at the current time mapped to ``t₀`` along the noise-free flow (RK4 backwards)."""
        x = pts
        for u, dt in reversed(self._intervals):
            uu = None if u is None else u.unsqueeze(1)
            f = self.model.drift
            k1 = f(x, uu)
            k2 = f(x - dt / 2 * k1, uu)
            k3 = f(x - dt / 2 * k2, uu)
            k4 = f(x - dt * k3, uu)
            x = x - dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            if self.chart == "mrp":
                x = switch_flow(x)[0]
        if self.chart == "mrp":  # the MRP set nearer the prior mean
            p = x[..., :3]
            ps = -p / (p * p).sum(-1, keepdim=True).clamp_min(torch.finfo(p.dtype).tiny)
            ref = self.prior_mean[:, None, :3]
            use = ((ps - ref) ** 2).sum(-1, keepdim=True) < ((p - ref) ** 2).sum(-1, keepdim=True)
            x = torch.cat((torch.where(use, ps, p), x[..., 3:]), -1)
        return x

    def _linearise(self, x0: Tensor):
        """Stacked residuals, ``x₀``-Jacobian and noise covariance of all frames at ``x₀ [B, S, n]``.

        ``y ≈ h(x(x₀)) + Λ δx₀ + Λ δw + v``: ``Λ = [Hₖ Sₖ]``; the process noise mapped
        back to ``t₀`` has covariance ``Σ̄ₖ = Sₖ⁻¹ Σₖ Sₖ⁻ᵀ``, so
        ``Cov(yₐ, y_b) = Rₐ δₐ_b + Λₐ Σ̄_{min(a,b)} Λ_bᵀ``.

        Returns:
            ``(r [B, S, D], Λ [B, S, D, n], R_tot [B, S, D, D])``.
        """
        flows = self._flow(x0, with_tangents=True)
        rs, Ls, Rs, back = [], [], [], []
        for f, (x, S, Sig) in zip(self._frames, flows):
            h, H = point_eval(f.measurement, x, jacobian=True)
            v = f.valid[:, None, :]
            rs.append(v * (f.y[:, None, :] - h))
            Ls.append(v[..., None] * (H @ S))
            Rs.append(f.R_eff[:, None].expand(-1, x.shape[1], -1, -1))
            Y = torch.linalg.solve(S, Sig)  # S⁻¹Σ
            Sb = torch.linalg.solve(S, Y.transpose(-1, -2))  # S⁻¹ΣS⁻ᵀ
            back.append(0.5 * (Sb + Sb.transpose(-1, -2)))
        r = torch.cat(rs, -1)
        Lam = torch.cat(Ls, -2)
        R_tot = _block_diag_list(Rs)
        sizes = [t.shape[-1] for t in rs]
        start = 0
        prev = torch.zeros_like(back[0])
        for k, size in enumerate(sizes):
            inc = back[k] - prev  # noise between frames k−1 and k, mapped back to t₀
            prev = back[k]
            Lk = Lam.clone()
            Lk[..., :start, :] = 0.0  # rows of frames ≥ k share this increment
            R_tot = R_tot + Lk @ inc @ Lk.transpose(-1, -2)
            start += size
        return r, Lam, 0.5 * (R_tot + R_tot.transpose(-1, -2))

    def _laplace(self, starts: Tensor):
        """Gauss–Newton (iterated-EKF form, step halving) for the mode of ``p(x₀ | y₁…ₖ)``.

        Cost ``(x₀ − m₀)ᵀP₀⁻¹(x₀ − m₀) + rᵀR_tot⁻¹r + log det R_tot`` with the
        linearised process noise in ``R_tot``; step
        ``x₀ ← m₀ + K(r + Λ(x₀ − m₀))``, ``K = P₀Λᵀ(ΛP₀Λᵀ + R_tot)⁻¹``.

        Args:
            starts: ``[B, S, n]``.

        Returns:
            ``(mode [B, S, n], covariance [B, S, n, n], log evidence [B, S])``.
        """
        m0 = self.prior_mean[:, None, :]
        P0 = self.prior_cov[:, None]
        L0 = torch.linalg.cholesky(P0)
        n = self.state_dim
        x = starts
        best_x = x
        best_cost = torch.full(x.shape[:-1], math.inf, dtype=x.dtype, device=x.device)
        best = None
        for it in range(self.gauss_newton_iterations + 1):
            r, Lam, R_tot = self._linearise(x)
            LR, info = torch.linalg.cholesky_ex(R_tot)
            ok = info == 0
            LR = torch.where(ok[..., None, None], LR, torch.eye(LR.shape[-1], dtype=x.dtype, device=x.device))
            zr = torch.linalg.solve_triangular(LR, r.unsqueeze(-1), upper=False).squeeze(-1)
            z0 = torch.linalg.solve_triangular(L0, (x - m0).unsqueeze(-1), upper=False).squeeze(-1)
            cost = (z0 * z0).sum(-1) + (zr * zr).sum(-1) + 2.0 * torch.log(LR.diagonal(dim1=-2, dim2=-1)).sum(-1)
            cost = torch.where(ok & torch.isfinite(cost), cost, torch.full_like(cost, math.inf))
            improved = cost < best_cost
            best_x = torch.where(improved[..., None], x, best_x)
            best_cost = torch.where(improved, cost, best_cost)
            if best is None:
                best = (r, Lam, R_tot)
            else:
                best = tuple(
                    torch.where(improved.reshape(*improved.shape, *([1] * (a.dim() - 2))), a, b)
                    for a, b in zip((r, Lam, R_tot), best)
                )
            if it == self.gauss_newton_iterations:
                break
            r_b, Lam_b, R_b = best
            PLt = P0 @ Lam_b.transpose(-1, -2)
            Sy = Lam_b @ PLt + R_b
            Ly, info_y = torch.linalg.cholesky_ex(0.5 * (Sy + Sy.transpose(-1, -2)))
            nu = r_b + (Lam_b @ (best_x - m0).unsqueeze(-1)).squeeze(-1)
            step = m0 + (PLt @ torch.cholesky_solve(nu.unsqueeze(-1), Ly)).squeeze(-1)
            step = torch.where((info_y == 0)[..., None] & torch.isfinite(step), step, best_x)
            new_x = torch.where(improved[..., None], step, 0.5 * (x + best_x))
            # converged when every step is far below the posterior spread: (Δx)ᵀ C⁻¹ (Δx) with
            # C⁻¹ = P₀⁻¹ + ΛᵀR_tot⁻¹Λ, i.e. |L₀⁻¹Δx|² + |L_R⁻¹ΛΔx|² (Cholesky solves)
            dx = (new_x - best_x).unsqueeze(-1)
            d0 = torch.linalg.solve_triangular(L0, dx, upper=False)
            LRb = torch.linalg.cholesky_ex(R_b)[0]
            d1 = torch.linalg.solve_triangular(LRb, Lam_b @ dx, upper=False)
            x = new_x
            if float(((d0 * d0).sum((-2, -1)) + (d1 * d1).sum((-2, -1))).max()) < 1e-10:
                break
        r, Lam, R_tot = best
        PLt = P0 @ Lam.transpose(-1, -2)
        Sy = 0.5 * (Lam @ PLt + R_tot + (Lam @ PLt + R_tot).transpose(-1, -2))
        Ly, info = torch.linalg.cholesky_ex(Sy)
        Kg = torch.cholesky_solve(PLt.transpose(-1, -2), Ly).transpose(-1, -2)  # [B, S, n, D]
        IKL = torch.eye(n, dtype=x.dtype, device=x.device) - Kg @ Lam
        C = IKL @ P0 @ IKL.transpose(-1, -2) + Kg @ R_tot @ Kg.transpose(-1, -2)
        C = 0.5 * (C + C.transpose(-1, -2))
        nu = r + (Lam @ (best_x - m0).unsqueeze(-1)).squeeze(-1)
        z = torch.linalg.solve_triangular(Ly, nu.unsqueeze(-1), upper=False).squeeze(-1)
        D = nu.shape[-1]
        logdet_y = 2.0 * torch.log(Ly.diagonal(dim1=-2, dim2=-1)).sum(-1)
        log_ev = -0.5 * ((z * z).sum(-1) + logdet_y + D * math.log(2 * math.pi))
        good = (info == 0) & torch.isfinite(log_ev) & torch.isfinite(best_x).all(-1)
        good = good & (torch.linalg.cholesky_ex(C).info == 0)
        C = torch.where(good[..., None, None], C, P0.expand_as(C))
        best_x = torch.where(good[..., None], best_x, m0.expand_as(best_x))
        log_ev = torch.where(good, log_ev, torch.full_like(log_ev, -math.inf))
        return best_x, C, log_ev

    def _redraw(self, sub: Tensor, boot_log_weights: Tensor, hints: Tensor | None):
        """Path-space importance sampling over every frame so far, for the trajectories ``sub``.

        ``x₀ ~ q`` (:class:`InitialStateProposal`: the prior and multivariate-t densities
        about Laplace fits from the prior mean, the best particles and the hints, with
        shares ``cₘ`` half by Laplace evidence, half equal), the noise path from its prior,
        ``log w = log p₀(x₀) − log q(x₀) + Σₖ log p(yₖ | x_{tₖ})``.

        Args:
            sub: trajectory indices ``[b]``.
            boot_log_weights: bootstrap log-weights ``[B, K]`` (they pick the particle starts).
            hints: ``[B, H, n]`` or ``None``.

        Returns:
            ``(samples [b, K, n], initial samples [b, K, n], log-weights [b, K])``.
        """
        K, n = self.num_samples, self.state_dim
        starts = [self.prior_mean[:, None, :]]
        if self.particle_starts > 0:
            top = torch.topk(boot_log_weights, min(self.particle_starts, K), -1).indices
            starts.append(torch.gather(self.initial_samples, 1, top[..., None].expand(-1, -1, n)))
        if hints is not None:
            starts.append(self._map_back(hints))
        mode, C, log_ev = self._laplace(torch.cat(starts, 1))  # whole batch: the measurement models are [B]
        mode, C, log_ev = mode[sub], C[sub], log_ev[sub]
        M = mode.shape[1]
        # component shares: half by Laplace evidence, half equal (robust to poor evidences)
        ev = torch.softmax(log_ev, -1)
        ev = torch.where(torch.isfinite(ev), ev, torch.zeros_like(ev))
        c = 0.5 * ev + 0.5 / M
        pr = self.prior
        prior = pr.replace(log_weights=pr.log_weights[sub], means=pr.means[sub], covs=pr.covs[sub], validate=False)
        proposal = InitialStateProposal(
            prior,
            mode,
            C,
            c / c.sum(-1, keepdim=True),
            defensive_weight=self.defensive_weight,
            t_dof=self.t_dof,
            t_scale=self.t_scale,
            chart=self.chart,
        )
        x0 = proposal.sample(K, self.generator)
        log_q = proposal.log_prob(x0)
        log_p0 = prior.log_prob(x0)  # [b, K]
        # re-simulate the noise path from t₀ and collect the likelihoods of every frame; the
        # measurement models carry the whole batch, so the states are embedded in it for them
        full = self.samples.clone()

        def frame_ll(f: Frame, x: Tensor) -> Tensor:
            full[sub] = x
            return self._frame_log_likelihood(f, full)[sub]

        x = canonical_points(x0, self.chart)
        ll = torch.zeros_like(log_p0)
        frames_at: dict[int, list[Frame]] = {}
        for f in self._frames:
            frames_at.setdefault(f.step, []).append(f)
        for f in frames_at.get(0, []):
            ll = ll + frame_ll(f, x)
        for i, (u, dt) in enumerate(self._intervals):
            x = self._em_interval(x, None if u is None else u[sub], dt)
            for f in frames_at.get(i + 1, []):
                ll = ll + frame_ll(f, x)
        lw = log_p0 - log_q + ll
        lw = torch.where(torch.isnan(lw), torch.full_like(lw, -math.inf), lw)
        lw = lw - torch.logsumexp(lw, -1, keepdim=True)
        return x, x0, lw


def _axpy3(base, k, a):
    return tuple(None if b is None else b + a * kk for b, kk in zip(base, k))


def _block_diag_list(blocks: list[Tensor]) -> Tensor:
    """Batched block-diagonal of ``[..., dₖ, dₖ]`` blocks → ``[..., D, D]``."""
    D = sum(b.shape[-1] for b in blocks)
    out = blocks[0].new_zeros(*blocks[0].shape[:-2], D, D)
    s = 0
    for b in blocks:
        d = b.shape[-1]
        out[..., s : s + d, s : s + d] = b
        s += d
    return out
