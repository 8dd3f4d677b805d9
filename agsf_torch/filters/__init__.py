"""Filters sharing one predict/update contract: EKF, GSF (and the adaptive GSF)."""

from .gaussian_sum import ExtendedKalmanFilter, GaussianSumFilter

__all__ = ["ExtendedKalmanFilter", "GaussianSumFilter"]
