"""Adaptive Gaussian sum filter: weights corrected during propagation (method.md §3, §3b).

After each propagation interval a *weight update*
(:mod:`agsf_torch.filters.weight_updates`) replaces the forecast weights by ones
that reduce the Fokker–Planck residual of the mixture: the paper's penalised QP
(``"penalty"``, the default) or the authors' later Galerkin form (``"galerkin"``).
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

from ..mixture import GaussianMixture
from ..models.base import ContinuousModel
from .gaussian_sum import GaussianSumFilter
from .weight_updates import WeightUpdate, make_weight_update

__all__ = ["AdaptiveGaussianSumFilter"]

_UNSET: Any = object()
_PENALTY_ONLY = frozenset({"reg", "scaling", "weight_ref"})


class AdaptiveGaussianSumFilter(GaussianSumFilter):
    """Gaussian sum filter whose weights minimise the FPKE residual between updates.

    Args:
        model: the continuous-time model.
        reg, scaling, weight_ref: options of the paper's update
            (:class:`~agsf_torch.filters.weight_updates.PenaltyWeightUpdate`): λ ≥ 0
            (default 1), ``"trace"`` (default) or ``"none"``, ``"update"`` (default)
            or ``"previous"``.
        weight_update: ``"penalty"`` (default; the paper, method.md §3),
            ``"galerkin"`` (the authors' later form, §3b) or a
            :class:`~agsf_torch.filters.weight_updates.WeightUpdate` object (then
            configure it there, not here).
        cadence: adapt the weights every ``cadence``-th ``predict`` call (1: every step).
        adapt: ``False`` switches the weight update off (the filter is then the GSF).
        quadrature: how the residual integrals under each product Gaussian are computed.
            ``None`` (default) takes the fastest exact route the model offers: for the
            Galerkin ``K``, closed-form Gaussian moments (``fokker_planck_moments``;
            the attitude models have them), for the paper's ``L`` an interpolatory
            product rule on the polynomial space of ``ℓ`` (``fpke_polynomial_space``:
            840 nodes per pair for 6-state attitude instead of 9261); otherwise the
            model's exact Gauss–Hermite rule (``fpke_quadrature_points``), else 7
            points per axis for ``n ≤ 4`` and a level-7 Smolyak grid above.  Or an int (points per axis), a
            tuple (points per axis), or ``(nodes [K, n], weights [K])`` for ``N(0, I)``
            (finite, weights summing to 1), applied as ``x = m + chol(S) ξ`` with the
            lower Cholesky factor — e.g. :func:`agsf_torch.quadrature.six_n_plus_one`,
            the authors' own rule.
        chunk_size: quadrature nodes (or, with a product rule, component pairs) per
            batched evaluation, a positive integer (``None``: sized automatically to
            bound memory); zero, negative or fractional values are a ``ValueError``.
        compile: evaluate the node kernels with ``torch.compile`` (fused elementwise
            work; a one-off compilation of 10–20 s per shape, kept in the on-disk
            inductor cache); unused by the closed-form Galerkin path.
        **kwargs: passed to :class:`GaussianSumFilter`.

    The filter follows one run (one batch of trajectories) at a time: the weight
    update's state (cadence counter, reference weights) lives in the filter —
    :meth:`state_dict` / :meth:`load_state_dict` save and restore it, :meth:`reset`
    starts a new run.

    Diagnostics after ``predict`` (besides the GSF's): ``weights_adapted`` (bool)
    and, when adapted, the weight update's own (``weight_update.diagnostic_keys``):
    for ``"penalty"`` ``fpke_error_before``, ``fpke_error_after`` (unscaled ``wᵀLw``
    with the propagated and the new weights, ``[...]``), ``qp_kkt_residual [...]``,
    ``qp_iterations`` (int); for ``"galerkin"`` ``galerkin_residual_change``,
    ``qp_kkt_residual``, ``qp_iterations`` (and, with ``residual_diagnostics``,
    ``fpke_error_before`` and ``fpke_error_with_rate``).
    """

    def __init__(
        self,
        model: ContinuousModel,
        reg: float | Tensor = _UNSET,
        scaling: str = _UNSET,
        weight_ref: str = _UNSET,
        *,
        weight_update: str | WeightUpdate = "penalty",
        cadence: int = _UNSET,
        adapt: bool = True,
        quadrature: Any = _UNSET,
        chunk_size: int | None = _UNSET,
        compile: bool = _UNSET,
        **kwargs: Any,
    ) -> None:
        super().__init__(model, **kwargs)
        given = {
            k: v
            for k, v in {
                "reg": reg, "scaling": scaling, "weight_ref": weight_ref, "cadence": cadence,
                "quadrature": quadrature, "chunk_size": chunk_size, "compile": compile,
            }.items()
            if v is not _UNSET
        }
        if weight_update == "galerkin":
            penalty_only = sorted(set(given) & _PENALTY_ONLY)
            if penalty_only:
                raise ValueError(f"{', '.join(penalty_only)} configure(s) the penalty weight update, not weight_update='galerkin'")
        update = make_weight_update(weight_update, **given)
        update.bind(model)
        self.weight_update = update
        self.adapt = bool(adapt)

    def diagnostic_keys(self, step: str) -> tuple[str, ...]:
        """As the GSF's; after ``predict`` also ``weights_adapted`` and, on steps that adapt, the weight
        update's own (``weight_update.diagnostic_keys``)."""
        keys = super().diagnostic_keys(step)
        return keys + ("weights_adapted",) + tuple(self.weight_update.diagnostic_keys) if step == "predict" else keys

    def reset(self) -> None:
        """Start a new run: the weight update forgets its counter and reference."""
        self.weight_update.reset()

    def state_dict(self) -> dict[str, Any]:
        """The run state: ``{"weight_update": …}`` (tensors and numbers only)."""
        return {"weight_update": self.weight_update.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (validated before anything changes)."""
        if not isinstance(state, dict) or set(state) != {"weight_update"}:
            raise ValueError(f"adaptive filter state must be {{'weight_update': ...}}, got keys {sorted(state) if isinstance(state, dict) else state!r}")
        self.weight_update.load_state_dict(state["weight_update"])

    def _check_mixture(self, mixture: GaussianMixture) -> None:
        super()._check_mixture(mixture)
        if self.adapt:
            self.weight_update.check(mixture)  # e.g. N ≤ MAX_COMPONENTS, before any work

    def _after_update(self, posterior: GaussianMixture) -> None:
        self.weight_update.observe_update(posterior.log_weights)

    def _adapt_weights(
        self, prior: GaussianMixture, propagated: GaussianMixture, u: Tensor | None, dt: float
    ) -> tuple[GaussianMixture, dict[str, Any]]:
        log_weights, extra = self.weight_update(self.model, prior, propagated, u, dt, enabled=self.adapt)
        if log_weights is None:
            return propagated, extra
        return propagated.replace(log_weights=log_weights, validate=False), extra
