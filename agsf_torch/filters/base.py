"""The filter contract: one protocol, and one base class whose steps a filter overrides.

Every filter of the package — EKF, GSF, the adaptive GSF and the multiplicative EKF —
follows the same two steps, each a sequence of small methods (the decomposition of
Stone Soup's Kalman updater)::

    predict = validate → propagate → adapt weights (hook) → diagnostics
    update  = validate → frame → gate → Kalman step → posterior (weights, chart) → diagnostics

A filter overrides only its mathematics: :meth:`BaseFilter._propagate` (the moment
equations of the GSF, the error-state transition of the MEKF),
:meth:`BaseFilter._adapt_weights` (the adaptive filter's weight update),
:meth:`BaseFilter._update_frame` (the coordinates the Kalman step works in: the
mixture itself, or the MEKF's error state) and :meth:`BaseFilter._posterior` (back
from those coordinates).  Validation, the innovation gate, the Kalman step, the
diagnostics and the run state are written once, here.  The consumers (the filter
loop, checkpoints, the registry) are typed against :class:`Filter`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

from ..finite import all_finite
from ..gating import chi2_threshold, innovation_gate
from ..mixture import GaussianMixture, as_real_tensor
from ..models.base import ContinuousModel, MeasurementModel
from ..models.contract import check_measurement_elementwise
from ..update import ComponentUpdate, kalman_update
from .management import gather_slots, spread_slots
from .options import FilterOptions
from .step_diagnostics import StepDiagnostics

__all__ = [
    "Filter",
    "BaseFilter",
    "UpdateFrame",
    "check_batched",
    "check_interval",
    "PREDICT_DIAGNOSTICS",
    "UPDATE_DIAGNOSTICS",
    "GATE_DIAGNOSTICS",
]

#: Keys of ``filt.diagnostics`` after ``predict`` (every filter).
PREDICT_DIAGNOSTICS = ("weight_entropy", "covariance_repairs")
#: Keys after ``update`` (every filter).
UPDATE_DIAGNOSTICS = ("log_likelihood", "nis", "nis_mixture", "dof", "weight_entropy", "covariance_repairs")
#: Keys an update adds when the innovation gate is on.
GATE_DIAGNOSTICS = ("gate_rejected", "gate_nis", "gate_accepted", "gate_overridden")


@runtime_checkable
class Filter(Protocol):
    """What the filter loop, checkpoints and the registry rely on.

    ``mixture = filt.predict(mixture, u, dt)``, ``mixture = filt.update(mixture, y, measurement)``,
    ``mean, cov = filt.estimate(mixture)``; after each step ``filt.diagnostics`` holds that
    step's numbers (keys: :meth:`diagnostic_keys`).  The run state (e.g. a weight update's
    counter) is saved and restored with :meth:`state_dict` / :meth:`load_state_dict`.
    """

    model: ContinuousModel
    diagnostics: StepDiagnostics

    def predict(self, mixture: GaussianMixture, u: Tensor | None, dt: float) -> GaussianMixture: ...

    def update(self, mixture: GaussianMixture, y: Tensor, measurement: MeasurementModel) -> GaussianMixture: ...

    def estimate(self, mixture: GaussianMixture) -> tuple[Tensor, Tensor]: ...

    def check_mixture(self, mixture: GaussianMixture) -> None: ...

    def diagnostic_keys(self, step: str) -> tuple[str, ...]: ...

    def reset(self) -> None: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


def check_batched(name: str, value: Tensor, batch_shape: torch.Size, last: int | None = None) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value [..., last]`` is finite and its leading
    dims equal the mixture's ``batch_shape`` (``last``: the required size of the last dim, if any).

    One entry per trajectory, never broadcast: a single trajectory's gyro reading or star frame given to a
    batch was applied to every trajectory without a word (wrong estimates for all but one).  An input
    meant for every trajectory is expanded by the caller (``value.expand(*batch_shape, -1)``)."""
    if last is not None and (value.dim() < 1 or value.shape[-1] != last):
        raise ValueError(f"{name} must have shape [..., {last}], got {tuple(value.shape)}")
    if not all_finite(value):
        idx = (~torch.isfinite(value)).nonzero()[0].tolist()
        raise ValueError(f"{name} must be finite; non-finite value at index {tuple(idx)}")
    if value.dim() < 1 or tuple(value.shape[:-1]) != tuple(batch_shape):
        want = (*batch_shape, value.shape[-1] if value.dim() else "…")
        raise ValueError(
            f"{name} has shape {tuple(value.shape)}; the mixture's batch shape is {tuple(batch_shape)}, so {name} must "
            f"be {want}: one entry per trajectory (not broadcast; for one value shared by every trajectory, "
            f"{name}.expand({', '.join(map(str, (*batch_shape, -1)))}))"
        )


def check_interval(dt: Any) -> float:
    """The propagation interval as a float (s): a real number or a one-element real tensor,
    finite and > 0 (``bool`` is refused).

    Raises:
        ValueError: naming ``dt`` and the value.
    """
    if isinstance(dt, bool) or not (isinstance(dt, (int, float)) or torch.is_tensor(dt)):
        raise ValueError(f"dt must be a finite positive number, got {dt!r}")
    if torch.is_tensor(dt) and (dt.numel() != 1 or dt.dtype == torch.bool or dt.is_complex()):
        raise ValueError(f"dt must be a real scalar, got a {dt.dtype} tensor of shape {tuple(dt.shape)}")
    value = float(dt)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"dt must be a finite positive number, got {value}")
    return value


@dataclass(frozen=True)
class UpdateFrame:
    """The belief in the coordinates the Kalman step works in.

    Attributes:
        log_weights: ``[..., N]``; means: ``[..., N, n]``; covs: ``[..., N, n, n]``.
        measurement: the measurement model in those coordinates.
        context: whatever :meth:`BaseFilter._posterior` needs to map back (e.g. the MEKF's
            reference attitude), or ``None``.
    """

    log_weights: Tensor
    means: Tensor
    covs: Tensor
    measurement: MeasurementModel
    context: Any = None


class BaseFilter:
    """The steps shared by every filter (module docstring); subclasses override the maths.

    Args:
        model: the continuous-time model (:attr:`model_type`).
        update_iterations: linearisations per measurement update; 1 (default) is the EKF update
            of the method, more give the iterated EKF update (:func:`agsf_torch.update.kalman_update`).
            This and the next three are the options of every filter
            (:class:`~agsf_torch.filters.options.FilterOptions`).
        gate_probability: ``None`` (default, the method: every measurement is used) or ``p``
            in (0, 1): each measurement block (a star) whose mixture NIS exceeds ``χ²_s(p)``
            (``s`` = the model's ``block_size``) is rejected before the update and counted
            in the diagnostics, unless fewer than ``min(2, V − 1)`` of the ``V`` valid blocks
            pass, in which case the prediction is distrusted and all are kept
            (:mod:`agsf_torch.gating`).  ``1 − 1e-4`` is a sensible choice.
        fused: ``True`` (default) takes the fused path of a model or measurement that has one
            (:mod:`agsf_torch.fused`) at the propagate and Kalman steps.
        compile_fused: runs the fused path compiled ahead of time (:mod:`agsf_torch.fused.lanes`).
        repair_covariance: if ``False`` (default) a component covariance that stops being
            positive definite raises ``ValueError`` naming the trajectory and component;
            if ``True`` it is repaired by clipping its eigenvalues at ``min_eigenvalue``
            times its largest one, and the repair is counted in the diagnostics.
        min_eigenvalue: relative eigenvalue floor of the repair, in (0, 1).
    """

    #: The model class the filter needs.
    model_type: type[ContinuousModel] = ContinuousModel
    #: The number of components the filter carries (``None``: any).
    num_components: int | None = None
    #: Whether the update reports the moment-matched mixture NIS (one-component filters read the component's).
    mixture_nis: bool = True

    def __init__(
        self,
        model: ContinuousModel,
        *,
        update_iterations: int = 1,
        gate_probability: float | None = None,
        fused: bool = True,
        compile_fused: bool = False,
        repair_covariance: bool = False,
        min_eigenvalue: float = 1e-12,
        management: Any = None,
    ) -> None:
        if management is not None:  # a Gaussian-sum filter takes it before this point
            raise ValueError(
                f"management (mixture management) applies to Gaussian-sum filters; {type(self).__name__} carries "
                "no managed mixture"
            )
        if not isinstance(model, self.model_type):
            raise TypeError(f"{type(self).__name__} needs a {self.model_type.__name__}, got {type(model).__name__}")
        n = getattr(model, "state_dim", None)
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(
                f"{type(model).__name__}.state_dim must be a positive integer (the state's size), got {n!r}"
            )
        options = FilterOptions(
            update_iterations=update_iterations,
            gate_probability=gate_probability,
            fused=fused,
            compile_fused=compile_fused,
        )
        if not 0.0 < min_eigenvalue < 1.0:
            raise ValueError(f"min_eigenvalue must lie in (0, 1), got {min_eigenvalue}")
        self.model = model
        self.update_iterations = int(options.update_iterations)
        self.gate_probability = None if options.gate_probability is None else float(options.gate_probability)
        self.fused = options.fused
        self.compile_fused = options.compile_fused
        self.repair_covariance = bool(repair_covariance)
        self.min_eigenvalue = float(min_eigenvalue)
        self.diagnostics: StepDiagnostics = StepDiagnostics()

    # ------------------------------------------------------------------ checks
    def check_mixture(self, mixture: GaussianMixture) -> None:
        """Raise unless ``mixture`` fits this filter: a :class:`GaussianMixture` of the model's state
        dimension (and, for a one-component filter, one component)."""
        if not isinstance(mixture, GaussianMixture):
            raise TypeError(f"mixture must be a GaussianMixture, got {type(mixture).__name__}")
        if mixture.state_dim != self.model.state_dim:
            raise ValueError(f"mixture state dimension {mixture.state_dim} != model state_dim {self.model.state_dim}")
        if self.num_components is not None and mixture.num_components != self.num_components:
            raise ValueError(
                f"{type(self).__name__} needs a one-component mixture, got {mixture.num_components} components"
            )

    def _ensure_positive_definite(self, covs: Tensor, where: str, what: str = "covariance") -> tuple[Tensor, int]:
        """``covs [..., N, n, n]`` checked by a Cholesky factorisation; where it fails, repaired
        (``repair_covariance``) or refused naming ``what``, ``where``, the trajectory and the
        component; a non-finite matrix is always refused (no clip repairs it).  Returns the covariances and the
        number of repairs."""
        bad = torch.linalg.cholesky_ex(covs).info != 0
        if not bool(bad.any()):
            return covs, 0
        lost = bad & ~torch.isfinite(covs).flatten(-2).all(-1)
        if bool(lost.any()):  # no eigenvalue clip repairs a non-finite matrix: it would return NaN
            idx = lost.nonzero()[0].tolist()
            raise ValueError(f"{what} is not finite {where} at trajectory index {tuple(idx[:-1])}, component {idx[-1]}")
        if not self.repair_covariance:
            idx = bad.nonzero()[0].tolist()
            raise ValueError(
                f"{what} is not positive definite {where} at trajectory index {tuple(idx[:-1])}, "
                f"component {idx[-1]} (enable repair_covariance=True to clip its eigenvalues)"
            )
        evals, evecs = torch.linalg.eigh(covs)
        floor = self.min_eigenvalue * evals[..., -1:].abs()
        fixed = evecs @ torch.diag_embed(torch.maximum(evals, floor)) @ evecs.transpose(-1, -2)
        fixed = 0.5 * (fixed + fixed.transpose(-1, -2))
        return torch.where(bad[..., None, None], fixed, covs), int(bad.sum())

    # ----------------------------------------------------------------- predict
    def predict(self, mixture: GaussianMixture, u: Tensor | None, dt: float) -> GaussianMixture:
        """Propagate the belief over ``dt`` with the input ``u`` held constant.

        Args:
            mixture: the belief at ``t`` (batch shape ``[...]``, ``N`` components).
            u: input ``[..., m]`` (e.g. the gyro rate, rad/s), or ``None``; ``m`` must be the
                model's ``input_dim`` when it declares one (checked, never broadcast).
            dt: interval (s), finite and > 0.

        Returns:
            The belief at ``t + dt``.
        """
        u, dt = self._validate_predict(mixture, u, dt)
        mixture, managed = self._manage(mixture, "predict", u=u)
        slots = self._computed_slots(mixture)
        if slots is None:
            propagated, repairs = self._propagate(mixture, u, dt)
        else:
            propagated, repairs = self._propagate(gather_slots(mixture, slots), u, dt)
            propagated, _ = spread_slots(mixture, propagated, slots)
        adapted, extra = self._adapt_weights(mixture, propagated, u, dt)
        self.diagnostics = StepDiagnostics(
            {"weight_entropy": adapted.entropy_of_weights(), "covariance_repairs": repairs, **managed, **extra}
        )
        return adapted

    def _manage(
        self,
        mixture: GaussianMixture,
        step: str,
        *,
        u: Tensor | None = None,
        measurement: MeasurementModel | None = None,
    ) -> tuple[GaussianMixture, dict[str, Tensor]]:
        """Hook before a propagation (``step = "predict"``, input ``u``) or an update (``"update"``, the
        ``measurement``): the mixture to go on with and diagnostics; by default the mixture as it is.  A
        Gaussian-sum filter's mixture management runs here (:mod:`agsf_torch.filters.management`)."""
        return mixture, {}

    def _computed_slots(self, mixture: GaussianMixture) -> Tensor | None:
        """The slots of ``mixture`` a propagation and an update compute, ``[..., A]`` indices
        (:func:`~agsf_torch.filters.management.active_slots`; the others are inactive and are restored as copies of
        the heaviest component by :func:`~agsf_torch.filters.management.spread_slots`), or ``None``: every slot.
        By default every slot."""
        return None

    def _validate_predict(self, mixture: GaussianMixture, u: Any, dt: Any) -> tuple[Tensor | None, float]:
        """Check the mixture, ``dt`` and ``u`` before anything changes; return ``(u [..., m] or None, dt)``."""
        self.check_mixture(mixture)
        dt = check_interval(dt)
        if u is not None:
            u = as_real_tensor("u", u, mixture.means.dtype, mixture.means.device)
        self.model.check_input(u)  # u [..., m] for a model that declares its input size m
        if u is not None:
            check_batched("u", u, mixture.batch_shape)
        return u, dt

    def _propagate(self, mixture: GaussianMixture, u: Tensor | None, dt: float) -> tuple[GaussianMixture, int]:
        """The belief at ``t + dt`` with the weights unchanged, and the number of covariance repairs."""
        raise NotImplementedError

    def _adapt_weights(
        self, prior: GaussianMixture, propagated: GaussianMixture, u: Tensor | None, dt: float
    ) -> tuple[GaussianMixture, dict[str, Any]]:
        """Hook for weight corrections during propagation (``u [..., m]`` or ``None``); by default
        the weights are kept."""
        return propagated, {}

    # ------------------------------------------------------------------ update
    def update(self, mixture: GaussianMixture, y: Tensor, measurement: MeasurementModel) -> GaussianMixture:
        """Bayes update of the belief with the measurement ``y``.

        Args:
            mixture: the predicted belief.
            y: measurement ``[..., d]`` (entries masked out by the measurement model are ignored
                but must still be finite), checked by ``measurement.check_measurement`` before
                anything changes.
            measurement: the measurement model.

        Returns:
            The posterior belief; trajectories without a valid entry are returned unchanged.
        """
        y = self._validate_update(mixture, y, measurement)
        mixture, managed = self._manage(mixture, "update", measurement=measurement)
        slots = self._computed_slots(mixture)
        computed = mixture if slots is None else gather_slots(mixture, slots)
        frame = self._update_frame(computed, measurement)
        mask, gate = self._gate(frame, y)
        result = self._kalman_step(frame, y, mask)
        posterior, repairs = self._posterior(computed, frame, result)
        nis = result.nis
        if slots is not None:
            posterior, (nis,) = spread_slots(mixture, posterior, slots, nis)
        nis_mixture = result.nis_mixture if result.nis_mixture is not None else result.nis[..., 0]
        self.diagnostics = StepDiagnostics(
            {
                "log_likelihood": result.log_likelihood,
                "nis": nis,
                "nis_mixture": nis_mixture,
                "dof": result.dof,
                "weight_entropy": posterior.entropy_of_weights(),
                "covariance_repairs": repairs,
                **managed,
                **gate,
            }
        )
        self._after_update(posterior)  # last: nothing above can fail after the run state moves
        return posterior

    def _validate_update(self, mixture: GaussianMixture, y: Any, measurement: MeasurementModel) -> Tensor:
        """Check the mixture, the measurement model and ``y`` (the model's own checks included); return ``y``."""
        self.check_mixture(mixture)
        if not isinstance(measurement, MeasurementModel):
            raise TypeError(f"measurement must be a MeasurementModel, got {type(measurement).__name__}")
        y = as_real_tensor("y", y, mixture.means.dtype, mixture.means.device)
        check_batched("y", y, mixture.batch_shape)
        return check_measurement_elementwise(measurement, mixture.means, measurement.check_measurement(y))

    def _update_frame(self, mixture: GaussianMixture, measurement: MeasurementModel) -> UpdateFrame:
        """The coordinates of the Kalman step; by default the mixture itself."""
        return UpdateFrame(mixture.log_weights, mixture.means, mixture.covs, measurement)

    def _gate(self, frame: UpdateFrame, y: Tensor) -> tuple[Tensor | None, dict[str, Tensor]]:
        """The innovation gate (:func:`agsf_torch.gating.innovation_gate`): ``(entry mask or None, diagnostics)``."""
        if self.gate_probability is None:
            return None, {}
        block = frame.measurement.block_size or y.shape[-1]
        threshold = chi2_threshold(self.gate_probability, block)
        accepted, gate_nis, mask, overridden = innovation_gate(
            frame.log_weights, frame.means, frame.covs, y, frame.measurement, threshold
        )
        return mask, {
            "gate_rejected": (~accepted).sum(-1),
            "gate_nis": gate_nis,
            "gate_accepted": accepted,
            "gate_overridden": overridden,
        }

    def _kalman_step(self, frame: UpdateFrame, y: Tensor, mask: Tensor | None) -> ComponentUpdate:
        """The update of every component and Bayes' rule on the weights: the measurement's fused path
        if it has one (``MeasurementModel.fused_update``) and ``fused`` is on, else the generic
        Joseph-form update (:func:`agsf_torch.update.kalman_update`), which alone takes the second-order terms
        where :meth:`_second_order_update` asks for them."""
        second_order = self._second_order_update()
        if self.fused and not second_order:
            result = frame.measurement.fused_update(
                frame.log_weights,
                frame.means,
                frame.covs,
                y,
                self.update_iterations,
                mask=mask,
                mixture_nis=self.mixture_nis,
                compile=self.compile_fused,
            )
            if result is not None:
                return result
        return kalman_update(
            frame.log_weights,
            frame.means,
            frame.covs,
            y,
            frame.measurement,
            self.update_iterations,
            mask=mask,
            mixture_nis=self.mixture_nis,
            second_order=second_order,
        )

    def _second_order_update(self) -> bool:
        """Whether the update takes the measurement's second-order terms (``kalman_update``'s
        ``second_order``); ``False`` (default: the EKF update, or the iterated EKF's)."""
        return False

    def _posterior(
        self, prior: GaussianMixture, frame: UpdateFrame, result: ComponentUpdate
    ) -> tuple[GaussianMixture, int]:
        """The posterior belief from the Kalman step's result, and the number of covariance repairs;
        by default the components re-expressed in the model's canonical chart."""
        means, covs, repairs = self._settle(
            result.means, result.covs, getattr(result, "positive_definite", None), "in the measurement update"
        )
        return prior.replace(log_weights=result.log_weights, means=means, covs=covs, validate=False), repairs

    def _settle(
        self, means: Tensor, covs: Tensor, positive_definite: Tensor | None, where: str
    ) -> tuple[Tensor, Tensor, int]:
        """Components re-expressed in the model's canonical chart and checked (or repaired) for positive
        definiteness; ``positive_definite`` (``[..., N]`` bool, from a fused kernel's own pivots) spares the
        factorisation when it holds everywhere and no component changed chart."""
        before = covs
        means, covs = self.model.canonicalize(means, covs)
        if positive_definite is None:
            covs, repairs = self._ensure_positive_definite(covs, where)
            return means, covs, repairs
        if covs is not before:  # components that changed chart are checked again
            positive_definite = positive_definite & ~(covs != before).flatten(-2).any(-1)
        if bool(positive_definite.all()):
            return means, covs, 0
        at = (~positive_definite).nonzero(as_tuple=True)
        checked, repairs = self._ensure_positive_definite(covs[at], where)
        if repairs == 0:
            return means, covs, 0
        return means, covs.index_put(at, checked), repairs

    def _after_update(self, posterior: GaussianMixture) -> None:
        """Hook after a measurement update (the adaptive filter records its reference weights)."""

    # --------------------------------------------------------------- estimates
    def estimate(self, mixture: GaussianMixture) -> tuple[Tensor, Tensor]:
        """Point estimate and covariance of the belief: the mixture's moments, after the
        components are expressed in the chart of the heaviest one (``model.align``).

        Returns:
            ``(mean [..., n], cov [..., n, n])``.
        """
        best = mixture.log_weights.argmax(-1)
        idx = best[..., None, None].expand(*best.shape, 1, mixture.state_dim)
        reference = torch.gather(mixture.means, -2, idx)
        means, covs = self.model.align(mixture.means, mixture.covs, reference)
        return mixture.replace(means=means, covs=covs, validate=False).moments()

    def diagnostic_keys(self, step: str) -> tuple[str, ...]:
        """The keys ``filt.diagnostics`` holds after a ``"predict"`` or an ``"update"`` (declared
        here once; the consumers read them, tests check them)."""
        if step == "predict":
            return PREDICT_DIAGNOSTICS
        if step == "update":
            return UPDATE_DIAGNOSTICS + (GATE_DIAGNOSTICS if self.gate_probability is not None else ())
        raise ValueError(f"step must be 'predict' or 'update', got {step!r}")

    # --------------------------------------------------------------- run state
    def reset(self) -> None:
        """Start a new run (a filter without run state has nothing to forget)."""

    def state_dict(self) -> dict[str, Any]:
        """The filter's run state, for checkpoints (``{}`` for a filter without one)."""
        return {}

    def checkpoint_options(self) -> dict[str, Any]:
        """The options the filter's numbers depend on, by their constructor's names: a checkpoint records them
        beside :meth:`state_dict`, and a run resumes (bit for bit) only under the options it was saved with
        (:func:`~agsf_torch.storage.checkpoint.load_checkpoint` refuses others)."""
        return {
            "update_iterations": self.update_iterations,
            "gate_probability": self.gate_probability,
            "fused": self.fused,
            "compile_fused": self.compile_fused,
            "repair_covariance": self.repair_covariance,
            "min_eigenvalue": self.min_eigenvalue,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (validated before anything changes)."""
        if state != {}:
            got = sorted(state) if isinstance(state, dict) else state
            raise ValueError(f"{type(self).__name__} keeps no run state; got {got!r}")
