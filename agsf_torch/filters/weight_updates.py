"""Weight updates during propagation: the step that makes a Gaussian sum filter adaptive.

A weight update takes the mixture before and after one propagation interval and
returns corrected forecast weights.  Two are provided, both minimising the
Fokker–Planck (FPKE) residual of the mixture (method.md §3 and §3b):

* :class:`PenaltyWeightUpdate` — the paper's QP
  ``w* = argmin_{w∈Δ} ½wᵀLw + (λ/2)‖w − w_ref‖²``, ``L_ij = ∫LᵢLⱼ dx``;
* :class:`GalerkinWeightUpdate` — the authors' later form: the weights' rate of
  change cancels the residual in L²,
  ``w⁺ = argmin_{w∈Δ} ∫(Σᵢ(wᵢ − w⁻ᵢ)/Δt·pᵢ + Σⱼw⁻ⱼLⱼ)² dx = argmin ½wᵀMw + wᵀ(Δt·K − M)w⁻``.

A weight update owns the state it needs (the cadence counter, the penalty's
reference weights), so a filter instance follows one run — one batch of
trajectories — at a time: call ``reset()`` before starting another.  Write your
own by subclassing :class:`WeightUpdate` and implementing :meth:`WeightUpdate.compute`.
"""

from __future__ import annotations

import inspect
from typing import Any

import torch
from torch import Tensor

from ..fpke import ComponentRates, fpke_matrix, galerkin_matrices, residual_rule
from ..fpke.matrices import check_chunk_size
from ..mixture import GaussianMixture
from ..models.base import ContinuousModel
from ..propagation import moment_derivatives
from ..qp import MAX_COMPONENTS, kkt_residual, solve_simplex_qp

__all__ = ["WeightUpdate", "PenaltyWeightUpdate", "GalerkinWeightUpdate", "WEIGHT_UPDATES", "make_weight_update"]


def _positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or int(value) != value or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def component_rates(model: ContinuousModel, mixture: GaussianMixture, u: Tensor | None) -> ComponentRates:
    """The mixture's components with their moment rates ``μ̇ᵢ, Ṗᵢ`` at ``u`` (``[..., 1, m]`` or ``None``)."""
    rates = moment_derivatives(model, mixture.means, mixture.covs, u)
    chol = torch.linalg.cholesky(mixture.covs)  # positive definiteness was ensured by predict
    return ComponentRates(mixture.means, chol, rates.mean_rate, rates.cov_rate)


def has_gaussian_moments(model: ContinuousModel) -> bool:
    """Whether ``model`` gives closed-form Gaussian moments of its Fokker–Planck terms."""
    return type(model).fokker_planck_moments is not ContinuousModel.fokker_planck_moments


def _check_finite_matrix(name: str, value: Tensor) -> None:
    bad = ~torch.isfinite(value).flatten(-2).all(-1)
    if bool(bad.any()):
        raise ValueError(f"{name} is not finite at trajectory index {tuple(bad.nonzero()[0].tolist())}")


class WeightUpdate:
    """A correction of the forecast weights after each propagation interval.

    Subclasses implement :meth:`compute`; this base class runs it every
    ``cadence``-th interval and keeps the counter.  One object serves one filter:
    its state is that filter's run state (passing the same object to two filters
    shares it, and :meth:`bind` rebinds it to the last filter's model).  State changes only after a
    step succeeds: an error leaves the update as it was (:meth:`check` runs before the interval
    is counted, :meth:`compute` must not change ``self`` before it can no longer fail).

    Args:
        cadence: adapt every ``cadence``-th ``predict`` call (1: every interval).
    """

    #: Short name used in configurations and reports.
    name = "custom"
    #: Diagnostics keys :meth:`compute` returns (besides ``weights_adapted``).
    diagnostic_keys: tuple[str, ...] = ()

    def __init__(self, *, cadence: int = 1) -> None:
        self.cadence = _positive_int("cadence", cadence)
        self._step = 0
        self._elapsed = 0.0

    def bind(self, model: ContinuousModel) -> None:
        """Called once by the filter with its model (build quadrature rules here)."""

    def __call__(
        self, model: ContinuousModel, prior: GaussianMixture, propagated: GaussianMixture, u: Tensor | None, dt: float,
        *, enabled: bool = True,
    ) -> tuple[Tensor | None, dict[str, Any]]:
        """Count the interval and, on the cadence, return new log-weights ``[..., N]``.

        Args:
            prior: the belief before the interval; propagated: after it (weights unchanged).
            u: input ``[..., 1, m]`` (broadcast over components) or ``None``; dt: the interval (s).
            enabled: ``False`` counts the interval without adapting.

        Returns:
            ``(log_weights or None, diagnostics)``; ``None`` when this interval is not adapted.
        """
        if enabled:
            self.check(propagated)
        step, elapsed = self._step + 1, self._elapsed + float(dt)
        if not enabled or step % self.cadence != 0 or propagated.num_components == 1:
            self._step, self._elapsed = step, elapsed
            return None, {"weights_adapted": False}
        log_weights, extra = self.compute(model, prior, propagated, u, elapsed)
        self._step, self._elapsed = step, 0.0
        return log_weights, {**extra, "weights_adapted": True}

    def check(self, mixture: GaussianMixture) -> None:
        """Raise ``ValueError`` if this update cannot adapt ``mixture`` (default: it can).  Called on every
        enabled interval before it is counted, and by the adaptive filter before it propagates."""

    def compute(
        self, model: ContinuousModel, prior: GaussianMixture, propagated: GaussianMixture, u: Tensor | None, elapsed: float
    ) -> tuple[Tensor, dict[str, Any]]:
        """New log-weights ``[..., N]`` and diagnostics; ``elapsed`` is the time since the last adaptation (s).
        Must not change ``self`` before it can no longer fail."""
        raise NotImplementedError

    def observe_update(self, log_weights: Tensor) -> None:
        """Called by the filter after each measurement update with the posterior log-weights ``[..., N]``:
        the weights are new, so the time over which they are held restarts (``elapsed = 0``)."""
        self._elapsed = 0.0

    def reset(self) -> None:
        """Forget the run: restart the cadence counter (and any reference)."""
        self._step, self._elapsed = 0, 0.0

    #: Keys of :meth:`state_dict` beyond ``kind``, ``step`` and ``elapsed``.
    extra_state_keys: tuple[str, ...] = ()

    def state_dict(self) -> dict[str, Any]:
        """The update's run state (numbers, strings and tensors only), tagged with its ``kind``."""
        return {"kind": self.name, "step": self._step, "elapsed": self._elapsed}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; validated before anything changes."""
        step, elapsed = self._parse_counter(state)
        self._step, self._elapsed = step, elapsed

    def _parse_counter(self, state: Any) -> tuple[int, float]:
        """Check ``state`` is this kind's state with exactly the expected keys; return ``(step, elapsed)``."""
        keys = {"kind", "step", "elapsed", *self.extra_state_keys}
        if isinstance(state, dict) and "kind" in state and state["kind"] != self.name:
            raise ValueError(f"the state is a {state['kind']!r} weight update's, not this {self.name!r} one's")
        if not isinstance(state, dict) or set(state) != keys:
            got = sorted(state) if isinstance(state, dict) else state
            raise ValueError(f"{type(self).__name__} state must have the keys {sorted(keys)}, got {got!r}")
        step, elapsed = state["step"], state["elapsed"]
        if isinstance(step, bool) or not isinstance(step, int) or step < 0:
            raise ValueError(f"weight-update state 'step' must be an integer ≥ 0, got {step!r}")
        if isinstance(elapsed, bool) or not isinstance(elapsed, (int, float)) or not 0.0 <= float(elapsed) < float("inf"):
            raise ValueError(f"weight-update state 'elapsed' must be a finite number ≥ 0, got {elapsed!r}")
        return step, float(elapsed)


class _QuadratureUpdate(WeightUpdate):
    """Shared options of the two FPKE weight updates: the rule and its evaluation."""

    factors = 2

    def __init__(self, *, cadence: int = 1, quadrature: Any = None, chunk_size: int | None = None, compile: bool = False) -> None:
        super().__init__(cadence=cadence)
        self.chunk_size = chunk_size
        self.compile = bool(compile)
        self.quadrature = quadrature
        self.nodes: Tensor | None = None
        self.node_weights: Tensor | None = None

    @property
    def chunk_size(self) -> int | None:
        """Nodes (or pairs) per batched evaluation, ``int ≥ 1`` or ``None``; checked when set."""
        return self._chunk_size

    @chunk_size.setter
    def chunk_size(self, value: int | None) -> None:
        self._chunk_size = check_chunk_size(value)

    def bind(self, model: ContinuousModel) -> None:
        self.nodes, self.node_weights = residual_rule(model, self.quadrature, self.factors)

    def check(self, mixture: GaussianMixture) -> None:
        """The weight QP (:func:`~agsf_torch.qp.solve_simplex_qp`) takes ``N ≤ MAX_COMPONENTS`` components."""
        if mixture.num_components > MAX_COMPONENTS:
            raise ValueError(
                f"the weight QP handles N ≤ {MAX_COMPONENTS} components, got a mixture of {mixture.num_components}"
            )


_SCALINGS = ("trace", "none")
_REFERENCES = ("update", "previous")


class PenaltyWeightUpdate(_QuadratureUpdate):
    """The paper's weight QP (method.md §3).

    .. math:: w^* = \\arg\\min_{w ∈ Δ} ½ w^T L w + \\frac{λ}{2} \\|w - w_{ref}\\|^2,
              \\qquad L_{ij} = ∫ L_i L_j\\,dx

    with ``L`` of the propagated components (:func:`agsf_torch.fpke.fpke_matrix`,
    integrand ``ℓᵢℓⱼ``).  In the form handed to the QP solver: Hessian ``L + λI``,
    linear term ``−λ w_ref``.

    Args:
        reg: λ ≥ 0 (the paper: 1); a tensor keeps its gradient.
        scaling: ``"trace"`` (default) solves with ``L / (tr L / N)`` so that λ is
            dimensionless — with star-camera covariances the raw ``L`` is
            astronomically large and the penalty would vanish; ``"none"`` uses the
            raw ``L`` (the paper's ``L + I``).
        weight_ref: ``"update"`` (default, the paper's ``w_{k|k}``) — the weights
            after the last measurement update (the initial weights before the
            first); ``"previous"`` — the weights of the previous step.
        cadence, quadrature, chunk_size, compile: see :class:`AdaptiveGaussianSumFilter`.

    Diagnostics: ``fpke_error_before``, ``fpke_error_after`` (unscaled ``wᵀLw``
    with the propagated and the new weights, ``[...]``), ``qp_kkt_residual [...]``,
    ``qp_iterations`` (int).
    """

    name = "penalty"
    factors = 2
    diagnostic_keys = ("fpke_error_before", "fpke_error_after", "qp_kkt_residual", "qp_iterations")

    def __init__(
        self, reg: float | Tensor = 1.0, scaling: str = "trace", weight_ref: str = "update", *, cadence: int = 1,
        quadrature: Any = None, chunk_size: int | None = None, compile: bool = False,
    ) -> None:
        reg_value = (
            float(reg) if isinstance(reg, (int, float)) and not isinstance(reg, bool)
            else float(reg.detach()) if torch.is_tensor(reg) and reg.numel() == 1 else None
        )
        if reg_value is None or not (reg_value >= 0 and reg_value != float("inf")):
            raise ValueError(f"reg must be a finite number ≥ 0, got {reg}")
        if scaling not in _SCALINGS:
            raise ValueError(f"scaling must be one of {_SCALINGS}, got {scaling!r}")
        if weight_ref not in _REFERENCES:
            raise ValueError(f"weight_ref must be one of {_REFERENCES}, got {weight_ref!r}")
        super().__init__(cadence=cadence, quadrature=quadrature, chunk_size=chunk_size, compile=compile)
        self.reg = reg if torch.is_tensor(reg) else float(reg)
        self.scaling = scaling
        self.weight_ref = weight_ref
        self._ref: Tensor | None = None

    extra_state_keys = ("ref_log_weights",)

    def observe_update(self, log_weights: Tensor) -> None:
        super().observe_update(log_weights)
        self._ref = log_weights

    def reset(self) -> None:
        super().reset()
        self._ref = None

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "ref_log_weights": self._ref}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        step, elapsed = self._parse_counter(state)
        ref = state["ref_log_weights"]
        floating = torch.is_tensor(ref) and ref.is_floating_point() and ref.dim() >= 1
        if ref is not None and (not floating or bool((torch.isnan(ref) | torch.isposinf(ref)).any())):
            got = f"a {ref.dtype} tensor" if torch.is_tensor(ref) else type(ref).__name__
            raise ValueError(f"weight-update state 'ref_log_weights' must be None or a floating-point tensor [..., N] "
                             f"without NaN or +inf, got {got}")
        self._step, self._elapsed, self._ref = step, elapsed, ref

    def compute(
        self, model: ContinuousModel, prior: GaussianMixture, propagated: GaussianMixture, u: Tensor | None, elapsed: float
    ) -> tuple[Tensor, dict[str, Any]]:
        means = propagated.means
        if self._ref is not None and self._ref.shape != propagated.log_weights.shape:
            raise ValueError(
                f"reference weights {tuple(self._ref.shape)} are from a run with another batch shape than the "
                f"mixture's {tuple(propagated.log_weights.shape)}; call reset() before a new run"
            )
        comp = component_rates(model, propagated, u)
        u_traj = None if u is None else u.squeeze(-2)
        Lmat = fpke_matrix(model, u_traj, comp, self.nodes, self.node_weights, self.chunk_size, compile=self.compile)
        bad = ~torch.isfinite(Lmat.scaled).flatten(-2).all(-1) | ~torch.isfinite(Lmat.log_scale)
        if bool(bad.any()):
            idx = bad.nonzero()[0].tolist()
            raise ValueError(f"FPKE matrix L is not finite at trajectory index {tuple(idx)}")
        N = propagated.num_components
        w_prop = propagated.weights
        if self.weight_ref == "update" and self._ref is not None:
            w_ref = self._ref.exp()
        elif self.weight_ref == "update":
            w_ref = prior.weights  # no update yet: the initial weights
        else:
            w_ref = w_prop
        eye = torch.eye(N, dtype=means.dtype, device=means.device)
        if self.scaling == "trace":
            tr = Lmat.scaled.diagonal(dim1=-2, dim2=-1).sum(-1)
            tiny = torch.finfo(means.dtype).tiny
            Ls = Lmat.scaled / (tr / N).clamp_min(tiny)[..., None, None]
        else:
            Ls = Lmat.full()
            if not bool(torch.isfinite(Ls).all()):
                idx = (~torch.isfinite(Ls)).flatten(-2).any(-1).nonzero()[0].tolist()
                raise ValueError(f"unscaled FPKE matrix overflows at trajectory index {tuple(idx)}; use scaling='trace'")
        res = solve_simplex_qp(Ls + self.reg * eye, -self.reg * w_ref)
        w_new = res.w.clamp_min(0.0)
        w_new = w_new / w_new.sum(-1, keepdim=True)
        log_w = torch.log(w_new)
        extra = {
            "fpke_error_before": Lmat.error(w_prop),
            "fpke_error_after": Lmat.error(w_new),
            "qp_kkt_residual": res.kkt_residual,
            "qp_iterations": res.iterations,
        }
        if self._ref is None:  # nothing can fail from here on: commit the reference
            self._ref = prior.log_weights
            # the first adaptation of a run normalised its log-weights once more in the original
            # implementation (1 ulp); kept so that the paper's numbers stay bit for bit
            log_w = log_w - torch.logsumexp(log_w, -1, keepdim=True)
        return log_w, extra


class GalerkinWeightUpdate(_QuadratureUpdate):
    """The authors' later weight update (method.md §3b): the weights' rate cancels the FPKE residual in L².

    .. math:: w^+ = \\arg\\min_{w ∈ Δ} ∫ \\Big(Σ_i \\frac{w_i - w^-_i}{Δt} p_i(x) + Σ_j w^-_j L_j(x)\\Big)^2 dx
                  = \\arg\\min_{w ∈ Δ} ½ w^T M w + w^T (Δt\\,K - M) w^-

    ``M_ij = ∫pᵢpⱼ = N(μᵢ; μⱼ, Pᵢ + Pⱼ)`` (closed form), ``K_ij = ∫pᵢLⱼ =
    z_ij E_{N(m_ij, S_ij)}[ℓⱼ]`` (:func:`agsf_torch.fpke.galerkin_matrices`, integrand
    ``ℓⱼ``: degree 6 for attitude, exact with 4 Gauss–Hermite points per MRP axis
    and 2 per bias axis).  ``w⁻`` are the weights before this adaptation (after the
    last measurement update, if there was one); ``Δt`` is the time since the last
    adaptation (the interval itself at ``cadence = 1``).  Both matrices are
    divided by ``max z_ij``, which leaves the minimiser unchanged.  No λ and no
    scaling choice.

    ``M`` is only positive *semi*-definite when components coincide (any split of
    their weight gives the same density).  Among the minimisers the update
    returns the one nearest ``w⁻``: it solves with ``M + εI`` and linear term
    ``(Δt K − M)w⁻ − εw⁻`` (a proximal term ``(ε/2)‖w − w⁻‖²``), ``ε = tikhonov ·
    max diag M̃``, whose minimiser tends to the projection of ``w⁻`` on the solution
    set as ε → 0 and moves the objective by at most ``ε·‖w − w⁻‖²/2``.  The default
    ε = 1e-9 keeps the KKT solve conditioned to ~1e9, so the weights in the flat
    directions are accurate to ~1e-7 (at 1e-12 rounding of the linear term alone
    left 1e-4); on the sine benchmark (method.md §5) the forecast ISE at t = 8 is
    the same to 8 digits for ε from 1e-12 to 1e-8.

    Args:
        cadence, quadrature, chunk_size, compile: see :class:`AdaptiveGaussianSumFilter`.
        tikhonov: the relative ε above (> 0; default 1e-9).
        residual_diagnostics: also evaluate the FPKE residual ``∫e²`` with the weights
            held (``fpke_error_before = w⁻ᵀLw⁻``, as the penalty update's) and with the
            chosen weight rate over the step (``fpke_error_with_rate``); this needs the paper's
            ``ℓᵢℓⱼ`` integrals (with the model's rule for them, as the penalty
            update's default) and costs as much as the penalty update.

    Diagnostics: ``galerkin_residual_change [...]`` (``∫e²`` after minus before,
    exact and cheap: ``[(w − w⁻)ᵀM(w − w⁻) + 2Δt(w − w⁻)ᵀKw⁻]/Δt²``, ≤ 0),
    ``qp_kkt_residual [...]`` (of the problem without the proximal term),
    ``qp_iterations``; with ``residual_diagnostics`` also the two errors.

    ``Δt`` restarts at each measurement update (:meth:`WeightUpdate.observe_update`):
    the posterior weights are the ``w⁻`` of the next adaptation.
    """

    name = "galerkin"
    factors = 1
    diagnostic_keys = ("galerkin_residual_change", "qp_kkt_residual", "qp_iterations")

    def __init__(
        self, *, cadence: int = 1, quadrature: Any = None, chunk_size: int | None = None, compile: bool = False,
        tikhonov: float = 1e-9, residual_diagnostics: bool = False,
    ) -> None:
        if isinstance(tikhonov, bool) or not isinstance(tikhonov, (int, float)) or not 0.0 < tikhonov < float("inf"):
            raise ValueError(f"tikhonov must be a finite number > 0 (it selects the minimiser nearest w⁻), got {tikhonov!r}")
        super().__init__(cadence=cadence, quadrature=quadrature, chunk_size=chunk_size, compile=compile)
        if not isinstance(residual_diagnostics, bool):
            raise ValueError(f"residual_diagnostics must be True or False, got {residual_diagnostics!r}")
        self.tikhonov = float(tikhonov)
        self.residual_diagnostics = residual_diagnostics
        if residual_diagnostics:
            self.diagnostic_keys = type(self).diagnostic_keys + ("fpke_error_before", "fpke_error_with_rate")
        self._residual_rule: tuple[Tensor, Tensor] | None = None

    def bind(self, model: ContinuousModel) -> None:
        if self.quadrature is None and has_gaussian_moments(model):
            self.nodes = self.node_weights = None  # K in closed form (fpke.moments)
        else:
            super().bind(model)
        if self.residual_diagnostics:
            self._residual_rule = residual_rule(model, None, 2)  # the model's rule for ℓᵢℓⱼ

    def compute(
        self, model: ContinuousModel, prior: GaussianMixture, propagated: GaussianMixture, u: Tensor | None, elapsed: float
    ) -> tuple[Tensor, dict[str, Any]]:
        comp = component_rates(model, propagated, u)
        u_traj = None if u is None else u.squeeze(-2)
        G = galerkin_matrices(model, u_traj, comp, self.nodes, self.node_weights, self.chunk_size, compile=self.compile)
        _check_finite_matrix("Galerkin matrix K", G.drift)
        _check_finite_matrix("Galerkin matrix M", G.mass)
        w0 = propagated.weights
        N = w0.shape[-1]
        c = ((elapsed * G.drift - G.mass) @ w0.unsqueeze(-1)).squeeze(-1)
        eps = self.tikhonov * G.mass.diagonal(dim1=-2, dim2=-1).amax(-1)
        eye = torch.eye(N, dtype=w0.dtype, device=w0.device)
        res = solve_simplex_qp(G.mass + eps[..., None, None] * eye, c - eps[..., None] * w0)
        w_new = res.w.clamp_min(0.0)
        w_new = w_new / w_new.sum(-1, keepdim=True)
        dw = w_new - w0
        change = (dw.unsqueeze(-2) @ G.mass @ dw.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        change = change + 2.0 * elapsed * (dw.unsqueeze(-2) @ G.drift @ w0.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        change = change * torch.exp(G.log_scale) / elapsed**2
        extra: dict[str, Any] = {
            "galerkin_residual_change": change,
            "qp_kkt_residual": kkt_residual(G.mass, c, w_new),
            "qp_iterations": res.iterations,
        }
        if self._residual_rule is not None:
            Lmat = fpke_matrix(model, u_traj, comp, *self._residual_rule, self.chunk_size, compile=self.compile)
            before = Lmat.error(w0)
            extra["fpke_error_before"] = before
            extra["fpke_error_with_rate"] = before + change
        return torch.log(w_new), extra


#: Names accepted by ``AdaptiveGaussianSumFilter(weight_update=...)``.
WEIGHT_UPDATES = {"penalty": PenaltyWeightUpdate, "galerkin": GalerkinWeightUpdate}


def make_weight_update(spec: str | WeightUpdate, **options: Any) -> WeightUpdate:
    """A weight update from its name (``"penalty"``, ``"galerkin"``) and options, or the object itself.

    Raises:
        ValueError: an unknown name (listing the choices), or options the update does not take.
    """
    if isinstance(spec, WeightUpdate):
        if options:
            raise ValueError(f"options {sorted(options)} configure a named weight update; pass them to {type(spec).__name__} instead")
        return spec
    if not isinstance(spec, str) or spec not in WEIGHT_UPDATES:
        raise ValueError(f"weight_update must be one of {sorted(WEIGHT_UPDATES)} or a WeightUpdate, got {spec!r}")
    cls = WEIGHT_UPDATES[spec]
    accepted = set(inspect.signature(cls.__init__).parameters) - {"self"}
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise ValueError(f"weight_update={spec!r} does not take {', '.join(unknown)} (it takes {', '.join(sorted(accepted))})")
    return cls(**options)
