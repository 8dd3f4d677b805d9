"""Filters sharing one predict/update contract: EKF, GSF and the adaptive GSF, and the
adaptive filter's weight updates."""

from .adaptive import AdaptiveGaussianSumFilter
from .gaussian_sum import ExtendedKalmanFilter, GaussianSumFilter
from .weight_updates import GalerkinWeightUpdate, PenaltyWeightUpdate, WeightUpdate

__all__ = [
    "ExtendedKalmanFilter",
    "GaussianSumFilter",
    "AdaptiveGaussianSumFilter",
    "WeightUpdate",
    "PenaltyWeightUpdate",
    "GalerkinWeightUpdate",
]
