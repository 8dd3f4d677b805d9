"""Truth attitude dynamics: quaternion propagation exact for a rate held over a step.

With the body rate ``ω`` (rad/s) held constant over ``(t_k, t_k + Δt]`` the attitude
matrix obeys ``Ċ = −[ω×] C``, so ``C_{k+1} = exp(−[ω×]Δt) C_k``, which in scalar-last
quaternions (``C(q_a ⊗ q_b) = C(q_a) C(q_b)``) is

    q_{k+1} = q(ω Δt) ⊗ q_k,    q(φ) = [sin(|φ|/2) φ/|φ|, cos(|φ|/2)]

(:func:`agsf_torch.rotations.rotvec_to_quat`); the result is renormalised each step.
This is the exact solution of the MRP kinematics ``ṗ = ¼ B(p) ω`` over the step.

Rate profile (**[choice]**): a constant 3-vector, or a callable ``rate(t) → ω`` with
``t [B]`` (s) and ``ω [B, 3]`` (rad/s), written in torch.  A callable profile is held
at its value at the step's midpoint, ``ω_{k+1} = rate(t_k + Δt/2)`` (zero-order hold,
second-order accurate in Δt for a smooth profile); the gyro then measures exactly
this held rate (:mod:`envs.gyro`), so the truth and the measurement model agree.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from agsf_torch.rotations import quat_multiply, rotvec_to_quat

from ._checks import check_real, check_rotation_per_step, check_vector

__all__ = [
    "DEFAULT_OMEGA0",
    "DEFAULT_RATE",
    "RateLike",
    "AttitudeDynamics",
    "check_constant_rate",
    "propagate_quat",
    "propagate_quat_block",
]

DEFAULT_OMEGA0 = 2.0 * math.pi / 100.0
"""ω₀ = 2π/100 rad/s."""
DEFAULT_RATE = (DEFAULT_OMEGA0, DEFAULT_OMEGA0, 0.0)
"""Default truth rate ω₀[1, 1, 0] (rad/s)."""

RateLike = Sequence[float] | Tensor | Callable[[Tensor], Tensor]


def propagate_quat(q: Tensor, omega: Tensor, dt: float) -> Tensor:
    """Exact attitude step for a body rate held over ``dt``: :func:`propagate_quat_block`
    with a block of one step.

    .. math:: q_{k+1} = q(ωΔt) ⊗ q_k / |q(ωΔt) ⊗ q_k|

    Args:
        q: ``[..., 4]`` scalar-last unit quaternions (inertial → body).
        omega: ``[..., 3]`` body rate (rad/s).
        dt: step (s).

    Returns:
        ``[..., 4]``.
    """
    return propagate_quat_block(q, omega[None], dt)[0]


def propagate_quat_block(q: Tensor, omega: Tensor, dt: float) -> Tensor:
    """S consecutive exact attitude steps (the step of :func:`propagate_quat`, written once).

    The step quaternions ``q(ω_j Δt)`` are formed for the whole block, then composed
    in order, renormalising after each product.

    Args:
        q: ``q_k`` ``[..., 4]`` scalar-last unit quaternions (inertial → body).
        omega: body rates held over the S steps ``[S, ..., 3]`` (rad/s).
        dt: step (s).

    Returns:
        ``q_{k+1} … q_{k+S}`` ``[S, ..., 4]``.
    """
    dq = rotvec_to_quat((omega * dt).contiguous())  # [S, ..., 4]
    out = []
    for j in range(dq.shape[0]):
        q = quat_multiply(dq[j], q)
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        out.append(q)
    return torch.stack(out)


def check_constant_rate(owner: str, rate: Any, dt: float) -> tuple[float, float, float]:
    """A constant truth rate (rad/s) as 3 floats, validated for the step Δt (s): 3 finite
    numbers whose rotation per step stays below half a turn (``|ω|·Δt < π``,
    :func:`~envs._checks.check_rotation_per_step`).  Shared by :class:`AttitudeDynamics` and
    :class:`~envs.config.StarTrackerConfig`.

    Raises:
        ValueError: naming ``owner``, ``rate`` and the value.
    """
    vec = check_vector(owner, "rate", rate, 3, unit=" (rad/s)")
    check_rotation_per_step(owner, f"rate {math.hypot(*vec):.6g} rad/s", math.hypot(*vec), dt)
    return vec  # type: ignore[return-value]


class AttitudeDynamics:
    """The truth rate profile and attitude step.

    Args:
        rate: constant body rate (3 finite numbers, rad/s) or a callable
            ``rate(t [B]) -> [B, 3]`` (torch; t in s, rate in rad/s).  Either must turn
            less than half a turn per step, ``|ω|·Δt < π`` (checked on every call of a
            callable profile, before the state it feeds is touched).
        dt: step Δt (s), finite > 0.

    Raises:
        ValueError: naming the field and value of any bad setting.
    """

    def __init__(self, rate: RateLike = DEFAULT_RATE, dt: float = 0.1) -> None:
        self.dt = check_real("AttitudeDynamics", "dt", dt, positive=True)
        self.rate_fn: Callable[[Tensor], Tensor] | None
        if callable(rate) and not isinstance(rate, Tensor):
            self.rate_fn = rate
            self.rate_const = None
        else:
            self.rate_fn = None
            self.rate_const = check_constant_rate("AttitudeDynamics", rate, self.dt)

    def rate(self, t: Tensor) -> Tensor:
        """Body rate at times ``t [B]`` (s) → ``[B, 3]`` (rad/s), dtype/device of ``t``.

        Raises:
            ValueError: if a callable profile returns the wrong shape, non-finite values or a
                rate with ``|ω|·Δt ≥ π`` (naming the rate and the time).
        """
        if self.rate_fn is None:
            w = torch.tensor(self.rate_const, dtype=t.dtype, device=t.device)
            return w.expand(*t.shape, 3)
        w = self.rate_fn(t)
        if not isinstance(w, Tensor) or w.shape != (*t.shape, 3):
            shape = tuple(w.shape) if isinstance(w, Tensor) else type(w).__name__
            raise ValueError(f"AttitudeDynamics: rate(t) must return a tensor of shape {(*t.shape, 3)}, got {shape}")
        if not torch.isfinite(w).all():
            raise ValueError("AttitudeDynamics: rate(t) returned non-finite values")
        norm = torch.linalg.vector_norm(w.detach(), dim=-1)
        if not bool((norm * self.dt < math.pi).all()):
            i = int(torch.argmax(norm.reshape(-1)))  # norm has the shape of t
            fast, at = float(norm.reshape(-1)[i]), float(t.reshape(-1)[i])
            what = f"rate(t) returned {fast:.6g} rad/s at t = {at:.6g} s, which"
            check_rotation_per_step("AttitudeDynamics", what, fast, self.dt)
        return w.to(t.dtype)

    def held_rate(self, t_start: Tensor) -> Tensor:
        """Rate held over ``(t_k, t_k + Δt]``: ``rate(t_k + Δt/2)`` → ``[B, 3]`` (rad/s)."""
        return self.rate(t_start + 0.5 * self.dt)

    def held_rates(
        self, t_start: Sequence[float], batch: int, dtype: torch.dtype = torch.float64, device=None
    ) -> Tensor:
        """Held rates of S consecutive steps for B trajectories: ``[S, B, 3]`` (rad/s).

        Row j is :meth:`held_rate` of ``t_start[j]`` (s) broadcast to the batch; a
        callable profile is called once per step with ``t [B]``, as in :meth:`held_rate`.
        Contiguous.
        """
        if self.rate_fn is None:
            w = torch.tensor(self.rate_const, dtype=dtype, device=device)
            return w.expand(len(t_start), batch, 3).contiguous()
        rows = [self.held_rate(torch.full((batch,), float(t), dtype=dtype, device=device)) for t in t_start]
        return torch.stack(rows)

    def step(self, q: Tensor, omega: Tensor) -> Tensor:
        """:func:`propagate_quat` with this Δt: ``[B, 4], [B, 3] → [B, 4]``."""
        return propagate_quat(q, omega, self.dt)

    def step_block(self, q: Tensor, omega: Tensor) -> Tensor:
        """:func:`propagate_quat_block` with this Δt: ``[B, 4], [S, B, 3] → [S, B, 4]``."""
        return propagate_quat_block(q, omega, self.dt)
