"""The weight QP's measurements: the batched torch solver against Clarabel called per problem, side by side.

Both sides solve the same problems, ``min ½wᵀHw + cᵀw`` on the simplex: the torch solver the whole batch in one
call (:func:`agsf_torch.qp.solve_simplex_qp`, as the filters call it), Clarabel one problem at a time on the first
``clarabel_samples`` of them, unpolished, as its users call it (:func:`agsf_torch.qp.solve_simplex_qp_clarabel`);
the two calls alternate (:func:`~.harness.side_by_side`) and each side's median is divided by its problem count.

* :func:`bench_qp` — random strictly convex problems, ``H = AAᵀ/N + I``, ``c`` minus a random point of the simplex;
* :func:`bench_qp_filter` — the filters' own problems: the ``(H, c)`` a weight update passes its solver in one
  predict step of a 6-state attitude mixture (:func:`filter_qp_problems`, captured at the call), the Galerkin
  update's ``M + εI`` and the penalty update's ``L̃ + λI`` on an ``N``-component mixture, and the managed Galerkin
  filter's at capacity ``N``, over the slots its active components need
  (:func:`agsf_torch.filters.management.active_slots`) with the inactive ones among them held at zero
  (:func:`agsf_torch.qp.hold_at_zero`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from types import ModuleType
from typing import Any
from unittest import mock

import torch
from torch import Tensor

from .harness import attitude_mixture, side_by_side

__all__ = ["bench_qp", "bench_qp_filter", "filter_qp_problems", "random_qp_problems", "time_qp", "FILTER_QP_PROBLEMS"]

F64 = torch.float64

#: The filters' problems :func:`filter_qp_problems` builds, by name: what each is.
FILTER_QP_PROBLEMS = {
    "galerkin": "AGSF-galerkin's M + εI and c, one predict of an N-component split of the attitude prior",
    "penalty": "AGSF (penalty)'s L̃ + λI and −λw_ref, one predict of an N-component split of the attitude prior",
    "galerkin-managed": "AGSF-galerkin-managed's QP at capacity N, one predict of the 5-component prior padded to "
    "N: over the slots its 5 active components need (active_slots: 8 at N = 16, 3 of them held at zero)",
}


def random_qp_problems(B: int, N: int, seed: int = 2) -> tuple[Tensor, Tensor]:
    """``B`` random strictly convex simplex QPs of size ``N``: ``H = AAᵀ/N + I`` (``A`` standard normal),
    ``c = −softmax(g)`` (``g`` standard normal)."""
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(B, N, N, generator=gen, dtype=F64)
    H = A @ A.transpose(-1, -2) / N + torch.eye(N, dtype=F64)
    c = -torch.softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    return H, c


def time_qp(H: Tensor, c: Tensor, clarabel_samples: int, repeats: int = 5) -> dict[str, Any]:
    """Seconds per problem of the torch solver on the whole batch ``(H [B, N, N], c [B, N])`` and of Clarabel on
    its first ``clarabel_samples`` problems, timed alternately; their speed-up, each side's largest KKT residual
    (:func:`agsf_torch.qp.kkt_residual`) and their largest weight difference on the shared problems."""
    from ...qp import kkt_residual, solve_simplex_qp, solve_simplex_qp_clarabel

    B = H.shape[0]
    S = min(clarabel_samples, B)
    Hs, cs = H[:S], c[:S]
    sec = side_by_side(
        {
            "torch": lambda: solve_simplex_qp(H, c),
            "clarabel": lambda: solve_simplex_qp_clarabel(Hs, cs, polish=False),
        },
        repeats,
    )
    res = solve_simplex_qp(H, c)
    w_ref = torch.as_tensor(solve_simplex_qp_clarabel(Hs, cs, polish=False))
    t_torch, t_clar = sec["torch"] / B, sec["clarabel"] / S
    return {
        "clarabel_samples": S,
        "torch_seconds_per_problem": t_torch,
        "clarabel_seconds_per_problem": t_clar,
        "speedup": t_clar / t_torch,
        "torch_max_kkt_residual": float(res.kkt_residual.max()),
        "clarabel_max_kkt_residual": float(kkt_residual(Hs, cs, w_ref).max()),
        "max_abs_difference": float((res.w[:S] - w_ref).abs().max()),
    }


def bench_qp(B: int = 8192, N: int = 5, clarabel_samples: int = 300, repeats: int = 5) -> dict[str, Any]:
    """The batched torch solver against Clarabel called directly, one problem at a time, on random strictly convex
    problems (:func:`random_qp_problems`, the filter's form ``L̃ + λI``)."""
    H, c = random_qp_problems(B, N)
    what = f"random strictly convex H = AAᵀ/N + I, c = −softmax(g), B={B} N={N}"
    return {"B": B, "N": N, "problems": "random", "what": what, **time_qp(H, c, clarabel_samples, repeats)}


@contextlib.contextmanager
def _captured(module: ModuleType) -> Iterator[list[tuple[Tensor, Tensor]]]:
    """The ``(H, c)`` of every call of ``module.solve_simplex_qp`` while the context is open (solved as before)."""
    solve = module.solve_simplex_qp
    calls: list[tuple[Tensor, Tensor]] = []

    def record(H: Tensor, c: Tensor, **kwargs: Any) -> Any:
        calls.append((H, c))
        return solve(H, c, **kwargs)

    with mock.patch.object(module, "solve_simplex_qp", record):
        yield calls


def filter_qp_problems(
    problems: str, B: int, N: int, compile: bool = False, seed: int = 5, chunk: int | None = 2048
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """The weight QP ``(H [B, N, N], c [B, N])`` a filter passes its solver in one predict step (one gyro interval,
    0.1 s at 0.06 rad/s per axis) of ``B`` random attitudes (:func:`~.harness.attitude_mixture`, 6-state), captured
    at the call: built by the filter's own weight update from a real mixture (:data:`FILTER_QP_PROBLEMS`), ``chunk``
    trajectories at a time, each chunk by a new filter (``None``: all at once; the problems are per trajectory, and
    the penalty update's ``L`` at N = 32 needs ~12 GB at B = 8192 in one piece).

    Returns:
        ``(H, c, info)``; ``info["active_components"]``: the mean count of components not held at zero.
    """
    from ...filters.management import pad_mixture
    from ...filters.registry import make_filter
    from ...filters.weight_updates import base as weight_update_base
    from ...models import AttitudeModel

    if problems not in FILTER_QP_PROBLEMS:
        raise ValueError(f"unknown QP problems {problems!r}; known: {', '.join(FILTER_QP_PROBLEMS)}")
    model = AttitudeModel(estimate_bias=True)
    gen = torch.Generator().manual_seed(seed)
    Hs, cs, active = [], [], []
    for start in range(0, B, chunk or B):
        size = min(chunk or B, B - start)
        u = torch.full((size, 3), 0.06, dtype=F64)
        if problems == "galerkin-managed":
            # the prior, not a posterior: a 5-star update (σ = 1e-5 rad) splits the 5 components into 15 and the
            # next pass prunes all but the heaviest, a QP of one active component
            filt = make_filter("AGSF-galerkin-managed", model, compile_fused=compile, capacity=N)
            prior = pad_mixture(attitude_mixture(size, 5, True, gen), N)
        else:
            filt = make_filter("AGSF-galerkin" if problems == "galerkin" else "AGSF", model, compile_fused=compile)
            prior = attitude_mixture(size, N, True, gen)
        with _captured(weight_update_base) as calls:  # every weight update solves its QP there
            filt.predict(prior, u, 0.1)
        H, c = calls[-1]
        Hs.append(H)
        cs.append(c)
        managed = problems == "galerkin-managed"
        active.append(filt.diagnostics["active_components"] if managed else torch.full((size,), N))
    mean_active = float(torch.cat(active).to(F64).mean())
    return torch.cat(Hs), torch.cat(cs), {"active_components": mean_active}


def bench_qp_filter(
    problems: str, B: int = 8192, N: int = 5, clarabel_samples: int = 300, repeats: int = 5, compile: bool = False
) -> dict[str, Any]:
    """The batched torch solver against Clarabel per problem on a filter's own problems (:func:`filter_qp_problems`;
    ``compile``: build them with the compiled kernels, which changes nothing in the problems but their cost)."""
    H, c, info = filter_qp_problems(problems, B, N, compile)
    what = f"{FILTER_QP_PROBLEMS[problems]}, B={B} N={N}"
    return {"B": B, "N": N, "problems": problems, "what": what, **info, **time_qp(H, c, clarabel_samples, repeats)}
