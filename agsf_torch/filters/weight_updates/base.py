"""The weight-update step: its options, run state and cadence, and the FPKE quadrature options.

:class:`WeightUpdate` is the base of every weight update (the package's two and a user's own);
:class:`QuadratureUpdate` adds the options of the two FPKE updates (the integration rule and
its evaluation).  See :mod:`agsf_torch.filters.weight_updates`.
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import Tensor

from ...chunks import check_chunk_size
from ...fpke import ComponentRates, residual_rule
from ...mixture import GaussianMixture
from ...models.base import ContinuousModel
from ...models.derived import provides
from ...propagation import moment_derivatives
from ...qp import MAX_COMPONENTS, QPResult, bounded_below, hold_at_zero, solve_simplex_qp
from ..management import active_slots, gather_slots
from ..options import option, positive_int

__all__ = [
    "WeightUpdate",
    "WeightUpdateRun",
    "QuadratureUpdate",
    "component_rates",
    "has_gaussian_moments",
    "check_finite_matrix",
    "solve_weight_qp",
    "MANAGED_WEIGHT_KEPT",
]

#: The share of its weight an active component of a managed mixture keeps at least through one weight update
#: (dimensionless).  In a managed mixture a zero weight marks a free slot: a zero from the weight QP (its
#: ``w ≥ 0`` bound active) would drop the component for good, which no later measurement could undo, and which
#: management's own pruning does not do by default (:class:`~agsf_torch.filters.management.MixtureManagement`'s
#: ``prune_weight``).  Each update may still lower a weight a thousandfold, ten updates between two frames by
#: 1e30.  On ``agsf validate``'s one-star scenario at 90°, the Galerkin QP set about 3 % of the trajectories'
#: steps' weights to zero, and one run of 32 lost the truth's component that way (``docs/results/management.md``).
MANAGED_WEIGHT_KEPT = 1e-3


def component_rates(model: ContinuousModel, mixture: GaussianMixture, u: Tensor | None) -> ComponentRates:
    """The mixture's components with their moment rates ``μ̇ᵢ, Ṗᵢ`` at ``u`` (``[..., m]``, one per trajectory, or ``None``)."""
    rates = moment_derivatives(model, mixture.means, mixture.covs, None if u is None else u.unsqueeze(-2))
    chol = torch.linalg.cholesky(mixture.covs)  # positive definiteness was ensured by predict
    return ComponentRates(mixture.means, chol, rates.mean_rate, rates.cov_rate)


def has_gaussian_moments(model: ContinuousModel) -> bool:
    """Whether ``model`` gives closed-form Gaussian moments of its Fokker–Planck terms (derived for its physics)."""
    return provides(model, "fokker_planck_moments", ContinuousModel)


def solve_weight_qp(run: WeightUpdateRun, H: Tensor, c: Tensor, log_weights: Tensor) -> tuple[Tensor, QPResult]:
    """The weights ``[..., N]`` (on the simplex) minimising ``½wᵀHw + cᵀw``, and the solver's result.

    Unmanaged (``run.hold_inactive`` unset): on the whole simplex, ``w ≥ 0``, as the method has it.  Managed: the
    inactive components (``−inf`` in ``log_weights [..., N]``) held at zero (:func:`~agsf_torch.qp.hold_at_zero`)
    and each active one kept at ``wᵢ ≥ κ·w⁰ᵢ``, ``w⁰ = softmax(log_weights)``, ``κ`` =
    :data:`MANAGED_WEIGHT_KEPT` (:func:`~agsf_torch.qp.bounded_below`), so that the QP cannot drop a component.
    The result's ``kkt_residual`` is that of the problem solved (in ``v`` where bounded below).
    """
    if not run.hold_inactive:
        res = solve_simplex_qp(H, c)
        w = res.w.clamp_min(0.0)
        return w / w.sum(-1, keepdim=True), res
    active = torch.isfinite(log_weights)
    lower = MANAGED_WEIGHT_KEPT * torch.softmax(log_weights, -1)
    Hv, cv, s = bounded_below(H, c, lower)
    res = solve_simplex_qp(*hold_at_zero(Hv, cv, active))
    w = torch.where(active, lower + s[..., None] * res.w.clamp_min(0.0), 0.0)
    return w / w.sum(-1, keepdim=True), res


def check_finite_matrix(name: str, value: Tensor) -> None:
    bad = ~torch.isfinite(value).flatten(-2).all(-1)
    if bool(bad.any()):
        raise ValueError(f"{name} is not finite at trajectory index {tuple(bad.nonzero()[0].tolist())}")


@dataclass
class WeightUpdateRun:
    """A weight update's run state (mutable; the options are not).

    Attributes:
        step: intervals counted since the run started.
        elapsed: time since the last adaptation or measurement update (s).
        reference: the penalty update's reference log-weights ``[..., N]`` (``None`` before the first).
        hold_inactive: set while :meth:`WeightUpdate.compute` runs for a managed mixture: the QP holds inactive
            components at zero weight and keeps the active ones (:func:`solve_weight_qp`).
    """

    step: int = 0
    elapsed: float = 0.0
    reference: Tensor | None = None
    hold_inactive: bool = False  # during compute: the mixture is managed (inactive slots' weights held at zero)


@dataclass(frozen=True, kw_only=True, eq=False)
class WeightUpdate:
    """A correction of the forecast weights after each propagation interval.

    Subclasses implement :meth:`compute`; this base class runs it every ``cadence``-th
    interval and keeps the counter.  One object serves one filter: its run state
    (:attr:`run`) is that filter's, and a second filter given the same object is refused
    (:meth:`claim`; it had shared the first's reference weights and counter, and rebound it to its
    own model).  State changes only after a step
    succeeds: an error leaves the update as it was (:meth:`check` runs before the interval
    is counted, :meth:`compute` must not change the run state before it can no longer fail).

    Options are fields (keyword-only, validated in ``__post_init__``, frozen); objects compare
    by identity, since each carries its own run.

    Attributes:
        cadence: adapt every ``cadence``-th ``predict`` call (1: every interval).
    """

    cadence: int = field(
        default=1,
        metadata=option("adaptive filters adapt their weights every cadence-th propagation step", config="int"),
    )
    run: WeightUpdateRun = field(default_factory=WeightUpdateRun, init=False, repr=False)

    #: Short name used in configurations and reports.
    name: ClassVar[str] = "custom"
    #: Diagnostics keys :meth:`compute` returns (besides ``weights_adapted``).
    DIAGNOSTICS: ClassVar[tuple[str, ...]] = ()
    #: Keys of :meth:`state_dict` beyond ``kind``, ``step`` and ``elapsed``.
    extra_state_keys: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        positive_int("cadence", self.cadence)

    def check_free(self, filt: object) -> None:
        """Raise ``ValueError`` if this update serves another filter than ``filt`` that still exists."""
        owner = self.__dict__.get("_owner")
        current = None if owner is None else owner()
        if current is not None and current is not filt:
            raise ValueError(
                f"this {type(self).__name__} already serves another filter (its run state, the reference weights and "
                f"the cadence counter, is that filter's): give each filter its own, e.g. dataclasses.replace(update) "
                f"or {type(self).__name__}(...) again"
            )

    def claim(self, filt: object) -> None:
        """Make this update ``filt``'s (:meth:`check_free` first).  The owner is held by a weak reference (a filter
        that is gone frees its update) and is not part of the update's state: a pickled or deep-copied update has
        none until its filter next checks a mixture."""
        self.check_free(filt)
        object.__setattr__(self, "_owner", weakref.ref(filt))

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.pop("_owner", None)  # a weak reference does not pickle, and names a filter of this process
        return state

    @property
    def diagnostic_keys(self) -> tuple[str, ...]:
        """The keys :meth:`compute` returns (besides ``weights_adapted``)."""
        return self.DIAGNOSTICS

    def bind(self, model: ContinuousModel, *, fused: bool = True, compile_fused: bool = False) -> None:
        """Called once by the filter with its model (build quadrature rules here) and its ``fused`` and
        ``compile_fused`` options (:class:`~agsf_torch.filters.options.FilterOptions`), for a weight update
        whose integrals have a fused kernel."""

    def __call__(
        self,
        model: ContinuousModel,
        prior: GaussianMixture,
        propagated: GaussianMixture,
        u: Tensor | None,
        dt: float,
        *,
        enabled: bool = True,
        weight_map: Tensor | None = None,
    ) -> tuple[Tensor | None, dict[str, Any]]:
        """Count the interval and, on the cadence, return new log-weights ``[..., N]``.

        Args:
            prior: the belief before the interval; propagated: after it (weights unchanged).
            u: input ``[..., m]`` (one per trajectory) or ``None``; dt: the interval (s).
            enabled: ``False`` counts the interval without adapting.
            weight_map: ``T [..., N, N]``, the action on the weights of the mixture management that ran before this
                interval (:class:`~agsf_torch.filters.management.ManagementResult`), or ``None``: the reference
                weights, if any, are mapped by it (``w ↦ Tw``, renormalised).  With it, the weight QP holds the
                weights of inactive components (``−inf`` log-weight) at zero and keeps the active ones
                (:func:`solve_weight_qp`).

        Returns:
            ``(log_weights or None, diagnostics)``; ``None`` when this interval is not adapted.
        """
        if enabled:
            self.check(propagated)
        step, elapsed = self.run.step + 1, self.run.elapsed + float(dt)
        reference = self.run.reference
        if weight_map is not None and reference is not None:
            K = weight_map.shape[-1]
            if reference.shape[-1] < K:  # recorded before the mixture was padded
                pad = reference.new_full((*reference.shape[:-1], K - reference.shape[-1]), float("-inf"))
                reference = torch.cat((reference, pad), -1)
            mapped = (weight_map @ reference.exp().unsqueeze(-1)).squeeze(-1)
            reference = torch.log(mapped) - torch.log(mapped.sum(-1, keepdim=True))
        if not enabled or step % self.cadence != 0 or propagated.num_components == 1:
            self.run.step, self.run.elapsed, self.run.reference = step, elapsed, reference
            return None, {"weights_adapted": False}
        before = self.run.reference
        self.run.reference, self.run.hold_inactive = reference, weight_map is not None
        try:
            log_weights, extra = self._compute_on_slots(model, prior, propagated, u, elapsed)
        except BaseException:
            self.run.reference = before
            raise
        finally:
            self.run.hold_inactive = False
        self.run.step, self.run.elapsed = step, 0.0
        return log_weights, {**extra, "weights_adapted": True}

    def _compute_on_slots(
        self,
        model: ContinuousModel,
        prior: GaussianMixture,
        propagated: GaussianMixture,
        u: Tensor | None,
        elapsed: float,
    ) -> tuple[Tensor, dict[str, Any]]:
        """:meth:`compute`; for a managed mixture, on the slots its active components need
        (:func:`~agsf_torch.filters.management.active_slots`: the pairs of a weight update grow with the square of
        the slots, and the inactive ones take no part), the new log-weights and the reference put back in their
        slots (the new log-weights ``−inf`` at the others, the reference as it was there)."""
        index = active_slots(propagated.log_weights) if self.run.hold_inactive else None
        if index is None:
            return self.compute(model, prior, propagated, u, elapsed)
        full = self.run.reference if self.run.reference is not None else prior.log_weights
        if self.run.reference is not None:
            self.run.reference = torch.gather(self.run.reference, -1, index)
        log_w, extra = self.compute(model, gather_slots(prior, index), gather_slots(propagated, index), u, elapsed)
        if self.run.reference is not None:
            self.run.reference = full.scatter(-1, index, self.run.reference)
        return torch.full_like(propagated.log_weights, -math.inf).scatter(-1, index, log_w), extra

    def check(self, mixture: GaussianMixture) -> None:
        """Raise ``ValueError`` if this update cannot adapt ``mixture`` (default: it can).  Called on every
        enabled interval before it is counted, and by the adaptive filter before it propagates."""

    def compute(
        self,
        model: ContinuousModel,
        prior: GaussianMixture,
        propagated: GaussianMixture,
        u: Tensor | None,
        elapsed: float,
    ) -> tuple[Tensor, dict[str, Any]]:
        """New log-weights ``[..., N]`` and diagnostics; ``u [..., m]`` or ``None``; ``elapsed`` is the time
        since the last adaptation (s).  Must not change the run state before it can no longer fail."""
        raise NotImplementedError

    def observe_update(self, log_weights: Tensor) -> None:
        """Called by the filter after each measurement update with the posterior log-weights ``[..., N]``:
        the weights are new, so the time over which they are held restarts (``elapsed = 0``)."""
        self.run.elapsed = 0.0

    def reset(self) -> None:
        """Forget the run: restart the cadence counter (and any reference)."""
        self.run.step, self.run.elapsed, self.run.reference = 0, 0.0, None

    def state_dict(self) -> dict[str, Any]:
        """The update's run state (numbers, strings and tensors only), tagged with its ``kind``."""
        return {"kind": self.name, "step": self.run.step, "elapsed": self.run.elapsed}

    def checkpoint_options(self) -> dict[str, Any]:
        """The update's kind (``weight_update``: :attr:`name`) and its options (its fields), which a checkpoint
        records beside its filter's run state (:meth:`~agsf_torch.filters.base.BaseFilter.checkpoint_options`)."""
        return {
            "weight_update": self.name,
            **{f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; validated before anything changes."""
        step, elapsed = self._parse_counter(state)
        self.run.step, self.run.elapsed = step, elapsed

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
        if (
            isinstance(elapsed, bool)
            or not isinstance(elapsed, (int, float))
            or not 0.0 <= float(elapsed) < float("inf")
        ):
            raise ValueError(f"weight-update state 'elapsed' must be a finite number ≥ 0, got {elapsed!r}")
        return step, float(elapsed)


@dataclass(frozen=True, kw_only=True, eq=False)
class QuadratureUpdate(WeightUpdate):
    """Shared options of the two FPKE weight updates: the rule and its evaluation.

    Attributes:
        quadrature: how the residual integrals under each product Gaussian are computed.
            ``None`` (default) takes the fastest exact route the model offers: for the
            Galerkin ``K``, closed-form Gaussian moments (``fokker_planck_moments``;
            the attitude models have them), for the paper's ``L`` the model's own exact route
            (``fpke_pair_products``: the attitude models evaluate ``ℓ`` at 84 nodes per pair on
            lanes, the 6-state one with the bias block in closed form) or an interpolatory product rule on the polynomial
            space of ``ℓ`` (``fpke_polynomial_space``: 840 nodes per pair for 6-state attitude
            instead of 9261); otherwise the
            model's exact Gauss–Hermite rule (``fpke_quadrature_points``), else 7
            points per axis for ``n ≤ 4`` and a level-7 Smolyak grid above.  Or an int
            (points per axis), a tuple (points per axis), or ``(nodes [K, n], weights [K])``
            for ``N(0, I)`` (finite, weights summing to 1), applied as ``x = m + chol(S) ξ``
            with the lower Cholesky factor — e.g. :func:`agsf_torch.quadrature.six_n_plus_one`,
            the authors' own rule.
        chunk_size: quadrature nodes (or, with a product rule, component pairs) per
            batched evaluation, a positive integer (``None``: sized automatically to
            bound memory).
        compile: compile the FPKE kernels ahead of time (:mod:`agsf_torch.compiled_kernels`, the package's one
            compile path): the model's own route (the attitude models' L on lanes,
            :mod:`agsf_torch.fused.pair_products`) or a generic model's node kernels (keyed by their exported
            graph, once per machine, model and shape); unused by the closed-form Galerkin path, whose fused pair
            kernel follows the filter's ``compile_fused``.  ``None`` (the default): as the filter's ``compile_fused``, so that
            one switch compiles every kernel of an adaptive filter; ``True`` or ``False`` overrides it.
    """

    quadrature: Any = field(default=None, metadata=option("the residual integrals' rule (None: the model's exact one)"))
    chunk_size: int | None = field(
        default=None, metadata=option("quadrature nodes or pairs per batched evaluation (None: automatic)")
    )
    compile: bool | None = field(
        default=None,
        metadata=option(
            "compile the FPKE kernels of the adaptive filters (auto: as the filter's compile_fused)",
            config="bool",
            off="auto",
        ),
    )
    rule: dict = field(default_factory=dict, init=False, repr=False)

    #: Residual factors in the integrand: 2 for ``ℓᵢℓⱼ``, 1 for ``ℓⱼ``.
    factors: ClassVar[int] = 2

    def __post_init__(self) -> None:
        super().__post_init__()
        check_chunk_size(self.chunk_size)
        if self.compile is not None and not isinstance(self.compile, bool):
            raise ValueError(
                f"compile must be True, False or None (as the filter's compile_fused), got {self.compile!r}"
            )

    def bind(self, model: ContinuousModel, *, fused: bool = True, compile_fused: bool = False) -> None:
        self.rule["nodes"], self.rule["weights"] = residual_rule(model, self.quadrature, self.factors)
        self.rule["fused"], self.rule["compile_fused"] = bool(fused), bool(compile_fused)
        # one switch: unless set here, the FPKE kernels compile as the filter's fused kernels do
        self.rule["compile"] = bool(compile_fused) if self.compile is None else self.compile

    def check(self, mixture: GaussianMixture) -> None:
        """The weight QP (:func:`~agsf_torch.qp.solve_simplex_qp`) takes ``N ≤ MAX_COMPONENTS`` components."""
        if mixture.num_components > MAX_COMPONENTS:
            raise ValueError(
                f"the weight QP handles N ≤ {MAX_COMPONENTS} components, got a mixture of {mixture.num_components}"
            )
