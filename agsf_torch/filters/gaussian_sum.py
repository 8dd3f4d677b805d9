"""Classic Gaussian sum filter and the EKF as its one-component case (method.md §2)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..mixture import GaussianMixture
from ..models.base import ContinuousModel, MeasurementModel
from ..propagation import propagate_moments
from .base import BaseFilter
from .management import (
    MANAGEMENT_DIAGNOSTICS,
    MixtureManagement,
    active_slots,
    entropy_nonlinearity,
    gather_slots,
    measurement_nonlinearity,
    pad_mixture,
)

__all__ = ["GaussianSumFilter", "ExtendedKalmanFilter"]


class GaussianSumFilter(BaseFilter):
    """Gaussian sum filter: every component is an EKF, weights change only at updates.

    All trajectories (leading dims) and components advance as one tensor program
    (the contract of :class:`~agsf_torch.filters.base.Filter`)::

        mixture = filt.predict(mixture, u, dt)          # propagate over one input interval
        mixture = filt.update(mixture, y, measurement)  # Bayes update with one measurement
        mean, cov = filt.estimate(mixture)

    After each call ``filt.diagnostics`` holds that step's diagnostics as a dict
    of tensors (computed during the step, never recomputed; a
    :class:`~agsf_torch.filters.step_diagnostics.StepDiagnostics`, which prints one
    summary line per key):

    * predict: ``weight_entropy [...]``, ``covariance_repairs`` (int, this call);
    * update: ``log_likelihood [...]`` (``log Σ wᵢβᵢ``), ``nis [..., N]``,
      ``nis_mixture [...]`` (moment-matched innovation of the mixture), ``dof [...]``
      (valid measurement entries), ``weight_entropy [...]``, ``covariance_repairs``;
      with gating also ``gate_rejected [...]`` (blocks rejected by this update, int64),
      ``gate_nis [..., G]`` (each block's mixture NIS), ``gate_accepted [..., G]`` and
      ``gate_overridden [...]`` (failing blocks kept by the consistency rule).

    Propagation integrates every component's moment equations with RK4 in the
    transition-matrix form (:func:`agsf_torch.propagation.propagate_moments`) and
    re-expresses it in the model's canonical chart.

    With ``management`` (:class:`~agsf_torch.filters.management.MixtureManagement`) the mixture has
    ``capacity`` slots (a smaller one is padded with inactive slots at the first step): before each
    propagation the components are pruned, merged and split where the propagation is nonlinear, before each
    update split where the measurement is; both steps then also report ``active_components``, ``splits``,
    ``merges`` and ``prunes`` (``[...]``, int64, this step's).

    Args:
        model: the continuous-time model.
        substeps: RK4 steps per ``predict`` interval.
        management: a :class:`~agsf_torch.filters.management.MixtureManagement`, or ``None`` (default: the
            components the mixture starts with, never split, merged or pruned).
        **options: ``update_iterations``, ``gate_probability``, ``repair_covariance``,
            ``min_eigenvalue`` (:class:`~agsf_torch.filters.base.BaseFilter`).
    """

    def __init__(
        self, model: ContinuousModel, *, substeps: int = 1, management: MixtureManagement | None = None, **options
    ) -> None:
        if management is not None and not isinstance(management, MixtureManagement):
            raise TypeError(f"management must be a MixtureManagement or None, got {type(management).__name__}")
        if management is not None and self.num_components == 1:
            raise ValueError(
                f"management (mixture management) needs a Gaussian sum; {type(self).__name__} has one component"
            )
        super().__init__(model, **options)
        if isinstance(substeps, bool) or int(substeps) != substeps or substeps < 1:
            raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
        self.substeps = int(substeps)
        self.management = management
        self.weight_map: Any = None  # the last management pass's action on the weights ([..., K, K])
        self._contract_checked: ContinuousModel | None = None  # the model check_contract passed for

    def checkpoint_options(self) -> dict[str, Any]:
        """The base filter's options, ``substeps`` and, when managed, ``management``
        (:meth:`BaseFilter.checkpoint_options`)."""
        options = {**super().checkpoint_options(), "substeps": self.substeps}
        if self.management is not None:
            options["management"] = self.management.as_dict()
        return options

    def check_mixture(self, mixture: GaussianMixture) -> None:
        """As the base filter's; with management, at most ``capacity`` components."""
        super().check_mixture(mixture)
        if self.management is not None and mixture.num_components > self.management.capacity:
            raise ValueError(
                f"management capacity {self.management.capacity} is below the mixture's {mixture.num_components} "
                f"components: raise capacity to at least {mixture.num_components}"
            )

    def diagnostic_keys(self, step: str) -> tuple[str, ...]:
        """The base filter's, and with management :data:`~agsf_torch.filters.management.MANAGEMENT_DIAGNOSTICS`."""
        keys = super().diagnostic_keys(step)
        return keys + MANAGEMENT_DIAGNOSTICS if self.management is not None else keys

    def _manage(
        self,
        mixture: GaussianMixture,
        step: str,
        *,
        u: Tensor | None = None,
        measurement: MeasurementModel | None = None,
    ) -> tuple[GaussianMixture, dict[str, Tensor]]:
        """The mixture padded to ``capacity``, pruned, merged and split (:meth:`MixtureManagement.apply`): by the
        entropy test before a propagation, by the measurement's curvature before an update."""
        mg = self.management
        if mg is None:
            return mixture, {}
        mixture = pad_mixture(mixture, mg.capacity)
        slots = active_slots(mixture.log_weights)  # the tests score the active components' slots only
        scored = mixture if slots is None else gather_slots(mixture, slots)
        score = axis = None
        threshold = 0.0
        if step == "predict" and mg.split_entropy_rate > 0:
            score, axis = entropy_nonlinearity(self.model, scored.means, scored.covs, u)
            threshold = mg.split_entropy_rate
        elif step == "update" and mg.split_measurement > 0 and measurement is not None:
            score, axis = measurement_nonlinearity(scored.means, scored.covs, measurement)
            threshold = mg.split_measurement
        if score is not None and slots is not None:  # back to their slots; an unscored (inactive) slot scores 0
            score = torch.zeros_like(mixture.log_weights).scatter(-1, slots, score)
            axis = torch.zeros_like(mixture.log_weights, dtype=axis.dtype).scatter(-1, slots, axis)
        result = mg.apply(mixture, self.model, score, axis, threshold, compile=self.compile_fused)
        self.weight_map = result.weight_map
        return result.mixture, result.counts

    def _computed_slots(self, mixture: GaussianMixture) -> Tensor | None:
        """With management, the slots the active components need (:func:`~agsf_torch.filters.management.active_slots`):
        a step computes only those, and the inactive slots, which carry no weight, are restored as copies of the
        heaviest component (:func:`~agsf_torch.filters.management.spread_slots`)."""
        return None if self.management is None else active_slots(mixture.log_weights)

    def _second_order_update(self) -> bool:
        """Management's ``second_order_update``: the update is then the generic second-order one
        (:func:`~agsf_torch.update.kalman_update`'s ``second_order``)."""
        return self.management is not None and self.management.second_order_update

    def _validate_predict(self, mixture: GaussianMixture, u: Any, dt: Any) -> tuple[Tensor | None, float]:
        """As the base class's, the model's shape contract at the first ``predict`` with it
        (``ContinuousModel.check_contract``) and its check of the interval (``ContinuousModel.check_step``)."""
        u, dt = super()._validate_predict(mixture, u, dt)
        if self._contract_checked is not self.model:
            self.model.check_contract(mixture.means, None if u is None else u.unsqueeze(-2))
            self._contract_checked = self.model
        self.model.check_step(mixture.means, u, dt)
        return u, dt

    def _propagate(self, mixture: GaussianMixture, u: Tensor | None, dt: float) -> tuple[GaussianMixture, int]:
        """The model's fused propagation if it has one and ``fused`` is on
        (``ContinuousModel.fused_propagation``), else :func:`~agsf_torch.propagation.propagate_moments`;
        then the canonical chart and the definiteness check."""
        u_c = None if u is None else u.unsqueeze(-2)  # broadcast over components
        fused = None
        if self.fused:
            fused = self.model.fused_propagation(
                mixture.means, mixture.covs, u_c, dt, self.substeps, compile=self.compile_fused
            )
        if fused is not None:
            means, covs, positive_definite = fused
        else:
            means, covs = propagate_moments(self.model, mixture.means, mixture.covs, u_c, dt, self.substeps)
            positive_definite = None
        means, covs, repairs = self._settle(means, covs, positive_definite, "during propagation")
        return mixture.replace(means=means, covs=covs, validate=False), repairs  # checked just above


class ExtendedKalmanFilter(GaussianSumFilter):
    """The extended Kalman filter: a Gaussian sum filter with one component.

    Build its belief with ``GaussianMixture.from_gaussian(mean, cov)``.
    """

    num_components = 1
