"""The attitude adapter of the filter loop: sensor observations → :class:`~agsf_torch.filter_loop.StepInput`.

The one place that knows how a gyro and a star camera drive the attitude filters,
whether the observations come from the simulator or from a recording:

* **gyro gaps**: a sample marked invalid (``gyro_valid`` false) is bridged by the
  last valid reading, and the prediction's attitude covariance is inflated for the
  error the hold makes (:class:`~agsf_torch.attitude.gyro_hold.GyroHold`);
* **known bias** (``known_bias=True``, the paper's 3-state filter): the true bias
  term ``½(b_k + b_{k+1})`` of the gyro model is removed from the reading, so the
  caller passes the true bias with each observation.  With ``known_bias=False`` the
  reading goes to the model as it is: a 6-state model estimates the bias, a
  3-state model subtracts its own ``bias`` parameter (learning fits it);
* **star frames**: an observation with any valid star gives the measurement
  ``(y, StarVectorMeasurement)``.

Observation keys (batched, as the environment's): ``gyro [B, 3]`` (rad/s),
``gyro_valid [B]`` or ``[B, 1]`` (optional), ``star_body`` / ``star_inertial
[B, M, 3]`` (unit vectors), ``star_mask [B, M]``.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..filter_loop import StepInput
from ..models.star_vectors import StarVectorMeasurement
from .gyro_hold import GyroHold
from .recordings import Recording

__all__ = ["AttitudeInputs", "recording_inputs", "as_float64"]


def as_float64(x: Any, dtype: torch.dtype = torch.float64) -> Tensor:
    """``x`` (tensor or array-like) as a tensor of ``dtype``."""
    return torch.as_tensor(np.asarray(x) if not torch.is_tensor(x) else x, dtype=dtype)


class AttitudeInputs:
    """Turns gyro and star-camera observations into the filter loop's inputs (module docstring).

    Args:
        sigma_s: σ_s of the star measurements (rad; a float or a tensor that may require grad).
        gyro_hold_sigma: σ_h of the gyro hold (rad/s), e.g. ``σ_v/√Δt`` (a float or a 0-d tensor).
        known_bias: remove the true bias passed with each observation (3-state, bias known).
        noise_model: the star-vector noise model (``"isotropic"`` or ``"tangent"``).

    Call :meth:`start` with the first observation (time 0), then the object once per
    later observation.
    """

    def __init__(
        self,
        *,
        sigma_s: float | Tensor,
        gyro_hold_sigma: float | Tensor,
        known_bias: bool = False,
        noise_model: str = "isotropic",
    ) -> None:
        self.sigma_s = sigma_s
        self.hold = GyroHold(gyro_hold_sigma)
        self.known_bias = bool(known_bias)
        self.noise_model = noise_model
        self._bias: Tensor | None = None

    @staticmethod
    def gyro_valid(obs: Mapping[str, Any], B: int) -> Tensor:
        """``obs["gyro_valid"]`` as ``[B]`` bool (all true when the source has no such key)."""
        if "gyro_valid" not in obs:
            return torch.ones(B, dtype=torch.bool)
        return as_float64(obs["gyro_valid"], torch.bool).reshape(B)

    def _bias_of(self, truth_bias: Tensor | None, gyro: Tensor) -> Tensor | None:
        """The true bias as ``[B, 3]`` float64 like ``gyro`` (``None`` unless ``known_bias``); any other
        shape — ``[B, 1]`` included — is refused, never broadcast over the axes."""
        if not self.known_bias:
            return None
        if truth_bias is None:
            raise ValueError("known_bias=True needs the true gyro bias with every observation")
        bias = as_float64(truth_bias)
        if bias.shape != gyro.shape:
            raise ValueError(
                f"truth_bias must have the gyro's shape {tuple(gyro.shape)} ([B, 3], rad/s), got {tuple(bias.shape)}"
            )
        if not bool(torch.isfinite(bias).all()):
            raise ValueError(
                f"truth_bias must be finite; non-finite at index {tuple((~torch.isfinite(bias)).nonzero()[0].tolist())}"
            )
        return bias

    def start(self, obs: Mapping[str, Any], dt: float, truth_bias: Tensor | None = None) -> None:
        """Start a run: the gyro hold forgets any earlier run and is primed with the first reading (and
        the known bias with its true value).  Everything is checked before anything changes."""
        gyro = as_float64(obs["gyro"])
        bias = self._bias_of(truth_bias, gyro)
        valid = self.gyro_valid(obs, gyro.shape[0])
        hold = GyroHold(self.hold.rate_sigma)
        hold.step(gyro, valid, dt)
        self.hold, self._bias = hold, bias

    def __call__(
        self, obs: Mapping[str, Any], dt: float, truth_bias: Tensor | None = None, context: Any = None
    ) -> StepInput:
        """The input of the interval of length ``dt`` that ends at ``obs``.

        Args:
            obs: the observation at the end of the interval.
            dt: the interval (s).
            truth_bias: the true bias ``[B, 3]`` at ``obs`` (with ``known_bias`` only).
            context: passed through to :attr:`StepInput.context`.
        """
        gyro = as_float64(obs["gyro"])
        B = gyro.shape[0]
        valid = self.gyro_valid(obs, B)
        bias = self._bias_of(truth_bias, gyro)
        measurement = None  # built (and checked) before the hold or the bias move
        mask = as_float64(obs["star_mask"], torch.bool)
        if bool(mask.any()):
            stars = {
                "star_body": as_float64(obs["star_body"]),
                "star_inertial": as_float64(obs["star_inertial"]),
                "star_mask": mask,
            }
            measurement = StarVectorMeasurement.from_observation(stars, self.sigma_s, noise_model=self.noise_model)
        u, held_var = self.hold.step(gyro, valid, dt)
        if bias is not None:
            u = u - 0.5 * (self._bias + bias)  # the gyro model's bias term over the interval
            self._bias = bias
        correct = None
        if bool((~valid).any()):
            correct = lambda mixture: GyroHold.inflate(mixture, held_var)  # noqa: E731
        return StepInput(float(dt), u, measurement, correct, {"gyro_held": (~valid).to(torch.int64)}, context)


def recording_inputs(rec: Recording, adapter: AttitudeInputs) -> Iterator[StepInput]:
    """The inputs of a recording's samples 1 … T−1 (sample 0, the prior's time, primes the adapter).

    With a known-bias adapter the recording must hold ``truth_bias``.
    """
    bias = (lambda k: None) if not adapter.known_bias else (lambda k: rec.truth_bias[:, k])
    if adapter.known_bias and rec.truth_bias is None:
        raise ValueError("known_bias=True needs the recording's truth_bias column")
    times = rec.time
    first_dt = float(times[1] - times[0]) if rec.num_samples > 1 else 1.0
    adapter.start(rec.observation(0), first_dt, bias(0))
    for k in range(1, rec.num_samples):
        yield adapter(rec.observation(k), float(times[k] - times[k - 1]), bias(k))
