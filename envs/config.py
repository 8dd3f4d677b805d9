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

import torch
from torch import Tensor

from ._checks import (
    MAX_STARS,
    check_camera_bounds,
    check_count,
    check_mrp,
    check_period,
    check_real,
    check_vector,
    real_number,
)
from .camera import NOISE_MODES
from .catalog import DEFAULT_MAX_MAGNITUDE
from .dynamics import DEFAULT_RATE, RateLike, check_constant_rate
from .faults import parse_faults
from .gyro import (
    DEFAULT_INITIAL_BIAS,
    DEFAULT_SIGMA_U,
    DEFAULT_SIGMA_V,
    check_gyro_settings,
)

__all__ = ["MAX_STEPS", "StarTrackerConfig"]


OWNER = "StarTrackerConfig"
MAX_STEPS = 2**53
"""Longest episode (steps): step times are computed as ``float64(k)·Δt``, and float64
holds every integer step index exactly only up to 2⁵³."""
_MAX_STEPS_WHY = " (step times float64(k)·dt hold the step index k exactly only up to 2⁵³)"
_MAX_STARS_WHY = " (every star of the Hipparcos catalogue: no frame can report more)"


def _positive(name: str, value: Any) -> float:
    """A finite float > 0, or ``ValueError`` naming the field."""
    return check_real(OWNER, name, value, positive=True)


def _nonnegative(name: str, value: Any) -> float:
    """A finite float ≥ 0, or ``ValueError`` naming the field."""
    return check_real(OWNER, name, value)


@dataclass(frozen=True)
class StarTrackerConfig:
    """Configuration of the star-tracker attitude environment (validated on creation).

    Numbers are Python or NumPy ints and floats (ints are converted to float); bools,
    strings and complex numbers are refused.  Every error is a ``ValueError`` naming the
    field and the value.  The physical limits below keep every simulated quantity
    finite and meaningful; their reasons are documented in :mod:`envs._checks`.

    Attributes:
        dt: gyro period Δt (s), ≥ 1e-9 s (1 GHz sampling).  One env step.
        star_period: time between star frames (s), a positive integer multiple of
            ``dt`` (to 1e-9 relative).  Frames at ``t = j·star_period``, j ≥ 1 (none at t = 0).
        sigma_v: gyro angle random walk (rad/s^½), ≥ 0.
        sigma_u: gyro rate random walk (rad/s^{3/2}), ≥ 0.
        initial_bias: ``b_0`` (rad/s), scalar (every axis) or 3 numbers; default 0.1 deg/hr.
            ``|b_0|·dt < π``, and the 1-σ gyro reading noise ``sqrt(σ_v²/dt + σ_u²dt/12)``
            likewise (:func:`envs.gyro.check_gyro_settings`: half a turn per step at most).
        sigma_s: star-camera noise σ_s (rad per axis), in ``[0, 1]`` (a small-angle model).
        fov_deg: full field of view (deg), number or ``(x, y)``, each in (0, 180).
        focal_length: f (m), in ``[1e-6, 1e3]``.
        max_stars: M, stars reported per frame, an integer in ``[1, 117 955]`` (at most
            every star of the Hipparcos catalogue).
        max_magnitude: Hipparcos magnitude cut (finite); must leave at least one star.
        star_noise: ``"focal_plane"`` or ``"unit_vector"`` (:mod:`envs.camera`).
        principal_point: ``(x₀, y₀)`` (m), within the imaged field:
            ``|x₀| ≤ f·tan(fov_x/2)``, ``|y₀| ≤ f·tan(fov_y/2)``.
        rate: truth body rate (rad/s): 3 numbers or a callable ``rate(t [B]) -> [B, 3]``;
            ``|ω|·dt < π`` (less than half a turn per step; a callable's values are
            checked as they are produced, before the state advances).
        initial_attitude: ``"random"`` (uniform on SO(3), from the episode seed) or an
            MRP (3 numbers, each within ±1e150).
        max_steps: episode length in steps, an integer in ``[1, 2⁵³]`` with
            ``max_steps·dt`` finite.
        faults: injected sensor faults (:mod:`envs.faults`): :class:`~envs.faults.SensorFault`
            objects or dicts such as ``{"kind": "star_outage", "start": 60, "end": 180}``;
            a ``misidentified_star`` slot must be below ``max_stars``.
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
        put("dt", check_period(OWNER, "dt", self.dt))
        put("star_period", _positive("star_period", self.star_period))
        ratio = self.star_period / self.dt
        if not math.isfinite(ratio):
            raise ValueError(
                f"StarTrackerConfig: star_period / dt must be a finite number of steps, got "
                f"{self.star_period!r} / {self.dt!r} = {ratio}"
            )
        n = round(ratio)
        if n < 1 or abs(ratio - n) > 1e-9 * max(1.0, ratio):
            raise ValueError(
                f"StarTrackerConfig: star_period must be a positive integer multiple of dt={self.dt}, "
                f"got {self.star_period!r}"
            )
        if not callable(self.rate) or isinstance(self.rate, Tensor):
            put("rate", check_constant_rate(OWNER, self.rate, self.dt))
        sigma_v, sigma_u, _, bias = check_gyro_settings(OWNER, self.sigma_v, self.sigma_u, self.dt, self.initial_bias)
        put("sigma_v", sigma_v)
        put("sigma_u", sigma_u)
        put("initial_bias", bias)
        put("sigma_s", _nonnegative("sigma_s", self.sigma_s))
        fov = check_vector(OWNER, "fov_deg", self.fov_deg, 2, scalar_ok=True)
        for v in fov:
            if v <= 0.0 or v >= 180.0:
                raise ValueError(f"StarTrackerConfig: fov_deg must be in (0, 180) degrees, got {self.fov_deg!r}")
        put("fov_deg", fov)
        put("focal_length", _positive("focal_length", self.focal_length))
        put("principal_point", check_vector(OWNER, "principal_point", self.principal_point, 2))
        check_camera_bounds(OWNER, self.focal_length, fov, self.sigma_s, self.principal_point, "sigma_s")
        put("max_stars", check_count(OWNER, "max_stars", self.max_stars, upper=MAX_STARS, why=_MAX_STARS_WHY))
        mag = real_number(OWNER, "max_magnitude", self.max_magnitude)
        if not math.isfinite(mag):
            raise ValueError(f"StarTrackerConfig: max_magnitude must be finite, got {self.max_magnitude!r}")
        put("max_magnitude", mag)
        if self.star_noise not in NOISE_MODES:
            raise ValueError(f"StarTrackerConfig: star_noise must be one of {NOISE_MODES}, got {self.star_noise!r}")
        if isinstance(self.initial_attitude, str):
            if self.initial_attitude != "random":
                raise ValueError(
                    f"StarTrackerConfig: initial_attitude must be 'random' or an MRP (3 numbers), "
                    f"got {self.initial_attitude!r}"
                )
        else:
            p0 = check_vector(OWNER, "initial_attitude", self.initial_attitude, 3)
            check_mrp(OWNER, "initial_attitude", torch.tensor(p0, dtype=torch.float64))
            put("initial_attitude", p0)
        put("max_steps", check_count(OWNER, "max_steps", self.max_steps, upper=MAX_STEPS, why=_MAX_STEPS_WHY))
        if not math.isfinite(self.max_steps * self.dt):
            raise ValueError(
                f"StarTrackerConfig: the episode duration max_steps·dt = {self.max_steps * self.dt} s must be finite "
                f"(max_steps={self.max_steps}, dt={self.dt})"
            )
        try:
            put("faults", parse_faults(self.faults, max_stars=self.max_stars))
        except ValueError as exc:
            raise ValueError(f"StarTrackerConfig: {exc}") from None

    @property
    def steps_per_star_frame(self) -> int:
        """``star_period / dt`` as an int."""
        return int(round(self.star_period / self.dt))

    @classmethod
    def from_overrides(cls, config: StarTrackerConfig | None = None, **overrides: Any) -> StarTrackerConfig:
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
