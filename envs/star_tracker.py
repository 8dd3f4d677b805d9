"""Star-tracker attitude environments (gymnasium): single and natively batched.

One step is one gyro period Δt.  Timeline (**[choice]**, documented):

* ``reset`` returns the observation at ``t_0 = 0``: a gyro reading with the bias
  held (``ω(0) + b_0 + noise``, which closes no interval; filters normally ignore
  it) and **no star frame** (``star_mask`` all false).
* ``step(action)`` scores the action — the estimate of the attitude at the time of
  the *last* observation, ``t_k`` — with ``reward = −θ(action, p_k)`` (rad, the
  rotation angle between the two attitudes; any MRP, shadow sets included, is
  accepted), then advances the truth over ``(t_k, t_{k+1}]`` with the held rate
  ``ω_{k+1}`` (:mod:`envs.dynamics`) and returns the observation at ``t_{k+1}``:
  the gyro reading ``ω̃_{k+1}`` of that interval (:mod:`envs.gyro`) — the one to
  propagate a filter from ``t_k`` to ``t_{k+1}`` — and, when ``k+1`` is a multiple of
  ``star_period/Δt``, a star frame taken at ``t_{k+1}``.  So with the defaults the
  first star frame arrives at t = 1 s, the paper's setting in which the filters
  first propagate a wide prior.
* ``info`` carries the truth at the new time: ``truth_mrp`` (p_{k+1}, short set
  ``|p| ≤ 1``), ``truth_bias`` (b_{k+1}, rad/s) and ``truth_rate`` (ω_{k+1}, the rate
  held over the step just taken, rad/s); ``reset``'s info the same at t_0 (rate ω(0)).
* The episode is truncated (never terminated) after ``max_steps`` steps.

Randomness is counter-based (:mod:`envs.random`): trajectory draws are pure
functions of ``(episode seed, step index, stream)``.  ``reset(seed=s)`` of the vector
env gives trajectory i the episode seed ``s + i``, which is exactly what the single
env gets from ``reset(seed=s + i)``: the trajectories are bit-identical.  An
unseeded reset continues deterministically from the previous episode seed
(``next = splitmix(seed) mod 2⁶²``, the same in both envs), or, before any seeded
reset, takes a fresh seed from the env's ``np_random``.

The vector env (:class:`StarTrackerAttitudeVectorEnv`) runs all B trajectories as one
tensor program and returns torch tensors; all trajectories share the step counter,
so they truncate together and are reset together on the next ``step`` call
(``AutoresetMode.NEXT_STEP``: that call ignores the actions and returns the reset
observation with zero reward).  :meth:`StarTrackerAttitudeVectorEnv.simulate` runs a
whole trajectory batch without actions for Monte Carlo runners.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from torch import Tensor

from agsf_torch.rotations import (
    mrp_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_to_dcm,
    quat_to_mrp,
    rotvec_to_quat,
)

from ._checks import check_real
from .camera import NOISE_MODES, StarCamera
from .catalog import DEFAULT_MAX_MAGNITUDE, StarCatalog
from .dynamics import DEFAULT_RATE, AttitudeDynamics, RateLike
from .faults import SensorFault, apply_gyro_faults, apply_star_faults, parse_faults
from .gyro import DEFAULT_INITIAL_BIAS, DEFAULT_SIGMA_U, DEFAULT_SIGMA_V, Gyro
from .random import CounterKey, as_int64, counter_normal, random_bits

__all__ = [
    "StarTrackerConfig",
    "StarTrackerSimulator",
    "StarTrackerAttitudeEnv",
    "StarTrackerAttitudeVectorEnv",
    "attitude_error_angle_elementwise",
    "STREAM_INITIAL_ATTITUDE",
    "STREAM_GYRO_RATE_NOISE",
    "STREAM_GYRO_BIAS_WALK",
    "STREAM_STAR_NOISE",
    "STREAM_NEXT_SEED",
]

STREAM_INITIAL_ATTITUDE = 1
"""Counter-RNG stream of the random initial attitude (step 0, 4 normals)."""
STREAM_GYRO_RATE_NOISE = 2
"""Stream of the gyro measurement noise N_v (step k, 3 normals)."""
STREAM_GYRO_BIAS_WALK = 3
"""Stream of the bias random walk N_u (step k, 3 normals)."""
STREAM_STAR_NOISE = 4
"""Stream of the star-camera noise (step k, M×3 normals)."""
STREAM_NEXT_SEED = 5
"""Stream deriving the next episode's seed on an unseeded reset."""

_SEED_MASK = (1 << 62) - 1
_BLOCK_ELEMENTS = 1 << 20  # simulate(): noise draws per block of time steps


# ============================================================================ config
def _positive(name: str, value: Any) -> float:
    return check_real("StarTrackerConfig", name, value, positive=True)


def _nonnegative(name: str, value: Any) -> float:
    return check_real("StarTrackerConfig", name, value)


def _count(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer, float)):
        raise ValueError(f"StarTrackerConfig: {name} must be an integer ≥ 1, got {value!r}")
    if isinstance(value, float) and (not math.isfinite(value) or value != int(value)):
        raise ValueError(f"StarTrackerConfig: {name} must be an integer ≥ 1, got {value!r}")
    if int(value) < 1:
        raise ValueError(f"StarTrackerConfig: {name} must be an integer ≥ 1, got {value!r}")
    return int(value)


def _finite_tuple(name: str, value: Any, n: int, scalar_ok: bool) -> tuple[float, ...]:
    if isinstance(value, Tensor):
        value = value.detach().cpu().tolist()
    if scalar_ok and isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool):
        value = (value,) * n
    try:
        vec = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"StarTrackerConfig: {name} must be {n} numbers, got {value!r}") from None
    if len(vec) != n or not all(math.isfinite(v) for v in vec):
        raise ValueError(f"StarTrackerConfig: {name} must be {n} finite numbers, got {value!r}")
    return vec


@dataclass(frozen=True)
class StarTrackerConfig:
    """Configuration of the star-tracker attitude environment (validated on creation).

    Attributes:
        dt: gyro period Δt (s), > 0.  One env step.
        star_period: time between star frames (s), a positive integer multiple of
            ``dt`` (to 1e-9 relative).  Frames at ``t = j·star_period``, j ≥ 1 (none at t = 0).
        sigma_v: gyro angle random walk (rad/s^½), ≥ 0.
        sigma_u: gyro rate random walk (rad/s^{3/2}), ≥ 0.
        initial_bias: ``b_0`` (rad/s), scalar (every axis) or 3 numbers; default 0.1 deg/hr.
        sigma_s: star-camera noise σ_s (rad per axis), ≥ 0.
        fov_deg: full field of view (deg), number or ``(x, y)``, each in (0, 180).
        focal_length: f (m), > 0.
        max_stars: M, stars reported per frame, ≥ 1.
        max_magnitude: Hipparcos magnitude cut (finite); must leave at least one star.
        star_noise: ``"focal_plane"`` or ``"unit_vector"`` (:mod:`envs.camera`).
        principal_point: ``(x₀, y₀)`` (m).
        rate: truth body rate (rad/s): 3 numbers or a callable ``rate(t [B]) -> [B, 3]``.
        initial_attitude: ``"random"`` (uniform on SO(3), from the episode seed) or an
            MRP (3 numbers).
        max_steps: episode length in steps, ≥ 1.
        faults: injected sensor faults (:mod:`envs.faults`): :class:`~envs.faults.SensorFault`
            objects or dicts such as ``{"kind": "star_outage", "start": 60, "end": 180}``.
    """

    dt: float = 0.1
    star_period: float = 1.0
    sigma_v: float = DEFAULT_SIGMA_V
    sigma_u: float = DEFAULT_SIGMA_U
    initial_bias: Any = DEFAULT_INITIAL_BIAS
    sigma_s: float = 10e-6
    fov_deg: Any = (8.0, 8.0)
    focal_length: float = 0.065
    max_stars: int = 5
    max_magnitude: float = DEFAULT_MAX_MAGNITUDE
    star_noise: str = "focal_plane"
    principal_point: Any = (0.0, 0.0)
    rate: RateLike = field(default=DEFAULT_RATE)
    initial_attitude: Any = "random"
    max_steps: int = 1000
    faults: Any = ()

    def __post_init__(self) -> None:
        put = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        put("dt", _positive("dt", self.dt))
        put("star_period", _positive("star_period", self.star_period))
        ratio = self.star_period / self.dt
        n = round(ratio)
        if n < 1 or abs(ratio - n) > 1e-9 * max(1.0, ratio):
            raise ValueError(
                f"StarTrackerConfig: star_period must be a positive integer multiple of dt={self.dt}, "
                f"got {self.star_period!r}"
            )
        put("sigma_v", _nonnegative("sigma_v", self.sigma_v))
        put("sigma_u", _nonnegative("sigma_u", self.sigma_u))
        put("initial_bias", _finite_tuple("initial_bias", self.initial_bias, 3, True))
        put("sigma_s", _nonnegative("sigma_s", self.sigma_s))
        fov = _finite_tuple("fov_deg", self.fov_deg, 2, True)
        for v in fov:
            if v <= 0.0 or v >= 180.0:
                raise ValueError(f"StarTrackerConfig: fov_deg must be in (0, 180) degrees, got {self.fov_deg!r}")
        put("fov_deg", fov)
        put("focal_length", _positive("focal_length", self.focal_length))
        put("max_stars", _count("max_stars", self.max_stars))
        try:
            mag = float(self.max_magnitude)
        except (TypeError, ValueError):
            raise ValueError(f"StarTrackerConfig: max_magnitude must be a number, got {self.max_magnitude!r}") from None
        if not math.isfinite(mag):
            raise ValueError(f"StarTrackerConfig: max_magnitude must be finite, got {self.max_magnitude!r}")
        put("max_magnitude", mag)
        if self.star_noise not in NOISE_MODES:
            raise ValueError(f"StarTrackerConfig: star_noise must be one of {NOISE_MODES}, got {self.star_noise!r}")
        put("principal_point", _finite_tuple("principal_point", self.principal_point, 2, False))
        if not callable(self.rate) or isinstance(self.rate, Tensor):
            put("rate", _finite_tuple("rate", self.rate, 3, False))
        if isinstance(self.initial_attitude, str):
            if self.initial_attitude != "random":
                raise ValueError(
                    f"StarTrackerConfig: initial_attitude must be 'random' or an MRP (3 numbers), "
                    f"got {self.initial_attitude!r}"
                )
        else:
            put("initial_attitude", _finite_tuple("initial_attitude", self.initial_attitude, 3, False))
        put("max_steps", _count("max_steps", self.max_steps))
        try:
            put("faults", parse_faults(self.faults))
        except ValueError as exc:
            raise ValueError(f"StarTrackerConfig: {exc}") from None

    @property
    def steps_per_star_frame(self) -> int:
        """``star_period / dt`` as an int."""
        return int(round(self.star_period / self.dt))

    @classmethod
    def from_overrides(cls, config: "StarTrackerConfig | None" = None, **overrides: Any) -> "StarTrackerConfig":
        """``config`` (default: defaults) with fields replaced by ``overrides``.

        Raises:
            ValueError: for an unknown field name or an invalid value.
        """
        base = config if config is not None else cls()
        if not isinstance(base, StarTrackerConfig):
            raise ValueError(f"config must be a StarTrackerConfig, got {type(base).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise ValueError(f"StarTrackerConfig: unknown field(s) {unknown}; valid fields: {sorted(names)}")
        return dataclasses.replace(base, **overrides) if overrides else base


@lru_cache(maxsize=8)
def _hipparcos(max_magnitude: float) -> StarCatalog:
    return StarCatalog.from_hipparcos(max_magnitude)


def attitude_error_angle_elementwise(p_a: Tensor, p_b: Tensor) -> Tensor:
    """Rotation angle (rad, in [0, π]) between two MRP attitudes, ``[..., 3] → [...]``.

    .. math:: θ = 2 \\arctan(|δq_v| / |δq_4|),\\quad δq = q(p_a) ⊗ q(p_b)^{-1}

    Same value as :func:`agsf_torch.rotations.attitude_error_angle`, written with
    elementwise operations only so that a trajectory's result does not depend on
    the batch it is computed in (torch's vectorised ``atan2`` does).
    """
    dq = quat_multiply(mrp_to_quat(p_a), quat_conjugate(mrp_to_quat(p_b)))
    x, y, z, w = dq.unbind(-1)
    n = torch.sqrt(x * x + y * y + z * z)
    return 2.0 * torch.atan((n / w.abs()).contiguous())


# ============================================================================ core
class StarTrackerSimulator:
    """The batched simulation behind both environments (torch, float64).

    Args:
        config: a :class:`StarTrackerConfig`.
        num_envs: B ≥ 1.
        device: torch device of every tensor.

    State after :meth:`reset` / :meth:`advance`: ``step_index`` k (shared),
    ``q`` ``[B, 4]`` truth quaternion, ``bias`` ``[B, 3]`` (rad/s), ``rate`` ``[B, 3]``
    (rad/s), ``seeds`` ``[B]`` int64 episode seeds.
    """

    def __init__(self, config: StarTrackerConfig, num_envs: int, device: torch.device | str = "cpu") -> None:
        if isinstance(num_envs, bool) or int(num_envs) != num_envs or int(num_envs) < 1:
            raise ValueError(f"num_envs must be an integer ≥ 1, got {num_envs!r}")
        self.config = config
        self.num_envs = int(num_envs)
        self.device = torch.device(device)
        self.dtype = torch.float64
        self.gyro = Gyro(config.sigma_v, config.sigma_u, config.dt, config.initial_bias)
        self.dynamics = AttitudeDynamics(config.rate, config.dt)
        catalog = _hipparcos(config.max_magnitude)
        if self.device.type != "cpu":
            catalog = StarCatalog(
                catalog.ids.numpy(), catalog.ra.numpy(), catalog.dec.numpy(), catalog.magnitude.numpy(),
                max_magnitude=catalog.max_magnitude, device=self.device,
            )
        self.camera = StarCamera(
            catalog,
            fov_deg=config.fov_deg,
            focal_length=config.focal_length,
            max_stars=config.max_stars,
            sigma=config.sigma_s,
            noise=config.star_noise,
            principal_point=config.principal_point,
        )
        self.step_index = 0
        self.seeds: Tensor | None = None
        self.q: Tensor | None = None
        self.bias: Tensor | None = None
        self.rate: Tensor | None = None
        self.last_gyro: Tensor | None = None  # fault-free reading of the last step

    # --------------------------------------------------------------- checkpoints
    _STATE = ("seeds", "q", "bias", "rate", "last_gyro")

    def state_dict(self) -> dict[str, Any]:
        """The simulation's full state (tensors and the step index); with the counter-based
        random numbers this is everything a bit-identical continuation needs."""
        state: dict[str, Any] = {"step_index": int(self.step_index)}
        for key in self._STATE:
            value = getattr(self, key)
            state[key] = None if value is None else value.clone()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; shapes must match this simulator's batch."""
        for key in self._STATE:
            value = state[key]
            if value is not None and value.shape[0] != self.num_envs:
                raise ValueError(f"state {key!r} has batch {value.shape[0]}, this simulator {self.num_envs}")
        self.step_index = int(state["step_index"])
        for key in self._STATE:
            value = state[key]
            setattr(self, key, None if value is None else value.to(self.device).clone())

    # ------------------------------------------------------------------ helpers
    def _time(self, k: int) -> float:
        return k * self.config.dt

    def _empty_stars(self) -> tuple[Tensor, Tensor, Tensor]:
        m, b = self.config.max_stars, self.num_envs
        z = torch.zeros(b, m, 3, dtype=self.dtype, device=self.device)
        return z, z.clone(), torch.zeros(b, m, dtype=torch.bool, device=self.device)

    def is_star_step(self, k: int) -> bool:
        """Whether step k (time k·Δt) carries a star frame: ``k ≥ 1`` and ``k % (star_period/Δt) = 0``."""
        return k >= 1 and k % self.config.steps_per_star_frame == 0

    def _obs(self, gyro: Tensor, k: int, stars: tuple[Tensor, Tensor, Tensor]) -> dict[str, Tensor]:
        t = torch.tensor(self._time(k), dtype=self.dtype, device=self.device)
        gyro, valid = apply_gyro_faults(self.config.faults, gyro, t)
        if self.config.faults and bool(stars[2].any()):
            stars = apply_star_faults(self.config.faults, self.camera.catalog.r, *stars, t)
        return {
            "gyro": gyro,
            "gyro_valid": valid[:, None],
            "star_body": stars[0],
            "star_inertial": stars[1],
            "star_mask": stars[2],
            "time": torch.full((self.num_envs, 1), self._time(k), dtype=self.dtype, device=self.device),
        }

    def _info(self) -> dict[str, Tensor]:
        assert self.q is not None and self.bias is not None and self.rate is not None
        return {"truth_mrp": quat_to_mrp(self.q), "truth_bias": self.bias.clone(), "truth_rate": self.rate.clone()}

    def truth_mrp(self) -> Tensor:
        """Current truth MRP ``[B, 3]`` (short set)."""
        assert self.q is not None, "call reset() first"
        return quat_to_mrp(self.q)

    def star_frame(self, q: Tensor, seeds: Tensor, k: Tensor | int):
        """Star frame of attitudes ``q [..., 4]`` with noise key ``(seeds [...], k, STREAM_STAR_NOISE)``."""
        return self.camera.observe(quat_to_dcm(q), CounterKey(seeds, k, STREAM_STAR_NOISE))

    # ------------------------------------------------------------------ API
    def reset(self, seeds: Tensor) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """Start episodes with int64 seeds ``[B]``; returns ``(obs, info)`` at t = 0."""
        cfg = self.config
        b = self.num_envs
        seeds = seeds.to(device=self.device, dtype=torch.int64).reshape(b)
        self.seeds = seeds
        self.step_index = 0
        if cfg.initial_attitude == "random":
            z = counter_normal(seeds, 0, STREAM_INITIAL_ATTITUDE, (4,), dtype=self.dtype)
            q = z / torch.linalg.vector_norm(z, dim=-1, keepdim=True)
        else:
            p0 = torch.tensor(cfg.initial_attitude, dtype=self.dtype, device=self.device)
            q = mrp_to_quat(p0).expand(b, 4).clone()
        self.q = q
        self.bias = self.gyro.initial_bias_tensor((b,), self.dtype, self.device)
        t0 = torch.zeros(b, dtype=self.dtype, device=self.device)
        self.rate = self.dynamics.rate(t0).expand(b, 3).clone()
        n_v = counter_normal(seeds, 0, STREAM_GYRO_RATE_NOISE, (3,), dtype=self.dtype)
        gyro = self.gyro.read(self.rate, self.bias, n_v)
        self.last_gyro = gyro
        return self._obs(gyro, 0, self._empty_stars()), self._info()

    def _advance_truth(self) -> Tensor:
        """Advance truth and gyro by one step; returns the gyro reading ``[B, 3]``."""
        assert self.q is not None and self.bias is not None and self.seeds is not None
        k = self.step_index
        t_start = torch.full((self.num_envs,), self._time(k), dtype=self.dtype, device=self.device)
        omega = self.dynamics.held_rate(t_start).expand(self.num_envs, 3).contiguous()
        self.q = self.dynamics.step(self.q, omega)
        n_v = counter_normal(self.seeds, k + 1, STREAM_GYRO_RATE_NOISE, (3,), dtype=self.dtype)
        n_u = counter_normal(self.seeds, k + 1, STREAM_GYRO_BIAS_WALK, (3,), dtype=self.dtype)
        gyro, self.bias = self.gyro.step(omega, self.bias, n_v, n_u)
        self.rate = omega
        self.step_index = k + 1
        self.last_gyro = gyro
        return gyro

    def advance(self) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """One step (Δt) for every trajectory; returns ``(obs, info)`` at the new time."""
        gyro = self._advance_truth()
        k = self.step_index
        if self.is_star_step(k):
            assert self.q is not None and self.seeds is not None
            stars = tuple(self.star_frame(self.q, self.seeds, k))
        else:
            stars = self._empty_stars()
        return self._obs(gyro, k, stars), self._info()  # type: ignore[arg-type]

    def reward(self, action: Tensor) -> Tensor:
        """``−θ(action, p_k)`` (rad) against the current truth; ``action [B, 3]`` → ``[B]``."""
        assert self.q is not None, "call reset() first"
        return -attitude_error_angle_elementwise(action, quat_to_mrp(self.q))

    def next_seeds(self) -> Tensor:
        """Seeds of the next episode derived from the current ones: ``[B]`` int64 in [0, 2⁶²)."""
        assert self.seeds is not None
        return random_bits(self.seeds, 0, STREAM_NEXT_SEED, ()) & _SEED_MASK

    def simulate(self, num_steps: int) -> dict[str, Tensor]:
        """Advance ``num_steps`` steps from the current state, stacking everything.

        The time loop only composes quaternions and accumulates the bias; the noise
        draws and gyro readings are formed in blocks of steps, and the star frames in
        blocks of frames after the loop (batched camera calls), all with the same
        noise keys and elementwise operations as :meth:`advance`, so the numbers
        equal step-by-step stepping bit for bit.  Temporaries stay at ~2²⁰ elements
        per tensor besides the outputs.

        Returns:
            a dict, batch-first (``T = num_steps``, ``F`` star frames among steps
            ``k₀+1 … k₀+T``, ``k₀`` the step index on entry):
            ``time [T+1]`` (s), ``step [T+1]`` (int64), ``gyro [B, T+1, 3]`` (rad/s; index 0
            is the reading on entry, i.e. the reset reading after a reset), ``gyro_valid
            [B, T+1]`` (bool, false for missing or saturated samples, :mod:`envs.faults`),
            ``truth_mrp / truth_bias / truth_rate [B, T+1, 3]``, ``star_steps [F]``
            (int64 step indices), ``star_time [F]`` (s), ``star_body / star_inertial
            [B, F, M, 3]``, ``star_mask [B, F, M]``.
        """
        assert self.q is not None and self.seeds is not None and self.bias is not None
        assert self.rate is not None and self.last_gyro is not None
        if num_steps < 0:
            raise ValueError(f"num_steps must be ≥ 0, got {num_steps}")
        k0, b, dt, m = self.step_index, self.num_envs, self.config.dt, self.config.max_stars
        opts = dict(dtype=self.dtype, device=self.device)
        mrp_out = torch.empty(b, num_steps + 1, 3, **opts)
        bias_out = torch.empty(b, num_steps + 1, 3, **opts)
        rate_out = torch.empty(b, num_steps + 1, 3, **opts)
        gyro_out = torch.empty(b, num_steps + 1, 3, **opts)
        q, bias = self.q, self.bias
        mrp_out[:, 0], bias_out[:, 0] = quat_to_mrp(q), bias
        rate_out[:, 0], gyro_out[:, 0] = self.rate, self.last_gyro
        steps = torch.arange(k0, k0 + num_steps + 1, device=self.device)
        star_cols = [j for j in range(1, num_steps + 1) if self.is_star_step(k0 + j)]
        star_steps = steps[star_cols]
        n_frames = len(star_cols)
        frame_of = {j: f for f, j in enumerate(star_cols)}
        q_star = torch.empty(b, n_frames, 4, **opts)
        # Blocks of time steps bound the memory of the temporaries; inside a block the
        # tensors are time-major [S, B, ...].  The operations are those of advance().
        block = max(1, _BLOCK_ELEMENTS // b)
        for j0 in range(0, num_steps, block):
            j1 = min(num_steps, j0 + block)
            nxt = steps[j0 + 1 : j1 + 1]  # step indices k+1 of the block
            n_v = counter_normal(self.seeds[None, :], nxt[:, None], STREAM_GYRO_RATE_NOISE, (3,), dtype=self.dtype)
            n_u = counter_normal(self.seeds[None, :], nxt[:, None], STREAM_GYRO_BIAS_WALK, (3,), dtype=self.dtype)
            omegas = torch.stack(
                [
                    self.dynamics.held_rate(torch.full((b,), self._time(k), **opts)).expand(b, 3)
                    for k in range(k0 + j0, k0 + j1)
                ]
            ).contiguous()
            dq = rotvec_to_quat((omegas * dt).contiguous())  # [S, B, 4]
            quats, biases = [], [bias]
            for j in range(j1 - j0):
                q = quat_multiply(dq[j], q)
                q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
                bias = bias + self.gyro.bias_step_std * n_u[j]
                quats.append(q)
                biases.append(bias)
                f = frame_of.get(j0 + j + 1)
                if f is not None:
                    q_star[:, f] = q
            b_blk = torch.stack(biases)  # [S+1, B, 3]
            measured = omegas + 0.5 * (b_blk[1:] + b_blk[:-1]) + self.gyro.rate_noise_std * n_v
            mrp_out[:, j0 + 1 : j1 + 1] = quat_to_mrp(torch.stack(quats)).transpose(0, 1)
            bias_out[:, j0 + 1 : j1 + 1] = b_blk[1:].transpose(0, 1)
            rate_out[:, j0 + 1 : j1 + 1] = omegas.transpose(0, 1)
            gyro_out[:, j0 + 1 : j1 + 1] = measured.transpose(0, 1)
        self.q, self.bias, self.step_index = q, bias, k0 + num_steps
        self.rate, self.last_gyro = rate_out[:, -1].clone(), gyro_out[:, -1].clone()

        sb = torch.zeros(b, n_frames, m, 3, **opts)
        si = torch.zeros(b, n_frames, m, 3, **opts)
        sm = torch.zeros(b, n_frames, m, dtype=torch.bool, device=self.device)
        fblock = max(1, _BLOCK_ELEMENTS // (4 * b * m))
        for f0 in range(0, n_frames, fblock):
            cols = star_cols[f0 : f0 + fblock]
            frame = self.star_frame(
                q_star[:, f0 : f0 + len(cols)], self.seeds[:, None], star_steps[None, f0 : f0 + len(cols)]
            )
            sb[:, f0 : f0 + len(cols)], si[:, f0 : f0 + len(cols)], sm[:, f0 : f0 + len(cols)] = frame
        star_time = star_steps.to(self.dtype) * self.config.dt
        if self.config.faults and n_frames:
            sb, si, sm = apply_star_faults(self.config.faults, self.camera.catalog.r, sb, si, sm, star_time[None, :])
        times = torch.tensor([self._time(int(k)) for k in steps.tolist()], dtype=self.dtype, device=self.device)
        gyro_out, gyro_valid = apply_gyro_faults(self.config.faults, gyro_out, times[None, :])
        out = {
            "time": steps.to(self.dtype) * self.config.dt,
            "step": steps,
            "gyro": gyro_out,
            "gyro_valid": gyro_valid,
            "truth_mrp": mrp_out,
            "truth_bias": bias_out,
            "truth_rate": rate_out,
            "star_steps": star_steps,
            "star_time": star_time,
            "star_body": sb,
            "star_inertial": si,
            "star_mask": sm,
        }
        return out


# ============================================================================ spaces
def _single_spaces(config: StarTrackerConfig) -> tuple[spaces.Dict, spaces.Box]:
    m = config.max_stars
    obs = spaces.Dict(
        {
            "gyro": spaces.Box(-np.inf, np.inf, (3,), dtype=np.float64),
            "gyro_valid": spaces.Box(0, 1, (1,), dtype=np.bool_),
            "star_body": spaces.Box(-1.0, 1.0, (m, 3), dtype=np.float64),
            "star_inertial": spaces.Box(-1.0, 1.0, (m, 3), dtype=np.float64),
            "star_mask": spaces.Box(0, 1, (m,), dtype=np.bool_),
            "time": spaces.Box(0.0, config.max_steps * config.dt, (1,), dtype=np.float64),
        }
    )
    # Short-set MRPs lie in the unit ball; shadow MRPs outside the box are accepted too.
    act = spaces.Box(-1.0, 1.0, (3,), dtype=np.float64)
    return obs, act


def _seed_tensor(seed: Any, num_envs: int) -> Tensor:
    """Episode seeds ``[B]``: ``seed + i`` for an int, or one per env from a sequence."""
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        return torch.tensor(as_int64(int(seed)), dtype=torch.int64) + torch.arange(num_envs, dtype=torch.int64)
    vals = [int(s) for s in (seed.tolist() if isinstance(seed, (Tensor, np.ndarray)) else seed)]
    if len(vals) != num_envs:
        raise ValueError(f"seed must be an int or {num_envs} ints, got {len(vals)} values")
    return torch.tensor([as_int64(v) for v in vals], dtype=torch.int64)


# ============================================================================ single env
class StarTrackerAttitudeEnv(gym.Env):
    """Single-trajectory star-tracker attitude environment (numpy observations).

    Args:
        config: :class:`StarTrackerConfig` (default: defaults).
        render_mode: must be ``None`` (no rendering).
        **overrides: config fields to replace, e.g. ``dt=0.05, max_stars=8``.

    Observation (dict of numpy arrays): ``gyro [3]`` (rad/s), ``gyro_valid [1]`` (bool:
    false for a missing or saturated sample, see :mod:`envs.faults`), ``star_body [M, 3]``,
    ``star_inertial [M, 3]`` (unit vectors, zeros where masked), ``star_mask [M]``
    (bool), ``time [1]`` (s).  Action: MRP estimate ``[3]``.  Reward: ``−θ`` (rad).
    Info: ``truth_mrp [3]``, ``truth_bias [3]`` (rad/s), ``truth_rate [3]`` (rad/s).
    See the module docstring for the timeline.
    """

    metadata = {"render_modes": []}

    def __init__(self, config: StarTrackerConfig | None = None, render_mode: str | None = None, **overrides: Any):
        if render_mode is not None:
            raise ValueError(f"render_mode must be None (no rendering), got {render_mode!r}")
        self.render_mode = None
        self.config = StarTrackerConfig.from_overrides(config, **overrides)
        self.sim = StarTrackerSimulator(self.config, 1)
        self.observation_space, self.action_space = _single_spaces(self.config)
        self._episode_seed: Tensor | None = None

    @staticmethod
    def _np(d: dict[str, Tensor]) -> dict[str, np.ndarray]:
        return {k: v[0].cpu().numpy().copy() for k, v in d.items()}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode; ``seed`` gives the episode seed (see the module docstring)."""
        super().reset(seed=seed)
        if seed is not None:
            seeds = _seed_tensor(int(seed), 1)
        elif self._episode_seed is not None:
            seeds = self.sim.next_seeds()
        else:
            seeds = torch.tensor([int(self.np_random.integers(0, 1 << 62))], dtype=torch.int64)
        self._episode_seed = seeds
        obs, info = self.sim.reset(seeds)
        return self._np(obs), self._np(info)

    def step(self, action):
        """Score ``action`` (MRP ``[3]``) against the truth at the current time, then advance Δt."""
        if self.sim.q is None:
            raise RuntimeError("call reset() before step()")
        if self.sim.step_index >= self.config.max_steps:
            raise RuntimeError("the episode is over (truncated); call reset()")
        a = torch.as_tensor(np.asarray(action, dtype=np.float64), device=self.sim.device)
        if a.shape != (3,):
            raise ValueError(f"action must be an MRP of shape (3,), got shape {tuple(a.shape)}")
        if not torch.isfinite(a).all():
            raise ValueError(f"action must be finite, got {np.asarray(action)!r}")
        reward = float(self.sim.reward(a[None])[0])
        obs, info = self.sim.advance()
        truncated = self.sim.step_index >= self.config.max_steps
        return self._np(obs), reward, False, truncated, self._np(info)

    def render(self) -> None:
        """No rendering (``render_mode`` is always ``None``)."""
        return None


# ============================================================================ vector env
class StarTrackerAttitudeVectorEnv(VectorEnv):
    """Natively batched star-tracker environment: B trajectories, one tensor program.

    Args:
        num_envs: B ≥ 1.
        config: :class:`StarTrackerConfig` (default: defaults).
        device: torch device (default CPU).
        render_mode: must be ``None``.
        **overrides: config fields to replace.

    Observations, rewards, terminations, truncations and infos are torch tensors with
    a leading batch dimension B (the keys of the single env).  Actions: ``[B, 3]``
    torch tensor or numpy array.  ``metadata["autoreset_mode"] = NEXT_STEP``.
    """

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 1,
        config: StarTrackerConfig | None = None,
        device: torch.device | str = "cpu",
        render_mode: str | None = None,
        **overrides: Any,
    ) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode must be None (no rendering), got {render_mode!r}")
        self.render_mode = None
        self.config = StarTrackerConfig.from_overrides(config, **overrides)
        self.sim = StarTrackerSimulator(self.config, num_envs, device)
        self.num_envs = self.sim.num_envs
        self.device = self.sim.device
        self.single_observation_space, self.single_action_space = _single_spaces(self.config)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._seeded = False
        self._needs_reset = False

    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict[str, Any] | None = None):
        """Start B episodes: trajectory i gets seed ``seed + i`` (or ``seed[i]`` for a sequence).

        Returns:
            ``(obs, info)``: dicts of ``[B, ...]`` torch tensors at t = 0.
        """
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            super().reset(seed=int(seed))
        if seed is not None:
            seeds = _seed_tensor(seed, self.num_envs)
        elif self._seeded:
            seeds = self.sim.next_seeds()
        else:
            base = int(self.np_random.integers(0, 1 << 62))
            seeds = _seed_tensor(base, self.num_envs)
        self._seeded = True
        self._needs_reset = False
        return self.sim.reset(seeds)

    def state_dict(self) -> dict[str, Any]:
        """Checkpointable state: the simulator's plus the episode bookkeeping."""
        return {"sim": self.sim.state_dict(), "seeded": self._seeded, "needs_reset": self._needs_reset}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (a resumed run continues bit for bit)."""
        self.sim.load_state_dict(state["sim"])
        self._seeded = bool(state["seeded"])
        self._needs_reset = bool(state["needs_reset"])

    def _action_tensor(self, actions: Any) -> Tensor:
        a = torch.as_tensor(actions, dtype=torch.float64, device=self.device)
        if a.shape != (self.num_envs, 3):
            raise ValueError(f"actions must have shape ({self.num_envs}, 3), got {tuple(a.shape)}")
        if not torch.isfinite(a).all():
            raise ValueError("actions must be finite")
        return a

    def step(self, actions: Any):
        """Score the actions against the truth at the current time, then advance Δt.

        Args:
            actions: MRP estimates ``[B, 3]`` (torch or numpy).

        Returns:
            ``(obs, reward [B], terminated [B], truncated [B], info)`` as torch tensors.
        """
        if self.sim.q is None:
            raise RuntimeError("call reset() before step()")
        b = self.num_envs
        false = torch.zeros(b, dtype=torch.bool, device=self.device)
        if self._needs_reset:  # NEXT_STEP autoreset: all trajectories ended together
            obs, info = self.reset()
            return obs, torch.zeros(b, dtype=torch.float64, device=self.device), false, false.clone(), info
        a = self._action_tensor(actions)
        reward = self.sim.reward(a)
        obs, info = self.sim.advance()
        done = self.sim.step_index >= self.config.max_steps
        self._needs_reset = done
        truncated = torch.full((b,), done, dtype=torch.bool, device=self.device)
        return obs, reward, false, truncated, info

    def simulate(self, num_steps: int | None = None, seed: int | Sequence[int] | None = None) -> dict[str, Tensor]:
        """Reset and run ``num_steps`` steps (default ``max_steps``) without actions.

        The numbers equal ``reset(seed)`` followed by ``num_steps`` calls of
        :meth:`step` bit for bit; the env is left at step ``num_steps``.

        Returns:
            The dict of :meth:`StarTrackerSimulator.simulate` (batch-first tensors:
            ``gyro``, ``truth_* [B, T+1, 3]``, ``star_* [B, F, M(, 3)]`` at ``star_steps [F]``).
        """
        n = self.config.max_steps if num_steps is None else num_steps
        if isinstance(n, bool) or int(n) != n or not 0 <= int(n) <= self.config.max_steps:
            raise ValueError(f"num_steps must be an integer in [0, max_steps={self.config.max_steps}], got {num_steps!r}")
        self.reset(seed=seed)
        out = self.sim.simulate(int(n))
        self._needs_reset = self.sim.step_index >= self.config.max_steps
        return out

    def render(self) -> None:
        """No rendering."""
        return None
