"""Validation of configuration numbers, shared by the simulator's components.

Every check raises ``ValueError`` naming the owner (``"StarTrackerConfig"``,
``"Gyro"``, …), the field and the offending value.  Numbers are Python or NumPy
integers and floats (an int is converted to float); ``bool``, strings, complex
numbers and other objects are refused rather than coerced.

Physical limits shared by several components (each documented where it is defined):

* :data:`MIN_PERIOD` — the shortest gyro period Δt.
* :func:`check_rotation_per_step` — a rate whose rotation over one step reaches half a turn.
* :data:`MRP_LIMIT` — the largest MRP component accepted (actions, initial attitude).
* :data:`MAX_STARS` — the most stars a frame can report.
* :func:`check_camera_bounds` — focal length, star noise and principal point ranges.
* :data:`MAX_SEED` / :func:`check_seeds` — episode seeds, one check for the single and the vector env.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "MAX_SEED",
    "check_seeds",
    "FOCAL_LENGTH_RANGE",
    "MAX_STARS",
    "MAX_STAR_SIGMA",
    "MIN_PERIOD",
    "MRP_LIMIT",
    "check_camera_bounds",
    "check_count",
    "check_mrp",
    "check_period",
    "check_real",
    "check_rotation_per_step",
    "check_vector",
    "real_number",
]

MIN_PERIOD = 1e-9
"""Shortest gyro period Δt (s): 1 ns, i.e. sampling at 1 GHz, far beyond any rate sensor.
With it, every rate below the half-turn limit (``π/Δt ≤ 3.2e9`` rad/s) and the bias walk
built from such rates stay finite for any episode length."""

MRP_LIMIT = 1e150
"""Largest ``|p_i|`` of an MRP (actions, initial attitude).  An MRP of norm ``|p| > 1`` is
the shadow of a rotation by ``4/|p|`` rad, so beyond 1e150 it stands for a rotation below
1e-149 rad (the identity to any precision), and at ``|p| ≈ 1.3e154`` the quaternion's
``|p|²`` overflows float64 (the error angle becomes NaN)."""

MAX_STARS = 117_955
"""Most stars one frame can report: every star of the Hipparcos 2 catalogue (``hip2.dat``
holds 117 955 records; every magnitude cut keeps fewer).  More slots could only ever be
padding."""

FOCAL_LENGTH_RANGE = (1e-6, 1e3)
"""Accepted focal lengths f (m): 1 µm to 1 km, orders of magnitude around any optics
(star trackers use tens of mm).  Within it the focal-plane coordinates (∝ f) and their
squares stay far from float64 underflow and overflow (at f = 1e-160 the measured star
vectors come out off unit norm; at f = 1e160 they come out zero)."""

MAX_STAR_SIGMA = 1.0
"""Largest star-camera noise σ (rad per axis).  Both noise models are small-angle
perturbations of the direction (σ per tangent-plane axis); at σ ≥ 1 rad (57°) a
"measured" direction carries no information about the star, and at σ ≈ 1e300 the
unit-vector model's vectors overflow to zero."""


def real_number(owner: str, name: str, value: Any) -> float:
    """``value`` as a float if it is a real number (Python/NumPy int or float, or a 0-d
    real array or tensor); ``ValueError`` naming ``owner``, ``name`` and the value for
    anything else, including ``bool``, strings and complex numbers."""
    if isinstance(value, Tensor):
        if value.ndim == 0 and not (value.dtype.is_complex or value.dtype == torch.bool):
            return float(value.item())
    elif isinstance(value, np.ndarray):
        if value.ndim == 0 and value.dtype.kind in "iuf":
            return float(value)
    elif isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)):
        return float(value)
    raise ValueError(f"{owner}: {name} must be a number, got {value!r} ({type(value).__name__})")


def _not_real(value: Any) -> bool:
    try:
        real_number("", "", value)
    except ValueError:
        return True
    return False


def check_real(owner: str, name: str, value: Any, *, positive: bool = False) -> float:
    """``value`` as a float (:func:`real_number`), or ``ValueError`` naming ``owner``, ``name`` and the value.

    Args:
        positive: require ``> 0`` (default: ``≥ 0``); non-finite values are always rejected.
    """
    v = real_number(owner, name, value)
    if not math.isfinite(v) or (v <= 0.0 if positive else v < 0.0):
        raise ValueError(f"{owner}: {name} must be finite and {'> 0' if positive else '≥ 0'}, got {value!r}")
    return v


def check_vector(
    owner: str, name: str, value: Any, n: int, *, scalar_ok: bool = False, unit: str = ""
) -> tuple[float, ...]:
    """``n`` finite floats from a sequence, array or tensor of real numbers (or one number
    repeated ``n`` times, if ``scalar_ok``); ``ValueError`` naming the field otherwise
    (strings, bools and complex numbers among the entries included).  ``unit`` (e.g.
    ``" (rad/s)"``) is appended to "n numbers" in the messages."""
    original = value
    if isinstance(value, (Tensor, np.ndarray)):
        value = value.detach().cpu().tolist() if isinstance(value, Tensor) else value.tolist()
    if scalar_ok and isinstance(value, numbers.Number) and not isinstance(value, (bool, np.bool_)):
        value = (value,) * n
    try:
        if isinstance(value, (str, bytes)):
            raise TypeError
        items = list(value)
    except TypeError:
        raise ValueError(f"{owner}: {name} must be {n} numbers{unit}, got {original!r}") from None
    try:
        vec = tuple(real_number(owner, name, v) for v in items)
    except ValueError:
        i = next(i for i, v in enumerate(items) if _not_real(v))
        raise ValueError(
            f"{owner}: {name} must be {n} numbers{unit}, got {original!r}: entry {i} is {items[i]!r} ({type(items[i]).__name__})"
        ) from None
    if len(vec) != n or not all(math.isfinite(v) for v in vec):
        raise ValueError(f"{owner}: {name} must be {n} finite numbers{unit}, got {original!r}")
    return vec


def check_count(owner: str, name: str, value: Any, *, upper: int | None = None, why: str = "") -> int:
    """An integer in ``[1, upper]`` (an integral float is accepted), or ``ValueError``
    naming the field, the value and, for ``> upper``, the limit and ``why``."""
    ok = isinstance(value, (numbers.Integral, float, np.floating)) and not isinstance(value, (bool, np.bool_))
    if ok and isinstance(value, (float, np.floating)):
        ok = math.isfinite(value) and value == int(value)
    if not ok or int(value) < 1:
        raise ValueError(f"{owner}: {name} must be an integer ≥ 1, got {value!r}")
    if upper is not None and int(value) > upper:
        raise ValueError(f"{owner}: {name} must be ≤ {upper}{why}, got {value!r}")
    return int(value)


def check_period(owner: str, name: str, value: Any) -> float:
    """A step period (s): finite, > 0 and ≥ :data:`MIN_PERIOD`; ``ValueError`` naming the field otherwise."""
    v = check_real(owner, name, value, positive=True)
    if v < MIN_PERIOD:
        raise ValueError(f"{owner}: {name} must be ≥ {MIN_PERIOD:g} s (sampling at most at 1 GHz), got {value!r}")
    return v


def check_rotation_per_step(owner: str, what: str, rate: float, dt: float) -> None:
    """Refuse a rate magnitude ``rate`` (rad/s) whose rotation over one step Δt (s) reaches half a turn.

    **Limit** ``|ω|·Δt < π``: a rotation sampled every Δt is only defined up to
    aliasing — a turn by θ > π per step is indistinguishable from one by 2π − θ the
    other way — so a truth rate, a gyro bias or a gyro noise level at or beyond π/Δt
    does not describe a sampled attitude (and at ~1e300 rad/s it overflows).

    Args:
        what: the subject of the message, naming the field and the rate
            (e.g. ``"rate 40 rad/s"``).

    Raises:
        ValueError: ``"{owner}: {what} turns … rad per step of dt=… s; …"``.
    """
    if not rate * dt < math.pi:
        raise ValueError(
            f"{owner}: {what} turns {rate * dt:.6g} rad per step of dt={dt!r} s; "
            f"it must stay below half a turn (|ω|·dt < π, i.e. |ω| < {math.pi / dt:.6g} rad/s)"
        )


def check_mrp(owner: str, name: str, p: Tensor) -> None:
    """Refuse MRPs ``p [..., 3]`` with a non-finite entry or one beyond :data:`MRP_LIMIT`,
    naming the first offending index and value."""
    bad = ~torch.isfinite(p)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(f"{owner}: {name} must be finite, got {float(p[idx])} at index {list(idx)}")
    big = p.abs() > MRP_LIMIT
    if bool(big.any()):
        idx = tuple(int(i) for i in big.nonzero()[0])
        raise ValueError(
            f"{owner}: {name} must have every MRP component within ±{MRP_LIMIT:g} "
            f"(such an MRP is the identity to any precision, and near 1.3e154 its |p|² overflows), "
            f"got {float(p[idx]):g} at index {list(idx)}"
        )


def check_camera_bounds(
    owner: str,
    focal_length: float,
    fov_deg: tuple[float, float],
    sigma: float,
    principal_point: tuple[float, float],
    sigma_name: str = "sigma",
) -> None:
    """Physical ranges of validated camera settings (f in m, FOV in degrees, σ in rad,
    principal point in m):

    * f within :data:`FOCAL_LENGTH_RANGE`;
    * σ ≤ :data:`MAX_STAR_SIGMA`;
    * ``|x₀| ≤ f·tan(fov_x/2)`` and ``|y₀| ≤ f·tan(fov_y/2)``: the principal point (where
      the boresight meets the focal plane) lies within the imaged field around the
      focal-plane origin.  Farther out, ``x − x₀`` cancels catastrophically (at
      x₀ = 1e300 m every star vector comes out as the boresight).

    Raises:
        ValueError: naming ``owner``, the field, the value and the range.
    """
    lo, hi = FOCAL_LENGTH_RANGE
    if not lo <= focal_length <= hi:
        raise ValueError(f"{owner}: focal_length must lie in [{lo:g}, {hi:g}] m, got {focal_length!r}")
    if sigma > MAX_STAR_SIGMA:
        raise ValueError(
            f"{owner}: {sigma_name} must be ≤ {MAX_STAR_SIGMA:g} rad (a small-angle noise model), got {sigma!r}"
        )
    for axis, x0, fov in zip("xy", principal_point, fov_deg):
        half = focal_length * math.tan(math.radians(fov) / 2.0)
        if abs(x0) > half:
            raise ValueError(
                f"{owner}: principal_point {axis}₀ = {x0!r} m lies outside the imaged field "
                f"(|{axis}₀| ≤ focal_length·tan(fov_{axis}/2) = {half:.6g} m)"
            )


#: The largest episode seed: every trajectory's seed is an integer in ``[0, 2⁶³ − 1]`` (an int64 without
#: wrapping, so that two trajectories never share one; gymnasium's own seeding needs it non-negative).
MAX_SEED = (1 << 63) - 1


def _seed_int(owner: str, value: Any, where: str) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, np.integer)):
        raise ValueError(f"{owner}: {where} must be an integer, got {type(value).__name__} {value!r}")
    v = int(value)
    if not 0 <= v <= MAX_SEED:
        raise ValueError(f"{owner}: {where} must lie in [0, 2**63 - 1], got {v}")
    return v


def _seed_forms(num_envs: int) -> str:
    """What a seed may be, for messages: "an integer" (one trajectory) or "an integer or B integers"."""
    return "an integer" if num_envs == 1 else f"an integer or {num_envs} integers (one per trajectory)"


def check_seeds(owner: str, seed: Any, num_envs: int) -> list[int]:
    """The episode seeds of ``num_envs`` trajectories from ``seed``: an integer ``s`` (Python or NumPy;
    trajectory ``i`` gets ``s + i``) or a sequence of ``num_envs`` integers (list, tuple, array or integer
    tensor).  ``bool``, floats, strings and out-of-range values (including ``s + num_envs − 1 > 2⁶³ − 1``)
    are refused with a ``ValueError`` naming the value."""
    if isinstance(seed, (numbers.Integral, np.integer)) and not isinstance(seed, (bool, np.bool_)):
        base = _seed_int(owner, seed, "seed")
        if base + num_envs - 1 > MAX_SEED:
            raise ValueError(f"{owner}: seed {base} + {num_envs - 1} (one per trajectory) exceeds 2**63 - 1")
        return [base + i for i in range(num_envs)]
    if isinstance(seed, Tensor):
        if seed.dtype.is_floating_point or seed.dtype.is_complex or seed.dtype == torch.bool:
            raise ValueError(f"{owner}: seed must hold integers, got a {seed.dtype} tensor")
        values = seed.reshape(-1).tolist() if seed.dim() == 1 else None
    elif isinstance(seed, np.ndarray):
        if seed.dtype.kind not in "iu":
            raise ValueError(f"{owner}: seed must hold integers, got an array of dtype {seed.dtype}")
        values = seed.tolist() if seed.ndim == 1 else None
    elif isinstance(seed, (list, tuple)):
        values = list(seed)
    else:
        raise ValueError(f"{owner}: seed must be {_seed_forms(num_envs)}, got {type(seed).__name__} {seed!r}")
    if values is None or len(values) != num_envs:
        raise ValueError(f"{owner}: seed must be {_seed_forms(num_envs)}, got {seed!r}")
    return [_seed_int(owner, v, f"seed[{i}]") for i, v in enumerate(values)]
