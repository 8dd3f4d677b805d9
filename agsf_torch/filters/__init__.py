"""Filters sharing one predict/update contract: EKF, GSF, the adaptive GSF (with its weight
updates) and the multiplicative EKF."""

from .adaptive import AdaptiveGaussianSumFilter
from .diagnostics_view import StepDiagnostics
from .gaussian_sum import ExtendedKalmanFilter, GaussianSumFilter
from .multiplicative import MultiplicativeEKF
from .weight_updates import GalerkinWeightUpdate, PenaltyWeightUpdate, WeightUpdate

__all__ = [
    "ExtendedKalmanFilter",
    "GaussianSumFilter",
    "AdaptiveGaussianSumFilter",
    "MultiplicativeEKF",
    "WeightUpdate",
    "PenaltyWeightUpdate",
    "GalerkinWeightUpdate",
    "StepDiagnostics",
]
