"""The contract a model of the user's keeps with the filters, checked before anything changes.

* the drift and noise gain act on states ``x [..., n]`` elementwise over the leading dims, returning ``[..., n]``
  and ``[..., n, q]``, and ``Q`` is a finite symmetric positive semidefinite ``[q, q]``
  (:func:`check_model_contract`, once per filter and model), also on :func:`elementwise_probe` states, which catch
  a function indexing ``x[:, i]`` where the filters' own shapes cannot;
* a measurement's parts are one per trajectory or one for all (:func:`check_measurement_batch`), its noise
  covariance is positive semidefinite (:func:`check_noise_cov`) and its ``predict`` acts on every state alike
  (:func:`check_measurement_elementwise`, once per measurement object).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn

from ..mixture import check_symmetric
from ..shapes import broadcast_shapes

__all__ = [
    "check_model_contract",
    "check_measurement_batch",
    "check_noise_cov",
    "check_measurement_elementwise",
    "check_elementwise",
    "elementwise_probe",
    "call_on_probe",
]


def check_measurement_batch(name: str, lead: tuple[int, ...], y: Tensor) -> None:
    """Raise ``ValueError`` unless a measurement model's part ``name`` with leading dims ``lead`` is one per
    trajectory (``lead`` equal to ``y [..., d]``'s leading dims) or one for all (``lead = ()``): a model built
    for one trajectory and given a batch's ``y`` applied that trajectory's stars (or mask, or noise) to all."""
    lead, want = tuple(lead), tuple(y.shape[:-1])
    if lead not in ((), want):
        raise ValueError(
            f"the measurement's {name} has leading dims {lead}, y has {want}: build the measurement model from "
            f"the same trajectories as y (one per trajectory, {want}, or one for all, no leading dims)"
        )


def _covers(lead: torch.Size, batch: torch.Size) -> bool:
    """Whether an output's leading dims ``lead`` are ``batch`` broadcast with others (the shape contract)."""
    try:
        return broadcast_shapes(lead, batch) == lead
    except RuntimeError:
        return False


@contextlib.contextmanager
def _dtype_named(model: nn.Module, x: Tensor):
    """Re-raise a ``RuntimeError`` from the model's own code as a ``ValueError`` naming the dtypes, where the model
    holds floating-point tensors of another dtype than the states ``x`` (a user's float64 matrix against a float32
    mixture fails inside torch with 'expected m1 and m2 to have the same dtype'); anything else passes through."""
    try:
        yield
    except RuntimeError as exc:
        held = sorted({str(t.dtype) for t in (*model.parameters(), *model.buffers()) if t.is_floating_point()})
        if any(d != str(x.dtype) for d in held):
            raise ValueError(
                f"{type(model).__name__} failed on the mixture's {x.dtype} states while holding {', '.join(held)} "
                f"tensors ({type(exc).__name__}: {exc}); build the mixture in float64 (the library's convention) or "
                f"convert the model (model.to({x.dtype}))"
            ) from exc
        raise


def _check_returned(what: str, value: Any, states: Tensor, event: tuple, hint: str) -> Tensor:
    """``value`` if it is a tensor ``[..., *event]`` whose leading dims cover ``states``' (``"q"`` in ``event``: any
    size), else a ``ValueError`` naming ``what``, the shape expected for ``states`` and the one returned."""
    k = len(event)
    fits = (
        isinstance(value, Tensor)
        and value.dim() >= k
        and all(want == "q" or have == want for have, want in zip(value.shape[-k:], event))
        and _covers(value.shape[:-k], states.shape[:-1])
    )
    if not fits:
        got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
        shape = "..., n, q" if k == 2 else "..., n"
        raise ValueError(
            f"{what} must return [{shape}] = {(*states.shape[:-1], *event)} for x {tuple(states.shape)}, got {got}{hint}"
        )
    return value


def elementwise_probe(x: Tensor) -> Tensor:
    """States to call a model's function on once, to check that it acts on ``x [..., n]`` elementwise over the
    leading dims: ``x`` under two new leading dims, ``[1, s, *x.shape]`` with ``s = 2`` (3 where ``x``'s first dim
    is 2), ``x``'s own leading dims, which per-trajectory parameters broadcast against, kept in place.  A function
    that indexes ``x[:, i]`` instead of ``x[..., i]`` picks along the new ``s`` axis and returns another shape, even
    where the filters' own shapes cannot tell (``[N, B, n]`` with ``B = n``).  ``s`` copies of ``x``: one call per
    model, not per step."""
    s = 3 if x.dim() and x.shape[0] == 2 else 2
    return x.unsqueeze(0).unsqueeze(0).expand(1, s, *x.shape).clone()


def call_on_probe(what: str, function: Callable[[Tensor], Any], probe: Tensor) -> Any:
    """``function(probe)``, a failure re-raised as a ``ValueError`` naming ``what`` and the probe's shape (a function
    written for the filters' exact shapes, ``[B, N, n]`` say, rather than elementwise)."""
    try:
        return function(probe)
    except (RuntimeError, IndexError) as exc:
        raise ValueError(
            f"{what} failed on states [{', '.join(map(str, (*probe.shape[:-1], 'n')))}] ({type(exc).__name__}: "
            f"{exc}): it must act on every state of x [..., n] alike, whatever the leading dims (index the state "
            "as x[..., i], let parameters broadcast)"
        ) from exc


def check_elementwise(name: str, function: Callable[[Tensor], Any], x: Tensor, event: tuple[int, ...]) -> None:
    """Call ``function`` (a measurement's ``predict`` or ``jacobian``, say) on :func:`elementwise_probe` states built
    from ``x [..., n]`` and require exactly ``[*probe_lead, *event]`` back.

    Raises:
        ValueError: naming ``name``, the probe's shape and what it returned (or why the call failed).
    """
    probe = elementwise_probe(x)
    value = call_on_probe(name, function, probe)
    want = (*probe.shape[:-1], *event)
    if not isinstance(value, Tensor) or tuple(value.shape) != want:
        got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
        raise ValueError(
            f"{name} must act on every state of x [..., n] alike (elementwise over the leading dims): on states "
            f"[{', '.join(map(str, (*probe.shape[:-1], 'n')))}] it returned {got}, not {want} (index the state as "
            "x[..., i], not x[:, i]: the filters pass [..., n])"
        )


def check_model_contract(model: nn.Module, x: Tensor, u: Tensor | None) -> None:
    """:meth:`~.base.ContinuousModel.check_contract`: the drift's and noise gain's shapes at ``x`` and at
    :func:`elementwise_probe` states (a failure there, or in any call while the model holds tensors of another dtype
    than ``x``, named), then ``Q``."""
    name = type(model).__name__
    with _dtype_named(model, x):
        q = _check_shapes(model, x, u)
    Q = model.noise_psd()
    lead = tuple(x.shape[:-1])
    if (
        not isinstance(Q, Tensor)
        or Q.dim() < 2
        or Q.shape[-2:] != (q, q)
        or Q.dim() - 2 > len(lead)
        or any(a != 1 and a != b for a, b in zip(reversed(Q.shape[:-2]), reversed(lead)))
    ):
        got = tuple(Q.shape) if isinstance(Q, Tensor) else type(Q).__name__
        raise ValueError(
            f"{name}.noise_psd must return [q, q] = {(q, q)} (q: noise_gain's last dim), or [..., q, q] with batch "
            f"dims that broadcast against the states' {lead} (one per trajectory), got {got}"
        )
    check_symmetric(f"{name}.noise_psd", Q.detach())
    eigenvalues = torch.linalg.eigvalsh(Q.detach().to(torch.float64))
    if q and bool((eigenvalues[..., 0] < -1e-12 * eigenvalues.abs().amax(-1)).any()):
        raise ValueError(
            f"{name}.noise_psd must be positive semidefinite (a spectral density), got eigenvalues {eigenvalues.tolist()}"
        )


def _check_shapes(model: nn.Module, x: Tensor, u: Tensor | None) -> int:
    """The shape checks of the drift and the noise gain at ``x``, then at :func:`elementwise_probe` states; returns
    ``q``, the noise gain's last dim."""
    name, n = type(model).__name__, model.state_dim
    hint = " (elementwise over the leading dims: index the state as x[..., i], not x[:, i]; the filters pass [..., n])"
    _check_returned(f"{name}.drift", model.drift(x, u), x, (n,), hint)
    g = _check_returned(f"{name}.noise_gain", model.noise_gain(x), x, (n, "q"), hint)
    probe = elementwise_probe(x)  # states no state size can be mistaken for: x[:, i] returns another shape
    _check_returned(
        f"{name}.drift", call_on_probe(f"{name}.drift", lambda z: model.drift(z, u), probe), probe, (n,), hint
    )
    _check_returned(
        f"{name}.noise_gain", call_on_probe(f"{name}.noise_gain", model.noise_gain, probe), probe, (n, "q"), hint
    )
    if type(model).drift_jacobian.__qualname__ != "ContinuousModel.drift_jacobian":  # a closed form of the model's own
        what = f"{name}.drift_jacobian"
        _check_returned(what, model.drift_jacobian(x, u), x, (n, n), hint)
        _check_returned(what, call_on_probe(what, lambda z: model.drift_jacobian(z, u), probe), probe, (n, n), hint)
    return g.shape[-1]


def check_noise_cov(name: str, R: Tensor) -> None:
    """Raise ``ValueError`` naming ``name`` unless the noise covariance ``R [..., d, d]`` is symmetric to rounding
    with a non-negative diagonal and positive semidefinite to rounding: ``R / max Rᵢᵢ + τ·I`` has a Cholesky factor
    (``τ = max(1e-10, 100 ε)``, as the QP's convexity check; a zero diagonal requires ``R = 0``)."""
    check_symmetric(name, R.detach())
    diagonal = R.detach().diagonal(dim1=-2, dim2=-1)
    if not bool((diagonal >= 0).all()):
        raise ValueError(
            f"{name} must be a covariance, with a non-negative diagonal, got diagonal {diagonal.flatten()[:8].tolist()}"
        )
    d = R.shape[-1]
    if not d:
        return
    Rd = R.detach()
    tol = max(1e-10, 100 * torch.finfo(Rd.dtype).eps)
    scale = diagonal.amax(-1)[..., None, None]
    unit = torch.where(scale > 0, Rd / torch.where(scale > 0, scale, 1.0), Rd)  # a zero diagonal: R itself, unscaled
    if bool((torch.linalg.cholesky_ex(unit + tol * torch.eye(d, dtype=Rd.dtype, device=Rd.device)).info != 0).any()):
        worst = torch.linalg.eigvalsh(Rd).amin(-1).flatten()
        raise ValueError(
            f"{name} must be a covariance, positive semidefinite, got a matrix with the eigenvalue "
            f"{float(worst.min()):.3g} (with a non-negative diagonal: an off-diagonal entry is larger than the "
            "variances allow)"
        )


def check_measurement_elementwise(measurement: nn.Module, means: Tensor, y: Tensor) -> Tensor:
    """``y [..., d]`` (the measurement's own checks passed), after, once per measurement object, its ``predict`` on
    :func:`elementwise_probe` states built from the components' means ``[..., N, n]`` as the filters pass them
    (components first, ``[N, ..., n]``) returned ``[*probe_lead, d]``; a ``predict`` indexing ``x[:, i]`` returns another shape, even where ``B = n`` makes the
    filters' own call look right.  A class that sets ``elementwise_checked = True`` (the library's own, whose tests
    check them; :class:`~.function_measurement.FunctionMeasurement`, which probes its function itself) is skipped,
    but not a subclass of it with a ``predict`` or ``jacobian`` of its own: the declaration holds for the functions
    of the class that made it.

    Raises:
        ValueError: naming the class, the probe's shape and what it returned.
    """
    if _declared_elementwise(measurement) or means.numel() == 0:
        return y
    d = y.shape[-1]
    n = means.shape[-1]
    checks = [("predict", (d,))]
    if type(measurement).jacobian.__qualname__ != "MeasurementModel.jacobian":  # a closed form of the model's own
        checks.append(("jacobian", (d, n)))
    for method, event in checks:  # the states as the filters pass them: components first
        check_elementwise(
            f"{type(measurement).__name__}.{method}", getattr(measurement, method), means.movedim(-2, 0), event
        )
    measurement.elementwise_checked = True
    return y


def _declared_elementwise(measurement: nn.Module) -> bool:
    """Whether ``measurement`` was probed already, or its class's ``elementwise_checked = True`` was declared by a
    class whose ``predict`` and ``jacobian`` are the ones it runs."""
    if measurement.__dict__.get("elementwise_checked", False):
        return True
    cls = type(measurement)
    owner = next((c for c in cls.__mro__ if "elementwise_checked" in c.__dict__), None)
    return bool(
        owner is not None
        and owner.__dict__["elementwise_checked"]
        and all(getattr(owner, m, None) is getattr(cls, m, None) for m in ("predict", "jacobian"))
    )
