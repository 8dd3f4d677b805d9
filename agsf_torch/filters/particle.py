"""Regularised particle filter: the belief as weighted samples, carried as a Gaussian mixture.

``M`` particles ``xᵢ`` with log-weights ``log wᵢ`` per trajectory are the means and log-weights of a
:class:`~agsf_torch.mixture.GaussianMixture` whose covariances are the regularisation kernel
(Musso, Oudjane & Le Gland, "Improving regularised particle filters", in Doucet, de Freitas & Gordon (eds.),
*Sequential Monte Carlo Methods in Practice*, Springer 2001, ch. 12):

.. math:: \\hat p(x) = Σ_i w_i\\, N(x; x_i, h^2 \\hat Σ),\\qquad
          h = \\Big(\\frac{4}{n+2}\\Big)^{1/(n+4)} M^{-1/(n+4)},

``Σ̂`` the particles' weighted covariance and ``h`` the bandwidth that minimises the mean integrated squared
error of a Gaussian kernel estimate of a Gaussian density (Silverman, *Density Estimation*, 1986, eq. 4.14),
times the ``bandwidth_scale`` option (1 by default).  So the one filter loop, checkpoints and every consumer of a
mixture take the particle filter as they are.  The filter's estimate is the particles' weighted mean and
covariance ``(m̂, Σ̂)``; the mixture's own moments add the kernel, ``(m̂, (1 + h²)Σ̂)``.

* **predict**: each particle follows the model's Itô SDE ``dx = f(x, u) dt + g(x) dβ``, ``E[dβ dβᵀ] = Q dt``,
  over ``substeps`` steps of Euler–Maruyama whose drift increment is one classical RK4 step,

  .. math:: x ← Φ^{RK4}_τ(x) + g(x)\\, Q^{1/2} ξ \\sqrt τ,\\qquad ξ \\sim N(0, I_q),\\ τ = Δt/\\text{substeps},

  (weak order 1 like Euler–Maruyama; the noise-free motion to fourth order, which a star camera resolves on a
  rotating spacecraft, :mod:`agsf_torch.sample_paths`), each step followed by the model's own chart
  switch (:meth:`~agsf_torch.models.base.ContinuousModel.canonicalize`: the MRP shadow set at ``|p| > 1``).
* **update**: ``log wᵢ += log N(y; h(xᵢ), R)`` over the valid entries, normalised with log-sum-exp;
  systematic resampling where ``ESS = 1/Σwᵢ² < ρM``, then roughening, with ``m̂, Σ̂ = LLᵀ`` of the weighted
  cloud before resampling and ``ξᵢ ~ N(0, I)``:

  .. math:: x_i ← \\hat m + a (x_i - \\hat m) + h L ξ_i,\\qquad a = \\sqrt{1 - h^2}

  (``roughening="liu-west"``, the default: Liu & West, "Combined parameter and state estimation in
  simulation-based filtering", in the same book, ch. 10), which keeps the cloud's mean and covariance in
  expectation, or ``a = 1`` (``"musso"``: the kernel itself, which adds ``h²Σ̂`` to the covariance at every
  resampling, a bias of order ``h² ∝ M^{−2/(n+4)}`` that decays more slowly than the Monte Carlo error
  ``M^{−1/2}``), or no jitter (``"none"``: the bootstrap filter).  A measurement too sharp for the particles is
  applied in stages (*progressive correction*, Oudjane & Musso, "Progressive correction for regularized
  particle filters", FUSION 2000, and Musso et al. 2001): ``l(y|x) = Π_k l(y|x)^{λ_k}``, ``Σλ_k = 1``, each
  exponent the largest that keeps ``ESS ≥ ρM`` (found by bisection, as in adaptive tempering), each stage
  followed by resampling and roughening.  A star camera after a wide prior needs tens of stages; a
  measurement no sharper than the predicted cloud, one (the plain update).

All trajectories and particles advance as one tensor program; the only Python loops are over substeps,
correction stages and the bisection of a stage's exponent.  Randomness comes from one ``torch.Generator``
seeded by the ``seed`` option, whose state is the filter's run state (:meth:`ParticleFilter.state_dict`).
"""

from __future__ import annotations

import dataclasses
import math
import operator
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..finite import all_finite
from ..mixture import GaussianMixture
from ..models.base import ContinuousModel, MeasurementModel
from ..sample_paths import em_rk4_interval, sqrt_psd
from ..update import ComponentUpdate
from ..weighted_samples import effective_sample_size, systematic_resample, weighted_moments
from .base import UPDATE_DIAGNOSTICS, BaseFilter, UpdateFrame
from .options import option, positive_int

__all__ = [
    "ParticleFilter",
    "ParticleOptions",
    "PARTICLE_DIAGNOSTICS",
    "ROUGHENINGS",
    "kernel_bandwidth",
]

#: Keys an update of the particle filter adds to :data:`~agsf_torch.filters.base.UPDATE_DIAGNOSTICS`.
PARTICLE_DIAGNOSTICS = ("ess", "resampled", "corrections")
#: The roughening rules after resampling (:class:`ParticleOptions`).
ROUGHENINGS = ("musso", "liu-west", "none")
#: Bisection steps of a correction stage's exponent over ``log₂ λ ∈ [log₂ λ_rem − 64, log₂ λ_rem]``: a resolution of
#: 64/2¹⁰ in ``log₂ λ`` (the exponent to 4.4 %: a stage a little short of its ESS target costs at most another stage).
_EXPONENT_BISECTIONS = 10
_EXPONENT_RANGE = 64.0


def kernel_bandwidth(num_particles: int, state_dim: int) -> float:
    """The optimal bandwidth ``h`` of a Gaussian kernel (Musso et al. 2001; Silverman 1986, eq. 4.14).

    .. math:: h = A\\, M^{-1/(n+4)},\\qquad A = \\Big(\\frac{4}{n+2}\\Big)^{1/(n+4)}

    Args:
        num_particles: ``M ≥ 1``; state_dim: ``n ≥ 1``.

    Returns:
        ``h`` (dimensionless: the kernel's covariance is ``h²Σ̂``).
    """
    n, M = int(state_dim), int(num_particles)
    return (4.0 / (n + 2)) ** (1.0 / (n + 4)) * M ** (-1.0 / (n + 4))


@dataclass(frozen=True, kw_only=True)
class ParticleOptions:
    """The particle filter's own options (besides :class:`~agsf_torch.filters.options.FilterOptions`).

    Attributes:
        particles: ``M ≥ 2`` particles per trajectory.
        substeps: Euler–Maruyama steps per ``predict`` interval (≥ 1).
        seed: seed of the filter's generator (an integer ≥ 0); :meth:`ParticleFilter.reset` returns to it.
        resample_threshold: ``ρ ∈ (0, 1]``: resample where ``ESS < ρM`` after an update; a correction
            stage's exponent keeps ``ESS ≥ ρM`` (so more than one stage needs ``ρ < 1``).
        roughening: the jitter of resampled particles (module docstring): ``"liu-west"`` (shrink by ``√(1 − h²)``
            towards the mean, then the kernel: mean and covariance kept), ``"musso"`` (the kernel ``N(0, h²Σ̂)``:
            the cloud's covariance grows by ``h²Σ̂``) or ``"none"`` (resampling only: the bootstrap filter).
        correction_stages: most stages of progressive correction per update (1: the plain update, the
            measurement's likelihood at once); the last stage takes what is left of the likelihood.
        bandwidth_scale: ``h`` as a multiple of :func:`kernel_bandwidth` (finite, > 0; below 1 for a posterior
            far from Gaussian, Musso et al.'s advice; ``h < 1`` is required with ``"liu-west"``).
    """

    particles: int = field(default=4096, metadata=option("particles per trajectory (M ≥ 2)", config="int"))
    substeps: int = field(default=1, metadata=option("Euler–Maruyama steps per predict interval", config="int"))
    # set through the API: a configuration file's ``seed`` is the run's (the simulator's and the prior draws')
    seed: int = field(default=0, metadata=option("seed of the particle filter's generator"))
    resample_threshold: float = field(
        default=0.5, metadata=option("resample where ESS < threshold·M, threshold in (0, 1]", config="float")
    )
    roughening: str = field(
        default="liu-west",
        metadata=option(
            "jitter after resampling: liu-west (shrunk: moments kept), musso (kernel h²Σ̂) or none", config="str"
        ),
    )
    correction_stages: int = field(
        default=64, metadata=option("most progressive-correction stages per update (1: plain update)", config="int")
    )
    bandwidth_scale: float = field(
        default=1.0, metadata=option("kernel bandwidth h as a multiple of the optimal one (> 0)", config="float")
    )

    def __post_init__(self) -> None:
        if positive_int("particles", self.particles) < 2:
            raise ValueError(
                f"particles must be an integer ≥ 2 (a weighted covariance needs two), got {self.particles}"
            )
        positive_int("substeps", self.substeps)
        try:
            seed = None if isinstance(self.seed, bool) else operator.index(self.seed)
        except TypeError:
            seed = None
        if seed is None or seed < 0:
            raise ValueError(f"seed must be an integer ≥ 0, got {self.seed!r}")
        rho = self.resample_threshold
        if isinstance(rho, bool) or not isinstance(rho, (int, float)) or not 0.0 < rho <= 1.0:
            raise ValueError(f"resample_threshold must lie in (0, 1], got {rho!r}")
        scale = self.bandwidth_scale
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (0.0 < scale < math.inf):
            raise ValueError(f"bandwidth_scale must be a finite number > 0, got {scale!r}")
        if self.roughening not in ROUGHENINGS:
            raise ValueError(f"roughening must be one of {ROUGHENINGS}, got {self.roughening!r}")
        if positive_int("correction_stages", self.correction_stages) > 1 and rho >= 1.0:
            raise ValueError(
                "correction_stages > 1 needs resample_threshold < 1 (a stage's exponent keeps ESS ≥ "
                f"resample_threshold·M, which only λ = 0 does at 1), got correction_stages={self.correction_stages}"
            )


@dataclass(frozen=True)
class _Noise:
    """The measurement noise over the valid entries: ``R_eff = vvᵀ∘R + diag(1 − v)`` as its diagonal ``[..., d]``
    (when diagonal) or its Cholesky factor ``[..., d, d]``, and ``−½ log det R_eff − ½ dof log 2π`` ``[...]``."""

    diagonal: Tensor | None
    factor: Tensor | None
    log_norm: Tensor

    def solve(self, nu: Tensor) -> Tensor:
        """``L⁻¹ν`` (whitened residuals) for ``ν [..., K, d]`` → ``[..., K, d]``."""
        if self.diagonal is not None:
            return nu / self.diagonal.sqrt().unsqueeze(-2)
        return torch.linalg.solve_triangular(self.factor, nu.transpose(-1, -2), upper=False).transpose(-1, -2)


class ParticleFilter(BaseFilter):
    """Regularised particle filter (module docstring) on the :class:`~agsf_torch.filters.base.Filter` contract.

    The belief is a :class:`~agsf_torch.mixture.GaussianMixture` of ``M = particles`` components: means the
    particles (in the model's canonical chart), log-weights theirs, covariances the kernel ``h²Σ̂`` (expressed
    in each particle's chart).  A mixture with another number of components (a prior ``N(m₀, P₀)``, a Gaussian
    sum) is a density to draw from: ``M`` particles are drawn from it (components by systematic resampling of
    its weights) at the start of ``predict`` or ``update``.  The covariances carry ``M`` copies of the kernel
    (the mixture keeps its own memory per component): ``M n²`` numbers per trajectory beside the ``M n`` of the
    particles.

    ``estimate`` gives the particles' weighted mean and covariance ``(m̂, Σ̂)`` (:func:`weighted_moments` of the
    means, aligned to the chart of the heaviest particle): the filter's estimates of the posterior moments.  The
    mixture's own moments, ``mixture.moments()``, are those of the regularised density, ``(m̂, (1 + h²)Σ̂)``.

    Diagnostics: those of every filter (:data:`~agsf_torch.filters.base.PREDICT_DIAGNOSTICS`,
    :data:`~agsf_torch.filters.base.UPDATE_DIAGNOSTICS`, the gate's with gating) and, after an update,
    ``ess [...]`` (the effective sample size after the last correction stage, before its resampling),
    ``resampled [...]`` (bool) and ``corrections [...]`` (int64 stages; 0 without a valid entry).  ``log_likelihood``
    is ``Σ_k log Σᵢ wᵢ l(y|xᵢ)^{λ_k}`` over the stages (with one stage ``log Σᵢ wᵢ N(y; h(xᵢ), R)``, the prior
    weights'; with several, the tempered estimate at the roughened particles), ``nis [..., 1]`` and
    ``nis_mixture [...]`` the NIS ``ν̄ᵀS̄⁻¹ν̄`` of the particles' predicted measurement, ``ȳ = Σwᵢh(xᵢ)``,
    ``S̄ = Σwᵢ(h(xᵢ) − ȳ)(h(xᵢ) − ȳ)ᵀ + R`` (NaN where ``S̄`` cannot be factored), ``covariance_repairs`` the number
    of weighted covariances ``Σ̂`` that were not positive definite (a collapsed cloud) and were repaired by
    clipping their eigenvalues at ``min_eigenvalue`` times the largest (at least ``ε(1 + |m̂|_∞)²``).  Such a
    ``Σ̂`` is always repaired, whatever ``repair_covariance``: it is an estimate of the cloud, not a propagated
    covariance.  The innovation gate (``gate_probability``) tests each block against the Gaussian ``N(m̂, Σ̂)``
    (:func:`agsf_torch.gating.innovation_gate`).

    Runs are reproducible from ``seed`` for a given batch shape (the draws are made for the whole batch, so a
    trajectory's particles depend on the batch it is run in).  A ``predict`` or ``update`` that raises leaves
    the generator as it was.

    Args:
        model: the continuous-time model.
        particles, substeps, seed, resample_threshold, roughening, correction_stages, bandwidth_scale:
            :class:`ParticleOptions`.
        **options: :class:`~agsf_torch.filters.base.BaseFilter`'s (one configuration builds every filter):
            ``gate_probability``, ``min_eigenvalue``; ``update_iterations`` and ``repair_covariance`` have no
            effect (no linearisation; ``Σ̂`` is always repaired), nor have ``fused`` and ``compile_fused`` (no
            fused path: they are recorded as ``False``).
    """

    def __init__(
        self,
        model: ContinuousModel,
        *,
        particles: int = 4096,
        substeps: int = 1,
        seed: int = 0,
        resample_threshold: float = 0.5,
        roughening: str = "liu-west",
        correction_stages: int = 64,
        bandwidth_scale: float = 1.0,
        **options: Any,
    ) -> None:
        ParticleOptions(
            particles=particles,
            substeps=substeps,
            seed=seed,
            resample_threshold=resample_threshold,
            roughening=roughening,
            correction_stages=correction_stages,
            bandwidth_scale=bandwidth_scale,
        )  # validated before anything else
        super().__init__(model, **options)
        self.options = ParticleOptions(  # as plain Python numbers (checkpoints record them)
            particles=int(particles),
            substeps=int(substeps),
            seed=operator.index(seed),
            resample_threshold=float(resample_threshold),
            roughening=roughening,
            correction_stages=int(correction_stages),
            bandwidth_scale=float(bandwidth_scale),
        )
        self.fused = False  # no fused path and nothing to compile: recorded as they act
        self.compile_fused = False
        self.particles = self.options.particles
        self.substeps = self.options.substeps
        self.seed = self.options.seed
        self.resample_threshold = self.options.resample_threshold
        self.roughening = roughening
        self.correction_stages = self.options.correction_stages
        self.bandwidth = self.options.bandwidth_scale * kernel_bandwidth(self.particles, model.state_dim)  # h
        if roughening == "liu-west" and self.bandwidth >= 1.0:
            raise ValueError(
                f"bandwidth_scale={bandwidth_scale} gives h = {self.bandwidth:.3g} ≥ 1 for {self.particles} particles "
                f"of {model.state_dim} states: 'liu-west' shrinks by √(1 − h²), which needs h < 1"
            )
        self.generator = torch.Generator().manual_seed(self.seed)
        self._contract_checked: ContinuousModel | None = None
        self._pending: dict[str, Any] = {}

    # --------------------------------------------------------------- run state
    def reset(self) -> None:
        """Start a new run: the generator returns to ``seed``."""
        self.generator.manual_seed(self.seed)

    def state_dict(self) -> dict[str, Any]:
        """``{"generator": state}``: the generator's state (a uint8 tensor), so a restored run draws the same numbers."""
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (checked before anything changes)."""
        if not isinstance(state, dict) or set(state) != {"generator"}:
            got = sorted(state) if isinstance(state, dict) else type(state).__name__
            raise ValueError(f"ParticleFilter's state is {{'generator': uint8 tensor}}, got {got!r}")
        g, like = state["generator"], self.generator.get_state()
        if not torch.is_tensor(g) or g.dtype != torch.uint8 or g.shape != like.shape:
            got = f"a {g.dtype} tensor of shape {tuple(g.shape)}" if torch.is_tensor(g) else type(g).__name__
            raise ValueError(f"state['generator'] must be a uint8 tensor of shape {tuple(like.shape)}, got {got}")
        self.generator.set_state(g.clone())

    def checkpoint_options(self) -> dict[str, Any]:
        """The base filter's options and :class:`ParticleOptions` (:meth:`BaseFilter.checkpoint_options`)."""
        return {**super().checkpoint_options(), **dataclasses.asdict(self.options)}

    def diagnostic_keys(self, step: str) -> tuple[str, ...]:
        """:meth:`BaseFilter.diagnostic_keys`, and :data:`PARTICLE_DIAGNOSTICS` after an update."""
        keys = super().diagnostic_keys(step)
        if step == "update":
            return UPDATE_DIAGNOSTICS + PARTICLE_DIAGNOSTICS + keys[len(UPDATE_DIAGNOSTICS) :]
        return keys

    # ----------------------------------------------------------------- draws
    def _randn(self, shape: tuple[int, ...], like: Tensor) -> Tensor:
        """Standard normals ``shape`` from the filter's generator, in ``like``'s dtype and on its device."""
        g = self.generator
        return torch.randn(shape, generator=g, dtype=like.dtype, device=g.device).to(like.device)

    def _rand(self, shape: tuple[int, ...], like: Tensor) -> Tensor:
        """Uniforms on ``[0, 1)`` of ``shape`` from the filter's generator, in ``like``'s dtype and on its device."""
        g = self.generator
        return torch.rand(shape, generator=g, dtype=like.dtype, device=g.device).to(like.device)

    def _guarded(self, step, *args):
        """``step(*args)``, the generator restored if it raises (a refused input leaves the run state as it was)."""
        state = self.generator.get_state()
        try:
            return step(*args)
        except BaseException:
            self.generator.set_state(state)
            raise

    # ------------------------------------------------------------ particles
    def _particles(self, mixture: GaussianMixture) -> tuple[Tensor, Tensor]:
        """``(x [..., M, n], log w [..., M])``: the mixture's means and log-weights if it has ``M`` components,
        else ``M`` draws from it (components by :func:`systematic_resample` of its weights, then ``μⱼ + Lⱼξ``,
        ``LⱼLⱼᵀ = Pⱼ``) in the model's canonical chart with equal weights."""
        if mixture.num_components == self.particles:
            return mixture.means, mixture.log_weights
        mu, lw = mixture.means, mixture.log_weights
        batch, n, M = mixture.batch_shape, mixture.state_dim, self.particles
        j = systematic_resample(lw, self._rand(tuple(batch), mu))  # [..., M]
        L = torch.linalg.cholesky(mixture.covs)
        L = L.gather(-3, j[..., None, None].expand(*batch, M, n, n))
        x = mu.gather(-2, j[..., None].expand(*batch, M, n))
        x = x + (L @ self._randn((*batch, M, n, 1), mu)).squeeze(-1)
        return self._canonical(x), torch.full((*batch, M), -math.log(M), dtype=mu.dtype, device=mu.device)

    def _canonical(self, x: Tensor) -> Tensor:
        """Particles ``[..., M, n]`` in the model's canonical chart (:meth:`ContinuousModel.canonicalize`)."""
        return self.model.canonicalize(x, _zero_covs(x))[0]

    def _aligned(self, x: Tensor, log_weights: Tensor) -> Tensor:
        """Particles in the chart of the heaviest one (:meth:`ContinuousModel.align`), where their moments mean something."""
        n = x.shape[-1]
        best = log_weights.argmax(-1)
        reference = x.gather(-2, best[..., None, None].expand(*best.shape, 1, n))
        return self.model.align(x, _zero_covs(x), reference)[0]

    def _cloud(self, x: Tensor, log_weights: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, int]:
        """``(aligned particles, m̂, Σ̂, L, repairs)``: :func:`weighted_moments` of the aligned particles, ``Σ̂``
        repaired where it is not positive definite (class docstring) and its Cholesky factor ``L``."""
        xa = self._aligned(x, log_weights)
        mean, cov = weighted_moments(xa, log_weights)
        L, info = torch.linalg.cholesky_ex(cov)
        bad = info != 0
        if not bool(bad.any()):
            return xa, mean, cov, L, 0
        evals, evecs = torch.linalg.eigh(cov)
        scale = 1.0 + mean.abs().amax(-1)
        floor = torch.maximum(self.min_eigenvalue * evals[..., -1], torch.finfo(cov.dtype).eps * scale * scale)
        fixed = (evecs * torch.maximum(evals, floor[..., None]).unsqueeze(-2)) @ evecs.transpose(-1, -2)
        cov = torch.where(bad[..., None, None], 0.5 * (fixed + fixed.transpose(-1, -2)), cov)
        return xa, mean, cov, torch.linalg.cholesky(cov), int(bad.sum())

    def _belief(self, x: Tensor, log_weights: Tensor) -> tuple[GaussianMixture, int]:
        """The mixture of particles ``x [..., M, n]`` (canonical chart) and ``log_weights [..., M]`` with the kernel
        ``h²Σ̂`` expressed in each particle's chart, and the number of repairs of ``Σ̂``."""
        xa, _, cov, _, repairs = self._cloud(x, log_weights)
        kernel = (self.bandwidth**2 * cov).unsqueeze(-3).expand(*x.shape, x.shape[-1])
        covs = self.model.canonicalize(xa, kernel)[1]
        return GaussianMixture(log_weights=log_weights, means=x, covs=covs, validate=False), repairs

    @staticmethod
    def _check_finite(values: Tensor, what: str, hint: str = "") -> None:
        """``ValueError`` naming ``what``, the trajectory and the particle unless ``values [..., M, k]`` are finite."""
        if not all_finite(values):
            idx = (~torch.isfinite(values)).any(-1).nonzero()[0].tolist()
            raise ValueError(f"{what} is not finite at trajectory index {tuple(idx[:-1])}, particle {idx[-1]}{hint}")

    # ----------------------------------------------------------------- predict
    def predict(self, mixture: GaussianMixture, u: Tensor | None, dt: float) -> GaussianMixture:
        """:meth:`BaseFilter.predict`: every particle along the SDE (module docstring); the weights are kept.

        Args:
            mixture: the belief at ``t`` (``M`` particles, or a density to draw them from).
            u: input ``[..., m]`` held over the interval (e.g. the gyro rate, rad/s), or ``None``.
            dt: interval (s), finite and > 0.

        Returns:
            The belief at ``t + dt``: ``M`` components.
        """
        return self._guarded(super().predict, mixture, u, dt)

    def _validate_predict(self, mixture: GaussianMixture, u: Any, dt: Any) -> tuple[Tensor | None, float]:
        """As the base class's, the model's shape contract at the first ``predict`` with it and its check of
        one substep ``dt/substeps`` (the chart is switched after every substep)."""
        u, dt = super()._validate_predict(mixture, u, dt)
        if self._contract_checked is not self.model:
            self.model.check_contract(mixture.means, None if u is None else u.unsqueeze(-2))
            self._contract_checked = self.model
        self.model.check_step(mixture.means, u, dt / self.substeps)
        return u, dt

    def _propagate(self, mixture: GaussianMixture, u: Tensor | None, dt: float) -> tuple[GaussianMixture, int]:
        """The particles after ``substeps`` Euler–Maruyama steps with an RK4 drift (module docstring), each
        followed by the model's chart switch; the weights unchanged; the kernel of the new cloud."""
        x, log_weights = self._particles(mixture)
        noise_sqrt = sqrt_psd(torch.as_tensor(self.model.noise_psd()).to(x))  # Q^{1/2}, [q, q] or [..., q, q]
        x = em_rk4_interval(
            self.model, x, u, dt, self.substeps, noise_sqrt, self._canonical, lambda shape: self._randn(shape, x)
        )
        self._check_finite(x, "a particle after propagation", " (more substeps may follow the model's drift)")
        return self._belief(x, log_weights)

    # ------------------------------------------------------------------ update
    def update(self, mixture: GaussianMixture, y: Tensor, measurement: MeasurementModel) -> GaussianMixture:
        """:meth:`BaseFilter.update`: reweighting by the likelihood (in stages where it is too sharp),
        resampling and roughening (module docstring).

        Args:
            mixture: the predicted belief (``M`` particles, or a density to draw them from).
            y: measurement ``[..., d]``; entries masked out by the measurement model (or rejected by the gate)
                drop out of the likelihood.
            measurement: the measurement model (``h``, ``R``, mask).

        Returns:
            The posterior belief; trajectories without a valid entry keep their particles and weights.
        """
        self._pending = {}
        posterior = self._guarded(super().update, mixture, y, measurement)
        self.diagnostics.update(self._pending)
        self._pending = {}
        return posterior

    def _update_frame(self, mixture: GaussianMixture, measurement: MeasurementModel) -> UpdateFrame:
        """The particles and their weights (drawn if ``mixture`` is not a particle set); the covariances are zeros
        (stored once): the particle update does not read them."""
        x, log_weights = self._particles(mixture)
        return UpdateFrame(log_weights, x, _zero_covs(x), measurement)

    def _gate(self, frame: UpdateFrame, y: Tensor) -> tuple[Tensor | None, dict[str, Tensor]]:
        """The shared innovation gate on the Gaussian ``N(m̂, Σ̂)`` of the cloud (class docstring)."""
        if self.gate_probability is None:
            return None, {}
        _, mean, cov, _, repairs = self._cloud(frame.means, frame.log_weights)
        self._pending["covariance_repairs"] = repairs
        gaussian = UpdateFrame(
            torch.zeros_like(mean[..., :1]), mean.unsqueeze(-2), cov.unsqueeze(-3), frame.measurement
        )
        return super()._gate(gaussian, y)

    def _kalman_step(self, frame: UpdateFrame, y: Tensor, mask: Tensor | None) -> ComponentUpdate:
        """The particle correction (in place of the Kalman step): reweighting in stages, resampling and
        roughening; ``means`` and ``log_weights`` of the result are the posterior particles and weights,
        ``innovation [..., 1, d]`` and ``innovation_cov [..., 1, d, d]`` the particles' predicted ``ν̄`` and ``S̄``."""
        x, log_weights, measurement = frame.means, frame.log_weights, frame.measurement
        batch, M = log_weights.shape[:-1], self.particles
        if mask is None:
            mask = measurement.mask()
        d = y.shape[-1]
        valid = (
            torch.ones((*batch, d), dtype=x.dtype, device=x.device)
            if mask is None
            else mask.to(x.dtype).expand(*batch, d)
        )
        noise = _noise(measurement, valid)
        dof = valid.sum(-1)
        ell, h = self._log_likelihood(measurement, x, y, valid, noise)
        nis, nu_bar, S_bar = _predicted_measurement(log_weights, h, y, valid, noise)

        active = dof > 0
        remaining = torch.ones(batch, dtype=x.dtype, device=x.device)
        total = torch.zeros(batch, dtype=x.dtype, device=x.device)
        ess = effective_sample_size(log_weights)
        resampled = torch.zeros(batch, dtype=torch.bool, device=x.device)
        stages = torch.zeros(batch, dtype=torch.int64, device=x.device)
        repairs = 0
        for stage in range(self.correction_stages):
            final = stage == self.correction_stages - 1
            exponent = self._stage_exponent(log_weights, ell, remaining, active, final)
            tempered = log_weights + exponent.unsqueeze(-1) * ell
            norm = torch.logsumexp(tempered, -1)
            total = total + torch.where(active, norm, torch.zeros_like(norm))
            log_weights = torch.where(active.unsqueeze(-1), tempered - norm.unsqueeze(-1), log_weights)
            remaining = torch.where(active, remaining - exponent, remaining)
            stages = stages + active.to(stages.dtype)
            stage_ess = effective_sample_size(log_weights)
            ess = torch.where(active, stage_ess, ess)
            partial = active & (remaining > 0)
            which = active & ((stage_ess < self.resample_threshold * M) | partial)
            if bool(which.any()):
                x, log_weights, fixed = self._resample(x, log_weights, which)
                resampled = resampled | which
                repairs += fixed
            active = partial
            if not bool(active.any()):
                break
            ell = self._log_likelihood(measurement, x, y, valid, noise)[0]
        self._pending.update(
            {
                "ess": ess,
                "resampled": resampled,
                "corrections": stages,
                "covariance_repairs": self._pending.get("covariance_repairs", 0) + repairs,
            }
        )
        return ComponentUpdate(
            means=x,
            covs=frame.covs,  # unused: the posterior's kernel is formed from its particles (_posterior)
            log_weights=log_weights,
            log_likelihood=total,
            nis=nis.unsqueeze(-1),
            dof=dof,
            innovation=nu_bar.unsqueeze(-2),
            innovation_cov=S_bar.unsqueeze(-3),
            nis_mixture=nis,
        )

    def _log_likelihood(
        self, measurement: MeasurementModel, x: Tensor, y: Tensor, valid: Tensor, noise: _Noise
    ) -> tuple[Tensor, Tensor]:
        """``(log N(y; h(xᵢ), R) over the valid entries [..., M], h(xᵢ) [..., M, d])``."""
        # particles first: the measurement's own tensors carry the trajectory dims only
        h = measurement.predict(x.movedim(-2, 0)).movedim(0, -2)
        if h.shape[-1] != y.shape[-1]:
            raise ValueError(f"y has {y.shape[-1]} entries but the measurement model predicts {h.shape[-1]}")
        z = noise.solve(valid.unsqueeze(-2) * (y.unsqueeze(-2) - h))
        ell = noise.log_norm.unsqueeze(-1) - 0.5 * (z * z).sum(-1)
        self._check_finite(ell.unsqueeze(-1), "the likelihood log N(y; h(x), R) of a particle")
        return ell, h

    def _stage_exponent(
        self, log_weights: Tensor, ell: Tensor, remaining: Tensor, active: Tensor, final: bool
    ) -> Tensor:
        """The exponent ``λ ∈ (0, λ_rem]`` of a correction stage ``[...]`` (0 where not ``active``): ``λ_rem`` (what
        is left) where ``ESS(w·l^{λ_rem}) ≥ ρM`` or on the ``final`` stage, else the largest ``λ`` with ``ESS ≥ ρM``
        on a grid of ``log₂ λ`` over ``[log₂ λ_rem − 64, log₂ λ_rem]`` by bisection (:data:`_EXPONENT_BISECTIONS`
        steps, the trajectories that need it only); below the grid, its lowest point."""
        target = self.resample_threshold * self.particles
        lam = torch.where(active, remaining, torch.zeros_like(remaining))
        if final:
            return lam
        need = active & (effective_sample_size(log_weights + lam.unsqueeze(-1) * ell) < target)
        if not bool(need.any()):
            return lam
        at = need.nonzero(as_tuple=True)
        lw, ll, rem = log_weights[at], ell[at], remaining[at]
        lo = torch.full_like(rem, -_EXPONENT_RANGE)
        hi = torch.zeros_like(rem)
        for _ in range(_EXPONENT_BISECTIONS):
            mid = 0.5 * (lo + hi)
            ok = effective_sample_size(lw + (rem * torch.exp2(mid)).unsqueeze(-1) * ll) >= target
            lo, hi = torch.where(ok, mid, lo), torch.where(ok, hi, mid)
        return lam.index_put(at, rem * torch.exp2(lo))

    def _resample(self, x: Tensor, log_weights: Tensor, which: Tensor) -> tuple[Tensor, Tensor, int]:
        """Systematic resampling and roughening of the trajectories flagged in ``which [...]``: ancestors by
        :func:`systematic_resample`, then (in the chart of the heaviest particle, with ``m̂, Σ̂ = LLᵀ`` of the
        weighted cloud before resampling) ``x ← x + hLξ`` (``"musso"``), ``x ← m̂ + a(x − m̂) + hLξ`` with
        ``a = √(1 − h²)`` (``"liu-west"``) or ``x`` (``"none"``); back in the canonical chart, equal weights.
        Returns ``(x, log w, repairs of Σ̂)``."""
        batch, (M, n) = log_weights.shape[:-1], x.shape[-2:]
        xa, mean, _, L, repairs = self._cloud(x, log_weights)
        ancestors = systematic_resample(log_weights, self._rand(tuple(batch), x))
        new = xa.gather(-2, ancestors[..., None].expand(*batch, M, n))
        if self.roughening != "none":
            h = self.bandwidth
            if self.roughening == "liu-west":
                a = math.sqrt(1.0 - h * h)
                new = mean.unsqueeze(-2) + a * (new - mean.unsqueeze(-2))
            new = new + h * (self._randn((*batch, M, n), x) @ L.transpose(-1, -2))
        new = self._canonical(new)
        x = torch.where(which[..., None, None], new, x)
        uniform = torch.full_like(log_weights, -math.log(M))
        return x, torch.where(which.unsqueeze(-1), uniform, log_weights), repairs

    def _posterior(
        self, prior: GaussianMixture, frame: UpdateFrame, result: ComponentUpdate
    ) -> tuple[GaussianMixture, int]:
        """The mixture of the posterior particles and weights with their kernel (:meth:`_belief`); the repairs
        of this update's ``Σ̂``."""
        posterior, repairs = self._belief(result.means, result.log_weights)
        return posterior, repairs + self._pending.pop("covariance_repairs", 0)

    # --------------------------------------------------------------- estimates
    def estimate(self, mixture: GaussianMixture) -> tuple[Tensor, Tensor]:
        """``(m̂ [..., n], Σ̂ [..., n, n])``: the weighted mean and covariance of the particles (the means of a mixture
        of ``M`` components, kernels left out), in the chart of the heaviest one; for another mixture (a prior
        not yet drawn from), its moments (:meth:`BaseFilter.estimate`)."""
        if mixture.num_components != self.particles:
            return super().estimate(mixture)
        return weighted_moments(self._aligned(mixture.means, mixture.log_weights), mixture.log_weights)


def _zero_covs(x: Tensor) -> Tensor:
    """Zero covariances ``[..., n, n]`` for points ``x [..., n]``, one stored zero (for the chart maps, which
    take a covariance beside each mean)."""
    return x.new_zeros(()).expand(*x.shape, x.shape[-1])


def _noise(measurement: MeasurementModel, valid: Tensor) -> _Noise:
    """The measurement noise over the valid entries ``valid [..., d]`` (1 or 0) (:class:`_Noise`).

    Raises:
        ValueError: where ``R`` is not positive definite over the valid entries (a likelihood needs a density).
    """
    R = torch.as_tensor(measurement.noise_cov()).to(valid)
    R_eff = valid[..., :, None] * valid[..., None, :] * R + torch.diag_embed(1.0 - valid)
    diagonal = R_eff.diagonal(dim1=-2, dim2=-1)
    dof = valid.sum(-1)
    log_2pi = math.log(2.0 * math.pi)
    if bool((R_eff == torch.diag_embed(diagonal)).all()):
        if bool((diagonal <= 0).any()):
            idx = (diagonal <= 0).nonzero()[0].tolist()
            raise ValueError(f"the measurement noise variance is not positive at entry {idx[-1]} (index {tuple(idx)})")
        return _Noise(diagonal, None, -0.5 * (torch.log(diagonal).sum(-1) + dof * log_2pi))
    L, info = torch.linalg.cholesky_ex(R_eff)
    if bool((info != 0).any()):
        idx = (info != 0).nonzero()[0].tolist()
        raise ValueError(
            f"the measurement noise covariance R is not positive definite over the valid entries at trajectory "
            f"index {tuple(idx)}: the particle weights need a likelihood density"
        )
    log_det = 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
    return _Noise(None, L, -0.5 * (log_det + dof * log_2pi))


def _predicted_measurement(
    log_weights: Tensor, h: Tensor, y: Tensor, valid: Tensor, noise: _Noise
) -> tuple[Tensor, Tensor, Tensor]:
    """The particles' predicted measurement and its NIS over the valid entries.

    .. math:: \\bar y = Σ_i w_i h(x_i),\\quad \\bar S = Σ_i w_i (h(x_i) - \\bar y)(h(x_i) - \\bar y)^T + R,
              \\quad \\mathrm{NIS} = \\bar ν^T \\bar S^{-1} \\bar ν,\\ \\bar ν = y - \\bar y

    (invalid entries: zero rows of ``ν̄`` and of the spread, identity block of ``R``).

    Args:
        log_weights: ``[..., M]``; h: ``[..., M, d]``; y: ``[..., d]``; valid: ``[..., d]``.

    Returns:
        ``(NIS [...] (NaN where S̄ is not positive definite), ν̄ [..., d], S̄ [..., d, d])``.
    """
    w = torch.softmax(log_weights, -1)
    y_bar = (w.unsqueeze(-2) @ h).squeeze(-2)
    spread = (h - y_bar.unsqueeze(-2)) * (w.sqrt().unsqueeze(-1) * valid.unsqueeze(-2))
    if noise.diagonal is not None:
        R = torch.diag_embed(noise.diagonal)
    else:
        R = noise.factor @ noise.factor.transpose(-1, -2)
    S = spread.transpose(-1, -2) @ spread + R
    S = 0.5 * (S + S.transpose(-1, -2))
    nu = valid * (y - y_bar)
    L, info = torch.linalg.cholesky_ex(S)
    z = torch.linalg.solve_triangular(L, nu.unsqueeze(-1), upper=False).squeeze(-1)
    nis = (z * z).sum(-1)
    return torch.where(info == 0, nis, torch.full_like(nis, math.nan)), nu, S
