"""The reference sampler: weighted samples of the exact filtering density of a model.

:class:`PosteriorReference` is a sequential Monte Carlo sampler whose particles are
whole paths of the model's Itô SDE ``dx = f(x, u) dt + g(x) dβ``, ``E[dβ dβᵀ] = Q dt``:

* **Forecast.** ``x₀`` from the prior (a Gaussian or a Gaussian mixture), then ``substeps`` steps per input
  interval of Euler–Maruyama with the drift integrated by one RK4 step (:mod:`agsf_torch.sample_paths`: weak
  order 1, the noise-free motion to fourth order).
* **Measurements.** Bootstrap reweighting by ``p(y | x)``; systematic resampling when
  ``ESS < resample_threshold·K``.  Where the bootstrap would collapse
  (``ESS/K < redraw_threshold``, e.g. the first sharp star frame), or resampling has
  left fewer than ``redraw_threshold·K`` lineages, the trajectory's particles are
  **redrawn** by path-space importance sampling over all frames so far
  (:mod:`agsf_torch.density.redraw`).  The redraw replaces the bootstrap particles
  only where its ESS is larger.

Every step is an exact importance-sampling or SMC step for that chain, so for fixed
``substeps`` all estimates are consistent as ``K → ∞`` (redraw weights are bounded,
``p₀/q ≤ 1/α``).  Every step's ESS and lineage count are recorded (:class:`ReferenceStepRecord`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..mixture import GaussianMixture, check_covariance
from ..models.base import ContinuousModel, MeasurementModel
from ..sample_paths import em_rk4_interval, sqrt_psd
from ..weighted_samples import effective_sample_size, systematic_resample
from .charts import canonical_points, chart_for, check_chart
from .frames import Frame, ReferenceStepRecord, point_eval
from .redraw import PathSpaceRedraw
from .score import density_score

__all__ = ["PosteriorReference"]


class PosteriorReference(PathSpaceRedraw):
    """Weighted samples of the exact filtering density of a model, advanced step by step.

    Drive it with the filters' inputs and measurements::

        ref = PosteriorReference(model, m0, P0, num_samples=4096, generator=gen)
        for k in range(T):
            ref.predict(u_k, dt)
            if frame:
                ref.update(y_k, measurement_k, hints=filter_mixture.means)
            score, se = ref.score(filter_mixture)

    Between measurements the samples are exact draws (see the module docstring for
    the scheme and what is exact).  ``hints`` (optional) are points at the current
    time — e.g. the filters' component means — that seed the Laplace fits of a
    redraw after being mapped back to ``t₀`` along the noise-free flow.

    Args:
        model: the continuous-time model (``drift``, ``noise_gain``, ``noise_psd``).
        prior_mean: ``m₀`` ``[B, n]``.
        prior_cov: ``P₀`` ``[B, n, n]`` or ``[n, n]``, symmetric positive definite.
        prior: instead of ``prior_mean, prior_cov``, a Gaussian-mixture prior ``[B]``.
        num_samples: ``K ≥ 2`` samples per trajectory.
        generator: the only source of randomness.
        substeps: stochastic steps per input interval.  The weak error is ``O(h)`` in
            the noise, ``h = Δt/substeps``; the drift is integrated to fourth order
            regardless.  1 suffices when the process noise is small against the motion
            (the attitude model); strongly diffusive models need more (the tests use
            10–20 for the sine and linear models).  Compare two values to check.
        chart: ``"euclidean"`` or ``"mrp"``; default :func:`chart_for` ``(model)``.
        redraw_threshold: redraw when the bootstrap ``ESS/K`` would fall below it.
        lineage_threshold: also redraw when resampling has left fewer than
            ``lineage_threshold·K`` lineages (default: ``redraw_threshold``).  A redraw
            re-simulates from ``t₀``, so over long runs a lower value (e.g. 0.02) saves
            most of the cost; the estimates stay consistent either way, only the
            lineage-based standard errors rest on fewer lineages.
        resample_threshold: resample when ``ESS/K`` falls below it.
        defensive_weight: ``α``, the prior's share of the redraw proposal (0 < α < 1).
        t_dof: degrees of freedom ``ν`` (integer ≥ 1) of the proposal's t components.
        t_scale: scale factor of the t components (their scale matrix is
            ``t_scale² C`` with ``C`` the Laplace covariance).
        particle_starts: best particles (by bootstrap weight) used as Gauss–Newton starts.
        gauss_newton_iterations: iterations of each Laplace fit.
    """

    def __init__(
        self,
        model: ContinuousModel,
        prior_mean: Tensor | None = None,
        prior_cov: Tensor | None = None,
        *,
        prior: GaussianMixture | None = None,
        num_samples: int,
        generator: torch.Generator,
        substeps: int = 1,
        chart: str | None = None,
        redraw_threshold: float = 0.1,
        lineage_threshold: float | None = None,
        resample_threshold: float = 0.5,
        defensive_weight: float = 0.1,
        t_dof: int = 4,
        t_scale: float = 1.2,
        particle_starts: int = 4,
        gauss_newton_iterations: int = 10,
    ) -> None:
        if prior is not None:
            if prior_mean is not None or prior_cov is not None:
                raise ValueError("give either prior_mean and prior_cov, or prior=, not both")
            if not isinstance(prior, GaussianMixture):
                raise ValueError(f"prior must be a GaussianMixture, got {type(prior).__name__}")
            if len(prior.batch_shape) != 1:
                raise ValueError(f"prior must have batch shape [B], got {tuple(prior.batch_shape)}")
            check_covariance("prior covs", prior.covs)
            prior = prior.replace(
                log_weights=prior.log_weights.to(torch.float64),
                means=prior.means.to(torch.float64),
                covs=prior.covs.to(torch.float64),
                validate=False,
            )  # checked above
        else:
            if prior_mean is None or prior_cov is None:
                raise ValueError("give prior_mean and prior_cov (or prior=)")
            mean = torch.as_tensor(prior_mean, dtype=torch.float64)
            if mean.dim() != 2:
                raise ValueError(f"prior_mean must have shape [B, n], got {tuple(mean.shape)}")
            cov = torch.as_tensor(prior_cov, dtype=mean.dtype, device=mean.device)
            B, n = mean.shape
            if cov.shape == (n, n):
                cov = cov.expand(B, n, n)
            if cov.shape != (B, n, n):
                raise ValueError(f"prior_cov must have shape [{B}, {n}, {n}] or [{n}, {n}], got {tuple(cov.shape)}")
            if not bool(torch.isfinite(mean).all()):
                raise ValueError("prior_mean must be finite")
            check_covariance("prior_cov", cov)
            prior = GaussianMixture(
                log_weights=torch.zeros(B, 1, dtype=mean.dtype, device=mean.device),
                means=mean.unsqueeze(1),
                covs=cov.unsqueeze(1),
                validate=False,
            )
        if lineage_threshold is not None and not 0.0 <= float(lineage_threshold) < 1.0:
            raise ValueError(f"lineage_threshold must lie in [0, 1), got {lineage_threshold}")
        self._init(
            model,
            prior,
            num_samples,
            generator,
            substeps,
            chart,
            redraw_threshold,
            resample_threshold,
            defensive_weight,
            t_dof,
            t_scale,
            particle_starts,
            gauss_newton_iterations,
        )
        self.lineage_threshold = self.redraw_threshold if lineage_threshold is None else float(lineage_threshold)

    # ------------------------------------------------------------------ set-up
    def _init(
        self,
        model,
        prior,
        num_samples,
        generator,
        substeps,
        chart,
        redraw_threshold,
        resample_threshold,
        defensive_weight,
        t_dof,
        t_scale,
        particle_starts,
        gauss_newton_iterations,
    ) -> None:
        if not isinstance(model, ContinuousModel):
            raise ValueError(f"model must be a ContinuousModel, got {type(model).__name__}")
        B, _, n = prior.means.shape
        if n != model.state_dim:
            raise ValueError(f"prior state dimension {n} != model state_dim {model.state_dim}")
        if not isinstance(generator, torch.Generator):
            raise ValueError(f"generator must be a torch.Generator, got {type(generator).__name__}")
        for name, v, lo in (
            ("num_samples", num_samples, 2),
            ("substeps", substeps, 1),
            ("t_dof", t_dof, 1),
            ("particle_starts", particle_starts, 0),
            ("gauss_newton_iterations", gauss_newton_iterations, 1),
        ):
            if isinstance(v, bool) or int(v) != v or v < lo:
                raise ValueError(f"{name} must be an integer ≥ {lo}, got {v}")
        for name, v in (
            ("redraw_threshold", redraw_threshold),
            ("resample_threshold", resample_threshold),
            ("defensive_weight", defensive_weight),
        ):
            if not 0.0 < float(v) < 1.0:
                raise ValueError(f"{name} must lie in (0, 1), got {v}")
        if not float(t_scale) > 0 or not math.isfinite(float(t_scale)):
            raise ValueError(f"t_scale must be a finite positive number, got {t_scale}")
        self.model = model
        self.chart = check_chart(chart_for(model) if chart is None else chart, n)
        self.prior = prior
        self.prior_mean, self.prior_cov = prior.moments()
        self.num_samples = K = int(num_samples)
        self.generator = generator
        self.substeps = int(substeps)
        self.redraw_threshold = float(redraw_threshold)
        self.resample_threshold = float(resample_threshold)
        self.defensive_weight = float(defensive_weight)
        self.t_dof = int(t_dof)
        self.t_scale = float(t_scale)
        self.particle_starts = int(particle_starts)
        self.gauss_newton_iterations = int(gauss_newton_iterations)
        self.batch_size = B
        self.state_dim = n
        self._dtype, self._device = prior.means.dtype, prior.means.device
        Q = torch.as_tensor(model.noise_psd(), dtype=self._dtype, device=self._device)
        self._Q_sqrt = sqrt_psd(Q)
        self._intervals: list[tuple[Tensor | None, float]] = []
        self._frames: list[Frame] = []
        self.time = 0.0
        x0 = self._sample_prior(K)
        self.initial_samples = x0  # x₀ of each particle's path, in the prior's coordinates [B, K, n]
        self.samples = canonical_points(x0, self.chart)
        self.log_weights = torch.zeros(B, K, dtype=self._dtype, device=self._device)
        self.lineage = self._own_lineage()
        self.history: list[ReferenceStepRecord] = []

    # ------------------------------------------------------------- utilities
    def _randn(self, *shape: int) -> Tensor:
        return torch.randn(*shape, generator=self.generator, dtype=self._dtype, device=self._device)

    def _own_lineage(self) -> Tensor:
        K = self.num_samples
        return torch.arange(K, device=self._device).expand(self.batch_size, K).clone()

    def _sample_prior(self, K: int) -> Tensor:
        """``K`` draws of the prior mixture per trajectory, ``[B, K, n]``."""
        pr = self.prior
        idx = torch.multinomial(pr.weights, K, replacement=True, generator=self.generator)  # [B, K]
        L = torch.linalg.cholesky(pr.covs)
        mu = torch.gather(pr.means, 1, idx[..., None].expand(-1, -1, self.state_dim))
        Lk = torch.gather(L, 1, idx[..., None, None].expand(-1, -1, self.state_dim, self.state_dim))
        z = self._randn(self.batch_size, K, self.state_dim)
        return mu + (Lk @ z.unsqueeze(-1)).squeeze(-1)

    def _check_input(self, u) -> Tensor | None:
        if u is None:
            return None
        u = torch.as_tensor(u, dtype=self._dtype, device=self._device)
        if u.dim() != 2 or u.shape[0] != self.batch_size:
            raise ValueError(f"u must have shape [B={self.batch_size}, m], got {tuple(u.shape)}")
        if not bool(torch.isfinite(u).all()):
            raise ValueError("u must be finite")
        return u

    def _em_interval(self, x: Tensor, u: Tensor | None, dt: float) -> Tensor:
        """One input interval of ``substeps`` steps of :func:`agsf_torch.sample_paths.em_rk4_interval`."""
        return em_rk4_interval(
            self.model, x, u, dt, self.substeps, self._Q_sqrt, self._canonical, lambda shape: self._randn(*shape)
        )

    def _canonical(self, x: Tensor) -> Tensor:
        """``x`` in the sampler's canonical chart (:func:`.charts.canonical_points`)."""
        return canonical_points(x, self.chart)

    def _frame_log_likelihood(self, frame: Frame, x: Tensor) -> Tensor:
        """``log N(y; h(x), R)`` over the valid entries, ``x [B, K, n]`` → ``[B, K]``."""
        h = point_eval(frame.measurement, x)
        if h.shape[-1] != frame.y.shape[-1]:
            raise ValueError(f"y has {frame.y.shape[-1]} entries but the measurement model predicts {h.shape[-1]}")
        nu = frame.valid[:, None, :] * (frame.y[:, None, :] - h)  # [B, K, d]
        # [B, d, K]: one triangular solve per trajectory, all samples as right-hand sides
        z = torch.linalg.solve_triangular(frame.chol, nu.transpose(-1, -2), upper=False)
        return frame.log_norm[:, None] - 0.5 * (z * z).sum(-2)

    def _make_frame(self, y, measurement: MeasurementModel) -> Frame:
        if not isinstance(measurement, MeasurementModel):
            raise ValueError(f"measurement must be a MeasurementModel, got {type(measurement).__name__}")
        y = torch.as_tensor(y, dtype=self._dtype, device=self._device)
        B = self.batch_size
        if y.dim() != 2 or y.shape[0] != B:
            raise ValueError(f"y must have shape [B={B}, d], got {tuple(y.shape)}")
        if not bool(torch.isfinite(y).all()):
            raise ValueError("y must be finite")
        d = y.shape[1]
        R = torch.as_tensor(measurement.noise_cov(), dtype=self._dtype, device=self._device)
        if R.dim() < 2 or R.shape[-2:] != (d, d):
            raise ValueError(f"y has {d} entries but the measurement noise covariance has shape {tuple(R.shape)}")
        try:
            R = R.expand(B, d, d)
        except RuntimeError:
            raise ValueError(f"noise_cov of shape {tuple(R.shape)} does not match y with d = {d}") from None
        mask = measurement.mask()
        if mask is None:
            valid = torch.ones(B, d, dtype=self._dtype, device=self._device)
        else:
            try:
                valid = torch.as_tensor(mask, device=self._device).to(self._dtype).expand(B, d)
            except RuntimeError:
                raise ValueError(f"measurement mask of shape {tuple(mask.shape)} does not match y [{B}, {d}]") from None
        R_eff = valid[..., :, None] * valid[..., None, :] * R + torch.diag_embed(1.0 - valid)
        L, info = torch.linalg.cholesky_ex(0.5 * (R_eff + R_eff.transpose(-1, -2)))
        if bool((info != 0).any()):
            bad = int((info != 0).nonzero()[0])
            raise ValueError(f"measurement noise covariance is not positive definite at trajectory {bad}")
        logdet = 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
        dof = valid.sum(-1)
        return Frame(
            len(self._intervals), y, measurement, valid, R_eff, L, -0.5 * (logdet + dof * math.log(2.0 * math.pi))
        )

    def _record(self, frame: bool, redrawn=None, resampled=None, boot=None, redraw=None) -> None:
        B = self.batch_size
        false = torch.zeros(B, dtype=torch.bool, device=self._device)
        nan = torch.full((B,), math.nan, dtype=self._dtype, device=self._device)
        lineages = _count_distinct(self.lineage)
        self.history.append(
            ReferenceStepRecord(
                self.time,
                frame,
                effective_sample_size(self.log_weights) if not frame else self._pre_resample_ess,
                lineages,
                false if redrawn is None else redrawn,
                false if resampled is None else resampled,
                nan if boot is None else boot,
                nan if redraw is None else redraw,
            )
        )

    # ------------------------------------------------------------------ steps
    def predict(self, u: Tensor | None, dt: float) -> None:
        """Advance every sample path over one input interval (Euler–Maruyama, ``substeps`` steps).

        Args:
            u: input held constant over the interval, ``[B, m]`` (e.g. gyro rate, rad/s), or ``None``.
            dt: interval length (s), finite and > 0.
        """
        if torch.is_tensor(dt) and dt.numel() == 1:
            dt = float(dt)
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a finite positive number, got {dt}")
        u = self._check_input(u)
        self.samples = self._em_interval(self.samples, u, float(dt))
        self._intervals.append((u, float(dt)))
        self.time += float(dt)
        self._record(False)

    def update(self, y: Tensor, measurement: MeasurementModel, *, hints: Tensor | None = None) -> None:
        """Condition on the measurement ``y = h(x) + v``, ``v ~ N(0, R)`` (masked entries ignored).

        .. math:: \\log w_i \\mathrel{+}= \\log N(y; h(x_i), R)

        (bootstrap reweighting), unless for a trajectory the bootstrap ESS would fall
        below ``redraw_threshold·K`` or fewer than ``lineage_threshold·K`` lineages are
        left; then that trajectory's particles are redrawn by path-space importance
        sampling over all frames so far (only those trajectories are re-simulated; the
        redraw is kept where its ESS beats ``min(bootstrap ESS, lineages)``).
        Afterwards systematic resampling where ``ESS < resample_threshold·K``.  The
        step's diagnostics are appended to :attr:`history`.

        Args:
            y: ``[B, d]``.
            measurement: the measurement model (``predict``, ``noise_cov``, ``mask``).
            hints: optional ``[B, H, n]`` points at the current time (e.g. filter
                component means) to seed the Laplace fits of a redraw.
        """
        frame = self._make_frame(y, measurement)
        if hints is not None:
            hints = torch.as_tensor(hints, dtype=self._dtype, device=self._device)
            if hints.dim() != 3 or hints.shape[0] != self.batch_size or hints.shape[2] != self.state_dim:
                raise ValueError(
                    f"hints must have shape [B={self.batch_size}, H, n={self.state_dim}], got {tuple(hints.shape)}"
                )
            if not bool(torch.isfinite(hints).all()):
                raise ValueError("hints must be finite")
        ll = self._frame_log_likelihood(frame, self.samples)
        self._frames.append(frame)
        lw = self.log_weights + ll
        lw = lw - torch.logsumexp(lw, -1, keepdim=True)
        ess_boot = effective_sample_size(lw)
        K = self.num_samples
        lineages = _count_distinct(self.lineage).to(ess_boot)
        # redraw where the bootstrap would collapse, or where resampling has left too few lineages
        need = (ess_boot < self.redraw_threshold * K) | (lineages < self.lineage_threshold * K)
        redrawn = torch.zeros_like(need)
        redraw_ess = None
        x, x0, lineage = self.samples, self.initial_samples, self.lineage
        if bool(need.any()):
            sub = need.nonzero().squeeze(-1)  # only these trajectories are re-simulated
            xr, x0r, lwr = self._redraw(sub, lw, hints)
            ess_r = effective_sample_size(lwr)
            better = ess_r > torch.minimum(ess_boot, lineages)[sub]
            take = sub[better]
            x, x0, lw, lineage = x.clone(), x0.clone(), lw.clone(), lineage.clone()
            x[take], x0[take], lw[take] = xr[better], x0r[better], lwr[better]
            lineage[take] = self._own_lineage()[take]
            redrawn[take] = True
            redraw_ess = torch.full_like(ess_boot, math.nan)
            redraw_ess[sub] = ess_r
        self.samples, self.initial_samples, self.log_weights, self.lineage = x, x0, lw, lineage
        self._pre_resample_ess = effective_sample_size(lw)
        resampled = self._pre_resample_ess < self.resample_threshold * K
        if bool(resampled.any()):
            self._resample(resampled)
        self._record(True, redrawn, resampled, ess_boot, redraw_ess)

    def _resample(self, which: Tensor) -> None:
        """Systematic resampling of the trajectories flagged in ``which [B]``."""
        B, K = self.log_weights.shape
        u0 = torch.rand(B, generator=self.generator, dtype=self._dtype, device=self._device)
        idx = systematic_resample(self.log_weights, u0)
        idx = torch.where(which[:, None], idx, torch.arange(K, device=self._device).expand(B, K))
        n = self.state_dim
        self.samples = torch.gather(self.samples, 1, idx[..., None].expand(-1, -1, n))
        self.initial_samples = torch.gather(self.initial_samples, 1, idx[..., None].expand(-1, -1, n))
        self.lineage = torch.gather(self.lineage, 1, idx)
        self.log_weights = torch.where(which[:, None], torch.zeros_like(self.log_weights), self.log_weights)

    # ------------------------------------------------------------------ output
    @property
    def ess(self) -> Tensor:
        """Effective sample size of the current weights, ``[B]``."""
        return effective_sample_size(self.log_weights)

    def score(self, mixture: GaussianMixture) -> tuple[Tensor, Tensor]:
        """:func:`density_score` of ``mixture [B]`` on the current samples (lineage-aware error).

        Returns:
            ``(score [B], standard_error [B])`` (nats).
        """
        return density_score(self.samples, self.log_weights, mixture, chart=self.chart, lineage=self.lineage)

    def stacked_history(self) -> dict[str, Tensor]:
        """The per-step diagnostics as ``[T]`` / ``[T, B]`` tensors (see :class:`ReferenceStepRecord`)."""
        if not self.history:
            return {}
        out = {
            "time": torch.tensor([r.time for r in self.history], dtype=torch.float64),
            "frame": torch.tensor([r.frame for r in self.history]),
        }
        for key in ("ess", "lineages", "redrawn", "resampled", "bootstrap_ess", "redraw_ess"):
            out[key] = torch.stack([getattr(r, key) for r in self.history])
        return out


def _count_distinct(idx: Tensor) -> Tensor:
    """Number of distinct entries in each row of ``idx [B, K]`` → ``[B]``."""
    srt = torch.sort(idx, -1).values
    return 1 + (srt[:, 1:] != srt[:, :-1]).sum(-1)
