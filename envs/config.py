"""Configuration of the star-tracker environments: :class:`StarTrackerConfig`.

One frozen dataclass holds every setting of the simulation (gyro, star camera,
truth rate, episode length, injected faults); it validates and normalises its
fields on creation (numbers to floats, vectors to tuples, faults to
:class:`~envs.faults.SensorFault` objects), so the simulator and the gym adapters
(:mod:`envs.simulator`, :mod:`envs.star_tracker`) can take it as given.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from torch import Tensor

from ._checks import check_real
from .camera import NOISE_MODES
from .catalog import DEFAULT_MAX_MAGNITUDE
from .dynamics import DEFAULT_RATE, RateLike
from .faults import parse_faults
from .gyro import DEFAULT_INITIAL_BIAS, DEFAULT_SIGMA_U, DEFAULT_SIGMA_V

__all__ = ["StarTrackerConfig"]


def _positive(name: str, value: Any) -> float:
    """A finite float > 0, or ``ValueError`` naming the field."""
    return check_real("StarTrackerConfig", name, value, positive=True)


def _nonnegative(name: str, value: Any) -> float:
    """A finite float ≥ 0, or ``ValueError`` naming the field."""
    return check_real("StarTrackerConfig", name, value)


def _count(name: str, value: Any) -> int:
    """An integer ≥ 1 (an integral float is accepted), or ``ValueError`` naming the field."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer, float)):
        raise ValueError(f"StarTrackerConfig: {name} must be an integer ≥ 1, got {value!r}")
    if isinstance(value, float) and (not math.isfinite(value) or value != int(value)):
        raise ValueError(f"StarTrackerConfig: {name} must be an integer ≥ 1, got {value!r}")
    if int(value) < 1:
        raise ValueError(f"StarTrackerConfig: {name} must be an integer ≥ 1, got {value!r}")
    return int(value)


def _finite_tuple(name: str, value: Any, n: int, scalar_ok: bool) -> tuple[float, ...]:
    """``n`` finite floats from a sequence or tensor (or a scalar repeated, if ``scalar_ok``)."""
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
