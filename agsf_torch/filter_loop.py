"""The filter loop: one generator over time steps that every consumer drives.

Each step gives every filter the same :class:`StepInput` — the interval ``dt``,
the input ``u``, an optional correction of the prediction (e.g. the covariance
inflation of a held gyro sample) and an optional measurement — and runs::

    mixture = filt.predict(mixture, u, dt)
    mixture = correct(mixture)                       # if the input has one
    mixture = filt.update(mixture, y, measurement)   # if it has a measurement

The Monte Carlo runner, the soak, the adaptation study, learning (through the
filter's likelihood) and the sine benchmark all consume :func:`filter_steps`;
what is specific to a sensor (for attitude: gyro gaps, the known bias, star
measurements from observations) is an adapter that turns its data into
:class:`StepInput` (:mod:`agsf_torch.attitude.inputs`).  This module knows no
sensor and no simulator.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import torch
from torch import Tensor

from .filters.base import Filter
from .filters.management import MANAGEMENT_DIAGNOSTICS
from .mixture import GaussianMixture

__all__ = [
    "FilterSetup",
    "StepInput",
    "FilterStep",
    "LoopStep",
    "filter_steps",
    "initial_mixtures",
    "sample_prior",
    "PRIOR_SEED_OFFSET",
]

#: Offset of the prior draw's generator seed from the run seed (the simulator uses the run seed itself).
PRIOR_SEED_OFFSET = 7919


@dataclass(frozen=True)
class FilterSetup:
    """A filter in a run and its initial mixture size.

    Attributes:
        filter: any :class:`~agsf_torch.filters.base.Filter`.
        num_components: components of the initial split of the prior.
        spread: share of the principal prior variance carried by the component means.
    """

    filter: Filter
    num_components: int = 1
    spread: float = 0.5


@dataclass(frozen=True)
class StepInput:
    """What every filter is given over one interval.

    Attributes:
        dt: the interval (s), > 0.
        u: the input over the interval ``[B, m]`` or ``None``.
        measurement: ``(y [B, d], MeasurementModel)`` at the end of the interval, or ``None``.
        correct: ``correct(mixture) -> mixture`` applied after the prediction, or ``None``
            (e.g. :meth:`agsf_torch.attitude.gyro_hold.GyroHold.inflate` for held inputs).
        extra: per-step values ``[B]`` copied into every filter's diagnostics.
        context: anything the source wants back with the step (e.g. the truth); the loop ignores it.
    """

    dt: float
    u: Tensor | None = None
    measurement: tuple[Tensor, Any] | None = None
    correct: Callable[[GaussianMixture], GaussianMixture] | None = None
    extra: Mapping[str, Tensor] = field(default_factory=dict)
    context: Any = None


class FilterStep:
    """One filter after one step: its belief and what the step produced.

    Attributes:
        mixture: the belief at the end of the step.
        nis: mixture NIS of the measurement (moment-matched innovation), NaN without one, ``[B]``.
        dof: valid measurement entries ``[B]`` (0 without a measurement).
        log_likelihood: ``log Σᵢ wᵢβᵢ`` of the measurement ``[B]``, ``None`` without one
            (differentiable in the model's parameters).
        extra: per-step diagnostics ``[B]``: the filter's own (predict and update), the
            input's (:attr:`StepInput.extra`) and ``gate_rejected`` (0 without gating).
        mean, cov: the point estimate and covariance (``filter.estimate``), ``[B, n]``,
            ``[B, n, n]``, computed when first read.
    """

    def __init__(
        self,
        filt: Filter,
        mixture: GaussianMixture,
        nis: Tensor,
        dof: Tensor,
        log_likelihood: Tensor | None,
        extra: dict[str, Tensor],
    ) -> None:
        self.filter = filt
        self.mixture = mixture
        self.nis = nis
        self.dof = dof
        self.log_likelihood = log_likelihood
        self.extra = extra

    @cached_property
    def _estimate(self) -> tuple[Tensor, Tensor]:
        return self.filter.estimate(self.mixture)

    @property
    def mean(self) -> Tensor:
        return self._estimate[0]

    @property
    def cov(self) -> Tensor:
        return self._estimate[1]


@dataclass(frozen=True)
class LoopStep:
    """One step of :func:`filter_steps`: its ``index``, the ``input`` and name → :class:`FilterStep`."""

    index: int
    input: StepInput
    filters: dict[str, FilterStep]


def sample_prior(truth: Tensor, cov: Tensor, gen: torch.Generator) -> Tensor:
    """Prior means drawn consistently with the prior covariance: ``x̂₀ = x + L z``, ``z ~ N(0, I)``.

    Args:
        truth: ``[B, n]``; cov: ``[n, n]`` (Cholesky factor ``L``); gen: the run's generator
            (by convention seeded with ``seed +`` :data:`PRIOR_SEED_OFFSET`).
    """
    L = torch.linalg.cholesky(cov)
    z = torch.randn(truth.shape, generator=gen, dtype=truth.dtype, device=truth.device)
    return truth + z @ L.T


def initial_mixtures(setups: Mapping[str, FilterSetup], mean: Tensor, cov: Tensor) -> dict[str, GaussianMixture]:
    """Each filter's initial belief: ``N(mean, cov)`` split into its ``num_components``, in its model's chart.

    Args:
        setups: name → :class:`FilterSetup`.
        mean: ``[B, n]``; cov: ``[n, n]`` or ``[B, n, n]``.
    """
    B, n = mean.shape
    out = {}
    for name, setup in setups.items():
        mix = GaussianMixture.from_gaussian(mean, cov.expand(B, n, n), setup.num_components, setup.spread)
        m, P = setup.filter.model.canonicalize(mix.means, mix.covs)
        out[name] = mix.replace(means=m, covs=P)
    return out


def _add_update_counts(extra: dict[str, Tensor], update: Mapping[str, Tensor]) -> None:
    """A managed filter's step diagnostics over its predict and its update: into ``extra`` (the step's, holding the
    predict's) the update's ``splits``, ``merges`` and ``prunes`` are added (each ``[B]`` int64, counts) and its
    ``active_components`` replaces the predict's (the count at the step's end); ``update`` is the filter's
    ``diagnostics`` after the update (:data:`~agsf_torch.filters.management.MANAGEMENT_DIAGNOSTICS`).  Nothing for a
    filter without management."""
    if "active_components" not in update or "active_components" not in extra:
        return
    for key in MANAGEMENT_DIAGNOSTICS:
        extra[key] = update[key] if key == "active_components" else extra[key] + update[key]


def filter_steps(
    filters: Mapping[str, Filter], mixtures: Mapping[str, GaussianMixture], inputs: Iterable[StepInput]
) -> Iterator[LoopStep]:
    """Run every filter over ``inputs``, yielding one :class:`LoopStep` per input.

    Args:
        filters: name → filter (:class:`~agsf_torch.filters.base.Filter`).
        mixtures: name → initial belief.
        inputs: the steps' inputs; may be a generator that reads the previous
            step's estimates (closed loop: an environment that takes the estimate as action).
    """
    beliefs = dict(mixtures)
    steps = iter(inputs)
    first = next(steps, None)
    if first is None:
        return
    for index, inp in enumerate(itertools.chain([first], steps)):
        out: dict[str, FilterStep] = {}
        for name, filt in filters.items():
            mix = filt.predict(beliefs[name], inp.u, inp.dt)
            extra = {k: v for k, v in filt.diagnostics.items() if torch.is_tensor(v) and k != "weight_entropy"}
            if inp.correct is not None:
                mix = inp.correct(mix)
            extra.update(inp.extra)
            B, like = mix.batch_shape, mix.means
            extra["gate_rejected"] = torch.zeros(B, dtype=torch.int64, device=like.device)
            nis = torch.full(B, float("nan"), dtype=like.dtype, device=like.device)
            dof = torch.zeros(B, dtype=like.dtype, device=like.device)
            log_likelihood = None
            if inp.measurement is not None:
                mix = filt.update(mix, *inp.measurement)
                diag = filt.diagnostics
                dof = diag["dof"]
                nis = torch.where(dof > 0, diag["nis_mixture"], nis)
                log_likelihood = diag["log_likelihood"]
                if "gate_rejected" in diag:
                    extra["gate_rejected"] = diag["gate_rejected"]
                _add_update_counts(extra, diag)
            beliefs[name] = mix
            out[name] = FilterStep(filt, mix, nis, dof, log_likelihood, extra)
        yield LoopStep(index, inp, out)
