"""Checkpoints: a filter run's full state saved and restored, safely.

A checkpoint is a ``torch.save`` file holding only tensors, numbers, strings,
lists and dicts, so it loads with ``torch.load(weights_only=True)`` (no code
execution).  It holds, per filter, the mixture (log-weights, means, covariances
and the adaptive filter's reference weights) and the filter's step counter, plus
any caller state (for example an environment's ``state_dict()`` and a
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

FORMAT = "agsf-checkpoint-1"


def _mixture_state(m: GaussianMixture) -> dict[str, Any]:
    return {"log_weights": m.log_weights, "means": m.means, "covs": m.covs, "ref_log_weights": m.ref_log_weights}


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
            name: {"mixture": _mixture_state(mixtures[name]), "step": int(getattr(filters[name], "_step", 0))}
            for name in mixtures
        },
        "extra": dict(extra or {}),
    }
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)
    return path


def load_checkpoint(path: str | Path, filters: Mapping[str, GaussianSumFilter]) -> tuple[dict[str, GaussianMixture], dict[str, Any]]:
    """Read a checkpoint (``weights_only=True``), restore the filters' counters, return
    ``(mixtures, extra)``."""
    state = torch.load(Path(path), weights_only=True)
    if state.get("format") != FORMAT:
        raise ValueError(f"{path} is not an {FORMAT} file (format {state.get('format')!r})")
    if set(state["filters"]) != set(filters):
        raise ValueError(f"checkpoint holds filters {sorted(state['filters'])}, got {sorted(filters)}")
    mixtures = {}
    for name, s in state["filters"].items():
        m = s["mixture"]
        mixtures[name] = GaussianMixture(
            log_weights=m["log_weights"], means=m["means"], covs=m["covs"], ref_log_weights=m["ref_log_weights"], validate=False
        )
        if hasattr(filters[name], "_step"):
            filters[name]._step = int(s["step"])
    return mixtures, state["extra"]
