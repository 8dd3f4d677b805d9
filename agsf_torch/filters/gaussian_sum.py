"""Classic Gaussian sum filter and the EKF as its one-component case (method.md §2)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..gating import chi2_threshold, innovation_gate
from ..mixture import GaussianMixture, as_real_tensor
from ..models.base import ContinuousModel, MeasurementModel
from ..propagation import propagate_moments
from ..update import kalman_update
from .diagnostics_view import StepDiagnostics

__all__ = ["GaussianSumFilter", "ExtendedKalmanFilter", "check_batched"]


def check_batched(name: str, value: Tensor, batch_shape: torch.Size, last: int | None = None) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value [..., last]`` is finite and its leading
    dims broadcast with the mixture's ``batch_shape`` (``last``: the required size of the last dim, if any)."""
    if last is not None and (value.dim() < 1 or value.shape[-1] != last):
        raise ValueError(f"{name} must have shape [..., {last}], got {tuple(value.shape)}")
    if not bool(torch.isfinite(value).all()):
        idx = (~torch.isfinite(value)).nonzero()[0].tolist()
        raise ValueError(f"{name} must be finite; non-finite value at index {tuple(idx)}")
    try:
        torch.broadcast_shapes(value.shape[:-1], batch_shape)
    except RuntimeError:
        raise ValueError(
            f"{name} has shape {tuple(value.shape)}, whose leading dims do not broadcast with "
            f"the mixture's batch shape {tuple(batch_shape)}"
        ) from None


#: Keys of ``filt.diagnostics`` after ``predict`` (every filter).
PREDICT_DIAGNOSTICS = ("weight_entropy", "covariance_repairs")
#: Keys after ``update`` (every filter).
UPDATE_DIAGNOSTICS = ("log_likelihood", "nis", "nis_mixture", "dof", "weight_entropy", "covariance_repairs")
#: Keys an update adds when the innovation gate is on.
GATE_DIAGNOSTICS = ("gate_rejected", "gate_nis", "gate_accepted", "gate_overridden")


def diagnostic_keys(step: str, gated: bool) -> tuple[str, ...]:
    """The keys of ``filt.diagnostics`` after a ``"predict"`` or an ``"update"`` (``gated``: the gate is on)."""
    if step == "predict":
        return PREDICT_DIAGNOSTICS
    if step == "update":
        return UPDATE_DIAGNOSTICS + (GATE_DIAGNOSTICS if gated else ())
    raise ValueError(f"step must be 'predict' or 'update', got {step!r}")


class GaussianSumFilter:
    """Gaussian sum filter: every component is an EKF, weights change only at updates.

    All trajectories (leading dims) and components advance as one tensor
    program.  The contract shared by every filter of the package::

        mixture = filt.predict(mixture, u, dt)          # propagate over one input interval
        mixture = filt.update(mixture, y, measurement)  # Bayes update with one measurement
        mean, cov = filt.estimate(mixture)

    After each call ``filt.diagnostics`` holds that step's diagnostics as a dict
    of tensors (computed during the step, never recomputed; a
    :class:`~agsf_torch.filters.diagnostics_view.StepDiagnostics`, which prints one
    summary line per key):

    * predict: ``weight_entropy [...]``, ``covariance_repairs`` (int, this call);
    * update: ``log_likelihood [...]`` (``log Σ wᵢβᵢ``), ``nis [..., N]``,
      ``nis_mixture [...]`` (moment-matched innovation of the mixture), ``dof [...]``
      (valid measurement entries), ``weight_entropy [...]``, ``covariance_repairs``;
      with gating also ``gate_rejected [...]`` (blocks rejected by this update, int64),
      ``gate_nis [..., G]`` (each block's mixture NIS), ``gate_accepted [..., G]`` and
      ``gate_overridden [...]`` (failing blocks kept by the consistency rule).

    Args:
        model: the continuous-time model.
        substeps: RK4 steps per ``predict`` interval.
        repair_covariance: if ``False`` (default) a component covariance that
            stops being positive definite raises ``ValueError`` naming the
            trajectory and component; if ``True`` it is repaired by clipping its
            eigenvalues at ``min_eigenvalue`` times its largest one, and the
            repair is counted in the diagnostics.
        min_eigenvalue: relative eigenvalue floor of the repair.
        update_iterations: linearisations per measurement update; 1 (default) is
            the EKF update of the method, more give the iterated EKF update
            (:func:`agsf_torch.update.kalman_update`).
        gate_probability: ``None`` (default, the method: every measurement is
            used) or ``p`` in (0, 1): each measurement block (a star) whose mixture
            NIS exceeds ``χ²_s(p)`` (s = the model's ``block_size``) is rejected
            before the update and counted in the diagnostics, unless fewer than
            ``min(2, V − 1)`` of the ``V`` valid blocks pass, in which case the
            prediction is distrusted and all are kept (:mod:`agsf_torch.gating`).  ``1 − 1e-4`` is a sensible choice.
    """

    def __init__(
        self,
        model: ContinuousModel,
        *,
        substeps: int = 1,
        repair_covariance: bool = False,
        min_eigenvalue: float = 1e-12,
        update_iterations: int = 1,
        gate_probability: float | None = None,
    ) -> None:
        if not isinstance(model, ContinuousModel):
            raise TypeError(f"model must be a ContinuousModel, got {type(model).__name__}")
        if int(substeps) != substeps or substeps < 1:
            raise ValueError(f"substeps must be a positive integer, got {substeps}")
        if not 0.0 < min_eigenvalue < 1.0:
            raise ValueError(f"min_eigenvalue must lie in (0, 1), got {min_eigenvalue}")
        if int(update_iterations) != update_iterations or update_iterations < 1:
            raise ValueError(f"update_iterations must be a positive integer, got {update_iterations}")
        self.update_iterations = int(update_iterations)
        if gate_probability is not None:
            chi2_threshold(gate_probability, 1)  # validates p
        self.gate_probability = None if gate_probability is None else float(gate_probability)
        self.model = model
        self.substeps = int(substeps)
        self.repair_covariance = bool(repair_covariance)
        self.min_eigenvalue = float(min_eigenvalue)
        self.diagnostics: StepDiagnostics = StepDiagnostics()

    # ----------------------------------------------------------------- checks
    def _check_mixture(self, mixture: GaussianMixture) -> None:
        if not isinstance(mixture, GaussianMixture):
            raise TypeError(f"mixture must be a GaussianMixture, got {type(mixture).__name__}")
        if mixture.state_dim != self.model.state_dim:
            raise ValueError(f"mixture state dimension {mixture.state_dim} != model state_dim {self.model.state_dim}")

    def _ensure_positive_definite(self, covs: Tensor, where: str) -> tuple[Tensor, int]:
        info = torch.linalg.cholesky_ex(covs).info
        bad = info != 0
        if not bool(bad.any()):
            return covs, 0
        if not self.repair_covariance:
            idx = bad.nonzero()[0].tolist()
            raise ValueError(
                f"covariance lost positive definiteness {where} at trajectory index {tuple(idx[:-1])}, "
                f"component {idx[-1]} (enable repair_covariance=True to clip its eigenvalues)"
            )
        evals, evecs = torch.linalg.eigh(covs)
        floor = self.min_eigenvalue * evals[..., -1:].abs()
        fixed = evecs @ torch.diag_embed(torch.maximum(evals, floor)) @ evecs.transpose(-1, -2)
        fixed = 0.5 * (fixed + fixed.transpose(-1, -2))
        return torch.where(bad[..., None, None], fixed, covs), int(bad.sum())

    # ------------------------------------------------------------- the steps
    def predict(self, mixture: GaussianMixture, u: Tensor | None, dt: float) -> GaussianMixture:
        """Propagate every component over ``dt`` with the input ``u`` held constant.

        Args:
            mixture: the belief at ``t`` (batch shape ``[...]``, ``N`` components).
            u: input ``[..., m]`` (e.g. the gyro rate, rad/s), or ``None``; ``m`` must be the
                model's ``input_dim`` when it declares one (checked, never broadcast).
            dt: interval (s), finite and > 0.

        Returns:
            The belief at ``t + dt``.
        """
        self._check_mixture(mixture)
        if not (isinstance(dt, (int, float)) or torch.is_tensor(dt)) or not float(dt) > 0 or not torch.isfinite(torch.tensor(float(dt))):
            raise ValueError(f"dt must be a finite positive number, got {dt}")
        if u is not None:
            u = as_real_tensor("u", u, mixture.means.dtype, mixture.means.device)
        self.model.check_input(u)  # u [..., m] for a model that declares its input size m
        if u is not None:
            check_batched("u", u, mixture.batch_shape)
            u = u.unsqueeze(-2)  # broadcast over components
        means, covs = propagate_moments(self.model, mixture.means, mixture.covs, u, float(dt), self.substeps)
        means, covs = self.model.canonicalize(means, covs)
        covs, repairs = self._ensure_positive_definite(covs, "during propagation")
        propagated = mixture.replace(means=means, covs=covs, validate=False)  # checked just above
        propagated, extra = self._adapt_weights(mixture, propagated, u, float(dt))
        self.diagnostics = StepDiagnostics(
            {"weight_entropy": propagated.entropy_of_weights(), "covariance_repairs": repairs, **extra}
        )
        return propagated

    def diagnostic_keys(self, step: str) -> tuple[str, ...]:
        """The keys ``filt.diagnostics`` holds after a ``"predict"`` or an ``"update"`` of this filter
        (declared here once; the consumers read them, tests check them)."""
        return diagnostic_keys(step, self.gate_probability is not None)

    def _adapt_weights(
        self, prior: GaussianMixture, propagated: GaussianMixture, u: Tensor | None, dt: float
    ) -> tuple[GaussianMixture, dict[str, Any]]:
        """Hook for weight corrections during propagation; the classic filter keeps the weights."""
        return propagated, {}

    def update(self, mixture: GaussianMixture, y: Tensor, measurement: MeasurementModel) -> GaussianMixture:
        """Bayes update of every component with the measurement ``y``.

        Args:
            mixture: the predicted belief.
            y: measurement ``[..., d]`` (entries masked out by the measurement
               model are ignored but must still be finite), checked by
               ``measurement.check_measurement`` before anything changes.
            measurement: the measurement model.

        Returns:
            The posterior belief.
        """
        self._check_mixture(mixture)
        if not isinstance(measurement, MeasurementModel):
            raise TypeError(f"measurement must be a MeasurementModel, got {type(measurement).__name__}")
        y = as_real_tensor("y", y, mixture.means.dtype, mixture.means.device)
        check_batched("y", y, mixture.batch_shape)
        y = measurement.check_measurement(y)  # the model's own checks (size d, unit vectors…)
        gate: dict[str, Tensor] = {}
        mask = None
        if self.gate_probability is not None:
            block = measurement.block_size or y.shape[-1]
            threshold = chi2_threshold(self.gate_probability, block)
            accepted, gate_nis, mask, overridden = innovation_gate(
                mixture.log_weights, mixture.means, mixture.covs, y, measurement, threshold
            )
            gate = {
                "gate_rejected": (~accepted).sum(-1),
                "gate_nis": gate_nis,
                "gate_accepted": accepted,
                "gate_overridden": overridden,
            }
        res = kalman_update(
            mixture.log_weights, mixture.means, mixture.covs, y, measurement, self.update_iterations, mask=mask
        )
        means, covs = self.model.canonicalize(res.means, res.covs)
        covs, repairs = self._ensure_positive_definite(covs, "in the measurement update")
        posterior = mixture.replace(log_weights=res.log_weights, means=means, covs=covs, validate=False)
        self.diagnostics = StepDiagnostics({
            "log_likelihood": res.log_likelihood,
            "nis": res.nis,
            "nis_mixture": res.nis_mixture,
            "dof": res.dof,
            "weight_entropy": posterior.entropy_of_weights(),
            "covariance_repairs": repairs,
            **gate,
        })
        self._after_update(posterior)  # last: nothing above can fail after the run state moves
        return posterior

    def _after_update(self, posterior: GaussianMixture) -> None:
        """Hook after a measurement update (the adaptive filter records its reference weights)."""

    # ------------------------------------------------------------- run state
    def reset(self) -> None:
        """Start a new run (the classic filter keeps no run state)."""

    def state_dict(self) -> dict[str, Any]:
        """The filter's run state, for checkpoints (the classic filter has none: ``{}``)."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        if state != {}:
            raise ValueError(f"{type(self).__name__} keeps no run state; got {sorted(state) if isinstance(state, dict) else state!r}")

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


class ExtendedKalmanFilter(GaussianSumFilter):
    """The extended Kalman filter: a Gaussian sum filter with one component.

    Build its belief with ``GaussianMixture.from_gaussian(mean, cov)``.
    """

    def _check_mixture(self, mixture: GaussianMixture) -> None:
        super()._check_mixture(mixture)
        if mixture.num_components != 1:
            raise ValueError(f"ExtendedKalmanFilter needs a one-component mixture, got {mixture.num_components}")
