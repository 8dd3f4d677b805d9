"""Adaptive Gaussian sum filter: weights corrected during propagation (method.md §3).

After each propagation step the weights solve

.. math:: w^* = \\arg\\min_{w ∈ Δ} ½ w^T L w + \\frac{λ}{2} \\|w - w_{ref}\\|^2,

``L_ij = ∫ Lᵢ Lⱼ dx`` the Fokker–Planck error matrix of the propagated
components (:mod:`agsf_torch.fpke`), ``Δ`` the probability simplex.  In the
form handed to the QP solver: Hessian ``L + λI``, linear term ``−λ w_ref``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..fpke import ComponentRates, fpke_matrix
from ..mixture import GaussianMixture
from ..models.base import ContinuousModel
from ..propagation import moment_derivatives
from ..qp import solve_simplex_qp
from ..quadrature import gauss_hermite, smolyak_gauss_hermite
from .gaussian_sum import GaussianSumFilter

__all__ = ["AdaptiveGaussianSumFilter"]

_SCALINGS = ("trace", "none")
_REFERENCES = ("update", "previous")


class AdaptiveGaussianSumFilter(GaussianSumFilter):
    """Gaussian sum filter whose weights minimise the FPKE error between updates.

    Args:
        model: the continuous-time model.
        reg: λ ≥ 0, weight of ``½‖w − w_ref‖²`` (the paper: 1).
        scaling: ``"trace"`` (default) solves with ``L / (tr L / N)`` so that λ is
            dimensionless — with star-camera covariances the raw ``L`` is
            astronomically large and the penalty would vanish; ``"none"`` uses
            the raw ``L`` (the paper's ``L + I``).
        weight_ref: ``"update"`` (default, the paper's ``w_{k|k}``) — the weights
            after the last measurement update (the initial weights before the
            first); ``"previous"`` — the weights of the previous step.
        cadence: adapt the weights every ``cadence``-th ``predict`` call (1: every step).
        adapt: ``False`` switches the weight update off (the filter is then the GSF).
        quadrature: rule for ``E[ℓᵢℓⱼ]`` under each product Gaussian: ``None``
            (the model's exact rule if it has one, else 7 Gauss–Hermite points
            per axis for ``n ≤ 4`` and a level-7 Smolyak grid above), an int
            (points per axis), a tuple (points per axis), or ``(nodes, weights)``.
        chunk_size: quadrature nodes per batched evaluation (``None``: sized
            automatically to bound memory, see :func:`agsf_torch.fpke.fpke_matrix`).
        compile: evaluate the quadrature with a ``torch.compile``-d kernel
            (several times faster for long runs; ~20 s compilation per shape).
        **kwargs: passed to :class:`GaussianSumFilter`.

    Diagnostics after ``predict`` (besides the GSF's): ``fpke_error_before``,
    ``fpke_error_after`` (unscaled ``wᵀLw`` with the propagated and the new
    weights, ``[...]``), ``qp_kkt_residual [...]``, ``qp_iterations`` (int),
    ``weights_adapted`` (bool).
    """

    def __init__(
        self,
        model: ContinuousModel,
        reg: float = 1.0,
        scaling: str = "trace",
        weight_ref: str = "update",
        *,
        cadence: int = 1,
        adapt: bool = True,
        quadrature: Any = None,
        chunk_size: int | None = None,
        compile: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(model, **kwargs)
        reg_value = float(reg) if isinstance(reg, (int, float)) else float(reg.detach()) if torch.is_tensor(reg) and reg.numel() == 1 else None
        if reg_value is None or not (reg_value >= 0 and reg_value != float("inf")):
            raise ValueError(f"reg must be a finite number ≥ 0, got {reg}")
        if scaling not in _SCALINGS:
            raise ValueError(f"scaling must be one of {_SCALINGS}, got {scaling!r}")
        if weight_ref not in _REFERENCES:
            raise ValueError(f"weight_ref must be one of {_REFERENCES}, got {weight_ref!r}")
        if int(cadence) != cadence or cadence < 1:
            raise ValueError(f"cadence must be a positive integer, got {cadence}")
        self.reg = reg if torch.is_tensor(reg) else float(reg)  # a tensor λ keeps its gradient
        self.scaling = scaling
        self.weight_ref = weight_ref
        self.cadence = int(cadence)
        self.adapt = bool(adapt)
        self.chunk_size = None if chunk_size is None else int(chunk_size)
        self.compile = bool(compile)
        self.nodes, self.node_weights = self._make_rule(quadrature, model.state_dim)
        self._step = 0

    def _make_rule(self, quadrature: Any, n: int) -> tuple[Tensor, Tensor]:
        if quadrature is None:
            pts = self.model.fpke_quadrature_points()
            if pts is not None:
                return gauss_hermite(tuple(pts))
            return gauss_hermite(7, n) if n <= 4 else smolyak_gauss_hermite(n, 7)
        if isinstance(quadrature, int):
            return gauss_hermite(quadrature, n)
        if isinstance(quadrature, tuple) and all(isinstance(q, int) for q in quadrature):
            if len(quadrature) != n:
                raise ValueError(f"quadrature needs one point count per state axis ({n}), got {quadrature}")
            return gauss_hermite(quadrature)
        nodes, weights = quadrature
        nodes, weights = torch.as_tensor(nodes, dtype=torch.float64), torch.as_tensor(weights, dtype=torch.float64)
        if nodes.dim() != 2 or nodes.shape[1] != n or weights.shape != nodes.shape[:1]:
            raise ValueError(f"quadrature (nodes [K, {n}], weights [K]) has shapes {tuple(nodes.shape)}, {tuple(weights.shape)}")
        return nodes, weights

    def reset(self) -> None:
        """Restart the cadence counter (call at the start of a new run)."""
        self._step = 0

    def _adapt_weights(
        self, prior: GaussianMixture, propagated: GaussianMixture, u: Tensor | None, dt: float
    ) -> tuple[GaussianMixture, dict[str, Any]]:
        self._step += 1
        if not self.adapt or self._step % self.cadence != 0 or propagated.num_components == 1:
            return propagated, {"weights_adapted": False}
        means, covs = propagated.means, propagated.covs
        rates = moment_derivatives(self.model, means, covs, u)
        chol = torch.linalg.cholesky(covs)  # positive definiteness was ensured by predict
        comp = ComponentRates(means, chol, rates.mean_rate, rates.cov_rate)
        u_traj = None if u is None else u.squeeze(-2)
        Lmat = fpke_matrix(self.model, u_traj, comp, self.nodes, self.node_weights, self.chunk_size, compile=self.compile)
        bad = ~torch.isfinite(Lmat.scaled).flatten(-2).all(-1) | ~torch.isfinite(Lmat.log_scale)
        if bool(bad.any()):
            idx = bad.nonzero()[0].tolist()
            raise ValueError(f"FPKE matrix L is not finite at trajectory index {tuple(idx)}")
        N = propagated.num_components
        w_prop = propagated.weights
        if self.weight_ref == "update" and propagated.ref_log_weights is not None:
            w_ref = propagated.ref_log_weights.exp()
        elif self.weight_ref == "update":
            w_ref = prior.weights  # no update yet: the initial weights
        else:
            w_ref = w_prop
        eye = torch.eye(N, dtype=means.dtype, device=means.device)
        if self.scaling == "trace":
            tr = Lmat.scaled.diagonal(dim1=-2, dim2=-1).sum(-1)
            tiny = torch.finfo(means.dtype).tiny
            Ls = Lmat.scaled / (tr / N).clamp_min(tiny)[..., None, None]
        else:
            Ls = Lmat.full()
            if not bool(torch.isfinite(Ls).all()):
                idx = (~torch.isfinite(Ls)).flatten(-2).any(-1).nonzero()[0].tolist()
                raise ValueError(f"unscaled FPKE matrix overflows at trajectory index {tuple(idx)}; use scaling='trace'")
        res = solve_simplex_qp(Ls + self.reg * eye, -self.reg * w_ref)
        w_new = res.w.clamp_min(0.0)
        w_new = w_new / w_new.sum(-1, keepdim=True)
        adapted = propagated.replace(log_weights=torch.log(w_new))
        if propagated.ref_log_weights is None:
            adapted = adapted.replace(ref_log_weights=prior.log_weights)
        extra = {
            "fpke_error_before": Lmat.error(w_prop),
            "fpke_error_after": Lmat.error(w_new),
            "qp_kkt_residual": res.kkt_residual,
            "qp_iterations": res.iterations,
            "weights_adapted": True,
        }
        return adapted, extra
