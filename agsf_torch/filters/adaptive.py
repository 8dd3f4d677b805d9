"""Adaptive Gaussian sum filter: weights corrected during propagation (method.md §3, §3b).

After each propagation interval a *weight update*
(:mod:`agsf_torch.filters.weight_updates`) replaces the forecast weights by ones
that reduce the Fokker–Planck residual of the mixture: the paper's penalised QP
(``"penalty"``, the default) or the authors' later Galerkin form (``"galerkin"``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from torch import Tensor

from ..mixture import GaussianMixture
from ..models.base import ContinuousModel
from ..qp import MAX_COMPONENTS
from .gaussian_sum import GaussianSumFilter
from .weight_updates import WEIGHT_UPDATES, WeightUpdate, make_weight_update

__all__ = ["AdaptiveGaussianSumFilter"]

#: Each weight-update option → the first registered update class that declares it (for error messages).
_WEIGHT_UPDATE_OPTIONS: dict[str, type[WeightUpdate]] = {}
for _cls in WEIGHT_UPDATES.values():
    for _f in dataclasses.fields(_cls):
        if _f.init:
            _WEIGHT_UPDATE_OPTIONS.setdefault(_f.name, _cls)


class AdaptiveGaussianSumFilter(GaussianSumFilter):
    """Gaussian sum filter whose weights minimise the FPKE residual between updates.

    Example::

        AdaptiveGaussianSumFilter(model)                                          # the paper's update, λ = 1
        AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(reg=0.1, cadence=2))
        AdaptiveGaussianSumFilter(model, weight_update="galerkin")                # the authors' later form

    Args:
        model: the continuous-time model.
        weight_update: ``"penalty"`` (default; the paper, method.md §3, with default options),
            ``"galerkin"`` (the authors' later form, §3b) or a
            :class:`~agsf_torch.filters.weight_updates.WeightUpdate` object carrying its options
            (:class:`~agsf_torch.filters.weight_updates.PenaltyWeightUpdate`: ``reg``, ``scaling``,
            ``weight_ref``; both: ``cadence``, ``quadrature``, ``chunk_size``, ``compile``).
        adapt: ``False`` switches the weight update off (the filter is then the GSF).
        **options: passed to :class:`GaussianSumFilter` (``substeps``, ``update_iterations``,
            ``gate_probability``, ``repair_covariance``, ``min_eigenvalue``).

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
        *,
        weight_update: str | WeightUpdate = "penalty",
        adapt: bool = True,
        **options: Any,
    ) -> None:
        misplaced = sorted(set(options) & _WEIGHT_UPDATE_OPTIONS.keys())
        if misplaced:
            name = misplaced[0]
            owner = weight_update if isinstance(weight_update, WeightUpdate) else _WEIGHT_UPDATE_OPTIONS[name]
            owner_name = type(owner).__name__ if isinstance(owner, WeightUpdate) else owner.__name__
            raise TypeError(
                f"{', '.join(misplaced)} configure{'s' if len(misplaced) == 1 else ''} the weight update, not the filter: "
                f"pass weight_update={owner_name}({name}=...)"
            )
        super().__init__(model, **options)
        if self.management is not None and self.management.capacity > MAX_COMPONENTS:
            raise ValueError(
                f"management capacity must be ≤ {MAX_COMPONENTS} for an adaptive filter (the weight QP's limit; the "
                f"GSF has none), got {self.management.capacity}"
            )
        update = make_weight_update(weight_update)
        update.check_free(self)  # before it is rebound to this filter's model
        update.bind(model, fused=self.fused, compile_fused=self.compile_fused)
        update.claim(self)
        self.weight_update = update
        self.adapt = bool(adapt)

    def diagnostic_keys(self, step: str) -> tuple[str, ...]:
        """As the GSF's; after ``predict`` also ``weights_adapted`` and, on steps that adapt, the weight
        update's own (``weight_update.diagnostic_keys``)."""
        keys = super().diagnostic_keys(step)
        return keys + ("weights_adapted",) + tuple(self.weight_update.diagnostic_keys) if step == "predict" else keys

    def check_mixture(self, mixture: GaussianMixture) -> None:
        """As the GSF's, and the weight update's own limits (e.g. ``N ≤ MAX_COMPONENTS``), before any work."""
        super().check_mixture(mixture)
        self.weight_update.claim(self)  # a copied or unpickled filter claims its update; a shallow copy is refused
        if self.adapt:
            self.weight_update.check(mixture)

    def _adapt_weights(
        self, prior: GaussianMixture, propagated: GaussianMixture, u: Tensor | None, dt: float
    ) -> tuple[GaussianMixture, dict[str, Any]]:
        weight_map = self.weight_map if self.management is not None else None
        log_weights, extra = self.weight_update(
            self.model, prior, propagated, u, dt, enabled=self.adapt, weight_map=weight_map
        )
        if log_weights is None:
            return propagated, extra
        return propagated.replace(log_weights=log_weights, validate=False), extra

    def _after_update(self, posterior: GaussianMixture) -> None:
        self.weight_update.observe_update(posterior.log_weights)

    # --------------------------------------------------------------- run state
    def reset(self) -> None:
        """Start a new run: the weight update forgets its counter and reference."""
        self.weight_update.reset()

    def state_dict(self) -> dict[str, Any]:
        """The run state: ``{"weight_update": …}`` (tensors and numbers only)."""
        return {"weight_update": self.weight_update.state_dict()}

    def checkpoint_options(self) -> dict[str, Any]:
        """The GSF's options, ``adapt`` and the weight update's (its kind and options:
        :meth:`~agsf_torch.filters.weight_updates.WeightUpdate.checkpoint_options`)."""
        return {**super().checkpoint_options(), "adapt": self.adapt, **self.weight_update.checkpoint_options()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (validated before anything changes)."""
        if not isinstance(state, dict) or set(state) != {"weight_update"}:
            got = sorted(state) if isinstance(state, dict) else state
            raise ValueError(f"adaptive filter state must be {{'weight_update': ...}}, got keys {got!r}")
        self.weight_update.load_state_dict(state["weight_update"])
