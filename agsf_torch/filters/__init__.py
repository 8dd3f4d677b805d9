"""Filters sharing one contract (:class:`~agsf_torch.filters.base.Filter`): EKF, GSF, the adaptive
GSF (with its weight updates), the multiplicative EKF, USQUE and the particle filter, built on one base with small steps."""

from .adaptive import AdaptiveGaussianSumFilter
from .base import BaseFilter, Filter
from .gaussian_sum import ExtendedKalmanFilter, GaussianSumFilter
from .management import MixtureManagement
from .multiplicative import MultiplicativeEKF
from .options import FilterOptions
from .particle import ParticleFilter, ParticleOptions
from .step_diagnostics import StepDiagnostics
from .unscented_quaternion import USQUE
from .weight_updates import GalerkinWeightUpdate, PenaltyWeightUpdate, WeightUpdate

__all__ = [
    "Filter",
    "BaseFilter",
    "FilterOptions",
    "ExtendedKalmanFilter",
    "GaussianSumFilter",
    "AdaptiveGaussianSumFilter",
    "MixtureManagement",
    "MultiplicativeEKF",
    "USQUE",
    "ParticleFilter",
    "ParticleOptions",
    "WeightUpdate",
    "PenaltyWeightUpdate",
    "GalerkinWeightUpdate",
    "StepDiagnostics",
]
