"""The authors' later weight update (method.md §3b): the weights' rate cancels the FPKE residual in L²."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import Tensor

from ...fpke import fpke_matrix, fused_galerkin_matrices, galerkin_matrices, residual_rule
from ...mixture import GaussianMixture
from ...models.base import ContinuousModel
from ...qp import kkt_residual
from ..options import option
from .base import QuadratureUpdate, check_finite_matrix, component_rates, has_gaussian_moments, solve_weight_qp

__all__ = ["GalerkinWeightUpdate"]


@dataclass(frozen=True, kw_only=True, eq=False)
class GalerkinWeightUpdate(QuadratureUpdate):
    """The authors' later weight update (method.md §3b): the weights' rate cancels the FPKE residual in L².

    .. math:: w^+ = \\arg\\min_{w ∈ Δ} ∫ \\Big(Σ_i \\frac{w_i - w^-_i}{Δt} p_i(x) + Σ_j w^-_j L_j(x)\\Big)^2 dx
                  = \\arg\\min_{w ∈ Δ} ½ w^T M w + w^T (Δt\\,K - M) w^-

    ``M_ij = ∫pᵢpⱼ = N(μᵢ; μⱼ, Pᵢ + Pⱼ)`` (closed form), ``K_ij = ∫pᵢLⱼ =
    z_ij E_{N(m_ij, S_ij)}[ℓⱼ]`` (:func:`agsf_torch.fpke.galerkin_matrices`, integrand
    ``ℓⱼ``: degree 6 for attitude, exact with 4 Gauss–Hermite points per MRP axis
    and 2 per bias axis; on lanes by the model's fused kernel when it has one and the filter's
    ``fused`` option is on, :mod:`agsf_torch.fused.galerkin`).  ``w⁻`` are the weights before this adaptation (after the
    last measurement update, if there was one); ``Δt`` is the time since the last
    adaptation (the interval itself at ``cadence = 1``).  Both matrices are
    divided by ``max z_ij``, which leaves the minimiser unchanged.  No λ and no
    scaling choice.

    ``M`` is only positive *semi*-definite when components coincide (any split of
    their weight gives the same density).  Among the minimisers the update
    returns the one nearest ``w⁻``: it solves with ``M + εI`` and linear term
    ``(Δt K − M)w⁻ − εw⁻`` (a proximal term ``(ε/2)‖w − w⁻‖²``), ``ε = tikhonov ·
    max diag M̃``, whose minimiser tends to the projection of ``w⁻`` on the solution
    set as ε → 0 and moves the objective by at most ``ε·‖w − w⁻‖²/2``.  The default
    ε = 1e-9 keeps the KKT solve conditioned to ~1e9, so the weights in the flat
    directions are accurate to ~1e-7 (at 1e-12 rounding of the linear term alone
    left 1e-4); on the sine benchmark (method.md §5) the forecast ISE at t = 8 is
    the same to 8 digits for ε from 1e-12 to 1e-8.

    Attributes:
        tikhonov: the relative ε above (> 0; default 1e-9).
        residual_diagnostics: also evaluate the FPKE residual ``∫e²`` with the weights
            held (``fpke_error_before = w⁻ᵀLw⁻``, as the penalty update's) and with the
            chosen weight rate over the step (``fpke_error_with_rate``); this needs the paper's
            ``ℓᵢℓⱼ`` integrals (with the model's rule for them, as the penalty
            update's default) and costs as much as the penalty update.
        cadence, quadrature, chunk_size, compile: :class:`WeightUpdate`, :class:`QuadratureUpdate`.

    Diagnostics: ``galerkin_residual_change [...]`` (``∫e²`` after minus before,
    exact and cheap: ``[(w − w⁻)ᵀM(w − w⁻) + 2Δt(w − w⁻)ᵀKw⁻]/Δt²``, ≤ 0 to rounding: a step that leaves the
    weights where they were may read +1e-16),
    ``qp_kkt_residual [...]`` (of the problem without the proximal term, and, in a managed mixture, without the
    share each component keeps, :func:`~.base.solve_weight_qp`),
    ``qp_iterations``; with ``residual_diagnostics`` also the two errors.

    ``Δt`` restarts at each measurement update (:meth:`WeightUpdate.observe_update`):
    the posterior weights are the ``w⁻`` of the next adaptation.
    """

    tikhonov: float = field(
        default=1e-9,
        metadata=option(
            "relative proximal weight ε of the Galerkin weight update (AGSF-galerkin), > 0", config="float"
        ),
    )
    residual_diagnostics: bool = field(
        default=False,
        metadata=option(
            "the Galerkin update also reports the FPKE residual ∫e² (costs as much as the paper's update)",
            config="bool",
        ),
    )

    name: ClassVar[str] = "galerkin"
    factors: ClassVar[int] = 1
    DIAGNOSTICS: ClassVar[tuple[str, ...]] = ("galerkin_residual_change", "qp_kkt_residual", "qp_iterations")

    def __post_init__(self) -> None:
        super().__post_init__()
        t = self.tikhonov
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0.0 < t < float("inf"):
            raise ValueError(f"tikhonov must be a finite number > 0 (it selects the minimiser nearest w⁻), got {t!r}")
        object.__setattr__(self, "tikhonov", float(t))
        if not isinstance(self.residual_diagnostics, bool):
            raise ValueError(f"residual_diagnostics must be True or False, got {self.residual_diagnostics!r}")

    @property
    def diagnostic_keys(self) -> tuple[str, ...]:
        extra = ("fpke_error_before", "fpke_error_with_rate") if self.residual_diagnostics else ()
        return self.DIAGNOSTICS + extra

    def bind(self, model: ContinuousModel, *, fused: bool = True, compile_fused: bool = False) -> None:
        super().bind(model, fused=fused, compile_fused=compile_fused)
        if self.quadrature is None and has_gaussian_moments(model):
            self.rule["nodes"] = self.rule["weights"] = None  # K in closed form (fpke.moments)
        # the model's rule for ℓᵢℓⱼ, for the residual diagnostics
        self.rule["residual"] = residual_rule(model, None, 2) if self.residual_diagnostics else None

    def compute(
        self,
        model: ContinuousModel,
        prior: GaussianMixture,
        propagated: GaussianMixture,
        u: Tensor | None,
        elapsed: float,
    ) -> tuple[Tensor, dict[str, Any]]:
        closed_form = self.rule["nodes"] is None
        comp = None
        G = None
        if closed_form and self.rule["fused"]:  # rates and pairs on lanes, if the model has the kernel
            G = fused_galerkin_matrices(model, u, propagated.means, propagated.covs, self.rule["compile_fused"])
        if G is None:
            comp = component_rates(model, propagated, u)
            G = galerkin_matrices(
                model,
                u,
                comp,
                self.rule["nodes"],
                self.rule["weights"],
                self.chunk_size,
                compile=self.rule["compile"],
                fused=False,
            )
        check_finite_matrix("Galerkin matrix K", G.drift)
        check_finite_matrix("Galerkin matrix M", G.mass)
        w0 = propagated.weights
        N = w0.shape[-1]
        c = ((elapsed * G.drift - G.mass) @ w0.unsqueeze(-1)).squeeze(-1)
        eps = self.tikhonov * G.mass.diagonal(dim1=-2, dim2=-1).amax(-1)
        eye = torch.eye(N, dtype=w0.dtype, device=w0.device)
        w_new, res = solve_weight_qp(
            self.run, G.mass + eps[..., None, None] * eye, c - eps[..., None] * w0, propagated.log_weights
        )
        dw = w_new - w0
        change = (dw.unsqueeze(-2) @ G.mass @ dw.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        change = change + 2.0 * elapsed * (dw.unsqueeze(-2) @ G.drift @ w0.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        change = change * torch.exp(G.log_scale) / elapsed**2
        extra: dict[str, Any] = {
            "galerkin_residual_change": change,
            "qp_kkt_residual": kkt_residual(G.mass, c, w_new),
            "qp_iterations": res.iterations,
        }
        residual = self.rule.get("residual")
        if residual is not None:
            comp = component_rates(model, propagated, u) if comp is None else comp
            Lmat = fpke_matrix(model, u, comp, *residual, self.chunk_size, compile=self.rule["compile"])
            before = Lmat.error(w0)
            extra["fpke_error_before"] = before
            extra["fpke_error_with_rate"] = before + change
        return torch.log(w_new), extra
