"""Sensor faults injected by configuration: the failures a real attitude sensor suite shows.

A :class:`SensorFault` is active over the half-open time window ``[start, end)``
(seconds of simulation time; a gyro sample belongs to the time ``t_k`` that ends
its interval, a star frame to the time it is taken).  Kinds:

``"misidentified_star"``
    In every star frame of the window, the star reported in slot ``slot`` carries a
    **wrong catalogue vector**: its inertial vector is replaced by that of the
    star nearest to the true one in the tracker's magnitude-cut catalogue (``max_magnitude``; the typical
    identification error of a star tracker: a neighbour it can also see).  Among the bright stars that neighbour
    lies 0.03° to 2° away (16 frames measured: up to a third of the field of view), not necessarily the nearest
    star of the full catalogue.  The measured body vector is untouched, so the
    measurement is an outlier of the size of that angular separation.
``"star_outage"``
    No star frames in the window (mask false, vectors zero).
``"gyro_dropout"``
    Gyro samples missing: the reading is reported as zeros with ``gyro_valid`` false.
``"gyro_saturation"``
    The gyro saturates at ``±limit`` (rad/s) per axis: readings are clipped and a
    sample with any axis beyond the range has ``gyro_valid`` false (the sensor's
    status flag).

Faults are pure functions of the (fault-free) readings and their times, so the
step-by-step environment and its batched :meth:`simulate` inject them
identically.  Several faults may overlap; they are applied in the order given.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ._checks import real_number

__all__ = [
    "FAULT_KINDS",
    "SensorFault",
    "parse_faults",
    "check_fault_slots",
    "apply_gyro_faults",
    "apply_star_faults",
    "nearest_other_star",
]

FAULT_KINDS = ("misidentified_star", "star_outage", "gyro_dropout", "gyro_saturation")
_TIME_TOLERANCE = 1e-9  # s: a sample at t = start (to rounding) is inside the window
_CHUNK_ROWS = 2048  # misidentified stars searched against the catalogue per chunk


@dataclass(frozen=True)
class SensorFault:
    """One injected fault (validated on creation).

    Attributes:
        kind: one of :data:`FAULT_KINDS`.
        start: window start (s), a number ≥ 0 (an int is converted; bools and strings are refused).
        end: window end (s), > ``start`` (exclusive).
        slot: ``misidentified_star`` only: the star slot (0 = brightest visible) whose
            catalogue vector is wrong, an integer ≥ 0 and below the camera's ``max_stars``
            (checked where the faults meet it: :func:`check_fault_slots`).
        limit: ``gyro_saturation`` only: the per-axis range (rad/s), > 0.
    """

    kind: str
    start: float
    end: float
    slot: int = 0
    limit: float | None = None

    def __post_init__(self) -> None:
        put = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"SensorFault: kind must be one of {FAULT_KINDS}, got {self.kind!r}")
        for name in ("start", "end"):
            v = real_number("SensorFault", name, getattr(self, name))
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"SensorFault: {name} must be finite and ≥ 0 (s), got {getattr(self, name)!r}")
            put(name, v)
        if not self.end > self.start:
            raise ValueError(f"SensorFault: end ({self.end}) must be after start ({self.start})")
        if isinstance(self.slot, bool) or not isinstance(self.slot, int) or self.slot < 0:
            raise ValueError(f"SensorFault: slot must be an integer ≥ 0, got {self.slot!r}")
        if self.kind == "gyro_saturation":
            if self.limit is None:
                raise ValueError("SensorFault: gyro_saturation needs limit > 0 (rad/s), got None")
            lim = real_number("SensorFault", "limit", self.limit)
            if not math.isfinite(lim) or lim <= 0:
                raise ValueError(f"SensorFault: gyro_saturation needs limit > 0 (rad/s), got {self.limit!r}")
            put("limit", lim)
        elif self.limit is not None:
            raise ValueError(f"SensorFault: limit applies to gyro_saturation only, not {self.kind!r}")

    def active(self, time: Tensor) -> Tensor:
        """``start ≤ t < end`` (to 1e-9 s) for times ``t`` (s), elementwise bool."""
        return (time >= self.start - _TIME_TOLERANCE) & (time < self.end - _TIME_TOLERANCE)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (TOML/JSON-ready) that :func:`parse_faults` accepts."""
        d: dict[str, Any] = {"kind": self.kind, "start": self.start, "end": self.end}
        if self.kind == "misidentified_star":
            d["slot"] = self.slot
        if self.kind == "gyro_saturation":
            d["limit"] = self.limit
        return d


def parse_faults(value: Any, max_stars: int | None = None) -> tuple[SensorFault, ...]:
    """Faults from :class:`SensorFault` objects or mappings (``{"kind": …, "start": …}``).

    Args:
        value: a list (or tuple) of faults, or ``None`` for none.
        max_stars: M, the stars per frame, if known: a ``misidentified_star`` fault must
            name an existing slot (< M; :func:`check_fault_slots`).  Without it the slot
            is checked when the faults meet a camera (:class:`~envs.config.StarTrackerConfig`).

    Raises:
        ValueError: naming the entry and the problem.
    """
    if value is None:
        return ()
    if isinstance(value, (SensorFault, Mapping)) or not isinstance(value, Sequence) or isinstance(value, str):
        raise ValueError(f"faults must be a list of SensorFault or dicts, got {value!r}")
    out = []
    for i, item in enumerate(value):
        if isinstance(item, SensorFault):
            out.append(item)
            continue
        if not isinstance(item, Mapping):
            raise ValueError(f"faults[{i}] must be a SensorFault or a dict, got {item!r}")
        unknown = sorted(set(item) - {"kind", "start", "end", "slot", "limit"})
        if unknown:
            raise ValueError(f"faults[{i}]: unknown key(s) {unknown}; valid: kind, start, end, slot, limit")
        missing = [k for k in ("kind", "start", "end") if k not in item]
        if missing:
            raise ValueError(f"faults[{i}]: no {', '.join(missing)} given; every fault needs kind, start and end")
        try:
            out.append(SensorFault(**item))
        except ValueError as exc:
            raise ValueError(f"faults[{i}]: {exc}") from None
    if max_stars is not None:
        check_fault_slots(out, max_stars)
    return tuple(out)


def check_fault_slots(faults: Sequence[SensorFault], max_stars: int) -> None:
    """Refuse a ``misidentified_star`` fault whose slot does not exist in a frame of
    ``max_stars`` (M) stars: slots are ``0 … M−1``, and a fault on a slot ≥ M would
    never be injected.

    Raises:
        ValueError: ``"faults[i]: misidentified_star slot s does not exist: …"``.
    """
    for i, fault in enumerate(faults):
        if fault.kind == "misidentified_star" and fault.slot >= max_stars:
            raise ValueError(
                f"faults[{i}]: misidentified_star slot {fault.slot} does not exist: a frame reports "
                f"max_stars={max_stars} stars (slots 0…{max_stars - 1})"
            )


def apply_gyro_faults(faults: Sequence[SensorFault], gyro: Tensor, time: Tensor) -> tuple[Tensor, Tensor]:
    """Gyro readings as the faulty sensor reports them.

    Args:
        faults: the configured faults (others than gyro kinds are ignored).
        gyro: fault-free readings ``[..., 3]`` (rad/s).
        time: sample times (s), broadcastable to ``gyro.shape[:-1]``.

    Returns:
        ``(gyro [..., 3], gyro_valid [...] bool)``.
    """
    valid = torch.ones(gyro.shape[:-1], dtype=torch.bool, device=gyro.device)
    for fault in faults:
        if fault.kind not in ("gyro_dropout", "gyro_saturation"):
            continue
        on = fault.active(time).expand(valid.shape)
        if fault.kind == "gyro_dropout":
            gyro = torch.where(on[..., None], torch.zeros_like(gyro), gyro)
            valid = valid & ~on
        else:
            beyond = (gyro.abs() > fault.limit).any(-1)
            gyro = torch.where(on[..., None], gyro.clamp(-fault.limit, fault.limit), gyro)
            valid = valid & ~(on & beyond)
    return gyro, valid


def apply_star_faults(
    faults: Sequence[SensorFault],
    catalog_vectors: Tensor,
    body: Tensor,
    inertial: Tensor,
    mask: Tensor,
    time: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Star frames as the faulty tracker reports them.

    Args:
        faults: the configured faults (gyro kinds are ignored).
        catalog_vectors: ``[S, 3]`` unit vectors of the catalogue the tracker identifies against.
        body, inertial: ``[..., M, 3]``; mask: ``[..., M]`` bool (fault-free frames).
        time: frame times (s), broadcastable to ``mask.shape[:-1]``.

    Returns:
        ``(star_body, star_inertial, star_mask)`` with the faults applied.

    Raises:
        ValueError: for a ``misidentified_star`` slot ≥ M (:func:`check_fault_slots`).
    """
    check_fault_slots(faults, mask.shape[-1])
    frame_shape = mask.shape[:-1]
    for fault in faults:
        if fault.kind == "star_outage":
            on = fault.active(time).expand(frame_shape)
            mask = mask & ~on[..., None]
            body = torch.where(on[..., None, None], torch.zeros_like(body), body)
            inertial = torch.where(on[..., None, None], torch.zeros_like(inertial), inertial)
        elif fault.kind == "misidentified_star":
            hit = fault.active(time).expand(frame_shape) & mask[..., fault.slot]
            if not bool(hit.any()):
                continue
            inertial = inertial.clone()
            rows = hit.nonzero(as_tuple=True)
            true_r = inertial[rows + (fault.slot,)]  # [K, 3]
            inertial[rows + (fault.slot,)] = nearest_other_star(catalog_vectors, true_r)
    return body, inertial, mask


def nearest_other_star(catalog_vectors: Tensor, r: Tensor) -> Tensor:
    """For each unit vector ``r [K, 3]`` (a catalogue star), the vector of the nearest
    *other* catalogue star ``[K, 3]`` (largest cosine after the star itself)."""
    out = torch.empty_like(r)
    cat = catalog_vectors.to(r)
    for i in range(0, r.shape[0], _CHUNK_ROWS):
        cos = r[i : i + _CHUNK_ROWS] @ cat.T  # [k, S]
        second = cos.topk(2, dim=-1).indices[:, 1]
        out[i : i + _CHUNK_ROWS] = cat[second]
    return out
