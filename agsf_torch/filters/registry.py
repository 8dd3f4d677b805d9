"""The filter registry: one place that maps a filter's name to how it is built.

The CLI's choices, configuration validation, learning and the benchmark all read
:data:`FILTERS`; a new filter is one entry here::

    from agsf_torch.filters.registry import make_filter
    filt = make_filter("AGSF-galerkin", model, update_iterations=3, cadence=2)

Options are declared once, as fields of frozen dataclasses: :class:`~agsf_torch.filters.options.FilterOptions`
(every filter) and each weight update's own
(:class:`~agsf_torch.filters.weight_updates.PenaltyWeightUpdate`,
:class:`~agsf_torch.filters.weight_updates.GalerkinWeightUpdate`).  :func:`make_filter` takes
any of them by name and gives each filter the ones it has, so one configuration builds
every filter; :data:`CONFIG_OPTIONS` lists those a configuration file can set.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..models.base import ContinuousModel
from .adaptive import AdaptiveGaussianSumFilter
from .base import BaseFilter, Filter
from .gaussian_sum import ExtendedKalmanFilter, GaussianSumFilter
from .management import MixtureManagement
from .multiplicative import MultiplicativeEKF
from .options import ConfigOption, FilterOptions, config_options
from .particle import ParticleFilter, ParticleOptions
from .unscented_quaternion import USQUE
from .weight_updates import GalerkinWeightUpdate, PenaltyWeightUpdate, WeightUpdate

__all__ = [
    "FilterSpec",
    "FILTERS",
    "FILTER_NAMES",
    "ADAPTIVE_FILTERS",
    "OPTION_CLASSES",
    "CONFIG_OPTIONS",
    "make_filter",
    "filter_spec",
]


@dataclass(frozen=True)
class FilterSpec:
    """A registered filter.

    Attributes:
        name: the name users write (CLI, configuration files, learning).
        description: one line for help texts.
        cls: the filter class (built as ``cls(model, **FilterOptions…)``).
        mixture: ``True`` if it carries ``components`` components, ``False`` for one.
        weight_update: the weight update class of an adaptive filter (built from its own
            options and passed as ``weight_update=``), or ``None``.
        fixed: constructor arguments of ``cls`` this entry fixes (``MEKF-fix``: ``start="star_fix"``).
        options: a dataclass declaring options of ``cls`` beyond :class:`FilterOptions` (the particle filter's
            :class:`~agsf_torch.filters.particle.ParticleOptions`), or ``None``.
        managed: the entry manages its mixture: built with ``management=MixtureManagement(...)`` from the
            :class:`~agsf_torch.filters.management.MixtureManagement` options.
    """

    name: str
    description: str
    cls: type[BaseFilter]
    mixture: bool
    weight_update: type[WeightUpdate] | None = None
    fixed: Mapping[str, Any] = field(default_factory=dict)
    options: type | None = None
    managed: bool = False

    @property
    def adaptive(self) -> bool:
        """Whether the filter adapts its weights during propagation."""
        return self.weight_update is not None

    @property
    def option_names(self) -> frozenset[str]:
        """The options this filter reads: every :class:`FilterOptions` field and its weight update's."""
        classes = (FilterOptions,) + tuple(
            c for c in (self.weight_update, self.options, MixtureManagement if self.managed else None) if c is not None
        )
        return frozenset(f.name for cls in classes for f in dataclasses.fields(cls) if f.init)

    def build(self, model: ContinuousModel, **options: Any) -> Filter:
        """The filter on ``model`` with the ``options`` its classes declare (others are ignored)."""
        kwargs = _own(FilterOptions, options)
        FilterOptions(**kwargs)  # validated here, whatever the filter does with them
        if self.weight_update is not None:
            kwargs["weight_update"] = self.weight_update(**_own(self.weight_update, options))
        if self.options is not None:
            kwargs.update(dataclasses.asdict(self.options(**_own(self.options, options))))
        if self.managed:
            kwargs["management"] = MixtureManagement(**_own(MixtureManagement, options))
        return self.cls(model, **kwargs, **self.fixed)


def _own(cls: type, options: dict[str, Any]) -> dict[str, Any]:
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    return {k: v for k, v in options.items() if k in names}


FILTERS: dict[str, FilterSpec] = {
    spec.name: spec
    for spec in (
        FilterSpec("EKF", "extended Kalman filter (one component)", ExtendedKalmanFilter, False),
        FilterSpec("GSF", "Gaussian sum filter, weights fixed between measurements", GaussianSumFilter, True),
        FilterSpec(
            "AGSF",
            "adaptive GSF, the paper's weight QP (method.md §3)",
            AdaptiveGaussianSumFilter,
            True,
            PenaltyWeightUpdate,
        ),
        FilterSpec(
            "AGSF-galerkin",
            "adaptive GSF, the authors' later Galerkin update (method.md §3b)",
            AdaptiveGaussianSumFilter,
            True,
            GalerkinWeightUpdate,
        ),
        FilterSpec(
            "GSF-managed",
            "GSF whose mixture splits, merges and prunes (filters.management)",
            GaussianSumFilter,
            True,
            managed=True,
        ),
        FilterSpec(
            "AGSF-managed",
            "adaptive GSF (the paper's weight QP) whose mixture splits, merges and prunes",
            AdaptiveGaussianSumFilter,
            True,
            PenaltyWeightUpdate,
            managed=True,
        ),
        FilterSpec(
            "AGSF-galerkin-managed",
            "adaptive GSF (the Galerkin update) whose mixture splits, merges and prunes",
            AdaptiveGaussianSumFilter,
            True,
            GalerkinWeightUpdate,
            managed=True,
        ),
        FilterSpec("MEKF", "multiplicative EKF (one component), the industry baseline", MultiplicativeEKF, False),
        FilterSpec(
            "MEKF-fix",
            "multiplicative EKF started from the first frame with two stars by a star fix, as flight software does",
            MultiplicativeEKF,
            False,
            fixed={"start": "star_fix"},
        ),
        FilterSpec("USQUE", "unscented quaternion estimator (one component; Crassidis & Markley 2003)", USQUE, False),
        FilterSpec(
            "PF",
            "regularised particle filter (Musso, Oudjane & Le Gland 2001), particles as the mixture's components",
            ParticleFilter,
            False,
            options=ParticleOptions,
        ),
    )
}
#: Every registered name, in registry order.
FILTER_NAMES: tuple[str, ...] = tuple(FILTERS)
#: The names of the filters that adapt their weights during propagation.
ADAPTIVE_FILTERS: tuple[str, ...] = tuple(n for n, s in FILTERS.items() if s.adaptive)
#: The dataclasses that declare the registered filters' options.
OPTION_CLASSES: tuple[type, ...] = (FilterOptions,) + tuple(
    dict.fromkeys(
        c
        for s in FILTERS.values()
        for c in (s.weight_update, s.options, MixtureManagement if s.managed else None)
        if c is not None
    )
)
#: The options a configuration file can set, by name (:func:`~agsf_torch.filters.options.config_options`).
CONFIG_OPTIONS: dict[str, ConfigOption] = config_options(*OPTION_CLASSES)
_OPTION_NAMES = tuple(dict.fromkeys(f.name for cls in OPTION_CLASSES for f in dataclasses.fields(cls) if f.init))


def filter_spec(name: str) -> FilterSpec:
    """The registry entry of ``name``; ``ValueError`` naming the known filters otherwise."""
    if name not in FILTERS:
        raise ValueError(f"unknown filter {name!r}; known: {', '.join(FILTER_NAMES)}")
    return FILTERS[name]


def make_filter(name: str, model: ContinuousModel, **options: Any) -> Filter:
    """Build the registered filter ``name`` on ``model``.

    Args:
        name: one of :data:`FILTER_NAMES`.
        model: the continuous-time model.
        **options: fields of :data:`OPTION_CLASSES` (a filter takes the ones its classes declare;
            names no class declares are an error).
    """
    spec = filter_spec(name)
    unknown = sorted(set(options) - set(_OPTION_NAMES))
    if unknown:
        raise ValueError(f"unknown filter option(s) {unknown}; known: {', '.join(_OPTION_NAMES)}")
    return spec.build(model, **options)
