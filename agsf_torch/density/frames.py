"""A measurement frame as :class:`~agsf_torch.density.PosteriorReference` records it."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from ..models.base import MeasurementModel


@dataclass(frozen=True)
class _Frame:
    step: int  # number of input intervals before the frame
    y: Tensor  # [B, d]
    measurement: MeasurementModel
    valid: Tensor  # [B, d] float
    R_eff: Tensor  # [B, d, d]
    chol: Tensor  # [B, d, d]
    log_norm: Tensor  # [B]: −½(log det R_eff + dof log 2π)


def _point_eval(measurement: MeasurementModel, x: Tensor, jacobian: bool = False):
    """``h`` (and ``H``) at ``x [B, K, n]`` with the sample dim moved in front for the call."""
    xm = x.movedim(1, 0)
    h = measurement.predict(xm).movedim(0, 1)
    if not jacobian:
        return h
    return h, measurement.jacobian(xm).movedim(0, 1)
