"""The paper's weight update (method.md §3): a QP penalising the FPKE residual and the distance to reference weights."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import Tensor

from ...fpke import fpke_matrix, fused_fpke_matrix
from ...fpke.rounding import without_rounding_rows
from ...mixture import GaussianMixture
from ...models.base import ContinuousModel
from ..options import option
from .base import QuadratureUpdate, component_rates, solve_weight_qp

__all__ = ["PenaltyWeightUpdate"]


_SCALINGS = ("trace", "none")
_REFERENCES = ("update", "previous")


@dataclass(frozen=True, kw_only=True, eq=False)
class PenaltyWeightUpdate(QuadratureUpdate):
    """The paper's weight QP (method.md §3).

    .. math:: w^* = \\arg\\min_{w ∈ Δ} ½ w^T L w + \\frac{λ}{2} \\|w - w_{ref}\\|^2,
              \\qquad L_{ij} = ∫ L_i L_j\\,dx

    with ``L`` of the propagated components (:func:`agsf_torch.fpke.fpke_matrix`,
    integrand ``ℓᵢℓⱼ``).  In the form handed to the QP solver: Hessian ``L + λI``,
    linear term ``−λ w_ref``.

    Attributes:
        reg: λ ≥ 0 (the paper: 1); a 0-d tensor keeps its gradient (learning).
        scaling: ``"trace"`` (default) solves with ``L / (tr L / N)`` so that λ is
            dimensionless — with star-camera covariances the raw ``L`` is
            astronomically large and the penalty would vanish; ``"none"`` uses the
            raw ``L`` (the paper's ``L + I``).  Either way, on the generic route the rows of components whose
            residual is zero to rounding (a linear model's, say) are set to zero first
            (:func:`agsf_torch.fpke.rounding.without_rounding_rows`): scaled by its own trace, rounding would
            move the weights at random.
        weight_ref: ``"update"`` (default, the paper's ``w_{k|k}``) — the weights
            after the last measurement update (the initial weights before the
            first); ``"previous"`` — the weights of the previous step.
        cadence, quadrature, chunk_size, compile: :class:`WeightUpdate`, :class:`QuadratureUpdate`.

    Diagnostics: ``fpke_error_before``, ``fpke_error_after`` (unscaled ``wᵀLw``
    with the propagated and the new weights, ``[...]``), ``qp_kkt_residual [...]`` (of the problem solved; in
    a managed mixture the one bounded below, :func:`~.base.solve_weight_qp`), ``qp_iterations`` (int).
    """

    reg: float | Tensor = field(
        default=1.0, metadata=option("λ of the paper's weight QP (AGSF), ≥ 0; the paper: 1", config="float")
    )
    scaling: str = field(
        default="trace",
        metadata=option(
            "scaling of the FPKE matrix in the weight QP (AGSF): 'trace' or 'none' (the paper's L + λI)", config="str"
        ),
    )
    weight_ref: str = field(
        default="update",
        metadata=option(
            "reference weights of the weight QP (AGSF): 'update' (the paper's w_k|k) or 'previous'", config="str"
        ),
    )

    name: ClassVar[str] = "penalty"
    factors: ClassVar[int] = 2
    DIAGNOSTICS: ClassVar[tuple[str, ...]] = (
        "fpke_error_before",
        "fpke_error_after",
        "qp_kkt_residual",
        "qp_iterations",
    )
    extra_state_keys: ClassVar[tuple[str, ...]] = ("ref_log_weights",)

    def __post_init__(self) -> None:
        super().__post_init__()
        reg = self.reg
        value = (
            float(reg)
            if isinstance(reg, (int, float)) and not isinstance(reg, bool)
            else float(reg.detach())
            if torch.is_tensor(reg) and reg.numel() == 1 and reg.is_floating_point()
            else None
        )
        if value is None or not (value >= 0 and value != float("inf")):
            raise ValueError(f"reg must be a finite number ≥ 0, got {reg!r}")
        if not torch.is_tensor(reg):
            object.__setattr__(self, "reg", value)
        if self.scaling not in _SCALINGS:
            raise ValueError(f"scaling must be one of {_SCALINGS}, got {self.scaling!r}")
        if self.weight_ref not in _REFERENCES:
            raise ValueError(f"weight_ref must be one of {_REFERENCES}, got {self.weight_ref!r}")

    def observe_update(self, log_weights: Tensor) -> None:
        super().observe_update(log_weights)
        self.run.reference = log_weights

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "ref_log_weights": self.run.reference}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        step, elapsed = self._parse_counter(state)
        ref = state["ref_log_weights"]
        floating = torch.is_tensor(ref) and ref.is_floating_point() and ref.dim() >= 1
        if ref is not None and (not floating or bool((torch.isnan(ref) | torch.isposinf(ref)).any())):
            got = f"a {ref.dtype} tensor" if torch.is_tensor(ref) else type(ref).__name__
            raise ValueError(
                f"weight-update state 'ref_log_weights' must be None or a floating-point tensor [..., N] "
                f"without NaN or +inf, got {got}"
            )
        self.run.step, self.run.elapsed, self.run.reference = step, elapsed, ref

    def compute(
        self,
        model: ContinuousModel,
        prior: GaussianMixture,
        propagated: GaussianMixture,
        u: Tensor | None,
        elapsed: float,
    ) -> tuple[Tensor, dict[str, Any]]:
        means = propagated.means
        ref = self.run.reference
        if ref is not None and ref.shape != propagated.log_weights.shape:
            raise ValueError(
                f"reference weights {tuple(ref.shape)} are from a run with another batch shape than the "
                f"mixture's {tuple(propagated.log_weights.shape)}; call reset() before a new run"
            )
        Lmat = None
        if self.quadrature is None and self.rule["fused"]:  # the model's exact rule: rates and pairs on lanes
            Lmat = fused_fpke_matrix(model, u, propagated.means, propagated.covs, self.rule["compile"])
        if Lmat is None:
            comp = component_rates(model, propagated, u).with_precision()  # Πᵢ formed once, for L and its floor
            Lmat = fpke_matrix(
                model, u, comp, self.rule["nodes"], self.rule["weights"], self.chunk_size, compile=self.rule["compile"]
            )
            Lmat = without_rounding_rows(Lmat, comp, model)
        bad = ~torch.isfinite(Lmat.scaled).flatten(-2).all(-1) | ~torch.isfinite(Lmat.log_scale)
        if bool(bad.any()):
            idx = bad.nonzero()[0].tolist()
            raise ValueError(f"FPKE matrix L is not finite at trajectory index {tuple(idx)}")
        N = propagated.num_components
        w_prop = propagated.weights
        if self.weight_ref == "update" and ref is not None:
            w_ref = ref.exp()
        elif self.weight_ref == "update":
            w_ref = prior.weights  # no update yet: the initial weights
        else:
            w_ref = w_prop
        eye = torch.eye(N, dtype=means.dtype, device=means.device)
        active = torch.isfinite(propagated.log_weights)
        if self.scaling == "trace":  # the mean diagonal entry over the active components
            tr = (Lmat.scaled.diagonal(dim1=-2, dim2=-1) * active).sum(-1)
            tiny = torch.finfo(means.dtype).tiny
            Ls = Lmat.scaled / (tr / active.sum(-1)).clamp_min(tiny)[..., None, None]
        else:
            Ls = Lmat.full()
            if not bool(torch.isfinite(Ls).all()):
                idx = (~torch.isfinite(Ls)).flatten(-2).any(-1).nonzero()[0].tolist()
                raise ValueError(
                    f"unscaled FPKE matrix overflows at trajectory index {tuple(idx)}; use scaling='trace'"
                )
        w_new, res = solve_weight_qp(self.run, Ls + self.reg * eye, -self.reg * w_ref, propagated.log_weights)
        log_w = torch.log(w_new)
        log_w = log_w - torch.logsumexp(log_w, -1, keepdim=True)  # normalised to rounding in the log domain
        extra = {
            "fpke_error_before": Lmat.error(w_prop),
            "fpke_error_after": Lmat.error(w_new),
            "qp_kkt_residual": res.kkt_residual,
            "qp_iterations": res.iterations,
        }
        if ref is None:  # nothing can fail from here on: commit the reference
            self.run.reference = prior.log_weights
        return log_w, extra
