"""Weight updates during propagation: the step that makes a Gaussian sum filter adaptive.

A weight update takes the mixture before and after one propagation interval and
returns corrected forecast weights.  Two are provided, both minimising the
Fokker–Planck (FPKE) residual of the mixture (method.md §3 and §3b):

* :class:`PenaltyWeightUpdate` — the paper's QP
  ``w* = argmin_{w∈Δ} ½wᵀLw + (λ/2)‖w − w_ref‖²``, ``L_ij = ∫LᵢLⱼ dx``;
* :class:`GalerkinWeightUpdate` — the authors' later form: the weights' rate of
  change cancels the residual in L²,
  ``w⁺ = argmin_{w∈Δ} ∫(Σᵢ(wᵢ − w⁻ᵢ)/Δt·pᵢ + Σⱼw⁻ⱼLⱼ)² dx = argmin ½wᵀMw + wᵀ(Δt·K − M)w⁻``.

A weight update is a frozen, keyword-only dataclass: its fields are its options
(validated when it is built, declared once — the registry, the experiment
configuration and the command line read them), e.g.
``AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(reg=0.1, cadence=2))``.
It also owns the run state it needs (the cadence counter, the penalty's
reference weights, in :class:`WeightUpdateRun`), so one object serves one filter, which
follows one run — one batch of trajectories — at a time: call ``reset()`` before starting
another; ``dataclasses.replace(update)`` gives a fresh object with the same options.
Write your own by subclassing :class:`WeightUpdate` and implementing
:meth:`WeightUpdate.compute`.
"""

from __future__ import annotations

from .base import QuadratureUpdate, WeightUpdate, WeightUpdateRun
from .galerkin import GalerkinWeightUpdate
from .penalty import PenaltyWeightUpdate

__all__ = [
    "WeightUpdate",
    "WeightUpdateRun",
    "QuadratureUpdate",
    "PenaltyWeightUpdate",
    "GalerkinWeightUpdate",
    "WEIGHT_UPDATES",
    "make_weight_update",
]


#: Names accepted by ``AdaptiveGaussianSumFilter(weight_update=...)``.
WEIGHT_UPDATES: dict[str, type[WeightUpdate]] = {"penalty": PenaltyWeightUpdate, "galerkin": GalerkinWeightUpdate}


def make_weight_update(spec: str | WeightUpdate) -> WeightUpdate:
    """A weight update from its name (``"penalty"``, ``"galerkin"``: default options) or the object itself.

    Raises:
        ValueError: an unknown name (listing the choices).
    """
    if isinstance(spec, WeightUpdate):
        return spec
    if not isinstance(spec, str) or spec not in WEIGHT_UPDATES:
        raise ValueError(f"weight_update must be one of {sorted(WEIGHT_UPDATES)} or a WeightUpdate, got {spec!r}")
    return WEIGHT_UPDATES[spec]()
