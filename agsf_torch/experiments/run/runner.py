"""Monte Carlo runner: drive filters on the batched star-tracker environment.

All filters of one run see the same truth, gyro samples and star frames: the
environment is stepped once per gyro period and every filter consumes the same
observation.  The only Python loops are over time and over the (few) filters.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ...attitude.inputs import AttitudeInputs, as_float64
from ...consistency import nees, rms
from ...filter_loop import PRIOR_SEED_OFFSET, FilterSetup, FilterStep, filter_steps, initial_mixtures, sample_prior
from ...rotations import attitude_error_angle, attitude_error_jacobian, attitude_error_vector, uniform_mrp

__all__ = [
    "FilterSetup",
    "FilterStep",
    "FilterTrace",
    "MonteCarloResult",
    "SimulatedStep",
    "monte_carlo_steps",
    "run_monte_carlo",
    "rotation_error",
    "rotation_sigma",
    "sample_prior",
]


@dataclass
class FilterTrace:
    """Per-time metrics of one filter over ``B`` trajectories and ``T`` steps (numpy, batch first).

    Attributes:
        estimate: the filter's estimate, its mixture's mean ``[B, T, n]`` (MRP, then the bias in rad/s).
        sigma: 1σ of the estimate's error ``[B, T, n]`` from the filter's covariance: the MRP
            covariance mapped to the rotation error by ``J P Jᵀ``
            (:func:`~agsf_torch.rotations.attitude_error_jacobian`), the bias part as is.
        cov: the filter's covariance ``[B, T, n, n]`` in its own chart (MRP² and (rad/s)²).
        nis: mixture NIS at star frames, NaN elsewhere ``[B, T]``; ``nis_dof`` its
            number of valid entries ``[B, T]``.
        weights: ``[B, T, N]``.
        weight_entropy: ``[B, T]``.
        error_angle: attitude error angle (rad) ``[B, T]``; ``None`` without the truth (a replay of flight data).
        error: state error ``[B, T, n]``: the attitude part is the rotation error, the
            small-angle vector of ``q_est ⊗ q_true⁻¹`` (rad, body axes of the truth;
            :func:`~agsf_torch.rotations.attitude_error_vector`), the bias part in rad/s; ``None`` without the truth.
        nees: ``eᵀP⁻¹e`` in the filter's chart ``[B, T]``; ``None`` without the truth.
        extra: any further per-step diagnostics of the filter, ``name -> [B, T, ...]``.
    """

    estimate: np.ndarray
    sigma: np.ndarray
    cov: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    weights: np.ndarray
    weight_entropy: np.ndarray
    error_angle: np.ndarray | None = None
    error: np.ndarray | None = None
    nees: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def rms_error(self) -> np.ndarray:
        """RMS attitude error angle over trajectories, ``[T]`` (rad); needs the truth."""
        if self.error_angle is None:
            raise ValueError("no attitude error without the truth (a replay of a recording without it)")
        return rms(self.error_angle, 0)


@dataclass
class MonteCarloResult:
    """Times ``[T]`` (s), star-frame flags ``[T]``, one :class:`FilterTrace` per filter and the attitude error
    of the prior mean at ``t = 0`` (every filter's estimate before its first step) ``[B]`` (rad; ``None`` without
    the truth)."""

    time: np.ndarray
    star_frame: np.ndarray
    traces: dict[str, FilterTrace]
    state_dim: int
    prior_error_angle: np.ndarray | None = None


@dataclass
class SimulatedStep:
    """Everything of one step for every filter: ``time`` (s), ``star_frame``, the truth
    ``x_true [B, n]`` / ``truth_mrp [B, 3]``, ``filters``: name → :class:`FilterStep`, and
    what the filters were given: ``u [B, 3]`` (the gyro input of the interval, bias-compensated
    in the 3-state model; invalid samples bridged by the last valid one, whose extra
    uncertainty the filters add to their covariance but ``u`` itself does not carry) and, at a star frame, ``measurement``
    ``(y [B, d], StarVectorMeasurement)``; ``prior_mean [B, n]`` is the mean of the Gaussian prior
    ``N(prior_mean, prior_cov)`` every filter's initial mixture was split from (its estimate at ``t = 0``,
    against the truth then ``prior_truth_mrp [B, 3]``); ``chart_error``:
    name → the state error of the filter's estimate against the truth in the estimate's chart
    ``[B, n]`` (MRP and rad/s: the units of the covariance, for NEES; :class:`FilterTrace`
    stores the error as a rotation instead, :func:`rotation_error`).  Without the truth (an environment whose
    ``reset`` gives an initial estimate, ``initial_mrp`` and ``initial_bias``, instead: a replay of flight data)
    ``x_true``, ``truth_mrp`` and ``prior_truth_mrp`` are ``None`` and ``chart_error`` is empty."""

    index: int
    time: float
    star_frame: bool
    x_true: Tensor | None
    truth_mrp: Tensor | None
    filters: dict[str, FilterStep]
    u: Tensor | None = None
    measurement: tuple | None = None
    prior_mean: Tensor | None = None
    chart_error: dict[str, Tensor] = field(default_factory=dict)
    prior_truth_mrp: Tensor | None = None


def monte_carlo_steps(
    env,
    filters: Mapping[str, FilterSetup],
    *,
    num_steps: int,
    prior_cov: Tensor,
    sigma_s: float,
    seed: int = 0,
    estimate_bias: bool = False,
    noise_model: str = "isotropic",
    gyro_hold_sigma: float | None = None,
    uniform_attitude: bool = False,
):
    """Drive every filter over ``num_steps`` gyro periods, yielding one :class:`SimulatedStep` per period.

    The environment side of the one filter loop (:func:`agsf_torch.filter_loop.filter_steps`):
    the attitude adapter (:class:`~agsf_torch.attitude.inputs.AttitudeInputs`) turns each
    observation into the filters' input, and the environment is stepped with the first
    filter's estimate as action.  Behind :func:`run_monte_carlo` (which keeps every step),
    the soak and the adaptation study (which keep running statistics); arguments as there.
    """
    first = next(iter(filters))
    n = filters[first].filter.model.state_dim
    if n != (6 if estimate_bias else 3):
        raise ValueError(f"the filters' model has {n} states, but estimate_bias={estimate_bias}")
    prior_cov = torch.as_tensor(prior_cov, dtype=torch.float64)
    if prior_cov.shape != (n, n):
        raise ValueError(
            f"prior_cov must be [{n}, {n}] for estimate_bias={estimate_bias}, got {tuple(prior_cov.shape)}"
        )
    if env.config.max_steps < num_steps:
        raise ValueError(f"the environment ends after max_steps={env.config.max_steps} < num_steps={num_steps}")
    obs, info = env.reset(seed=seed)
    truthful = "truth_mrp" in info
    if truthful:
        truth_p, truth_b = as_float64(info["truth_mrp"]), as_float64(info["truth_bias"])
        gen = torch.Generator().manual_seed(int(seed) + PRIOR_SEED_OFFSET)
        mean0 = sample_prior(torch.cat((truth_p, truth_b), -1)[:, :n], prior_cov, gen)
        if uniform_attitude:  # a lost-in-space start: the prior's attitude uniformly random, whatever the truth
            mean0 = torch.cat((uniform_mrp(truth_p.shape[0], gen), mean0[:, 3:]), -1)
    elif "initial_mrp" in info:  # no truth: the filters start at the environment's initial estimate
        truth_p, truth_b = None, as_float64(info["initial_bias"])
        mean0 = torch.cat((as_float64(info["initial_mrp"]), truth_b), -1)[:, :n]
    else:
        raise ValueError("the environment's reset gives neither the truth (truth_mrp) nor an initial estimate")
    truth0 = truth_p
    for setup in filters.values():
        setup.filter.reset()  # a filter follows one run: forget any earlier one
    mixtures = initial_mixtures(filters, mean0, prior_cov)
    dt = float(env.config.dt)
    if gyro_hold_sigma is None:
        gyro_hold_sigma = float(filters[first].filter.model.sigma_v) / dt**0.5
    adapter = AttitudeInputs(
        sigma_s=sigma_s, gyro_hold_sigma=gyro_hold_sigma, known_bias=not estimate_bias, noise_model=noise_model
    )
    adapter.start(obs, dt, truth_b)  # without the truth, the known bias (3 states) is the initial estimate's
    action = {"mrp": filters[first].filter.estimate(mixtures[first])[0][:, :3]}

    def inputs():
        bias, truth_p, x_true = truth_b, None, None  # without the truth: the initial estimate's bias throughout
        for _ in range(num_steps):
            obs, _, _, _, step_info = env.step(action["mrp"])
            if truthful:
                truth_p, bias = as_float64(step_info["truth_mrp"]), as_float64(step_info["truth_bias"])
                x_true = torch.cat((truth_p, bias), -1)[:, :n]
            time = float(as_float64(obs["time"]).reshape(-1)[0])
            yield adapter(obs, dt, bias, context=(time, truth_p, x_true))

    for step in filter_steps({k: s.filter for k, s in filters.items()}, mixtures, inputs()):
        action["mrp"] = step.filters[first].mean[:, :3]
        time, truth_p, x_true = step.input.context
        errors = (
            {}
            if x_true is None
            else {name: fs.filter.model.state_error(fs.mean, x_true) for name, fs in step.filters.items()}
        )
        yield SimulatedStep(
            step.index,
            time,
            step.input.measurement is not None,
            x_true,
            truth_p,
            step.filters,
            step.input.u,
            step.input.measurement,
            mean0,
            errors,
            truth0,
        )


def rotation_sigma(mean: Tensor, cov: Tensor) -> Tensor:
    """The 1σ of the estimate's error as a rotation (:class:`FilterTrace` ``sigma``): ``sqrt(diag(J P Jᵀ))``
    with ``J = ∂δθ/∂p`` at the estimate (rad) for the attitude, ``sqrt(diag P)`` (rad/s) for the bias.

    Args:
        mean: ``[..., n]`` (MRP, then the bias if ``n = 6``); cov: ``[..., n, n]`` in the MRP chart.

    Returns:
        ``[..., n]``.
    """
    n = mean.shape[-1]
    J = torch.eye(n, dtype=cov.dtype, device=cov.device).expand(cov.shape).clone()
    J[..., :3, :3] = attitude_error_jacobian(mean[..., :3])
    return (J @ cov @ J.transpose(-1, -2)).diagonal(dim1=-2, dim2=-1).sqrt()


def rotation_error(mean: Tensor, cov: Tensor, x_true: Tensor) -> tuple[Tensor, Tensor]:
    """The estimate's error as a rotation and its 1σ (:class:`FilterTrace` ``error``, ``sigma``).

    Args:
        mean: ``[..., n]`` (MRP, then the bias in rad/s if ``n = 6``); cov: ``[..., n, n]`` in the
            MRP chart; x_true: ``[..., n]``.

    Returns:
        ``(error [..., n], sigma [..., n])``: attitude part ``δθ`` of ``q_est ⊗ q_true⁻¹`` (rad)
        and :func:`rotation_sigma`; bias part ``b̂ − b`` (rad/s).
    """
    error = torch.cat((attitude_error_vector(mean[..., :3], x_true[..., :3]), mean[..., 3:] - x_true[..., 3:]), -1)
    return error, rotation_sigma(mean, cov)


def run_monte_carlo(
    env,
    filters: Mapping[str, FilterSetup],
    *,
    num_steps: int,
    prior_cov: Tensor,
    sigma_s: float,
    seed: int = 0,
    estimate_bias: bool = False,
    progress: bool = False,
    callback=None,
    noise_model: str = "isotropic",
    gyro_hold_sigma: float | None = None,
    uniform_attitude: bool = False,
    label: str = "monte carlo",
) -> MonteCarloResult:
    """Run every filter over ``num_steps`` gyro periods of a batched environment.

    Args:
        env: a batched ``agsf/StarTrackerAttitude-v0`` vector environment.
        filters: name → :class:`FilterSetup`.
        num_steps: gyro periods to simulate.
        prior_cov: ``[n, n]`` prior covariance (MRP² and (rad/s)²).
        sigma_s: star noise σ_s assumed by the filters (rad).
        seed: seeds the environment and the prior draws (without the truth the prior is not drawn: it is
            centred on the environment's initial estimate).
        estimate_bias: ``False`` → the filters' model is 3-state and the gyro
            is compensated with the true bias (the paper's "bias known"; without the truth, the initial
            estimate's); ``True`` → 6-state.
        progress: show a progress bar, labelled ``label``.
        callback: optional ``callback(step, name, filter, mixture)`` after each step.
        noise_model: star-vector noise model of the filters (``"isotropic"`` or ``"tangent"``).
        gyro_hold_sigma: σ_h of :class:`~agsf_torch.attitude.gyro_hold.GyroHold`, which bridges
            gyro samples the environment marks invalid (``gyro_valid``); default
            ``σ_v/√Δt`` of the first filter's model.
        uniform_attitude: the filters' prior attitude uniformly random, independent of the truth (a lost-in-space
            start; ``prior_cov`` then only says how wide the filters take their prior to be).

    Per-step extras of every trace (besides the filter's own diagnostics):
    ``gate_rejected [B, T]`` (star blocks rejected by the filter's innovation gate;
    0 without gating) and ``gyro_held [B, T]`` (1 where the gyro sample was bridged).  A managed filter's
    ``splits``, ``merges`` and ``prunes [B, T]`` count the step's predict and update together, and its
    ``active_components [B, T]`` is the count at the step's end (after the update at a star frame).
    """
    # per step the filters' own outputs; the scores against the truth are computed once, at the end, over [B, T]
    raw = ("mean", "cov", "chart_error", "nis", "nis_dof", "weights", "weight_entropy", "extra")
    records: dict[str, dict[str, list]] = {name: {k: [] for k in raw} for name in filters}
    times, frames, truths, truth_mrps = [], [], [], []
    steps = monte_carlo_steps(
        env,
        filters,
        num_steps=num_steps,
        prior_cov=prior_cov,
        sigma_s=sigma_s,
        seed=seed,
        estimate_bias=estimate_bias,
        noise_model=noise_model,
        gyro_hold_sigma=gyro_hold_sigma,
        uniform_attitude=uniform_attitude,
    )
    if progress:
        from .progress import progress_bar

        steps = progress_bar(steps, desc=label, unit="step", total=num_steps)
    prior_error = None
    for step in steps:
        if prior_error is None and step.prior_truth_mrp is not None:
            prior_error = attitude_error_angle(step.prior_mean[:, :3], step.prior_truth_mrp).numpy()
        times.append(step.time)
        frames.append(step.star_frame)
        if step.x_true is not None:
            truths.append(step.x_true)
            truth_mrps.append(step.truth_mrp)
        for name, fs in step.filters.items():
            rec = records[name]
            rec["mean"].append(fs.mean)
            rec["cov"].append(fs.cov)
            if name in step.chart_error:
                rec["chart_error"].append(step.chart_error[name])
            rec["nis"].append(fs.nis)
            rec["nis_dof"].append(fs.dof)
            rec["weights"].append(fs.mixture.weights)
            rec["weight_entropy"].append(fs.mixture.entropy_of_weights())
            rec["extra"].append(fs.extra)
            if callback is not None:
                callback(step.index, name, filters[name].filter, fs.mixture)

    traces = {}
    x_true, truth_mrp = (torch.stack(t, 1) if t else None for t in (truths, truth_mrps))
    for name, rec in records.items():
        extra, chart_error = rec.pop("extra"), rec.pop("chart_error")
        stacked = {k: torch.stack(v, 1) for k, v in rec.items()}
        mean, cov = stacked.pop("mean"), stacked["cov"]
        stacked["estimate"], stacked["sigma"] = mean, rotation_sigma(mean, cov)
        if x_true is not None:  # scored against the truth
            stacked["error"] = rotation_error(mean, cov, x_true)[0]
            stacked["error_angle"] = attitude_error_angle(mean[..., :3], truth_mrp)
            stacked["nees"] = nees(torch.stack(chart_error, 1), cov)
        extra_keys = extra[0].keys() if extra else []
        traces[name] = FilterTrace(
            **{k: v.numpy() for k, v in stacked.items()},
            extra={k: torch.stack([e[k] for e in extra], 1).numpy() for k in extra_keys},
        )
    state_dim = next(iter(filters.values())).filter.model.state_dim
    return MonteCarloResult(np.array(times), np.array(frames), traces, state_dim, prior_error)
