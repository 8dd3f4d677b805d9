"""Models: the continuous-time / measurement protocol and the attitude models."""

from .attitude import DEFAULT_SIGMA_U, DEFAULT_SIGMA_V, AttitudeModel
from .base import ContinuousModel, MeasurementModel, batched_jacobian
from .benchmarks import LorenzModel, SineDriftModel
from .function_measurement import FunctionMeasurement
from .linear import LinearModel
from .star_vectors import StarVectorMeasurement

__all__ = [
    "ContinuousModel",
    "MeasurementModel",
    "FunctionMeasurement",
    "batched_jacobian",
    "LinearModel",
    "LorenzModel",
    "SineDriftModel",
    "AttitudeModel",
    "StarVectorMeasurement",
    "DEFAULT_SIGMA_V",
    "DEFAULT_SIGMA_U",
]
