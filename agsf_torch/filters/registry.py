"""The filter registry: one place that maps a filter's name to how it is built.

The CLI's choices, configuration validation, learning and the benchmark all read
:data:`FILTERS`; a new filter is one entry here::

    from agsf_torch.filters.registry import make_filter
    filt = make_filter("AGSF-galerkin", model, update_iterations=3)

Options (:class:`FilterOptions`) are shared by all entries; each builder takes the
ones its filter has and ignores the rest, so one configuration builds every filter.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

from ..models.base import ContinuousModel
from .adaptive import AdaptiveGaussianSumFilter
from .gaussian_sum import ExtendedKalmanFilter, GaussianSumFilter
from .multiplicative import MultiplicativeEKF

__all__ = ["FilterOptions", "FilterSpec", "FILTERS", "FILTER_NAMES", "ADAPTIVE_FILTERS", "make_filter", "filter_spec"]


@dataclass(frozen=True)
class FilterOptions:
    """Options of the registered filters (each uses the ones it has).

    Attributes:
        update_iterations: linearisations per measurement update (all filters).
        gate_probability: innovation gate ``p`` or ``None`` (all filters).
        reg: λ of the paper's weight QP (``AGSF``); a float or a 0-d tensor (learning).
        scaling: ``"trace"`` or ``"none"``, scaling of the FPKE matrix (``AGSF``).
        weight_ref: ``"update"`` or ``"previous"``, reference weights of the QP (``AGSF``).
        compile: ``torch.compile`` the FPKE kernel (adaptive filters).
        cadence: adapt the weights every ``cadence``-th predict (adaptive filters).
    """

    update_iterations: int = 1
    gate_probability: float | None = None
    reg: Any = 1.0
    scaling: str = "trace"
    weight_ref: str = "update"
    compile: bool = False
    cadence: int = 1


@dataclass(frozen=True)
class FilterSpec:
    """A registered filter.

    Attributes:
        name: the name users write (CLI, configuration files, learning).
        description: one line for help texts.
        mixture: ``True`` if it carries ``components`` components, ``False`` for one.
        adaptive: ``True`` if it adapts the weights during propagation.
        build: ``build(model, options) -> filter``.
    """

    name: str
    description: str
    mixture: bool
    adaptive: bool
    build: Callable[[ContinuousModel, FilterOptions], GaussianSumFilter]


def _common(o: FilterOptions) -> dict[str, Any]:
    return {"update_iterations": o.update_iterations, "gate_probability": o.gate_probability}


FILTERS: dict[str, FilterSpec] = {
    spec.name: spec
    for spec in (
        FilterSpec("EKF", "extended Kalman filter (one component)", False, False,
                   lambda m, o: ExtendedKalmanFilter(m, **_common(o))),
        FilterSpec("GSF", "Gaussian sum filter, weights fixed between measurements", True, False,
                   lambda m, o: GaussianSumFilter(m, **_common(o))),
        FilterSpec("AGSF", "adaptive GSF, the paper's weight QP (method.md §3)", True, True,
                   lambda m, o: AdaptiveGaussianSumFilter(
                       m, reg=o.reg, scaling=o.scaling, weight_ref=o.weight_ref, compile=o.compile,
                       cadence=o.cadence, **_common(o))),
        FilterSpec("AGSF-galerkin", "adaptive GSF, the authors' later Galerkin update (method.md §3b)", True, True,
                   lambda m, o: AdaptiveGaussianSumFilter(
                       m, weight_update="galerkin", compile=o.compile, cadence=o.cadence, **_common(o))),
        FilterSpec("MEKF", "multiplicative EKF (one component), the industry baseline", False, False,
                   lambda m, o: MultiplicativeEKF(m, **_common(o))),
    )
}
#: Every registered name, in registry order.
FILTER_NAMES: tuple[str, ...] = tuple(FILTERS)
#: The names of the filters that adapt their weights during propagation.
ADAPTIVE_FILTERS: tuple[str, ...] = tuple(n for n, s in FILTERS.items() if s.adaptive)
_OPTION_NAMES = tuple(f.name for f in fields(FilterOptions))


def filter_spec(name: str) -> FilterSpec:
    """The registry entry of ``name``; ``ValueError`` naming the known filters otherwise."""
    if name not in FILTERS:
        raise ValueError(f"unknown filter {name!r}; known: {', '.join(FILTER_NAMES)}")
    return FILTERS[name]


def make_filter(name: str, model: ContinuousModel, **options: Any) -> GaussianSumFilter:
    """Build the registered filter ``name`` on ``model``.

    Args:
        name: one of :data:`FILTER_NAMES`.
        model: the continuous-time model.
        **options: fields of :class:`FilterOptions` (unknown keys are an error).
    """
    spec = filter_spec(name)
    unknown = sorted(set(options) - set(_OPTION_NAMES))
    if unknown:
        raise ValueError(f"unknown filter option(s) {unknown}; known: {', '.join(_OPTION_NAMES)}")
    return spec.build(model, FilterOptions(**options))
