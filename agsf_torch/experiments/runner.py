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

from ..filters.gaussian_sum import GaussianSumFilter
from ..input_gaps import GyroHold
from ..metrics import nees
from ..mixture import GaussianMixture
from ..models.star_vectors import StarVectorMeasurement
from ..rotations import attitude_error_angle

__all__ = [
    "FilterSetup", "FilterStep", "FilterTrace", "MonteCarloResult", "Step", "monte_carlo_steps", "run_monte_carlo", "sample_prior",
]


@dataclass(frozen=True)
class FilterSetup:
    """A filter in a Monte Carlo run and its initial mixture size.

    Attributes:
        filter: any filter with the predict/update/estimate contract.
        num_components: components of the initial split of the prior.
        spread: share of the principal prior variance carried by the component means.
    """

    filter: GaussianSumFilter
    num_components: int = 1
    spread: float = 0.5


@dataclass
class FilterTrace:
    """Per-time metrics of one filter over ``T`` steps and ``B`` trajectories (numpy).

    Attributes:
        error_angle: attitude error angle (rad) ``[T, B]``.
        error: state error, attitude part in rad (small-angle, ``4 δp``) and bias in
            rad/s, ``[T, B, n]``.
        sigma: 1σ of the same quantities from the filter's covariance ``[T, B, n]``.
        nees: ``eᵀP⁻¹e`` ``[T, B]``.
        nis: mixture NIS at star frames, NaN elsewhere ``[T, B]``; ``nis_dof`` its
            number of valid entries ``[T, B]``.
        weights: ``[T, B, N]``.
        weight_entropy: ``[T, B]``.
        extra: any further per-step diagnostics of the filter, ``name -> [T, ...]``.
    """

    error_angle: np.ndarray
    error: np.ndarray
    sigma: np.ndarray
    nees: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    weights: np.ndarray
    weight_entropy: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def rms_error(self) -> np.ndarray:
        """RMS attitude error angle over trajectories, ``[T]`` (rad)."""
        return np.sqrt((self.error_angle**2).mean(1))


@dataclass
class MonteCarloResult:
    """Times ``[T]`` (s), star-frame flags ``[T]`` and one :class:`FilterTrace` per filter."""

    time: np.ndarray
    star_frame: np.ndarray
    traces: dict[str, FilterTrace]
    state_dim: int


def sample_prior(truth: Tensor, cov: Tensor, gen: torch.Generator) -> Tensor:
    """Prior means drawn consistently with the prior covariance: ``x̂₀ = x + L z``, ``z ~ N(0, I)``.

    Args:
        truth: ``[B, n]``; cov: ``[n, n]``; gen: the run's generator.
    """
    L = torch.linalg.cholesky(cov)
    z = torch.randn(truth.shape, generator=gen, dtype=truth.dtype, device=truth.device)
    return truth + z @ L.T


def _as_tensor(x, dtype=torch.float64) -> Tensor:
    return torch.as_tensor(np.asarray(x) if not torch.is_tensor(x) else x, dtype=dtype)


def _gyro_valid(obs, B: int) -> Tensor:
    """``obs["gyro_valid"]`` as ``[B]`` bool (all true when the source has no such key)."""
    if "gyro_valid" not in obs:
        return torch.ones(B, dtype=torch.bool)
    return _as_tensor(obs["gyro_valid"], torch.bool).reshape(B)


@dataclass
class FilterStep:
    """One filter after one step: its belief and what the step produced.

    Attributes:
        mixture: the belief at the step's time.
        mean, cov: its point estimate and covariance (``filter.estimate``), ``[B, n]``, ``[B, n, n]``.
        error: state error against the truth in the estimate's chart, ``[B, n]``
            (MRP and rad/s; multiply the attitude part by 4 for radians).
        nis: mixture NIS at a star frame, NaN elsewhere, ``[B]``; dof: its valid entries ``[B]``.
        extra: per-step diagnostics ``[B]`` (the filter's own, plus ``gate_rejected`` and ``gyro_held``).
    """

    mixture: GaussianMixture
    mean: Tensor
    cov: Tensor
    error: Tensor
    nis: Tensor
    dof: Tensor
    extra: dict[str, Tensor]


@dataclass
class Step:
    """Everything of one step for every filter: ``time`` (s), ``star_frame``, the truth
    ``x_true [B, n]`` / ``truth_mrp [B, 3]``, ``filters``: name → :class:`FilterStep`, and
    what the filters were given: ``u [B, 3]`` (the gyro input of the interval, bias-compensated
    in the 3-state model; invalid samples bridged by the last valid one, whose extra
    uncertainty the filters add to their covariance but ``u`` itself does not carry) and, at a star frame, ``measurement``
    ``(y [B, d], StarVectorMeasurement)``; ``prior_mean [B, n]`` is the mean of the Gaussian prior
    ``N(prior_mean, prior_cov)`` every filter's initial mixture was split from."""

    index: int
    time: float
    star_frame: bool
    x_true: Tensor
    truth_mrp: Tensor
    filters: dict[str, FilterStep]
    u: Tensor | None = None
    measurement: tuple | None = None
    prior_mean: Tensor | None = None


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
):
    """Drive every filter over ``num_steps`` gyro periods, yielding one :class:`Step` per period.

    The generator behind :func:`run_monte_carlo` (which keeps every step) and the
    soak test (which keeps running statistics only); arguments as there.
    """
    n = 6 if estimate_bias else 3
    prior_cov = torch.as_tensor(prior_cov, dtype=torch.float64)
    if prior_cov.shape != (n, n):
        raise ValueError(f"prior_cov must be [{n}, {n}] for estimate_bias={estimate_bias}, got {tuple(prior_cov.shape)}")
    if env.config.max_steps < num_steps:
        raise ValueError(f"the environment ends after max_steps={env.config.max_steps} < num_steps={num_steps}")
    obs, info = env.reset(seed=seed)
    truth_p = _as_tensor(info["truth_mrp"])
    truth_b = _as_tensor(info["truth_bias"])
    B = truth_p.shape[0]
    gen = torch.Generator().manual_seed(int(seed) + 7919)
    x_true = torch.cat((truth_p, truth_b), -1)[:, :n]
    mean0 = sample_prior(x_true, prior_cov, gen)
    mixtures: dict[str, GaussianMixture] = {}
    for name, setup in filters.items():
        setup.filter.reset()  # a filter follows one run: forget any earlier one
        mix = GaussianMixture.from_gaussian(mean0, prior_cov.expand(B, n, n), setup.num_components, setup.spread)
        m, P = setup.filter.model.canonicalize(mix.means, mix.covs)
        mixtures[name] = mix.replace(means=m, covs=P)
    dt = float(env.config.dt)
    prev_bias = truth_b
    first = next(iter(filters))
    if gyro_hold_sigma is None:
        gyro_hold_sigma = float(filters[first].filter.model.sigma_v) / dt**0.5
    hold = GyroHold(gyro_hold_sigma)
    hold.step(_as_tensor(obs["gyro"]), _gyro_valid(obs, B), dt)  # primes the hold with the reset reading
    for k in range(num_steps):
        action = filters[first].filter.estimate(mixtures[first])[0][:, :3]
        obs, _, _, _, info = env.step(action)
        truth_p = _as_tensor(info["truth_mrp"])
        truth_b = _as_tensor(info["truth_bias"])
        x_true = torch.cat((truth_p, truth_b), -1)[:, :n]
        gyro_valid = _gyro_valid(obs, B)
        gyro, held_var = hold.step(_as_tensor(obs["gyro"]), gyro_valid, dt)
        any_held = bool((~gyro_valid).any())
        # known bias: remove exactly the bias term ½(b_k + b_{k+1}) of the gyro model
        u = gyro if estimate_bias else gyro - 0.5 * (prev_bias + truth_b)
        prev_bias = truth_b
        mask = torch.as_tensor(obs["star_mask"], dtype=torch.bool)
        has_stars = bool(mask.any())
        if has_stars:
            y, meas = StarVectorMeasurement.from_observation(
                {"star_body": _as_tensor(obs["star_body"]), "star_inertial": _as_tensor(obs["star_inertial"]), "star_mask": mask},
                sigma_s,
                noise_model=noise_model,
            )
        time = float(_as_tensor(obs["time"]).reshape(B, -1)[0, 0])
        out: dict[str, FilterStep] = {}
        for name, setup in filters.items():
            filt = setup.filter
            mix = filt.predict(mixtures[name], u, dt)
            extra = {key: v for key, v in filt.diagnostics.items() if torch.is_tensor(v) and key != "weight_entropy"}
            if any_held:
                mix = GyroHold.inflate(mix, held_var)
            extra["gyro_held"] = (~gyro_valid).to(torch.int64)
            extra["gate_rejected"] = torch.zeros(B, dtype=torch.int64)
            nis = torch.full((B,), float("nan"), dtype=torch.float64)
            dof = torch.zeros(B, dtype=torch.float64)
            if has_stars:
                mix = filt.update(mix, y, meas)
                nis = torch.where(filt.diagnostics["dof"] > 0, filt.diagnostics["nis_mixture"], nis)
                dof = filt.diagnostics["dof"]
                if "gate_rejected" in filt.diagnostics:
                    extra["gate_rejected"] = filt.diagnostics["gate_rejected"]
            mixtures[name] = mix
            mean, cov = filt.estimate(mix)
            out[name] = FilterStep(mix, mean, cov, filt.model.state_error(mean, x_true), nis, dof, extra)
        yield Step(k, time, has_stars, x_true, truth_p, out, u, (y, meas) if has_stars else None, mean0)


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
) -> MonteCarloResult:
    """Run every filter over ``num_steps`` gyro periods of a batched environment.

    Args:
        env: a batched ``agsf/StarTrackerAttitude-v0`` vector environment.
        filters: name → :class:`FilterSetup`.
        num_steps: gyro periods to simulate.
        prior_cov: ``[n, n]`` prior covariance (MRP² and (rad/s)²).
        sigma_s: star noise σ_s assumed by the filters (rad).
        seed: seeds the environment and the prior draws.
        estimate_bias: ``False`` → the filters' model is 3-state and the gyro
            is compensated with the true bias (the paper's "bias known");
            ``True`` → 6-state.
        progress: show a progress bar.
        callback: optional ``callback(step, name, filter, mixture)`` after each step.
        noise_model: star-vector noise model of the filters (``"isotropic"`` or ``"tangent"``).
        gyro_hold_sigma: σ_h of :class:`~agsf_torch.input_gaps.GyroHold`, which bridges
            gyro samples the environment marks invalid (``gyro_valid``); default
            ``σ_v/√Δt`` of the first filter's model.

    Per-step extras of every trace (besides the filter's own diagnostics):
    ``gate_rejected [T, B]`` (star blocks rejected by the filter's innovation gate;
    0 without gating) and ``gyro_held [T, B]`` (1 where the gyro sample was bridged).
    """
    n = 6 if estimate_bias else 3
    records: dict[str, dict[str, list]] = {name: {k: [] for k in FilterTrace.__dataclass_fields__} for name in filters}
    times, frames = [], []
    steps = monte_carlo_steps(
        env, filters, num_steps=num_steps, prior_cov=prior_cov, sigma_s=sigma_s, seed=seed,
        estimate_bias=estimate_bias, noise_model=noise_model, gyro_hold_sigma=gyro_hold_sigma,
    )
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc="monte carlo", unit="step", total=num_steps)
    scale = torch.ones(n, dtype=torch.float64)
    scale[:3] = 4.0  # δθ ≈ 4 δp for small MRP errors
    for step in steps:
        times.append(step.time)
        frames.append(step.star_frame)
        for name, fs in step.filters.items():
            rec = records[name]
            rec["error_angle"].append(attitude_error_angle(fs.mean[:, :3], step.truth_mrp))
            rec["error"].append(fs.error * scale)
            rec["sigma"].append(fs.cov.diagonal(dim1=-2, dim2=-1).sqrt() * scale)
            rec["nees"].append(nees(fs.error, fs.cov))
            rec["nis"].append(fs.nis)
            rec["nis_dof"].append(fs.dof)
            rec["weights"].append(fs.mixture.weights)
            rec["weight_entropy"].append(fs.mixture.entropy_of_weights())
            rec["extra"].append(fs.extra)
            if callback is not None:
                callback(step.index, name, filters[name].filter, fs.mixture)

    traces = {}
    for name, rec in records.items():
        stacked = {k: torch.stack(v).numpy() for k, v in rec.items() if k != "extra"}
        extra_keys = rec["extra"][0].keys() if rec["extra"] else []
        stacked["extra"] = {k: torch.stack([e[k] for e in rec["extra"]]).numpy() for k in extra_keys}
        traces[name] = FilterTrace(**stacked)
    return MonteCarloResult(np.array(times), np.array(frames), traces, n)
