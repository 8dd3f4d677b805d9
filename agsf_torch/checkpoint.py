"""Checkpoints: a filter run's full state saved and restored, safely.

A checkpoint is a ``torch.save`` file holding only tensors, numbers, strings,
lists and dicts, so it loads with ``torch.load(weights_only=True)`` (no code
execution).  It holds, per filter, the mixture (log-weights, means, covariances)
and the filter's run state (``filter.state_dict()``: the adaptive filter's
weight-update counter and reference weights), plus any caller state (for example an environment's ``state_dict()`` and a
:class:`~agsf_torch.input_gaps.GyroHold`'s).  Restoring it
and continuing gives the same numbers, bit for bit, as never stopping.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from .filters.gaussian_sum import GaussianSumFilter
from .mixture import GaussianMixture

__all__ = ["save_checkpoint", "load_checkpoint", "FORMAT"]

FORMAT = "agsf-checkpoint-2"
_OLD_FORMAT = "agsf-checkpoint-1"  # counter and reference weights beside the mixture; still read


def _mixture_state(m: GaussianMixture) -> dict[str, Any]:
    return {"log_weights": m.log_weights, "means": m.means, "covs": m.covs}


def save_checkpoint(
    path: str | Path,
    mixtures: Mapping[str, GaussianMixture],
    filters: Mapping[str, GaussianSumFilter],
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write a checkpoint atomically (a temporary file renamed into place).

    Args:
        mixtures / filters: name → the current belief / the filter that owns it.
        extra: further state (tensors, numbers, strings, lists, dicts), e.g. ``env.state_dict()``.
    """
    if set(mixtures) != set(filters):
        raise ValueError(f"mixtures {sorted(mixtures)} and filters {sorted(filters)} must name the same filters")
    state = {
        "format": FORMAT,
        "filters": {
            name: {"mixture": _mixture_state(mixtures[name]), "filter": filters[name].state_dict()}
            for name in mixtures
        },
        "extra": dict(extra or {}),
    }
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)
    return path


def _filter_state(s: dict[str, Any], fmt: str, filt: GaussianSumFilter) -> dict[str, Any]:
    """The ``state_dict`` for ``filt`` from a checkpoint entry.

    Format 1 kept the step counter beside the mixture and the reference weights in it
    (for every filter, adaptive or not): they become the adaptive filter's weight-update
    state (the reference only for the paper's penalty update, the one that uses it) and
    are dropped for the other filters, which never used them.
    """
    if fmt == FORMAT:
        return s["filter"]
    update = getattr(filt, "weight_update", None)
    if update is None:
        return {}
    state = {"kind": update.name, "step": int(s["step"]), "elapsed": 0.0}
    if "ref_log_weights" in update.extra_state_keys:
        state["ref_log_weights"] = s["mixture"].get("ref_log_weights")
    return {"weight_update": state}


def load_checkpoint(path: str | Path, filters: Mapping[str, GaussianSumFilter]) -> tuple[dict[str, GaussianMixture], dict[str, Any]]:
    """Read a checkpoint (``weights_only=True``), restore the filters' run state, return
    ``(mixtures, extra)``.  Everything is validated first; if a filter refuses its state,
    the filters restored before it are put back as they were.

    Raises:
        ValueError: naming the file (and the filter) for any malformed or mismatched content.
    """
    state = torch.load(Path(path), weights_only=True)
    fmt = state.get("format") if isinstance(state, dict) else None
    if fmt not in (FORMAT, _OLD_FORMAT):
        raise ValueError(f"{path} is not an {FORMAT} file (format {fmt!r})")
    try:
        entries, extra = state["filters"], state["extra"]
        if set(entries) != set(filters):
            raise ValueError(f"checkpoint holds filters {sorted(entries)}, got {sorted(filters)}")
        mixtures, restored = {}, {}
        for name, s in entries.items():
            m = s["mixture"]
            try:
                mixtures[name] = GaussianMixture(log_weights=m["log_weights"], means=m["means"], covs=m["covs"])
            except ValueError as exc:
                raise ValueError(f"filter {name!r}: {exc}") from None
            restored[name] = _filter_state(s, fmt, filters[name])
    except (KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: malformed checkpoint ({type(exc).__name__}: {exc})") from None
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    previous = {name: filt.state_dict() for name, filt in filters.items()}
    current = None
    try:
        for current, filt in filters.items():
            filt.load_state_dict(restored[current])
    except ValueError as exc:  # put every filter back as it was
        for name, filt in filters.items():
            filt.load_state_dict(previous[name])
        raise ValueError(f"{path}: filter {current!r}: {exc}") from None
    return mixtures, extra
