"""Learning the noise model from the measurements: maximum likelihood through the filter.

The whole filter is a torch program, so the measurement log-likelihood

.. math:: \\ell(θ) = Σ_{\\text{updates}} \\log Σ_i w_i β_i

is differentiable in the model parameters θ (through propagation, the Joseph
update and, for the adaptive filter, the weight QP).  :func:`fit_attitude_parameters`
maximises it with L-BFGS over log-parametrised positive parameters (the gyro
bias is unconstrained), and reports an uncertainty from the curvature: the
inverse Hessian of ``−ℓ`` in the fitted coordinates, mapped to 95 % intervals.
A configured value outside its interval is flagged: the data disagree with it.

Parameters: ``sigma_v`` (rad/s^½), ``sigma_u`` (rad/s^{3/2}), ``sigma_s`` (rad),
``bias`` (rad/s, 3-vector, 3-state model), ``reg`` (λ, adaptive filter),
``prior_scale`` (multiplies the prior covariance).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..filter_loop import FilterSetup, filter_steps, initial_mixtures
from ..filters.registry import filter_spec, make_filter
from ..models import AttitudeModel
from .inputs import AttitudeInputs, recording_inputs
from .recordings import Recording

__all__ = ["PARAMETERS", "FitResult", "attitude_log_likelihood", "fit_attitude_parameters"]

PARAMETERS = ("sigma_v", "sigma_u", "sigma_s", "bias", "reg", "prior_scale")
_POSITIVE = {"sigma_v", "sigma_u", "sigma_s", "reg", "prior_scale"}
F64 = torch.float64


class _Diverged(Exception):
    """The likelihood or its gradient became non-finite."""


@dataclass
class FitResult:
    """Learned values, 95 % intervals, the configured values and whether each lies inside.

    Attributes:
        learned / configured: name → value (float, or list of 3 for ``bias``).
        interval: name → (low, high) (per axis for ``bias``); NaN where the curvature
            is not positive definite.
        inside: name → the configured value lies in the interval (all axes for ``bias``); ``None`` (no
            verdict) when the fit did not converge, the interval is undefined or the data do not identify it.
        notes: name → why the data do not identify it (the curvature of ``−ℓ`` in its fitted coordinate and
            the interval it gives), or ``None``.
        converged: L-BFGS stopped on its tolerances, not on its iteration budget, and did not diverge.
        nll: final −ℓ; history: −ℓ per iteration; message: how the fit ended.
    """

    learned: dict
    configured: dict
    interval: dict
    inside: dict
    nll: float
    history: list = field(default_factory=list)
    converged: bool = True
    message: str = ""
    notes: dict = field(default_factory=dict)


def attitude_log_likelihood(
    rec: Recording,
    params: Mapping[str, Tensor],
    *,
    prior_mean: Tensor,
    prior_cov: Tensor,
    filter_kind: str = "EKF",
    num_components: int = 1,
    estimate_bias: bool = False,
    update_iterations: int = 1,
    noise_model: str = "isotropic",
    gyro_hold_sigma: float | Tensor | None = None,
    gate_probability: float | None = None,
) -> Tensor:
    """``Σ_b Σ_updates log Σᵢ wᵢβᵢ`` of a recording under the parameters ``params``.

    The recording drives the one filter loop (:func:`agsf_torch.filter_loop.filter_steps`)
    through the attitude adapter, as ``agsf run`` does: invalid gyro samples
    (``gyro_valid``) are held with the covariance inflation of
    :class:`~agsf_torch.attitude.gyro_hold.GyroHold`; the 3-state model subtracts its ``bias``
    parameter (the bias is learned here, not known).

    Args:
        rec: the recording (``B`` trajectories; sample 0 is the prior's time).
        params: ``sigma_v``, ``sigma_u``, ``sigma_s``, ``bias``, ``reg``, ``prior_scale``
            (tensors; any may require grad).
        prior_mean: ``[B, n]``; prior_cov: ``[n, n]`` (scaled by ``prior_scale``).
        filter_kind: a registered filter name (:data:`~agsf_torch.filters.registry.FILTER_NAMES`).
        num_components: components of a mixture filter (one-component filters ignore it).
        noise_model: the star-vector noise model (:class:`~agsf_torch.models.StarVectorMeasurement`).
        gate_probability: the filter's innovation gate (:mod:`agsf_torch.gating`), ``None``: off.
        gyro_hold_sigma: σ_h of the gyro hold (rad/s); default ``σ_v/√Δt`` of the first interval.
    """
    model = AttitudeModel(
        estimate_bias=estimate_bias, sigma_v=params["sigma_v"], sigma_u=params["sigma_u"], bias=params["bias"]
    )
    spec = filter_spec(filter_kind)
    options = {"update_iterations": update_iterations, "gate_probability": gate_probability}
    if filter_kind == "AGSF":
        options["reg"] = params["reg"]
    setup = FilterSetup(make_filter(filter_kind, model, **options), num_components if spec.mixture else 1)
    cov0 = params["prior_scale"] * torch.as_tensor(prior_cov, dtype=F64)
    mixtures = initial_mixtures({"filter": setup}, torch.as_tensor(prior_mean, dtype=F64), cov0)
    if gyro_hold_sigma is None:
        dt0 = float(rec.time[1] - rec.time[0]) if rec.num_samples > 1 else 1.0
        gyro_hold_sigma = params["sigma_v"] / dt0**0.5
    adapter = AttitudeInputs(sigma_s=params["sigma_s"], gyro_hold_sigma=gyro_hold_sigma, noise_model=noise_model)
    total = torch.zeros((), dtype=F64)
    for step in filter_steps({"filter": setup.filter}, mixtures, recording_inputs(rec, adapter)):
        ll = step.filters["filter"].log_likelihood
        if ll is not None:
            total = total + ll.sum()
    return total


def fit_attitude_parameters(
    rec: Recording,
    configured: Mapping[str, object],
    learn: list[str],
    *,
    prior_mean: Tensor,
    prior_cov: Tensor,
    max_iter: int = 40,
    log: Callable[[int, float, dict], None] | None = None,
    **likelihood_kwargs,
) -> FitResult:
    """Maximum-likelihood fit of the parameters in ``learn``, the others held at ``configured``.

    Args:
        rec: training recording.
        configured: every parameter of :data:`PARAMETERS` (the starting point).
        learn: the names to fit.
        max_iter: L-BFGS iterations (strong-Wolfe line search).
        log: optional ``log(iteration, nll, values)`` (e.g. TensorBoard).
        **likelihood_kwargs: passed to :func:`attitude_log_likelihood`.
    """
    unknown = [p for p in list(learn) + list(configured) if p not in PARAMETERS]
    if unknown:
        raise ValueError(f"unknown parameter(s) {unknown}; known: {PARAMETERS}")
    missing = [p for p in PARAMETERS if p not in configured]
    if missing:
        raise ValueError(f"configured values missing for {missing}")
    if not learn:
        raise ValueError("nothing to learn: name at least one parameter")
    base = {k: torch.as_tensor(v, dtype=F64) for k, v in configured.items()}
    for k in _POSITIVE:
        if not bool((base[k] > 0).all()):
            raise ValueError(f"configured {k} must be > 0 to be log-parametrised, got {base[k].tolist()}")
    # unconstrained coordinates: log for positive parameters, identity for the bias
    sizes = {k: base[k].numel() for k in learn}
    x0 = torch.cat([(base[k].log() if k in _POSITIVE else base[k]).reshape(-1) for k in learn])

    def unpack(x: Tensor) -> dict[str, Tensor]:
        out, i = dict(base), 0
        for k in learn:
            v = x[i : i + sizes[k]].reshape(base[k].shape)
            out[k] = v.exp() if k in _POSITIVE else v
            i += sizes[k]
        return out

    def nll(x: Tensor) -> Tensor:
        return -attitude_log_likelihood(rec, unpack(x), prior_mean=prior_mean, prior_cov=prior_cov, **likelihood_kwargs)

    x = x0.clone().requires_grad_(True)
    opt = torch.optim.LBFGS(
        [x], lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-12
    )
    history: list[float] = []
    last_finite = x0.clone()
    state = {"diverged": False}

    def closure():
        opt.zero_grad()
        loss = nll(x)
        if not torch.isfinite(loss):
            raise _Diverged
        loss.backward()
        if not bool(torch.isfinite(x.grad).all()):
            raise _Diverged
        history.append(float(loss.detach()))
        last_finite.copy_(x.detach())
        if log is not None:
            log(
                len(history),
                float(loss.detach()),
                {k: v.detach().tolist() for k, v in unpack(x.detach()).items() if k in learn},
            )
        return loss

    try:
        opt.step(closure)
    except (_Diverged, RuntimeError, ValueError):  # non-finite likelihood, or a failed factorisation at a wild step
        state["diverged"] = True
    # L-BFGS stops on its own tolerances (gradient, change of −ℓ or of the step) or when its iteration
    # budget is spent; only the former is a converged fit
    iterations = int(opt.state[opt.param_groups[0]["params"][0]].get("n_iter", 0))
    exhausted = iterations >= max_iter
    x_hat = last_finite if state["diverged"] or not torch.isfinite(x).all() else x.detach()
    values = unpack(x_hat)
    hess = torch.autograd.functional.hessian(nll, x_hat)
    hess = 0.5 * (hess + hess.T)
    curvature = hess.diagonal()
    # coordinates the data do not constrain (no positive curvature) are held at their value; the others get
    # intervals from the inverse of their block of the Hessian
    kept = curvature > 0
    half = torch.full_like(x_hat, float("nan"))
    if bool(kept.any()):
        L, info = torch.linalg.cholesky_ex(hess[kept][:, kept])
        if int(info) == 0:
            half[kept] = 1.959963984540054 * torch.cholesky_inverse(L).diagonal().sqrt()
    learned, interval, inside, configured_out, notes, i = {}, {}, {}, {}, {}, 0
    for k in learn:
        s = sizes[k]
        lo, hi = x_hat[i : i + s] - half[i : i + s], x_hat[i : i + s] + half[i : i + s]
        if k in _POSITIVE:
            lo, hi = lo.exp(), hi.exp()
        c = base[k].reshape(-1)
        learned[k] = _plain(values[k])
        configured_out[k] = _plain(base[k])
        interval[k] = (_plain(lo), _plain(hi))
        notes[k] = _identification(k, curvature[i : i + s], half[i : i + s])
        defined = bool(torch.isfinite(lo).all() and torch.isfinite(hi).all()) and notes[k] is None
        inside[k] = bool(((c >= lo) & (c <= hi)).all()) if defined else None
        i += s
    if state["diverged"]:
        message = "diverged: stopped with the last finite parameters"
    elif exhausted:
        message = f"not converged: L-BFGS used all {max_iter} iterations (raise --max-iter)"
    else:
        message = f"converged after {iterations} L-BFGS iterations"
    converged = not state["diverged"] and not exhausted
    if not converged:  # no verdict on parameters the fit did not settle
        inside = {k: None for k in learn}
    nll_hat = float(nll(x_hat).detach())
    return FitResult(learned, configured_out, interval, inside, nll_hat, history, converged, message, notes)


#: The widest 95 % interval of a positive parameter that still counts as learned: a factor of 10 either way
#: (in the fitted log coordinate, a half-width of log 10).
WIDEST_LOG_INTERVAL = math.log(10.0)
#: The widest 95 % half-width of a learned gyro bias, rad/s (1 °/h: the bias of a navigation-grade gyro is
#: 0.01–1 °/h, so data that cannot tell 1 °/h from none do not identify it).
WIDEST_BIAS_INTERVAL = math.pi / 180 / 3600


def _identification(name: str, curvature: Tensor, half: Tensor) -> str | None:
    """``None`` where the data identify ``name`` (positive curvature, a 95 % interval no wider than
    :data:`WIDEST_LOG_INTERVAL` or :data:`WIDEST_BIAS_INTERVAL`); otherwise why not, in words, with the curvature
    of ``−ℓ`` in the fitted coordinate (``log`` of a positive parameter)."""
    coordinate = f"log {name}" if name in _POSITIVE else f"{name} (rad/s)"
    curv = ", ".join(f"{float(c):.3g}" for c in curvature)
    if not bool((curvature > 0).all()):
        return f"not identified by these data: −log-likelihood has curvature {curv} in {coordinate} (none to fit)"
    widest = WIDEST_LOG_INTERVAL if name in _POSITIVE else WIDEST_BIAS_INTERVAL
    if not bool(torch.isfinite(half).all()) or float(half.max()) > widest:
        h = float(half.max())
        if name not in _POSITIVE:
            span = f"± {h:.3g} rad/s"
        else:  # a factor exp(h), which overflows a float beyond h ≈ 709
            span = f"×/÷ {math.exp(h):.3g}" if h < 700 else f"×/÷ e^{h:.3g}"
        return (
            f"not identified by these data: −log-likelihood has curvature {curv} in {coordinate}, a 95 % interval "
            f"of {span}"
        )
    return None


def _plain(t: Tensor):
    t = t.detach()
    return float(t) if t.numel() == 1 else [float(v) for v in t.reshape(-1)]
