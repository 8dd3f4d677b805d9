"""Gyro gaps: propagate through missing or saturated gyro samples.

The attitude filters are driven by the gyro (the input ``u``).  When a sample is
missing or saturated (``gyro_valid`` false) :class:`GyroHold` substitutes the
last valid reading and inflates the attitude covariance of every component for
the error that the hold makes.  A held reading is off the true rate by its own
noise and by any change of the rate since, ``δω`` with per-axis standard
deviation ``σ_h`` (``rate_sigma``, rad/s); held over ``j`` consecutive steps it
turns the attitude by ``δω · jΔt``, so the angle variance grows by

.. math:: σ_h^2 Δt^2 \\left(j^2 - (j-1)^2\\right) = σ_h^2 Δt^2 (2j - 1)

at the ``j``-th held step (per axis, in the body frame).  In the MRP chart of a component with mean ``p`` the
error angle maps as ``δp = ¼ B(p) δθ`` with ``B Bᵀ = (1 + |p|²)² I``
(:mod:`agsf_torch.filters.multiplicative`), so the MRP covariance grows by that variance times
``(1 + |p|²)² / 16``: 1/16 of it at ``p = 0``, up to 1/4 at ``|p| = 1``.  The default ``σ_h = σ_v / √Δt`` is the noise of one gyro
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

from ..mixture import GaussianMixture

__all__ = ["GyroHold"]


class GyroHold:
    """Hold the last valid gyro reading over gaps, with the matching covariance inflation.

    Args:
        rate_sigma: ``σ_h``, per-axis 1σ error of a held reading (rad/s), ≥ 0; a float, or a
            0-d or ``[B]`` (one per trajectory) tensor, which may require grad: the inflation is then
            differentiable in it.

    State: ``last [B, 3]`` (the last valid reading; zeros before any) and
    ``held_steps [B]`` (consecutive held samples so far), saved by
    :meth:`state_dict`.  One hold follows one run of ``B`` trajectories: a reading of
    another batch size is refused (start a new run with a new hold or :meth:`reset`).
    """

    def __init__(self, rate_sigma: float) -> None:
        value = rate_sigma.detach() if torch.is_tensor(rate_sigma) else torch.tensor(float(rate_sigma))
        if value.dim() > 1 or not bool(torch.isfinite(value).all()) or bool((value < 0).any()):
            raise ValueError(f"rate_sigma must be finite and ≥ 0 (rad/s), a number or [B], got {rate_sigma!r}")
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
        valid = (
            torch.ones(B, dtype=torch.bool, device=gyro.device)
            if valid is None
            else torch.as_tensor(valid, dtype=torch.bool, device=gyro.device).reshape(-1)
        )
        if valid.shape != (B,):
            raise ValueError(f"gyro_valid must have shape [{B}], got {tuple(valid.shape)}")
        if not bool(torch.isfinite(gyro[valid]).all()):
            raise ValueError("valid gyro readings must be finite")
        if self.last is not None and self.last.shape != gyro.shape:
            raise ValueError(
                f"gyro has shape {tuple(gyro.shape)} but this hold follows a run of shape {tuple(self.last.shape)}; "
                "call reset() to start another run"
            )
        if self.last is None:
            self.last = torch.zeros_like(gyro)
            self.held_steps = torch.zeros(B, dtype=torch.int64, device=gyro.device)
        assert self.held_steps is not None
        u = torch.where(valid[:, None], gyro, self.last)
        self.last = u.clone()
        self.held_steps = torch.where(valid, torch.zeros_like(self.held_steps), self.held_steps + 1)
        j = self.held_steps.to(gyro.dtype)
        var = torch.where(valid, torch.zeros_like(j), (self.rate_sigma * dt) ** 2 * (2.0 * j - 1.0))
        return u, var

    @staticmethod
    def inflate(mixture: GaussianMixture, angle_variance: Tensor) -> GaussianMixture:
        """Add the MRP covariance of an isotropic error angle of variance ``angle_variance`` (per axis) to the
        attitude block of every component: ``angle_variance · (1 + |pᵢ|²)² / 16 · I₃`` for the component of mean
        MRP ``pᵢ`` (module docstring; ``T P_δ Tᵀ`` of :mod:`agsf_torch.filters.multiplicative` with
        ``P_δ = angle_variance · I₃``).

        Args:
            mixture: batch ``[B]``, state ``[p (3), …]``.
            angle_variance: ``[B]`` (rad²), finite and ≥ 0 (as :meth:`step` returns it).

        The result is a valid mixture without a new factorisation: adding a positive
        semidefinite diagonal keeps every covariance positive definite.
        """
        angle_variance = torch.as_tensor(angle_variance)
        B = mixture.batch_shape
        if len(B) != 1 or angle_variance.shape != B:
            raise ValueError(
                f"angle_variance must have the mixture's batch shape [B] = {tuple(B)}, got {tuple(angle_variance.shape)}"
            )
        if mixture.state_dim < 3:
            raise ValueError(
                f"the mixture's state must start with the 3 MRP entries, got state dimension {mixture.state_dim}"
            )
        bad = ~torch.isfinite(angle_variance) | (angle_variance < 0)
        if bool(bad.any()):
            k = int(bad.nonzero()[0])
            raise ValueError(
                f"angle_variance must be finite and ≥ 0 (rad²), got {float(angle_variance[k])} at trajectory {k}"
            )
        n = mixture.state_dim
        attitude = torch.zeros(n, dtype=mixture.covs.dtype, device=mixture.covs.device)
        attitude[:3] = 1.0
        scale = (1.0 + mixture.means[..., :3].square().sum(-1)).square() / 16.0  # [B, N]: (1 + |p|²)² / 16
        add = (angle_variance.to(mixture.covs)[:, None] * scale)[..., None, None] * torch.diag(attitude)
        return mixture.replace(covs=mixture.covs + add, validate=False)

    def state_dict(self) -> dict[str, Any]:
        """The hold's state (for checkpoints)."""
        return {
            "rate_sigma": self.rate_sigma.tolist() if torch.is_tensor(self.rate_sigma) else self.rate_sigma,
            "last": None if self.last is None else self.last.clone(),
            "held_steps": None if self.held_steps is None else self.held_steps.clone(),
        }

    def reset(self) -> None:
        """Forget the run (the last reading and the held-step counts)."""
        self.last = None
        self.held_steps = None

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; validated before anything changes.

        Raises:
            ValueError: naming the entry — other keys, ``rate_sigma`` not finite and ≥ 0, ``last`` not a
                finite floating tensor ``[B, 3]``, ``held_steps`` not an integer tensor ``[B]`` ≥ 0,
                or only one of the two given.
        """
        if not isinstance(state, dict) or set(state) != {"rate_sigma", "last", "held_steps"}:
            got = sorted(state) if isinstance(state, dict) else type(state).__name__
            raise ValueError(f"GyroHold state must have the keys ['held_steps', 'last', 'rate_sigma'], got {got}")
        sigma, last, held = state["rate_sigma"], state["last"], state["held_steps"]
        values = sigma if isinstance(sigma, list) else [sigma]
        if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < math.inf for v in values):
            raise ValueError(
                f"GyroHold state 'rate_sigma' must be a finite number ≥ 0 or a list of them, got {sigma!r}"
            )
        if (last is None) != (held is None):
            raise ValueError("GyroHold state 'last' and 'held_steps' must both be None or both be tensors")
        if last is not None:
            if not torch.is_tensor(last) or not last.is_floating_point() or last.dim() != 2 or last.shape[-1] != 3:
                got = tuple(last.shape) if torch.is_tensor(last) else type(last).__name__
                raise ValueError(f"GyroHold state 'last' must be a floating tensor [B, 3], got {got}")
            if not bool(torch.isfinite(last).all()):
                raise ValueError("GyroHold state 'last' must be finite")
            B = last.shape[0]
            if not torch.is_tensor(held) or held.is_floating_point() or held.dtype == torch.bool or held.shape != (B,):
                got = f"{held.dtype} {tuple(held.shape)}" if torch.is_tensor(held) else type(held).__name__
                raise ValueError(f"GyroHold state 'held_steps' must be an integer tensor [{B}], got {got}")
            if bool((held < 0).any()):
                raise ValueError("GyroHold state 'held_steps' must be ≥ 0")
        self.rate_sigma = torch.tensor(sigma, dtype=torch.float64) if isinstance(sigma, list) else float(sigma)
        self.last = None if last is None else last.clone()
        self.held_steps = None if held is None else held.to(torch.int64).clone()
