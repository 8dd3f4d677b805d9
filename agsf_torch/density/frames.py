"""What :class:`~agsf_torch.density.PosteriorReference` records: its measurement frames and the
diagnostics of every step (:class:`ReferenceStepRecord`)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from ..models.base import MeasurementModel

__all__ = ["ReferenceStepRecord", "Frame", "point_eval"]


@dataclass(frozen=True)
class Frame:
    """A measurement frame of the density references: its data, model, valid entries and the Cholesky factor and
    normalisation of its effective noise covariance."""

    step: int  # number of input intervals before the frame
    y: Tensor  # [B, d]
    measurement: MeasurementModel
    valid: Tensor  # [B, d] float
    R_eff: Tensor  # [B, d, d]
    chol: Tensor  # [B, d, d]
    log_norm: Tensor  # [B]: −½(log det R_eff + dof log 2π)


def point_eval(measurement: MeasurementModel, x: Tensor, jacobian: bool = False):
    """``h`` (and ``H``) at ``x [B, K, n]`` with the sample dim moved in front for the call."""
    xm = x.movedim(1, 0)
    h = measurement.predict(xm).movedim(0, 1)
    if not jacobian:
        return h
    return h, measurement.jacobian(xm).movedim(0, 1)


@dataclass(frozen=True)
class ReferenceStepRecord:
    """Diagnostics of one :class:`PosteriorReference` step (``predict`` or ``update``).

    Attributes:
        time: time after the step (s).
        frame: ``True`` for an ``update``.
        ess: effective sample size of the weights at the end of the step, before any
            resampling ``[B]``.
        lineages: distinct lineages (ancestors at the last independent draw) ``[B]``.
        redrawn: the particles were replaced by a path-space redraw ``[B]`` bool.
        resampled: systematic resampling after the step ``[B]`` bool.
        bootstrap_ess: ESS the bootstrap reweighting would have had (``update``; NaN
            for ``predict``) ``[B]``.
        redraw_ess: ESS of the redraw where one was computed, NaN elsewhere ``[B]``.
    """

    time: float
    frame: bool
    ess: Tensor
    lineages: Tensor
    redrawn: Tensor
    resampled: Tensor
    bootstrap_ess: Tensor
    redraw_ess: Tensor
