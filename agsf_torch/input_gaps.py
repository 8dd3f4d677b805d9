"""Gyro gaps: propagate through missing or saturated gyro samples.

The attitude filters are driven by the gyro (the input ``u``).  When a sample is
missing or saturated (``gyro_valid`` false) :class:`GyroHold` substitutes the
last valid reading and inflates the attitude covariance of every component for
the error that the hold makes.  A held reading is off the true rate by its own
noise and by any change of the rate since, ``δω`` with per-axis standard
deviation ``σ_h`` (``rate_sigma``, rad/s); held over ``j`` consecutive steps it
turns the attitude by ``δω · jΔt``, so the angle variance grows by

.. math:: σ_h^2 Δt^2 \\left(j^2 - (j-1)^2\\right) = σ_h^2 Δt^2 (2j - 1)

at the ``j``-th held step (per axis; an MRP variance is that over 16, from
``δθ ≈ 4 δp``).  The default ``σ_h = σ_v / √Δt`` is the noise of one gyro
sample, right for a constant or slowly varying rate; a manoeuvring spacecraft
needs ``σ_h`` of its rate change over the gap.  Without this inflation a filter
that holds the rate for a minute becomes overconfident and its innovation gate
(:mod:`agsf_torch.gating`) then rejects good stars after the gap.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from .mixture import GaussianMixture

__all__ = ["GyroHold"]


class GyroHold:
    """Hold the last valid gyro reading over gaps, with the matching covariance inflation.

    Args:
        rate_sigma: ``σ_h``, per-axis 1σ error of a held reading (rad/s), ≥ 0; a float, or a
            0-d tensor (which may require grad: the inflation is then differentiable in it).

    State: ``last [B, 3]`` (the last valid reading; zeros before any) and
    ``held_steps [B]`` (consecutive held samples so far), saved by
    :meth:`state_dict`.
    """

    def __init__(self, rate_sigma: float) -> None:
        value = float(rate_sigma.detach()) if torch.is_tensor(rate_sigma) else float(rate_sigma)
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"rate_sigma must be finite and ≥ 0 (rad/s), got {rate_sigma!r}")
        self.rate_sigma = rate_sigma if torch.is_tensor(rate_sigma) else float(rate_sigma)
        self.last: Tensor | None = None
        self.held_steps: Tensor | None = None

    def step(self, gyro: Tensor, valid: Tensor | None, dt: float) -> tuple[Tensor, Tensor]:
        """The input to propagate with over the interval ending at this sample.

        Args:
            gyro: readings ``[B, 3]`` (rad/s).
            valid: ``[B]`` bool (``None``: all valid).
            dt: the interval (s).

        Returns:
            ``(u [B, 3], angle_variance [B])``: the reading or the held one, and the
            per-axis attitude-angle variance (rad²) to add after this propagation
            (0 for valid samples).
        """
        gyro = torch.as_tensor(gyro)
        if gyro.dim() != 2 or gyro.shape[-1] != 3:
            raise ValueError(f"gyro must have shape [B, 3], got {tuple(gyro.shape)}")
        B = gyro.shape[0]
        valid = torch.ones(B, dtype=torch.bool) if valid is None else torch.as_tensor(valid, dtype=torch.bool).reshape(-1)
        if valid.shape != (B,):
            raise ValueError(f"gyro_valid must have shape [{B}], got {tuple(valid.shape)}")
        if not bool(torch.isfinite(gyro[valid]).all()):
            raise ValueError("valid gyro readings must be finite")
        if self.last is None or self.last.shape != gyro.shape:
            self.last = torch.zeros_like(gyro)
            self.held_steps = torch.zeros(B, dtype=torch.int64)
        assert self.held_steps is not None
        u = torch.where(valid[:, None], gyro, self.last)
        self.last = u.clone()
        self.held_steps = torch.where(valid, torch.zeros_like(self.held_steps), self.held_steps + 1)
        j = self.held_steps.to(gyro.dtype)
        var = torch.where(valid, torch.zeros_like(j), (self.rate_sigma * dt) ** 2 * (2.0 * j - 1.0))
        return u, var

    @staticmethod
    def inflate(mixture: GaussianMixture, angle_variance: Tensor) -> GaussianMixture:
        """Add ``angle_variance / 16`` (MRP units) to the attitude block of every component.

        Args:
            mixture: batch ``[B]``, state ``[p (3), …]``.
            angle_variance: ``[B]`` (rad²).
        """
        n = mixture.state_dim
        diag = torch.zeros(n, dtype=mixture.covs.dtype, device=mixture.covs.device)
        diag[:3] = 1.0 / 16.0
        add = angle_variance.to(mixture.covs)[:, None, None, None] * torch.diag(diag)
        return mixture.replace(covs=mixture.covs + add)

    def state_dict(self) -> dict[str, Any]:
        """The hold's state (for checkpoints)."""
        return {
            "rate_sigma": float(self.rate_sigma),
            "last": None if self.last is None else self.last.clone(),
            "held_steps": None if self.held_steps is None else self.held_steps.clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.rate_sigma = float(state["rate_sigma"])
        self.last = None if state["last"] is None else state["last"].clone()
        self.held_steps = None if state["held_steps"] is None else state["held_steps"].clone()
