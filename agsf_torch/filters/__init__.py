"""Filters sharing one predict/update contract: EKF, GSF and the adaptive GSF."""

from .adaptive import AdaptiveGaussianSumFilter
from .gaussian_sum import ExtendedKalmanFilter, GaussianSumFilter

__all__ = ["ExtendedKalmanFilter", "GaussianSumFilter", "AdaptiveGaussianSumFilter"]
