"""Mixture management's measurements (:mod:`agsf_torch.filters.management`): a managed filter's step beside the
fused GSF's, alternated (:func:`~.harness.side_by_side`).

Both sides start from the same ``B`` random attitudes (:func:`~.harness.attitude_mixture`, 6-state, the prior
split into 5 components), the same gyro interval (0.1 s at 0.06 rad/s per axis) and, for an update, the same
5 star vectors per trajectory (σ = 1e-5 rad, :func:`~.fused._star_problem`).  The managed filter takes that
mixture padded to ``capacity`` slots with inactive ones (:func:`~agsf_torch.filters.management.pad_mixture`) and
runs management with its defaults (:class:`~agsf_torch.filters.management.MixtureManagement`: the entropy test
before the propagation, the measurement's curvature before the update, pruning and merging in each pass), so it
carries all ``capacity`` slots through every kernel; the fused GSF carries its 5 components.  Every timed call
starts from the same mixture, so every repeat does the same work.

* :func:`bench_managed_gsf` — GSF-managed predict + star update against the fused GSF's predict + update;
* :func:`bench_managed_galerkin` — AGSF-galerkin-managed predict against the fused GSF's predict, with the
  unmanaged Galerkin AGSF at 5 components beside them for reference.

Each row also reports what management did in its step (mean over trajectories of ``active_components``,
``splits``, ``merges``, ``prunes`` after the predict and after the update).
"""

from __future__ import annotations

from typing import Any

import torch

from .fused import _star_problem
from .harness import attitude_mixture, side_by_side

__all__ = ["bench_managed_gsf", "bench_managed_galerkin"]

F64 = torch.float64


def _counts(diagnostics: Any) -> dict[str, float]:
    from ...filters.management import MANAGEMENT_DIAGNOSTICS

    return {k: float(torch.as_tensor(diagnostics[k]).to(F64).mean()) for k in MANAGEMENT_DIAGNOSTICS}


def _problem(B: int, capacity: int):
    from ...filters.management import pad_mixture
    from ...models import AttitudeModel

    model = AttitudeModel(estimate_bias=True)
    mix = attitude_mixture(B, 5, True, torch.Generator().manual_seed(1))
    u = torch.full((B, 3), 0.06, dtype=F64)
    return model, mix, pad_mixture(mix, capacity), u


def bench_managed_gsf(B: int = 4096, capacity: int = 16, repeats: int = 5, compile: bool = True) -> dict[str, Any]:
    """Seconds of one predict + star update of GSF-managed (``capacity`` slots, management's defaults) and of the
    fused GSF at N = 5 (compiled if ``compile``, as both filters' kernels), alternated; the ratio managed ÷ GSF."""
    from ...filters.registry import make_filter

    model, mix, padded, u = _problem(B, capacity)
    y, meas = _star_problem(B)
    gsf = make_filter("GSF", model, compile_fused=compile)
    managed = make_filter("GSF-managed", model, compile_fused=compile, capacity=capacity)
    seen: dict[str, Any] = {}

    def managed_step():
        predicted = managed.predict(padded, u, 0.1)
        seen["predict"] = dict(managed.diagnostics)
        managed.update(predicted, y, meas)
        seen["update"] = dict(managed.diagnostics)

    sec = side_by_side(
        {"GSF": lambda: gsf.update(gsf.predict(mix, u, 0.1), y, meas), "GSF-managed": managed_step}, repeats
    )
    return {
        "what": f"predict (0.1 s) + star update (5 stars), 6-state B={B}: GSF-managed from the 5-component "
        f"mixture padded to {capacity} slots (management's defaults) against the fused GSF at N=5",
        "B": B,
        "N": 5,
        "capacity": capacity,
        "compiled": compile,
        "seconds": sec,
        "ratio": sec["GSF-managed"] / sec["GSF"],
        "management": {step: _counts(d) for step, d in seen.items()},
    }


def bench_managed_galerkin(B: int = 4096, capacity: int = 16, repeats: int = 5, compile: bool = True) -> dict[str, Any]:
    """Seconds of one predict of AGSF-galerkin-managed (``capacity`` slots, management's defaults), of the fused
    GSF at N = 5 and, for reference, of AGSF-galerkin at N = 5, alternated; the ratios to the fused GSF."""
    from ...filters.registry import make_filter

    model, mix, padded, u = _problem(B, capacity)
    gsf = make_filter("GSF", model, compile_fused=compile)
    galerkin = make_filter("AGSF-galerkin", model, compile_fused=compile)
    managed = make_filter("AGSF-galerkin-managed", model, compile_fused=compile, capacity=capacity)
    seen: dict[str, Any] = {}

    def managed_step():
        managed.predict(padded, u, 0.1)
        seen["predict"] = dict(managed.diagnostics)

    sec = side_by_side(
        {
            "GSF": lambda: gsf.predict(mix, u, 0.1),
            "AGSF-galerkin": lambda: galerkin.predict(mix, u, 0.1),
            "AGSF-galerkin-managed": managed_step,
        },
        repeats,
    )
    return {
        "what": f"predict (0.1 s), 6-state B={B}: AGSF-galerkin-managed from the 5-component mixture padded to "
        f"{capacity} slots (management's defaults) against the fused GSF at N=5",
        "B": B,
        "N": 5,
        "capacity": capacity,
        "compiled": compile,
        "seconds": sec,
        "ratio": sec["AGSF-galerkin-managed"] / sec["GSF"],
        "unmanaged_ratio": sec["AGSF-galerkin"] / sec["GSF"],
        "management": {step: _counts(d) for step, d in seen.items()},
    }
