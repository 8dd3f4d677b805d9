"""Rate-integrating gyro with angle and rate random walk (method.md §1).

Discrete model at gyro period Δt (Farrenkopf's model as used by Crassidis & Junkins):

    ω̃_{k+1} = ω_{k+1} + ½ (b_{k+1} + b_k) + sqrt(σ_v²/Δt + σ_u² Δt/12) · N_v
    b_{k+1}  = b_k + σ_u sqrt(Δt) · N_u

with ``N_v, N_u ~ N(0, I₃)`` independent.  Here ``ω_{k+1}`` is the true body rate
over ``(t_k, t_{k+1}]`` (held constant over the step; see :mod:`envs.dynamics`).
Units: σ_v in rad/s^½ (angle random walk), σ_u in rad/s^{3/2} (rate random walk),
Δt in s, rates and biases in rad/s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from ._checks import check_period, check_real, check_rotation_per_step, check_vector

__all__ = [
    "DEG_PER_HOUR",
    "DEFAULT_SIGMA_V",
    "DEFAULT_SIGMA_U",
    "DEFAULT_INITIAL_BIAS",
    "Gyro",
    "check_gyro_settings",
]

# The simulated gyro's own values (the truth); the filters' assumed values are in
# agsf_torch.constants (envs depends on agsf_torch.rotations only), equal by a test.
DEG_PER_HOUR = math.pi / 180.0 / 3600.0
"""One degree per hour in rad/s."""
DEFAULT_SIGMA_V = math.sqrt(10.0) * 1e-7
"""Angle random walk σ_v (rad/s^½)."""
DEFAULT_SIGMA_U = math.sqrt(10.0) * 1e-10
"""Rate random walk σ_u (rad/s^{3/2})."""
DEFAULT_INITIAL_BIAS = (0.1 * DEG_PER_HOUR,) * 3
"""Initial bias, 0.1 deg/hr on each axis (rad/s)."""


def check_gyro_settings(
    owner: str, sigma_v: Any, sigma_u: Any, dt: Any, initial_bias: Any
) -> tuple[float, float, float, tuple[float, float, float]]:
    """Validated gyro settings ``(σ_v, σ_u, Δt, b_0)``, shared by :class:`Gyro` and
    :class:`~envs.config.StarTrackerConfig`.

    Ranges: σ_v, σ_u finite ≥ 0 (rad/s^½, rad/s^{3/2}); Δt finite and ≥
    :data:`~envs._checks.MIN_PERIOD` (s); ``b_0`` a number (every axis) or 3 finite
    numbers (rad/s).  Physical limit (:func:`~envs._checks.check_rotation_per_step`):
    the initial bias ``|b_0|`` and the 1-σ reading noise ``sqrt(σ_v²/Δt + σ_u²Δt/12)``
    must each turn less than half a turn per step (``·Δt < π``): a reading is a rate
    over one step, and beyond π/Δt it no longer describes a sampled rotation.

    Raises:
        ValueError: naming ``owner``, the field and the value.
    """
    sigma_v = check_real(owner, "sigma_v", sigma_v)
    sigma_u = check_real(owner, "sigma_u", sigma_u)
    dt = check_period(owner, "dt", dt)
    bias = check_vector(owner, "initial_bias", initial_bias, 3, scalar_ok=True)
    check_rotation_per_step(owner, f"initial_bias {math.hypot(*bias):.6g} rad/s", math.hypot(*bias), dt)
    noise = math.hypot(sigma_v / math.sqrt(dt), sigma_u * math.sqrt(dt / 12.0))
    check_rotation_per_step(owner, f"gyro noise (1-σ reading) {noise:.6g} rad/s", noise, dt)
    return sigma_v, sigma_u, dt, bias  # type: ignore[return-value]


class Gyro:
    """The discrete gyro model above, batched over leading dims.

    Args:
        sigma_v: angle random walk σ_v (rad/s^½), finite ≥ 0.
        sigma_u: rate random walk σ_u (rad/s^{3/2}), finite ≥ 0.
        dt: gyro period Δt (s), finite, ≥ 1e-9 s.
        initial_bias: ``b_0`` (rad/s), a scalar (every axis) or 3 numbers, finite.

    The bias and the reading noise must each turn less than half a turn per step
    (:func:`check_gyro_settings`).

    Attributes:
        rate_noise_std: ``sqrt(σ_v²/Δt + σ_u²Δt/12)`` (rad/s), std of each axis of
            the measurement noise.
        bias_step_std: ``σ_u sqrt(Δt)`` (rad/s), std of each axis of a bias step.

    Raises:
        ValueError: naming the field and value of any bad setting.
    """

    def __init__(
        self,
        sigma_v: float = DEFAULT_SIGMA_V,
        sigma_u: float = DEFAULT_SIGMA_U,
        dt: float = 0.1,
        initial_bias: float | Sequence[float] = DEFAULT_INITIAL_BIAS,
    ) -> None:
        self.sigma_v, self.sigma_u, self.dt, self.initial_bias = check_gyro_settings(
            "Gyro", sigma_v, sigma_u, dt, initial_bias
        )
        dt = self.dt
        self.rate_noise_std = math.sqrt(self.sigma_v**2 / dt + self.sigma_u**2 * dt / 12.0)
        self.bias_step_std = self.sigma_u * math.sqrt(dt)

    def initial_bias_tensor(
        self, batch_shape: Sequence[int] = (), dtype: torch.dtype = torch.float64, device=None
    ) -> Tensor:
        """``b_0`` broadcast to ``[*batch_shape, 3]`` (rad/s)."""
        b = torch.tensor(self.initial_bias, dtype=dtype, device=device)
        return b.expand(*batch_shape, 3).clone()

    def step(self, omega: Tensor, bias: Tensor, n_v: Tensor, n_u: Tensor) -> tuple[Tensor, Tensor]:
        """One gyro period: :meth:`step_block` with a block of one step.

        .. math::
            b_{k+1} = b_k + σ_u\\sqrt{Δt}\\, n_u,\\qquad
            ω̃_{k+1} = ω_{k+1} + ½(b_{k+1} + b_k) + \\sqrt{σ_v^2/Δt + σ_u^2Δt/12}\\; n_v

        Args:
            omega: true rate ``ω_{k+1}`` over the step ``[..., 3]`` (rad/s).
            bias: ``b_k`` ``[..., 3]`` (rad/s).
            n_v, n_u: standard normals ``[..., 3]``.

        Returns:
            ``(ω̃_{k+1} [..., 3], b_{k+1} [..., 3])`` (rad/s).
        """
        measured, biases = self.step_block(omega[None], bias, n_v[None], n_u[None])
        return measured[0], biases[0]

    def step_block(self, omega: Tensor, bias: Tensor, n_v: Tensor, n_u: Tensor) -> tuple[Tensor, Tensor]:
        """S consecutive gyro periods (the model of :meth:`step`, written once).

        The bias walk is accumulated step by step (``b_{j+1} = b_j + σ_u√Δt n_u[j]``, the
        same additions in the same order as S calls of :meth:`step`, so the numbers are
        identical); the readings are then formed for the whole block.

        Args:
            omega: true rates ``ω_{k+1} … ω_{k+S}`` ``[S, ..., 3]`` (rad/s).
            bias: ``b_k`` ``[..., 3]`` (rad/s).
            n_v, n_u: standard normals ``[S, ..., 3]`` (row j for the step to ``k+j+1``).

        Returns:
            ``(ω̃ [S, ..., 3], b [S, ..., 3])``: readings ``ω̃_{k+1} … ω̃_{k+S}`` and biases
            ``b_{k+1} … b_{k+S}`` (rad/s).
        """
        walk = self.bias_step_std * n_u
        if bias.shape != walk.shape[1:]:
            bias = torch.broadcast_tensors(bias, walk[0])[0]
        biases = [bias]
        for j in range(walk.shape[0]):
            biases.append(biases[-1] + walk[j])
        b = torch.stack(biases)  # [S+1, ..., 3]: b_k … b_{k+S}
        measured = omega + 0.5 * (b[1:] + b[:-1]) + self.rate_noise_std * n_v
        return measured, b[1:]

    def read(self, omega: Tensor, bias: Tensor, n_v: Tensor) -> Tensor:
        """A reading with the bias held: ``ω + b + sqrt(σ_v²/Δt + σ_u²Δt/12) n_v`` (rad/s).

        Used for the reading that accompanies the initial observation, which closes
        no gyro interval.  Shapes ``[..., 3]``.
        """
        return omega + bias + self.rate_noise_std * n_v
