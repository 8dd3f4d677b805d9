"""Test data, comparisons and readers shared by the test modules: random data (the float64 dtype, unit vectors,
SPD matrices, attitudes), the one comparison every accuracy assertion goes through (:func:`assert_within`) and its
statistical counterpart (:func:`assert_statistic`), and what an experiment wrote (its files' digests, its
TensorBoard records).

Every draw goes through an explicit ``torch.Generator`` (the ``gen`` fixture of ``conftest.py``,
seeded by ``pytest --seed``).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import torch
from scipy.special import ndtri

from agsf_torch.models import ContinuousModel

__all__ = [
    "F64",
    "CubicDrift",
    "InvalidBound",
    "assert_within",
    "assert_statistic",
    "relative_bound",
    "random_unit_vectors",
    "random_spd",
    "random_mrps",
    "file_digests",
    "event_records",
]


class InvalidBound(Exception):
    """A test error, not a failure of the code under test: a bound that is negative, not finite, or zero where
    the compared values are not (a bound that holds only where two code paths round alike)."""


class _Jitter:
    """``pytest --jitter-ulps K``: every :func:`assert_within` moves ``actual`` by 1 to ``K`` units in the last
    place of each nonzero entry, with a random sign, before comparing (set per test by ``conftest.py``, seeded
    from ``--seed`` and the test's id).  An exact zero stays zero: it is the one value every rounding keeps."""

    ulps: int = 0
    rng: np.random.Generator | None = None


JITTER = _Jitter()


def _as_array(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu()
        if x.dtype == torch.bfloat16:
            x = x.float()
        return x.numpy()
    return np.asarray(x)


def _v(x) -> str:
    return repr(x.item() if hasattr(x, "item") else x)


def _jittered(a: np.ndarray) -> np.ndarray:
    if JITTER.ulps <= 0 or not np.issubdtype(a.dtype, np.floating):
        return a
    rng = JITTER.rng if JITTER.rng is not None else np.random.default_rng(0)
    steps = rng.integers(1, JITTER.ulps + 1, size=a.shape) * rng.choice((-1.0, 1.0), size=a.shape)
    moved = a + (steps * np.spacing(np.abs(a))).astype(a.dtype)
    return np.where((a != 0) & np.isfinite(a), moved, a)


def assert_within(actual, expected, bound, what: str) -> None:
    """Assert ``|actual − expected| ≤ bound`` entry by entry (every argument broadcast against the others).

    ``bound`` must come from the conditioning of what is computed (an error analysis of both sides), never from
    what one machine printed: it is refused as :class:`InvalidBound` (a test error) where it is negative, not
    finite, or zero where ``actual`` or ``expected`` is not.  Non-finite values must be equal on both sides (the
    same infinity, or NaN against NaN).  Under ``pytest --jitter-ulps K`` ``actual`` is first moved by up to ``K``
    ulps of each entry (:class:`_Jitter`), so a bound that holds only where both sides round alike fails on every
    machine.  A failure names ``what``, the worst entry's index, both values, the bound and their ratio.
    """
    a = _as_array(actual)
    e = _as_array(expected)
    b = np.asarray(_as_array(bound), dtype=np.float64)
    try:
        a, e, b = np.broadcast_arrays(a, e, b)
    except ValueError as err:
        raise InvalidBound(
            f"test error in {what}: shapes {a.shape}, {e.shape} and bound {b.shape} do not broadcast"
        ) from err
    a = _jittered(np.array(a))
    finite = np.isfinite(a) & np.isfinite(e)
    if np.isnan(b).any() or (np.isinf(b) & finite).any():
        at = np.unravel_index(np.argmax(~np.isfinite(b)), b.shape)
        raise InvalidBound(f"test error in {what}: the bound is not finite at {tuple(map(int, at))} ({_v(b[at])})")
    if (b < 0).any():
        at = np.unravel_index(np.argmin(b), b.shape)
        raise InvalidBound(f"test error in {what}: the bound is negative at {tuple(map(int, at))} ({_v(b[at])})")
    zero = (b == 0) & finite & ((a != 0) | (e != 0))
    if zero.any():
        at = np.unravel_index(np.argmax(zero), b.shape)
        raise InvalidBound(
            f"test error in {what}: the bound is 0 at {tuple(map(int, at))} where the values are not "
            f"(actual {_v(a[at])}, expected {_v(e[at])}): it holds only where both sides round alike"
        )
    same_nonfinite = ~finite & ((a == e) | (np.isnan(a) & np.isnan(e)))
    if (~finite & ~same_nonfinite).any():
        at = np.unravel_index(np.argmax(~finite & ~same_nonfinite), a.shape)
        raise AssertionError(f"{what}: at {tuple(map(int, at))} actual {_v(a[at])}, expected {_v(e[at])}")
    with np.errstate(over="ignore", invalid="ignore"):
        err = np.where(finite, np.abs(a.astype(np.float64) - e.astype(np.float64)), 0.0)
    if a.size == 0 or bool((err <= b).all()):
        return
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(err > b, err / b, 0.0)
    at = np.unravel_index(np.argmax(np.nan_to_num(ratio, posinf=np.inf)), ratio.shape)
    count = int((err > b).sum())
    raise AssertionError(
        f"{what}: {count} of {a.size} entries outside the bound; the worst at {tuple(map(int, at))}: "
        f"actual {_v(a[at])}, expected {_v(e[at])}, |difference| {err[at]:.6g} against the bound {b[at]:.6g} "
        f"({ratio[at]:.3g}× it)"
    )


def relative_bound(expected, units: float, floor) -> np.ndarray:
    """``units·|expected| + floor``: a bound of ``units`` relative to each entry plus an absolute ``floor``
    (the scale of the terms that cancel where ``expected`` is small; it must not be zero where they are not)."""
    return units * np.abs(_as_array(expected)).astype(np.float64) + np.asarray(_as_array(floor), dtype=np.float64)


def assert_statistic(estimate, expected, standard_error, what: str, *, false_failure: float) -> None:
    """Assert a statistic agrees with its expectation within the normal quantile of a stated false-failure rate.

    ``|estimate − expected| ≤ z·standard_error`` entry by entry, ``z = Φ⁻¹(1 − α/(2m))`` with ``α =
    false_failure`` the probability that a correct implementation fails the whole assertion and ``m`` the number
    of entries (a Bonferroni split): the statistic must be asymptotically normal with that standard error, which
    the test states and derives from its distribution.  Not jittered: the sampling spread, not rounding, sets it.
    """
    if not 0.0 < false_failure < 0.5:
        raise InvalidBound(f"test error in {what}: a false-failure rate must lie in (0, 0.5), got {false_failure}")
    est = np.asarray(_as_array(estimate), dtype=np.float64)
    exp = np.asarray(_as_array(expected), dtype=np.float64)
    se = np.asarray(_as_array(standard_error), dtype=np.float64)
    est, exp, se = np.broadcast_arrays(est, exp, se)
    if not np.isfinite(se).all() or (se <= 0).any():
        raise InvalidBound(f"test error in {what}: a standard error must be positive and finite, got {_v(se.min())}")
    z = float(ndtri(1.0 - false_failure / (2 * max(est.size, 1))))
    dev = np.abs(est - exp) / se
    if est.size == 0 or bool((dev <= z).all()):
        return
    at = np.unravel_index(np.argmax(np.nan_to_num(dev, nan=np.inf)), dev.shape)
    raise AssertionError(
        f"{what}: the worst entry at {tuple(map(int, at))} is {_v(est[at])} against {_v(exp[at])}, {dev[at]:.3g} "
        f"standard errors ({se[at]:.4g}) away; the limit is {z:.3g} for a false-failure rate of {false_failure:g}"
    )


#: The package's default dtype.
F64 = torch.float64


class CubicDrift(ContinuousModel):
    """A user's model: ``dx = (x − x³) dt + dβ``, ``E[dβ²] = 0.25 dt``; its drift's slope ``1 − 3x²`` is steep far
    from the wells at ±1 (−805.9 1/s at x = 16.4), where an RK4 step of 0.1 s cannot follow it."""

    state_dim = 1

    def drift(self, x, u=None):
        return x - x**3

    def noise_gain(self, x):
        return torch.ones_like(x).unsqueeze(-1)

    def noise_psd(self):
        return torch.full((1, 1), 0.25, dtype=F64)


def random_unit_vectors(gen: torch.Generator, *shape: int) -> torch.Tensor:
    """Uniformly random unit vectors ``[*shape, 3]``."""
    r = torch.randn(*shape, 3, generator=gen, dtype=F64)
    return r / r.norm(dim=-1, keepdim=True)


def random_spd(gen: torch.Generator, *shape: int, n: int = 3, scale: float = 1.0, floor: float = 0.1) -> torch.Tensor:
    """Random symmetric positive definite matrices ``[*shape, n, n]``: ``scale·(AAᵀ/n + floor·I)`` with
    ``A`` standard normal, symmetrised exactly (a rounded ``AAᵀ`` is not; a covariance must be).
    Eigenvalues lie in ``scale·[floor, floor + O(1)]``."""
    A = torch.randn(*shape, n, n, generator=gen, dtype=F64)
    S = scale * (A @ A.transpose(-1, -2) / n + floor * torch.eye(n, dtype=F64))
    return 0.5 * (S + S.transpose(-1, -2))


def random_mrps(num: int, gen: torch.Generator, max_norm: float = 1.0) -> torch.Tensor:
    """Uniformly random attitudes as MRPs ``[num, 3]`` with ``|p| ≤ 1``, scaled to ``max_norm``."""
    q = torch.randn(num, 4, generator=gen, dtype=F64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = q * torch.where(q[:, 3:] < 0, -1.0, 1.0)
    return max_norm * q[:, :3] / (1.0 + q[:, 3:])


#: Configuration overrides that run a preset eagerly: no kernel compiled (a test compiles nothing: conftest's guard).
EAGER = ["compile=false", "compile_fused=false"]
#: ``agsf`` arguments of the smallest run of a preset: 2 runs of 0.3 s, the EKF alone, eager, no progress output.
TINY_CLI = [*(a for s in ("runs=2", "duration=0.3", 'filters=["EKF"]', *EAGER) for a in ("--set", s)), "--quiet"]


def file_digests(root: Path) -> dict[str, str]:
    """Every file under ``root`` (but the TensorBoard events, whose names hold a time) and a digest of its bytes."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and "tfevents" not in p.name and p.name != ".agsf.lock"
    }


def event_records(root: Path) -> dict[str, dict]:
    """Every TensorBoard run under ``root`` (relative path) → its tags → ``[(step, value)]`` (histograms and the
    text as their serialised protos)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    runs = {}
    for run in sorted({p.parent for p in root.rglob("events.out.tfevents.*")}):
        acc = EventAccumulator(str(run), size_guidance={"scalars": 0, "histograms": 0, "tensors": 0})
        acc.Reload()
        tags = acc.Tags()
        events = {t: [(e.step, e.value) for e in acc.Scalars(t)] for t in tags["scalars"]}
        events |= {t: [(e.step, str(e.histogram_value)) for e in acc.Histograms(t)] for t in tags["histograms"]}
        events |= {t: [(e.step, e.tensor_proto.SerializeToString()) for e in acc.Tensors(t)] for t in tags["tensors"]}
        runs[str(run.relative_to(root))] = events
    assert runs
    return runs
