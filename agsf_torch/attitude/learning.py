"""Learning the noise model from the measurements: maximum likelihood through the filter.

The whole filter is a torch program, so the log-likelihood of the measurements

.. math:: \\ell(θ) = Σ_{\\text{updates}} \\log Σ_i w_i N(T^T ν_i; 0, T^T S_i T)

(the data's, two degrees of freedom per star:
:meth:`~agsf_torch.models.StarVectorMeasurement.data_log_likelihood`) is differentiable in the model
parameters θ (through propagation and the Joseph update).  :func:`fit_datasets` maximises it for ``D``
independent data sets at once, each with its own parameters (the model's noise per trajectory), by Newton's
method in log coordinates for the positive parameters (the gyro bias in rad/s): each data set's Hessian is one
``p × p`` block of a block-diagonal whole, so ``p + 1`` backward passes give every block.  It reports an
uncertainty from the curvature: the inverse Hessian of ``−ℓ`` in the fitted coordinates, mapped to 95 %
intervals.  Verdicts are tests at the 5 % level:

* **jointly** (:attr:`FitResult.joint`): the likelihood-ratio test of the configured values,
  ``2(ℓ(θ̂) − ℓ(θ₀)) ≤ χ²_p(0.95)`` over all ``p`` learned coordinates (one more pass of the filter at ``θ₀``).
  It holds the family-wise false-alarm rate at 5 %, and, unlike a test built on the curvature, it keeps its
  level where the likelihood is far from quadratic (a weakly identified noise density whose maximum may lie near
  0: σ_v from ten seconds, σ_u from minutes, a prior scale from one trajectory);
* **each parameter**: the same test when it is the only one learned; among several, Wald's,
  ``(x̂ − x₀)ᵀ C⁻¹ (x̂ − x₀) ≤ χ²_k(0.95)`` with ``C`` the parameter's block of the inverse Hessian (``k = 1``, or 3
  for the bias): for a scalar, the configured value lies in its 95 % interval.  Each flags a correct model 5 % of
  the time where the data identify the parameter well, so ``m`` of them flag one up to ``1 − 0.95^m``: the joint
  verdict is the one that controls the family.

:func:`fit_attitude_parameters` is the one-data-set case (``agsf learn``).

Parameters: ``sigma_v`` (rad/s^½), ``sigma_u`` (rad/s^{3/2}), ``sigma_s`` (rad),
``bias`` (rad/s, 3-vector, 3-state model), ``reg`` (λ, adaptive filter; one data set only: the FPKE terms
take one noise model for all trajectories), ``prior_scale`` (multiplies the prior covariance).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ..filter_loop import FilterSetup, filter_steps, initial_mixtures
from ..filters.registry import filter_spec, make_filter
from ..models import AttitudeModel
from ..quantiles import chi2_quantile
from .inputs import AttitudeInputs, recording_inputs
from .recordings import Recording

__all__ = [
    "PARAMETERS",
    "FitResult",
    "DatasetFits",
    "attitude_log_likelihood",
    "fit_attitude_parameters",
    "fit_datasets",
]

PARAMETERS = ("sigma_v", "sigma_u", "sigma_s", "bias", "reg", "prior_scale")
_POSITIVE = {"sigma_v", "sigma_u", "sigma_s", "reg", "prior_scale"}
F64 = torch.float64
#: How far below its starting value (in log) a positive parameter's estimate counts as at 0: a factor e^-12.
AT_ZERO = 12.0
#: The level of every verdict (each parameter's and the joint one).
LEVEL = 0.95
_Z95 = 1.959963984540054


@dataclass
class FitResult:
    """Learned values, 95 % intervals, the configured values and whether each lies inside.

    Attributes:
        learned / configured: name → value (float, or list of 3 for ``bias``).
        interval: name → (low, high) (per axis for ``bias``); NaN where the curvature
            is not positive definite.
        inside: name → the configured value passes the parameter's Wald test at 5 % (a scalar: it lies in the
            interval); ``None`` (no verdict) when the fit did not converge, the interval is undefined or the data
            do not identify it.
        notes: name → why the data do not identify it (the curvature of ``−ℓ`` in its fitted coordinate and
            the interval it gives), or ``None``.
        joint: the family-wise verdict over the identified parameters (module docstring): ``statistic``,
            ``dof``, ``p_value``, ``consistent`` (``None`` where nothing is judged).
        converged: Newton stopped on its tolerance, not on its iteration budget, and did not diverge.
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
    joint: dict = field(default_factory=dict)


@dataclass
class DatasetFits:
    """:func:`fit_datasets`'s result for ``D`` data sets (``p`` fitted coordinates).

    Attributes:
        names: the learned parameters; sizes: name → coordinates (1, or 3 for the bias).
        learned / configured: name → ``[D]`` (``[D, 3]`` for the bias), natural units.
        fitted: ``[D, p]`` the estimate in the fitted coordinates (``log`` of a positive parameter).
        half_width: ``[D, p]`` 95 % half-widths there (NaN where the curvature does not define one).
        low / high: name → the 95 % interval, natural units.
        curvature: ``[D, p]`` the diagonal of the Hessian of ``−ℓ`` at the estimate.
        identified: name → ``[D]`` bool: positive curvature and an interval no wider than
            :data:`WIDEST_LOG_INTERVAL` / :data:`WIDEST_BIAS_INTERVAL`.
        statistic: name → ``[D]`` the parameter's statistic at its configured value (χ² with ``sizes[name]``
            degrees of freedom at the truth): the likelihood ratio when it is the only one learned, else Wald's;
            inside: name → ``[D]`` bool, it passes at 5 %.
        judged: name → ``[D]`` bool: a verdict is given (converged and identified).
        joint_statistic / joint_dof / joint_p_value: ``[D]`` the likelihood-ratio test of the configured values,
            ``2(ℓ(θ̂) − ℓ(θ₀))`` against χ² with ``p`` degrees of freedom (every learned coordinate);
            joint_consistent: ``[D]`` bool (meaningful where converged).
        alternative_ratio: ``[A, D]`` the same statistic at each of ``alternatives``.
        converged / diverged: ``[D]`` bool; iterations: ``[D]`` Newton iterations; nll: ``[D]`` −ℓ at the estimate;
        history: −ℓ ``[D]`` per iteration.
    """

    names: tuple
    sizes: dict
    learned: dict
    configured: dict
    fitted: Tensor
    half_width: Tensor
    low: dict
    high: dict
    curvature: Tensor
    identified: dict
    statistic: dict
    inside: dict
    judged: dict
    joint_statistic: Tensor
    joint_dof: Tensor
    joint_p_value: Tensor
    joint_consistent: Tensor
    converged: Tensor
    diverged: Tensor
    iterations: Tensor
    nll: Tensor
    alternative_ratio: Tensor
    history: list = field(default_factory=list)


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
    per_trajectory: bool = False,
) -> Tensor:
    """``Σ_b Σ_updates log Σᵢ wᵢβᵢ`` of a recording under the parameters ``params``.

    The recording drives the one filter loop (:func:`agsf_torch.filter_loop.filter_steps`)
    through the attitude adapter, as ``agsf run`` does: invalid gyro samples
    (``gyro_valid``) are held with the covariance inflation of
    :class:`~agsf_torch.attitude.gyro_hold.GyroHold`; the 3-state model subtracts its ``bias``
    parameter (the bias is learned here, not known).

    Args:
        rec: the recording (``B`` trajectories; sample 0 is the prior's time).
        params: ``sigma_v``, ``sigma_u``, ``sigma_s``, ``bias``, ``reg``, ``prior_scale`` (tensors; any may
            require grad), each one for all trajectories (``[]``, ``[3]`` for the bias) or one per trajectory
            (``[B]``, ``[B, 3]``; not ``reg``, and not with the adaptive filters, whose FPKE terms take one model).
        prior_mean: ``[B, n]``; prior_cov: ``[n, n]`` (scaled by ``prior_scale``).
        filter_kind: a registered filter name (:data:`~agsf_torch.filters.registry.FILTER_NAMES`).
        num_components: components of a mixture filter (one-component filters ignore it).
        noise_model: the star-vector noise model (:class:`~agsf_torch.models.StarVectorMeasurement`).
        gate_probability: the filter's innovation gate (:mod:`agsf_torch.gating`), ``None``: off.
        gyro_hold_sigma: σ_h of the gyro hold (rad/s); default ``σ_v/√Δt`` of the first interval.
        per_trajectory: return ``[B]``, each trajectory's log-likelihood, instead of their sum.
    """
    B = int(torch.as_tensor(prior_mean).shape[0])
    sigma_v, sigma_u, sigma_s, bias, prior_scale = (
        _per_trajectory(name, params[name], B, event)
        for name, event in (("sigma_v", 0), ("sigma_u", 0), ("sigma_s", 0), ("bias", 1), ("prior_scale", 0))
    )
    model = AttitudeModel(
        estimate_bias=estimate_bias,
        sigma_v=sigma_v[:, None] if sigma_v.dim() else sigma_v,
        sigma_u=sigma_u[:, None] if sigma_u.dim() else sigma_u,
        bias=bias[:, None] if bias.dim() > 1 else bias,
    )
    spec = filter_spec(filter_kind)
    options = {"update_iterations": update_iterations, "gate_probability": gate_probability}
    if filter_kind == "AGSF":
        options["reg"] = params["reg"]
    setup = FilterSetup(make_filter(filter_kind, model, **options), num_components if spec.mixture else 1)
    scale = prior_scale[:, None, None] if prior_scale.dim() else prior_scale
    cov0 = scale * torch.as_tensor(prior_cov, dtype=F64)
    mixtures = initial_mixtures({"filter": setup}, torch.as_tensor(prior_mean, dtype=F64), cov0)
    if gyro_hold_sigma is None:
        dt0 = float(rec.time[1] - rec.time[0]) if rec.num_samples > 1 else 1.0
        gyro_hold_sigma = sigma_v / dt0**0.5
    adapter = AttitudeInputs(sigma_s=sigma_s, gyro_hold_sigma=gyro_hold_sigma, noise_model=noise_model)
    total = torch.zeros(B, dtype=F64)
    for step in filter_steps({"filter": setup.filter}, mixtures, recording_inputs(rec, adapter)):
        ll = step.filters["filter"].log_likelihood
        if ll is not None:
            total = total + ll
    return total if per_trajectory else total.sum()


def _per_trajectory(name: str, value, B: int, event: int) -> Tensor:
    """``value`` as a tensor, ``[]``/``[3]`` (one for all) or ``[B]``/``[B, 3]`` (one per trajectory); any other
    shape is refused, naming ``name``."""
    t = torch.as_tensor(value, dtype=F64) if not isinstance(value, Tensor) else value
    if t.dim() == event or (t.dim() == event + 1 and t.shape[0] == B):
        return t
    want = "[] or [B]" if event == 0 else "[3] or [B, 3]"
    raise ValueError(f"{name} must be {want} (B = {B} trajectories), got {tuple(t.shape)}")


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
    """Maximum-likelihood fit of the parameters in ``learn`` on all of ``rec`` (one data set), the others held
    at ``configured``: :func:`fit_datasets` with ``datasets = 1``.

    Args:
        rec: training recording.
        configured: every parameter of :data:`PARAMETERS` (the starting point and the values judged).
        learn: the names to fit.
        max_iter: Newton iterations.
        log: optional ``log(iteration, nll, values)`` (e.g. TensorBoard).
        **likelihood_kwargs: passed to :func:`attitude_log_likelihood`.
    """

    def log_one(iteration: int, nll: Tensor, values: dict) -> None:
        if log is not None:
            log(iteration, float(nll[0]), {k: _plain(v[0]) for k, v in values.items()})

    fits = fit_datasets(
        rec,
        configured,
        learn,
        datasets=1,
        prior_mean=prior_mean,
        prior_cov=prior_cov,
        max_iter=max_iter,
        log=log_one,
        **likelihood_kwargs,
    )
    converged, diverged = bool(fits.converged[0]), bool(fits.diverged[0])
    iterations = int(fits.iterations[0])
    if diverged:
        message = "diverged: stopped with the last finite parameters"
    elif not converged and iterations < max_iter:
        message = "not converged: no shorter Newton step decreased −log-likelihood (flat or noisy there)"
    elif not converged:
        message = f"not converged: Newton used all {max_iter} iterations (raise --max-iter)"
    else:
        message = f"converged after {iterations} Newton iterations"
    learned, interval, inside, notes, i = {}, {}, {}, {}, 0
    for k in fits.names:
        s = fits.sizes[k]
        learned[k] = _plain(fits.learned[k][0])
        interval[k] = (_plain(fits.low[k][0]), _plain(fits.high[k][0]))
        notes[k] = _identification(k, fits.curvature[0, i : i + s], fits.half_width[0, i : i + s])
        inside[k] = bool(fits.inside[k][0]) if bool(fits.judged[k][0]) else None
        i += s
    joint = {}
    if converged and int(fits.joint_dof[0]) > 0:
        joint = {
            "statistic": float(fits.joint_statistic[0]),
            "dof": int(fits.joint_dof[0]),
            "p_value": float(fits.joint_p_value[0]),
            "consistent": bool(fits.joint_consistent[0]),
        }
    history = [float(h[0]) for h in fits.history]
    configured_out = {k: _plain(fits.configured[k][0]) for k in fits.names}
    return FitResult(
        learned, configured_out, interval, inside, float(fits.nll[0]), history, converged, message, notes, joint
    )


def fit_datasets(
    rec: Recording,
    configured: Mapping[str, object],
    learn: list[str],
    *,
    datasets: int,
    prior_mean: Tensor,
    prior_cov: Tensor,
    max_iter: int = 40,
    tolerance: float = 1e-6,
    log: Callable[[int, Tensor, dict], None] | None = None,
    chunk: int | None = None,
    alternatives: Sequence[Mapping[str, object]] = (),
    **likelihood_kwargs,
) -> DatasetFits:
    """Maximum-likelihood fits of ``datasets`` independent data sets in one batched program.

    The ``B`` trajectories of ``rec`` are grouped consecutively into ``D = datasets`` data sets of ``B / D``
    each; data set ``d`` has its own parameters ``θ_d`` (the model's noise per trajectory), so
    ``−ℓ(θ) = Σ_d −ℓ_d(θ_d)`` and its Hessian is block diagonal.  Each iteration forms ``g_d`` and the ``p × p``
    blocks ``H_d`` (``p + 1`` backward passes through one forward pass), takes the Newton step
    ``Δ_d = −V|Λ|⁻¹Vᵀg_d`` (``H_d = VΛVᵀ``, so the step descends where ``H_d`` is indefinite; at most a factor
    ``e`` on a positive parameter, 10 °/h on the bias) and halves it, data set by data set, until
    ``−ℓ_d`` falls by ``10⁻⁴`` of the predicted decrease.  A data set has converged when its Newton decrement
    ``½ g_dᵀ|H_d|⁻¹g_d`` (the predicted decrease, nats, whatever the coordinates' units) is below ``tolerance``,
    or when a positive parameter has fallen :data:`AT_ZERO` below its start in log (the maximum is at 0); it then
    stays where it is.  A flat direction (the data do not constrain it) has a zero decrement.

    Args:
        rec: the recording (``B`` trajectories, ``B`` a multiple of ``datasets``).
        configured: every parameter of :data:`PARAMETERS` (one value for all data sets: the starting point and
            the value judged).
        learn: the names to fit (not ``reg`` unless ``datasets = 1``).
        datasets: ``D``.
        prior_mean: ``[B, n]``; prior_cov: ``[n, n]``.
        max_iter: Newton iterations.
        tolerance: the Newton decrement at convergence (nats).
        log: optional ``log(iteration, nll [D], values)``, values name → ``[D]`` / ``[D, 3]``.
        chunk: fit at most this many data sets at a time, one group after another (the autograd graph of a pass
            holds every step of every trajectory: the memory it takes); ``None``: all at once.
        alternatives: other values of the learned parameters (name → value, one for all data sets) at which the
            likelihood-ratio statistic is also evaluated (:attr:`DatasetFits.alternative_ratio`): how often a filter
            configured there would be judged mis-modelled, one forward pass each.
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
    if len(set(learn)) != len(learn):
        raise ValueError(f"a parameter is named twice in {list(learn)}")
    base = {k: torch.as_tensor(v, dtype=F64) for k, v in configured.items()}
    for k in _POSITIVE & set(learn):
        if not bool((base[k] > 0).all()):
            raise ValueError(f"configured {k} must be > 0 to be log-parametrised, got {base[k].tolist()}")
    if isinstance(datasets, bool) or not isinstance(datasets, int) or datasets < 1:
        raise ValueError(f"datasets must be a positive integer, got {datasets!r}")
    B = int(torch.as_tensor(prior_mean).shape[0])
    if B % datasets:
        raise ValueError(f"{B} trajectories do not split into {datasets} data sets of equal size")
    if datasets > 1 and "reg" in learn:
        raise ValueError("reg (the adaptive filter's λ) is learned from one data set at a time (datasets=1)")
    D, per = datasets, B // datasets
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"chunk must be a positive integer or None, got {chunk!r}")
    if chunk is not None and chunk < D:
        parts = []
        for start in range(0, D, chunk):  # groups of data sets, for memory: each group is batched
            rows = np.arange(start * per, min(D, start + chunk) * per)
            parts.append(
                fit_datasets(
                    rec.trajectories(rows),
                    configured,
                    learn,
                    datasets=len(rows) // per,
                    prior_mean=torch.as_tensor(prior_mean)[rows],
                    prior_cov=prior_cov,
                    max_iter=max_iter,
                    tolerance=tolerance,
                    alternatives=alternatives,
                    **likelihood_kwargs,
                )
            )
        return _concatenate(parts)
    names = tuple(learn)
    sizes = {k: base[k].numel() for k in names}
    p = sum(sizes.values())
    x0 = torch.cat([(base[k].log() if k in _POSITIVE else base[k]).reshape(-1) for k in names])
    positive = torch.cat([torch.full((sizes[k],), k in _POSITIVE) for k in names])
    cap = torch.cat(
        [torch.full((sizes[k],), 1.0 if k in _POSITIVE else 10.0 * WIDEST_BIAS_INTERVAL, dtype=F64) for k in names]
    )

    def unpack(x: Tensor) -> dict[str, Tensor]:
        """``x [k, p]`` → the parameters, the learned ones per data set ``[k]`` / ``[k, 3]``."""
        out, i = {}, 0
        for k in names:
            v = x[:, i : i + sizes[k]].reshape(x.shape[0], *base[k].shape)
            out[k] = v.exp() if k in _POSITIVE else v
            i += sizes[k]
        return out

    mean0 = torch.as_tensor(prior_mean, dtype=F64)

    def nll(x: Tensor, which: Tensor) -> Tensor:
        """``−ℓ_d`` ``[k]`` at ``x [k, p]`` of the data sets ``which [k]`` (indices): only their trajectories run."""
        values = unpack(x)
        params = dict(base)
        for k, v in values.items():
            params[k] = v.repeat_interleave(per, 0)
        if D == 1:  # one for all: the fused paths and the FPKE terms take it
            params.update({k: v[0] for k, v in values.items()})
        rows = (which[:, None] * per + torch.arange(per)).reshape(-1)
        part = rec if len(which) == D else rec.trajectories(rows.numpy())
        ll = attitude_log_likelihood(
            part, params, prior_mean=mean0[rows], prior_cov=prior_cov, per_trajectory=True, **likelihood_kwargs
        )
        return -ll.reshape(len(which), per).sum(1)

    x = x0.expand(D, p).clone()
    active = torch.ones(D, dtype=torch.bool)
    converged = torch.zeros(D, dtype=torch.bool)
    diverged = torch.zeros(D, dtype=torch.bool)
    iterations = torch.zeros(D, dtype=torch.int64)
    f = torch.full((D,), float("nan"), dtype=F64)
    H = torch.full((D, p, p), float("nan"), dtype=F64)
    # a positive parameter this far below its starting value has its maximum at 0 (the data show none of it):
    # the likelihood flattens there and Newton would creep towards it, e^-1 an iteration
    floor = torch.where(positive, x0 - AT_ZERO, torch.full_like(x0, -math.inf))
    history: list[Tensor] = []
    for iteration in range(max_iter + 1):
        which = active.nonzero().flatten()
        if not len(which):  # every data set stopped in the last line search
            break
        fa, ga, Ha = _value_gradient_hessian(lambda z: nll(z, which), x[which])
        f[which], H[which] = fa, Ha
        bad = ~(torch.isfinite(fa) & torch.isfinite(ga).all(1) & torch.isfinite(Ha).flatten(1).all(1))
        diverged[which[bad]] = True  # a point whose value was finite gave a non-finite gradient
        history.append(f.clone())
        if log is not None:
            log(iteration + 1, f.clone(), {k: v.detach() for k, v in unpack(x).items()})
        step, decrement, definite = _newton_step(ga, Ha)
        at_zero = (x[which] <= floor).any(1)
        done = ~bad & (at_zero | (0.5 * decrement <= tolerance))
        converged[which[done]] = True
        active[which[bad | done]] = False
        keep = ~(bad | done)
        which, step, g_kept = which[keep], step[keep], ga[keep]
        if not len(which) or iteration == max_iter:
            break
        scale = torch.clamp(cap / step.abs().clamp_min(1e-300), max=1.0).amin(1, keepdim=True)
        step = step * scale
        slope = (g_kept * step).sum(1)  # < 0: a descent direction
        x_new, moved, nonfinite = _backtrack(lambda z, m: nll(z, which[m]), x[which], f[which], step, slope)
        x[which] = x_new
        diverged[which[~moved & nonfinite]] = True  # every shorter step gave a non-finite likelihood
        iterations[which] += 1
        # no decrease along a descent direction: the optimum to rounding where the decrement is small, else stuck
        near = definite[keep] & (0.5 * decrement[keep] <= 1e3 * tolerance)
        converged[which[~moved & near]] = True
        active[which[~moved]] = False
    every = torch.arange(D)
    with torch.no_grad():
        ratio = 2.0 * (nll(x0.expand(D, p), every) - f)  # the likelihood-ratio statistic at the configured values
        others = []
        for values in alternatives:
            unknown = [k for k in values if k not in names]
            if unknown:
                raise ValueError(f"alternatives name {unknown}, which are not learned ({list(names)})")
            point = dict(base, **{k: torch.as_tensor(v, dtype=F64) for k, v in values.items()})
            xa = torch.cat([(point[k].log() if k in _POSITIVE else point[k]).reshape(-1) for k in names])
            others.append(2.0 * (nll(xa.expand(D, p), every) - f))
        alternative = torch.stack(others) if others else torch.zeros(0, D, dtype=F64)
        return _summarise(
            names,
            sizes,
            base,
            x,
            H,
            unpack(x),
            f,
            converged & ~diverged,
            diverged,
            iterations,
            history,
            ratio,
            alternative,
        )


def _concatenate(parts: list[DatasetFits]) -> DatasetFits:
    """The fits of groups of data sets as one (their histories: −ℓ per iteration, NaN once a group has stopped)."""
    first = parts[0]

    def cat(get):
        values = [get(p) for p in parts]
        if isinstance(values[0], dict):
            return {k: torch.cat([v[k] for v in values]) for k in values[0]}
        return torch.cat(values)

    longest = max(len(p.history) for p in parts)
    history = [
        torch.cat([p.history[i] if i < len(p.history) else torch.full_like(p.history[0], float("nan")) for p in parts])
        for i in range(longest)
    ]
    tensors = {
        f: cat(lambda p, f=f: getattr(p, f))
        for f in DatasetFits.__dataclass_fields__
        if f not in ("names", "sizes", "history", "alternative_ratio")
    }
    tensors["alternative_ratio"] = torch.cat([p.alternative_ratio for p in parts], 1)
    return DatasetFits(names=first.names, sizes=first.sizes, history=history, **tensors)


def _value_gradient_hessian(nll: Callable[[Tensor], Tensor], x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(f [D], g [D, p], H [D, p, p])`` of the block-separable ``f`` at ``x [D, p]``: ``H[:, :, j]`` is the
    gradient of ``Σ_d g_dj`` (the blocks do not couple data sets).  An error inside the filter (a failed
    factorisation at a wild point) gives NaN, which the caller treats as a diverged data set."""
    x = x.detach().requires_grad_(True)
    try:
        f = nll(x)
        (g,) = torch.autograd.grad(f.sum(), x, create_graph=True)
        columns = [torch.autograd.grad(g[:, j].sum(), x, retain_graph=True)[0] for j in range(x.shape[1])]
    except (RuntimeError, ValueError):
        nan = torch.full(x.shape[:1], float("nan"), dtype=x.dtype)
        return nan, torch.full_like(x, float("nan")), torch.full((*x.shape, x.shape[1]), float("nan"), dtype=x.dtype)
    H = torch.stack(columns, -1).detach()
    return f.detach(), g.detach(), 0.5 * (H + H.transpose(-1, -2))


def _newton_step(g: Tensor, H: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(Δ [D, p], gᵀ|H|⁻¹g [D], H positive definite [D])``: ``Δ = −V|Λ|⁻¹Vᵀg`` with the eigenvalues' magnitudes
    floored at ``10⁻¹²·max|λ|`` (and a tiny absolute floor), a descent direction wherever ``g ≠ 0``."""
    g0 = torch.nan_to_num(g)
    lam, V = torch.linalg.eigh(torch.nan_to_num(H))
    mag = lam.abs()
    floor = (1e-12 * mag.amax(-1, keepdim=True)).clamp_min(1e-300)
    w = (V.transpose(-1, -2) @ g0.unsqueeze(-1)).squeeze(-1) / torch.maximum(mag, floor)
    step = -(V @ w.unsqueeze(-1)).squeeze(-1)
    return step, -(g0 * step).sum(1), (lam > 0).all(-1)


def _backtrack(
    nll: Callable[[Tensor], Tensor],
    x: Tensor,
    f: Tensor,
    step: Tensor,
    slope: Tensor,
    halvings: int = 8,
) -> tuple[Tensor, Tensor, Tensor]:
    """Armijo backtracking per data set: ``x + αΔ`` with ``α = 1, ½, …, 2⁻⁸`` until ``f(x + αΔ) ≤ f + 10⁻⁴α gᵀΔ``;
    returns the new ``x``, which data sets moved and which met a non-finite likelihood.  ``nll(x_k, mask)`` evaluates the data sets ``mask``; one
    batched evaluation per halving, of the data sets still trying a shorter step."""
    alpha = torch.ones_like(f)
    pending = torch.ones(f.shape, dtype=torch.bool)
    accepted = torch.zeros_like(pending)
    nonfinite = torch.zeros_like(pending)
    with torch.no_grad():
        for _ in range(halvings):
            trial = x + alpha[:, None] * step
            ft = torch.full_like(f, float("inf"))
            try:
                ft[pending] = nll(trial[pending], pending)
            except (RuntimeError, ValueError):  # a failed factorisation at a wild point: shorter steps for all
                alpha = torch.where(pending, 0.5 * alpha, alpha)
                continue
            nonfinite |= pending & ~torch.isfinite(ft)
            ok = pending & torch.isfinite(ft) & (ft <= f + 1e-4 * alpha * slope)
            accepted |= ok
            pending &= ~ok
            if not bool(pending.any()):
                break
            alpha = torch.where(pending, 0.5 * alpha, alpha)
    alpha = torch.where(accepted, alpha, torch.zeros_like(alpha))
    return x + alpha[:, None] * step, accepted, nonfinite


def _summarise(
    names, sizes, base, x, H, values, f, converged, diverged, iterations, history, ratio, alternative
) -> DatasetFits:
    """Intervals from the inverse Hessian of each data set's positive-curvature coordinates, the verdicts (the
    likelihood ratio jointly and for a single parameter, Wald's for each of several) and the identification flags,
    all ``[D]``-batched."""
    D, p = x.shape
    curvature = H.diagonal(dim1=-2, dim2=-1)
    kept = curvature > 0  # [D, p]: coordinates the data constrain
    both = kept[:, :, None] & kept[:, None, :]
    eye = torch.eye(p, dtype=x.dtype).expand(D, p, p)
    Hk = torch.where(both, H, eye)
    L, info = torch.linalg.cholesky_ex(Hk)
    cov = torch.cholesky_inverse(L)
    usable = (info == 0)[:, None] & kept
    half = torch.where(usable, _Z95 * cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt(), float("nan"))
    learned, configured, low, high, identified, statistic, inside, judged = ({} for _ in range(8))
    x_conf = torch.cat([(base[k].log() if k in _POSITIVE else base[k]).reshape(-1) for k in names]).expand(D, p)
    coordinate_ok = torch.zeros(D, p, dtype=torch.bool)
    i = 0
    for k in names:
        s = sizes[k]
        sl = slice(i, i + s)
        lo, hi = x[:, sl] - half[:, sl], x[:, sl] + half[:, sl]
        if k in _POSITIVE:
            lo, hi = lo.exp(), hi.exp()
        shape = (D, *base[k].shape)
        learned[k], low[k], high[k] = values[k], lo.reshape(shape), hi.reshape(shape)
        configured[k] = base[k].expand(shape)
        widest = WIDEST_LOG_INTERVAL if k in _POSITIVE else WIDEST_BIAS_INTERVAL
        ident = (kept[:, sl] & torch.isfinite(half[:, sl]) & (half[:, sl] <= widest)).all(1)
        identified[k] = ident
        coordinate_ok[:, sl] = ident[:, None]
        single = len(names) == 1  # the likelihood ratio is the parameter's own test
        wald = _wald(x[:, sl] - x_conf[:, sl], cov[:, sl, sl], usable[:, sl])
        statistic[k] = ratio.clamp_min(0.0) if single else wald
        inside[k] = statistic[k] <= chi2_quantile(LEVEL, s)
        judged[k] = ident & converged & torch.isfinite(statistic[k])
        i += s
    joint = ratio.clamp_min(0.0)  # below 0 only by the rounding of a converged maximum
    dof = torch.full((D,), p, dtype=torch.int64)
    limit = torch.tensor([chi2_quantile(LEVEL, int(k)) if k > 0 else float("nan") for k in dof.tolist()])
    from scipy.special import gammaincc

    p_value = torch.as_tensor(gammaincc(dof.to(F64).clamp_min(1).numpy() / 2, joint.numpy() / 2), dtype=F64)
    p_value = torch.where(dof > 0, p_value, float("nan"))
    return DatasetFits(
        names=names,
        sizes=sizes,
        learned=learned,
        configured=configured,
        fitted=x,
        half_width=half,
        low=low,
        high=high,
        curvature=curvature,
        identified=identified,
        statistic=statistic,
        inside=inside,
        judged=judged,
        joint_statistic=joint,
        joint_dof=dof,
        joint_p_value=p_value,
        joint_consistent=(dof > 0) & (joint <= limit),
        alternative_ratio=alternative.clamp_min(0.0),
        converged=converged,
        diverged=diverged,
        iterations=iterations,
        nll=f,
        history=history,
    )


def _wald(d: Tensor, cov: Tensor, use: Tensor) -> Tensor:
    """``dᵀ C_UU⁻¹ d`` over the coordinates ``use [D, q]`` of each data set (``d [D, q]``, ``C [D, q, q]``), by a
    Cholesky solve; 0 where none is used, NaN where ``C_UU`` is not positive definite."""
    both = use[:, :, None] & use[:, None, :]
    eye = torch.eye(d.shape[1], dtype=d.dtype).expand_as(cov)
    L, info = torch.linalg.cholesky_ex(torch.where(both, cov, eye))
    du = torch.where(use, d, torch.zeros_like(d))
    z = torch.linalg.solve_triangular(L, du.unsqueeze(-1), upper=False).squeeze(-1)
    return torch.where(info == 0, (z * z).sum(1), float("nan"))


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
