"""Mixture management: a Gaussian sum of fixed capacity that splits, merges and prunes its components.

The mixture keeps its shape ``[..., K]`` (``K`` = :attr:`MixtureManagement.capacity`): a component that is
not in use is an *inactive slot*, with log-weight ``−inf`` (weight zero), so every trajectory advances in one
tensor program however many components it carries.  An inactive slot holds a copy of its trajectory's heaviest
component (a finite, positive definite Gaussian): it takes no part in the estimate, the likelihood, the weight
QP (held at zero, :func:`agsf_torch.qp.hold_at_zero`) or the density, and costs nothing that could fail.  The
weight QP keeps every active component active (:func:`~agsf_torch.filters.weight_updates.base.solve_weight_qp`):
only management makes a slot inactive.

Each management pass (:meth:`MixtureManagement.apply`) runs, batched over trajectories:

1. **prune**: a component whose weight is below ``prune_weight`` becomes inactive (never the heaviest);
2. **merge** (Runnalls 2007): ``merge_rounds`` rounds in which every pair of *mutual* nearest components by
   Runnalls' bound on the Kullback–Leibler discrimination of the merged pair from the pair at equal weights,

   .. math:: b_{ij} = ½\\big[\\log\\det\\big(½P_i + ½P_j + ¼ δδ^T\\big) − ½\\log\\det P_i − ½\\log\\det P_j\\big],
             \\qquad δ = m_i − m_j

   (a dissimilarity of the two Gaussians whatever their weights, as the ACTS fitter's symmetric KL distance: a
   light component far from the others is not merged for being light, which is pruning's decision),
   merges where ``b_ij ≤ merge_bound`` (nats), moment-preserving and in the chart of the heavier
   (``model.align``: the attitude's MRP set or its shadow), into the heavier's slot (``b_ij`` compares the means in
   the charts they are stored in);
3. **split**: a component whose nonlinearity score exceeds its threshold is split along the axis the score
   names into three, preserving its mean and covariance exactly (:data:`SPLIT_WEIGHTS`), into free slots,
   heaviest candidates first; where no two slots are free, the pair of least bound is merged first when the
   pair is lighter than the candidate.

The scores (:func:`measurement_nonlinearity` before an update, :func:`entropy_nonlinearity` before a
propagation) are taken along the axes ``s_k = L e_k`` of each component (``P = LLᵀ``): relative to the
component's own covariance, so the thresholds do not depend on the state's units.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..mixture import GaussianMixture
from ..models.base import ContinuousModel, MeasurementModel
from ..update import cholesky_axes, measurement_curvature
from .options import option, positive_int

__all__ = [
    "MixtureManagement",
    "ManagementResult",
    "MANAGEMENT_DIAGNOSTICS",
    "SPLIT_WEIGHTS",
    "SPLIT_OFFSETS",
    "SPLIT_VARIANCE",
    "pad_mixture",
    "active_slots",
    "slot_count",
    "gather_slots",
    "spread_slots",
    "runnalls_bound",
    "merged_moments",
    "measurement_nonlinearity",
    "entropy_nonlinearity",
]

#: Keys a managed filter adds to ``diagnostics`` after ``predict`` and ``update`` (each ``[...]``, int64).
MANAGEMENT_DIAGNOSTICS = ("active_components", "splits", "merges", "prunes")

#: The three-way split of a unit Gaussian along one axis: weights and offsets (in standard deviations) of
#: DeMars, Bishop & Jah (2013), with the children's variance chosen so that the split keeps the variance exactly:
#: ``Σ wⱼ (σ² + μⱼ²) = 1``.
SPLIT_WEIGHTS = (0.2252246249, 0.5495507502, 0.2252246249)
SPLIT_OFFSETS = (-1.0575154615, 0.0, 1.0575154615)
SPLIT_VARIANCE = 1.0 - sum(w * m * m for w, m in zip(SPLIT_WEIGHTS, SPLIT_OFFSETS, strict=True))

#: Largest accepted ``merge_bound`` (nats): at ½ nat two equal components three standard deviations apart
#: (a clearly bimodal pair) already merge.
MAX_MERGE_BOUND = 0.5


def _nonnegative(name: str, value: Any, upper: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= float(value) <= upper:
        bound = "a finite number ≥ 0" if upper == math.inf else f"a number in [0, {upper}]"
        raise ValueError(f"{name} must be {bound}, got {value!r}")
    if not math.isfinite(float(value)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return float(value)


@dataclass(frozen=True, kw_only=True)
class MixtureManagement:
    """Options of a Gaussian-sum filter's mixture management (module docstring); ``0`` switches a step off.

    Example::

        GaussianSumFilter(model, management=MixtureManagement())                # the defaults
        AdaptiveGaussianSumFilter(model, management=MixtureManagement(capacity=32, split_measurement=0.5))

    Attributes:
        capacity: ``K``, the mixture's slots (≥ the initial component count; for the adaptive filters ≤
            :data:`~agsf_torch.qp.MAX_COMPONENTS`, the weight QP's limit, which the GSF does not have).  A mixture
            given with fewer components is padded with inactive slots at the filter's first step; a step computes
            only the slots its active components need (:func:`active_slots`).  Default 64: on ``agsf validate``'s
            one-star scenario from a uniform attitude 16 slots left the managed GSF at 10–20 times the floor, 32 at
            about 1.3 times, 64 at it (16 runs each; the merge test's pairs grow as the square of the active
            slots).
        prune_weight: weight (dimensionless, in [0, 0.5)) below which a component is dropped; the heaviest is
            never dropped.  Default 0 (never): with a precise sensor after a wide prior the linearised update drives
            the weights of the components it cannot yet judge far below 1e-30, and a dropped component cannot
            come back (on ``agsf validate``'s one-star scenario from a uniform attitude, pruning at any weight from
            1e-4, the ACTS fitter's, down to 1e-30 left 50 times the error of no pruning).  Merging frees the slots
            of components that coincide.
        merge_bound: the pair's Runnalls bound per unit weight ``b_ij`` (nats) at or below which a mutual-nearest
            pair merges, in ``[0, 0.5]``.  Default 1e-3 nats: pairs that one Gaussian describes to within a
            thousandth of a nat (two equal components merge when their means are less than 0.09 standard
            deviations apart); a split's adjacent children (``b`` = 0.22) stay apart.
        merge_rounds: rounds of mutual-nearest merging per pass (each merges disjoint pairs in parallel).
        split_measurement: split before a measurement update where the measurement's curvature along a
            component's axis, ``½‖h(m + s_k) + h(m − s_k) − 2h(m)‖`` in noise standard deviations (the
            diagonal of ``R``, valid entries only), exceeds this (dimensionless; the linearisation's error
            at one standard deviation along that axis, in units of the noise).  Default 1.
        split_entropy_rate: split before a propagation where the rate at which the linearised propagation
            misjudges the entropy, ``|E[∇·f] − ∇·f(m)|`` (nats/s; DeMars, Bishop & Jah's test in continuous
            time, the expectation to second order from the axes ``±s_k``), exceeds this.  Default 0.05 nats/s.
        second_order_update: update every component with the second-order terms of the measurement over its
            spread (:func:`agsf_torch.update.kalman_update` with ``second_order``: the prediction
            ``h + ½Σ_k c_k`` and innovation covariance ``+ ½Σ_k c_k c_kᵀ + Σ_{k<l} M_kl M_klᵀ`` from the second
            differences along the component's axes and across each pair of them, taken over the prior and kept by
            every relinearisation of an iterated update, which keeps its plain posterior for a mixture where the
            measurement is linear over every component's posterior and the frame agrees with the prediction:
            :data:`agsf_torch.update.LINEAR_POSTERIOR`), on the generic update path.  Default ``True``: a component still too wide for the sensor when the slots are
            spent is then not updated as if the measurement were linear over it (``docs/results/management.md``
            measures what it buys).
            ``False``: the EKF update of the method (the fused path where the measurement has one).  With
            splitting and merging off (``merge_bound=0``, ``split_measurement=0``, ``split_entropy_rate=0``) and
            ``capacity`` equal to the components, this is the unmanaged filter with the second-order update.
    """

    capacity: int = field(
        default=64, metadata=option("managed filters: slots K of the mixture (≥ components)", config="int")
    )
    prune_weight: float = field(
        default=0.0,
        metadata=option("managed filters: drop components below this weight (0: never)", config="float"),
    )
    merge_bound: float = field(
        default=1e-3,
        metadata=option(
            "managed filters: merge mutual-nearest pairs with Runnalls' bound ≤ this (nats)", config="float"
        ),
    )
    merge_rounds: int = field(
        default=2, metadata=option("managed filters: rounds of pairwise merging per pass", config="int")
    )
    split_measurement: float = field(
        default=1.0,
        metadata=option(
            "managed filters: split before an update where h's curvature at 1 sigma exceeds this many noise sds "
            "(0: never)",
            config="float",
        ),
    )
    split_entropy_rate: float = field(
        default=0.05,
        metadata=option(
            "managed filters: split before propagation where linearisation misjudges entropy by > this (nats/s; "
            "0: never)",
            config="float",
        ),
    )

    second_order_update: bool = field(
        default=True,
        metadata=option(
            "managed filters: update each component with the second-order terms of the measurement's curvature "
            "(false: the EKF update)",
            config="bool",
        ),
    )

    def __post_init__(self) -> None:
        positive_int("capacity", self.capacity)
        _nonnegative("prune_weight", self.prune_weight)
        if not self.prune_weight < 0.5:
            raise ValueError(
                f"prune_weight must be < 0.5 (a larger one would drop every component but the heaviest), "
                f"got {self.prune_weight!r}"
            )
        if isinstance(self.merge_bound, (int, float)) and not isinstance(self.merge_bound, bool):
            if float(self.merge_bound) > MAX_MERGE_BOUND:
                raise ValueError(
                    f"merge_bound must be ≤ {MAX_MERGE_BOUND} nats: a larger bound merges clearly separate components "
                    f"(at {MAX_MERGE_BOUND}, two equal ones 3 standard deviations apart), got {self.merge_bound!r}"
                )
        _nonnegative("merge_bound", self.merge_bound, MAX_MERGE_BOUND)
        positive_int("merge_rounds", self.merge_rounds)
        if not isinstance(self.second_order_update, bool):
            raise ValueError(f"second_order_update must be True or False, got {self.second_order_update!r}")
        _nonnegative("split_measurement", self.split_measurement)
        _nonnegative("split_entropy_rate", self.split_entropy_rate)
        for name in ("prune_weight", "merge_bound", "split_measurement", "split_entropy_rate"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "capacity", int(self.capacity))
        object.__setattr__(self, "merge_rounds", int(self.merge_rounds))

    def as_dict(self) -> dict[str, Any]:
        """The options by name (for checkpoints and reports)."""
        return dataclasses.asdict(self)

    def apply(
        self,
        mixture: GaussianMixture,
        model: ContinuousModel,
        score: Tensor | None = None,
        axis: Tensor | None = None,
        threshold: float = 0.0,
        *,
        compile: bool = False,
    ) -> ManagementResult:
        """One management pass: prune, merge, then split the components whose ``score > threshold``.

        Args:
            mixture: ``K = capacity`` slots (padded already: :func:`pad_mixture`), batch ``[...]``.
            model: the filter's model (``align`` and ``canonicalize`` for the charts).
            score: ``[..., K]`` nonlinearity scores, or ``None`` (no split); axis: ``[..., K]`` int64, the axis
                ``k`` of each component to split along (``s_k = L e_k``, ``P = LLᵀ``).
            threshold: split where ``score > threshold``.
            compile: the pair dissimilarities' kernel compiled ahead of time (:func:`runnalls_bound`).

        Returns:
            :class:`ManagementResult`.
        """
        log_w, means, covs = mixture.log_weights, mixture.means, mixture.covs
        K = log_w.shape[-1]
        T = torch.eye(K, dtype=means.dtype, device=means.device).expand(*log_w.shape, K).clone()
        counts = {}
        log_w, T, counts["prunes"] = self._prune(log_w, T)
        merges = torch.zeros_like(counts["prunes"])
        if self.merge_bound > 0 and bool((torch.isfinite(log_w).sum(-1) > 1).any()):  # else nothing to merge
            log_w, means, covs, T, merges = _merge_rounds(
                log_w, means, covs, T, model, self.merge_bound, self.merge_rounds, compile
            )
        splits = torch.zeros_like(merges)
        if score is not None:
            want = torch.isfinite(log_w) & (score > threshold)
            if bool(want.any()):
                log_w, means, covs, T, forced = _make_room(log_w, means, covs, T, model, want, compile)
                merges = merges + forced
                log_w, means, covs, T, splits = _split(log_w, means, covs, T, want, axis)
                means, covs = model.canonicalize(means, covs)
        counts["merges"], counts["splits"] = merges, splits
        log_w = log_w - torch.logsumexp(log_w, -1, keepdim=True)
        means, covs = _fill_inactive(log_w, means, covs)
        counts["active_components"] = torch.isfinite(log_w).sum(-1)
        managed = mixture.replace(log_weights=log_w, means=means, covs=covs, validate=False)
        return ManagementResult(managed, T, counts)

    def _prune(self, log_w: Tensor, T: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        if self.prune_weight <= 0.0:
            return log_w, T, torch.zeros(log_w.shape[:-1], dtype=torch.int64, device=log_w.device)
        heaviest = torch.nn.functional.one_hot(log_w.argmax(-1), log_w.shape[-1]).bool()
        drop = torch.isfinite(log_w) & (log_w < math.log(self.prune_weight)) & ~heaviest
        log_w = log_w.masked_fill(drop, -math.inf)
        return log_w, T.masked_fill(drop[..., None], 0.0), drop.sum(-1)


@dataclass(frozen=True)
class ManagementResult:
    """A management pass's outcome.

    Attributes:
        mixture: the managed mixture (normalised, inactive slots filled, canonical chart).
        weight_map: ``T [..., K, K]``: the pass's action on weights, ``w ↦ T w`` before normalisation (a merge adds
            a row into another, a split scales one into three, a prune zeroes one).  The penalty weight update
            maps its reference weights by it.
        counts: ``active_components``, ``splits``, ``merges``, ``prunes``, each ``[...]`` int64.
    """

    mixture: GaussianMixture
    weight_map: Tensor
    counts: dict[str, Tensor]


def pad_mixture(mixture: GaussianMixture, capacity: int) -> GaussianMixture:
    """``mixture`` with ``capacity − N`` inactive slots appended (log-weight ``−inf``, a copy of the heaviest).

    Raises:
        ValueError: naming ``capacity`` when the mixture has more components than slots.
    """
    N = mixture.num_components
    if N > capacity:
        raise ValueError(
            f"management capacity {capacity} is below the mixture's {N} components: raise capacity to at least {N}"
        )
    if N == capacity:
        return mixture
    extra = capacity - N
    log_w = torch.cat((mixture.log_weights, mixture.log_weights.new_full((*mixture.batch_shape, extra), -math.inf)), -1)
    means = torch.cat((mixture.means, mixture.means[..., :1, :].expand(*mixture.batch_shape, extra, -1)), -2)
    covs = torch.cat((mixture.covs, mixture.covs[..., :1, :, :].expand(*mixture.batch_shape, extra, -1, -1)), -3)
    means, covs = _fill_inactive(log_w, means, covs)
    return mixture.replace(log_weights=log_w, means=means, covs=covs, validate=False)


def slot_count(active: int) -> int:
    """The slots a computation over ``active`` components takes: the smallest of ``1, 2, 3, 4, 6, 8, 12, 16, 24,
    …`` (``2ᵏ`` and ``3·2ᵏ⁻¹``) that is at least ``active``.  Kernels specialised to a slot count then serve many
    steps (``2·log₂K`` counts up to a capacity ``K = 2ᵐ``), and a step carries at most a third more slots than it
    has active components (a power of two alone: up to twice as many, four times the pairs of a weight update)."""
    power = 1 << max(0, int(active) - 1).bit_length()  # the smallest power of two ≥ active
    three_quarters = 3 * power // 4
    return three_quarters if power >= 4 and three_quarters >= active else power


def active_slots(log_weights: Tensor) -> Tensor | None:
    """The slots a computation over a managed mixture's components needs, ``[..., A]`` slot indices: each
    trajectory's active slots first (in slot order), then its inactive ones, where ``A`` is :func:`slot_count` of
    the batch's largest active count, or ``None`` where that is every one of the ``K`` slots.  A trajectory with
    fewer active slots than ``A`` keeps some inactive ones (weight zero, a copy of its heaviest component).

    Args:
        log_weights: ``[..., K]``, ``−inf`` at inactive slots.
    """
    K = log_weights.shape[-1]
    active = torch.isfinite(log_weights)
    A = min(K, slot_count(int(active.sum(-1).max())))
    if A >= K:
        return None
    return torch.argsort((~active).to(torch.uint8), dim=-1, stable=True)[..., :A]


def gather_slots(mixture: GaussianMixture, index: Tensor) -> GaussianMixture:
    """The mixture of the slots ``index [..., A]`` (:func:`active_slots`) of ``mixture`` (``[..., K]`` slots)."""
    log_w, means, covs = _slot_tensors(index, mixture.log_weights, mixture.means, mixture.covs)
    return GaussianMixture(log_weights=log_w, means=means, covs=covs, validate=False)


def spread_slots(
    mixture: GaussianMixture, computed: GaussianMixture, index: Tensor, *per_component: Tensor
) -> tuple[GaussianMixture, tuple[Tensor, ...]]:
    """The ``K`` slots of ``mixture`` after a step computed only the slots ``index [..., A]``
    (:func:`active_slots`), whose result is ``computed`` (``A`` slots): each active slot takes its computed
    component, each inactive slot (weight zero) a copy of its trajectory's heaviest computed component, the
    invariant of a managed mixture.

    Args:
        mixture: the ``K`` slots the step started from (their shapes and charts).
        computed: the step's result on the slots ``index``.
        index: ``[..., A]`` slot indices, distinct within a trajectory.
        per_component: tensors ``[..., A, ...]`` of the step (e.g. each component's NIS), spread the same way.

    Returns:
        ``(the K-slot mixture, the per-component tensors [..., K, ...])``.
    """
    K, A = mixture.log_weights.shape[-1], index.shape[-1]
    lw = computed.log_weights
    heaviest = lw.argmax(-1, keepdim=True)  # [..., 1], a position among the computed slots
    position = torch.arange(A, device=index.device).expand_as(index)
    source = heaviest.expand(*index.shape[:-1], K).clone()  # where each slot takes its component from
    source.scatter_(-1, index, torch.where(torch.isfinite(lw), position, heaviest))
    log_w = torch.full_like(mixture.log_weights, -math.inf).scatter(-1, index, lw)
    spread = mixture.replace(
        log_weights=log_w,
        means=_take_slots(computed.means, source),
        covs=_take_slots(computed.covs, source),
        validate=False,
    )
    return spread, tuple(_take_slots(t, source) for t in per_component)


def _take_slots(values: Tensor, index: Tensor) -> Tensor:
    """``values [..., K, *rest]`` at the slots ``index [..., A]``: ``[..., A, *rest]``."""
    rest = values.shape[index.dim() :]
    at = index.reshape(*index.shape, *(1,) * len(rest)).expand(*index.shape, *rest)
    return torch.gather(values, index.dim() - 1, at)


def _slot_tensors(index: Tensor, log_w: Tensor, means: Tensor, covs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``log_w [..., K]``, ``means [..., K, n]`` and ``covs [..., K, n, n]`` at the slots ``index [..., A]``."""
    return _take_slots(log_w, index), _take_slots(means, index), _take_slots(covs, index)


def _fill_inactive(log_w: Tensor, means: Tensor, covs: Tensor) -> tuple[Tensor, Tensor]:
    """Inactive slots hold a copy of their trajectory's heaviest component."""
    inactive = ~torch.isfinite(log_w)
    if not bool(inactive.any()):
        return means, covs
    best = log_w.argmax(-1)
    m_best = torch.gather(means, -2, best[..., None, None].expand(*best.shape, 1, means.shape[-1]))
    P_best = torch.gather(covs, -3, best[..., None, None, None].expand(*best.shape, 1, *covs.shape[-2:]))
    means = torch.where(inactive[..., None], m_best, means)
    covs = torch.where(inactive[..., None, None], P_best, covs)
    return means, covs


def _logdet(P: Tensor) -> Tensor:
    L, info = torch.linalg.cholesky_ex(P)
    logdet = 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
    return torch.where(info == 0, logdet, torch.full_like(logdet, math.nan))


def runnalls_bound(log_w: Tensor, means: Tensor, covs: Tensor, *, compile: bool = False) -> Tensor:
    """The dissimilarity ``b_ij`` of every pair of active components, in nats.

    ``b_ij`` is Runnalls' bound on the Kullback–Leibler discrimination of the merged pair from the pair, taken at
    equal weights (a weight-free dissimilarity of the two Gaussians, as the ACTS fitter's symmetric KL distance): a
    light component far from the others is not merged for being light, which is pruning's decision.

    .. math:: b_{ij} = ½\\big[\\log\\det\\big(½P_i + ½P_j + ¼ δδ^T\\big) − ½\\log\\det P_i − ½\\log\\det P_j\\big],\\quad
              δ = m_i − m_j

    The means are compared in the charts they are stored in (canonical for attitude): two components that describe
    nearly the same attitude from different MRP sets (near a 180° rotation) are far apart here and are not merged.
    Evaluated on lanes (:func:`agsf_torch.fused.merge_bound.pair_dissimilarity_kernel`), compiled if
    ``compile``, over the pairs of the slots the active components need (:func:`active_slots`); the arguments are
    detached (the bound only decides which pairs merge).

    Args:
        log_w: ``[..., K]`` (``−inf``: inactive); means: ``[..., K, n]``; covs: ``[..., K, n, n]``.

    Returns:
        ``b [..., K, K]`` nats, symmetric, ``+inf`` on the diagonal, for inactive slots and where a covariance is
        not positive definite.
    """
    from ..fused.lanes import DEFAULT_CHUNK, run_in_chunks
    from ..fused.merge_bound import pair_dissimilarity_kernel

    K, n = means.shape[-2:]
    lead = log_w.shape[:-1]
    index = active_slots(log_w)
    if index is not None:  # the pairs of the slots the active components need (active_slots), +inf elsewhere
        lead = torch.broadcast_shapes(lead, means.shape[:-2], covs.shape[:-3])
        index = index.expand(*lead, index.shape[-1])
        A = index.shape[-1]
        slots = _slot_tensors(index, log_w.expand(*lead, K), means.expand(*lead, K, n), covs.expand(*lead, K, n, n))
        b = runnalls_bound(*slots, compile=compile)
        at = (index[..., :, None] * K + index[..., None, :]).reshape(*lead, A * A)
        full = b.new_full((*lead, K * K), math.inf).scatter(-1, at, b.reshape(*lead, A * A))
        return full.reshape(*lead, K, K)
    count = math.prod(lead)
    iu, ju = torch.triu_indices(K, K, 1, device=log_w.device)
    pairs = iu.numel()
    inputs = (
        means.detach().expand(*lead, K, n).reshape(count, K, n),
        covs.detach().expand(*lead, K, n, n).reshape(count, K, n, n),
    )
    (b,) = run_in_chunks(
        pair_dissimilarity_kernel,
        inputs,
        compile=compile,
        chunk=max(1, DEFAULT_CHUNK // max(pairs, 1)),
        key=("merge-bound",),
    )
    b = b.reshape(*lead, pairs)
    active = torch.isfinite(log_w)
    ok = active[..., iu] & active[..., ju] & torch.isfinite(b)
    b = torch.where(ok, b.clamp_min(0.0), torch.full_like(b, math.inf))
    full = b.new_full((*lead, K, K), math.inf)
    full[..., iu, ju] = b
    full[..., ju, iu] = b
    return full


def merged_moments(
    log_w_a: Tensor,
    mean_a: Tensor,
    cov_a: Tensor,
    log_w_b: Tensor,
    mean_b: Tensor,
    cov_b: Tensor,
    model: ContinuousModel,
) -> tuple[Tensor, Tensor]:
    """The moment-preserving merge of component ``b`` into ``a``, in ``a``'s chart (``model.align``: for attitude
    the MRP set, or its shadow, nearer ``a``'s mean), with the pair's own weights ``f = w / (w_a + w_b)`` formed in
    the log domain:

    .. math:: m = f_a m_a + f_b m_b,\\quad P = f_a P_a + f_b P_b + f_a f_b δδ^T,\\quad δ = m_a − m_b

    Args:
        log_w_a, log_w_b: ``[...]``; mean_a, mean_b: ``[..., n]``; cov_a, cov_b: ``[..., n, n]``.

    Returns:
        ``(m [..., n], P [..., n, n])`` (symmetrised).
    """
    mean_b, cov_b = model.align(mean_b, cov_b, mean_a)
    lw = torch.logaddexp(log_w_a, log_w_b)
    fa, fb = torch.exp(log_w_a - lw), torch.exp(log_w_b - lw)
    d = mean_a - mean_b
    m = fa[..., None] * mean_a + fb[..., None] * mean_b
    P = (
        fa[..., None, None] * cov_a
        + fb[..., None, None] * cov_b
        + (fa * fb)[..., None, None] * (d[..., :, None] * d[..., None, :])
    )
    return m, 0.5 * (P + P.transpose(-1, -2))


def _apply_merges(
    log_w: Tensor, means: Tensor, covs: Tensor, T: Tensor, keep: Tensor, partner: Tensor, model: ContinuousModel
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Merge ``partner[i]`` into ``i`` where ``keep[..., i]`` (disjoint pairs; :func:`merged_moments`)."""
    n = means.shape[-1]
    m_p = torch.gather(means, -2, partner[..., None].expand(*partner.shape, n))
    P_p = torch.gather(covs, -3, partner[..., None, None].expand(*partner.shape, n, n))
    lw_partner = torch.gather(log_w, -1, partner)
    m_new, P_new = merged_moments(log_w, means, covs, lw_partner, m_p, P_p, model)
    absorbed = _scatter_slots(torch.zeros_like(keep), torch.where(keep, partner, keep.shape[-1]), keep)
    log_w = torch.where(keep, torch.logaddexp(log_w, lw_partner), log_w).masked_fill(absorbed, -math.inf)
    T_partner = torch.gather(T, -2, partner[..., None].expand_as(T))
    T = torch.where(keep[..., None], T + T_partner, T).masked_fill(absorbed[..., None], 0.0)
    means = torch.where(keep[..., None], m_new, means)
    covs = torch.where(keep[..., None, None], P_new, covs)
    return log_w, means, covs, T


def _merge_rounds(
    log_w: Tensor,
    means: Tensor,
    covs: Tensor,
    T: Tensor,
    model: ContinuousModel,
    bound_max: float,
    rounds: int,
    compile: bool,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """``rounds`` rounds: in each, every mutual-nearest pair with ``b ≤ bound_max`` merges into the heavier's slot.

    The dissimilarities are evaluated once (:func:`runnalls_bound`); a later round sees the pairs of components no
    earlier round touched (their ``b`` unchanged: it depends on the pair alone), so a merged component merges again
    at the next pass."""
    K = log_w.shape[-1]
    log_w = log_w - torch.logsumexp(log_w, -1, keepdim=True)
    bound = runnalls_bound(log_w, means, covs, compile=compile)
    slots = torch.arange(K, device=log_w.device)
    merges = torch.zeros(log_w.shape[:-1], dtype=torch.int64, device=log_w.device)
    for _ in range(rounds):
        best, partner = bound.min(-1)
        mutual = torch.gather(partner, -1, partner) == slots
        lw_partner = torch.gather(log_w, -1, partner)
        heavier = (log_w > lw_partner) | ((log_w == lw_partner) & (slots < partner))
        keep = mutual & heavier & (best <= bound_max)
        if not bool(keep.any()):
            break
        touched = keep | _scatter_slots(torch.zeros_like(keep), torch.where(keep, partner, K), keep)
        log_w, means, covs, T = _apply_merges(log_w, means, covs, T, keep, partner, model)
        merges = merges + keep.sum(-1)
        bound = bound.masked_fill(touched[..., :, None] | touched[..., None, :], math.inf)
    return log_w, means, covs, T, merges


def _make_room(
    log_w: Tensor, means: Tensor, covs: Tensor, T: Tensor, model: ContinuousModel, want: Tensor, compile: bool
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Where a split is wanted and fewer than two slots are free, merge the pair of least bound if it is lighter
    than the heaviest candidate (one pair per trajectory)."""
    free = (~torch.isfinite(log_w)).sum(-1)
    need = want.any(-1) & (free < len(SPLIT_WEIGHTS) - 1)
    if not bool(need.any()):
        return log_w, means, covs, T, torch.zeros_like(free)
    K = log_w.shape[-1]
    log_w = log_w - torch.logsumexp(log_w, -1, keepdim=True)
    bound = runnalls_bound(log_w, means, covs, compile=compile)
    flat = bound.flatten(-2).argmin(-1)
    i, j = flat // K, flat % K
    lw_i, lw_j = torch.gather(log_w, -1, i[..., None])[..., 0], torch.gather(log_w, -1, j[..., None])[..., 0]
    keeper = torch.where(lw_i >= lw_j, i, j)
    other = torch.where(lw_i >= lw_j, j, i)
    candidate = torch.where(want, log_w, torch.full_like(log_w, -math.inf)).amax(-1)
    lighter = torch.logaddexp(lw_i, lw_j) < candidate
    ok = need & lighter & torch.isfinite(bound.flatten(-2).amin(-1))
    keep = torch.nn.functional.one_hot(keeper, K).bool() & ok[..., None]
    partner = torch.where(keep, other[..., None].expand_as(keep), torch.arange(K, device=log_w.device))
    log_w, means, covs, T = _apply_merges(log_w, means, covs, T, keep, partner, model)
    return log_w, means, covs, T, ok.long()


def _scatter_slots(base: Tensor, dest: Tensor, src: Tensor) -> Tensor:
    """``base`` with ``base[..., dest[..., i]] = src[..., i]`` wherever ``dest < K`` (``dest == K``: nowhere).
    The destinations below ``K`` must be distinct within a trajectory."""
    padded = torch.cat((base, base.new_zeros((*base.shape[:-1], 1))), -1)
    return padded.scatter(-1, dest, src)[..., : base.shape[-1]]


def _split(
    log_w: Tensor, means: Tensor, covs: Tensor, T: Tensor, want: Tensor, axis: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Split the wanted components, heaviest first, into free slots (``len(SPLIT_WEIGHTS) − 1`` each)."""
    K, n = log_w.shape[-1], means.shape[-1]
    S = len(SPLIT_WEIGHTS) - 1  # new slots per split
    free = ~torch.isfinite(log_w)
    n_free = free.sum(-1, keepdim=True)
    # rank of each wanted component by weight (0: heaviest)
    key = torch.where(want, log_w, torch.full_like(log_w, -math.inf))
    order = key.argsort(dim=-1, descending=True, stable=True)
    rank = torch.empty_like(order).scatter_(-1, order, torch.arange(K, device=log_w.device).expand_as(order))
    allowed = want & (rank < n_free // S)
    # the free slots, in slot order
    free_slots = (~free).to(torch.int64).argsort(dim=-1, stable=True)  # free ones first
    source = torch.arange(K, device=log_w.device).expand_as(log_w).clone()
    offset = torch.zeros_like(log_w)
    share = torch.ones_like(log_w)
    centre = SPLIT_WEIGHTS[S // 2]
    share = torch.where(allowed, torch.full_like(share, centre), share)
    children = [(w, m) for k, (w, m) in enumerate(zip(SPLIT_WEIGHTS, SPLIT_OFFSETS, strict=True)) if k != S // 2]
    for c, (wc, mc) in enumerate(children):  # the two outer children, each into its own free slot
        slot = torch.gather(free_slots, -1, (S * rank + c).clamp_max(K - 1))  # [..., K]
        dest = torch.where(allowed, slot, K)  # K: no slot
        source = _scatter_slots(source, dest, torch.arange(K, device=log_w.device).expand_as(dest))
        offset = _scatter_slots(offset, dest, torch.full_like(offset, mc))
        share = _scatter_slots(share, dest, torch.full_like(share, wc))
    child = offset != 0.0
    split_parent = allowed | child
    parent_axis = torch.gather(axis, -1, source)
    P_src = torch.gather(covs, -3, source[..., None, None].expand(*source.shape, n, n))
    m_src = torch.gather(means, -2, source[..., None].expand(*source.shape, n))
    L = torch.linalg.cholesky(P_src)
    d = torch.gather(L, -1, parent_axis[..., None, None].expand(*source.shape, n, 1))[..., 0]  # column k of L
    m_split = m_src + offset[..., None] * d
    P_split = P_src - (1.0 - SPLIT_VARIANCE) * d[..., :, None] * d[..., None, :]
    P_split = 0.5 * (P_split + P_split.transpose(-1, -2))
    lw_src = torch.gather(log_w, -1, source)
    log_w = torch.where(split_parent, lw_src + torch.log(share), log_w)
    T_src = torch.gather(T, -2, source[..., None].expand_as(T))
    T = torch.where(split_parent[..., None], share[..., None] * T_src, T)
    means = torch.where(split_parent[..., None], m_split, means)
    covs = torch.where(split_parent[..., None, None], P_split, covs)
    return log_w, means, covs, T, allowed.sum(-1)


def measurement_nonlinearity(
    means: Tensor, covs: Tensor, measurement: MeasurementModel, curvature: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """The measurement's curvature along each component's axes, in noise standard deviations.

    .. math:: ν_k = ½ \\Big\\| \\frac{c_k}{σ} \\Big\\|

    with ``c_k`` of :func:`agsf_torch.update.measurement_curvature` (given, or evaluated here), ``σ`` the square roots of ``R``'s
    diagonal and the sum over the valid entries (``measurement.mask()``): the second-order error of the linearised
    prediction one standard deviation along ``s_k``.

    Args:
        means: ``[..., K, n]``; covs: ``[..., K, n, n]``; curvature: ``[..., K, n, d]`` or ``None``.

    Returns:
        ``(score [..., K] = max_k ν_k, axis [..., K]`` int64 ``= argmax_k ν_k)``.
    """
    c = measurement_curvature(means, covs, measurement) if curvature is None else curvature
    var = measurement.noise_cov().diagonal(dim1=-2, dim2=-1).clamp_min(torch.finfo(means.dtype).tiny)
    z2 = c * c / var[..., None, None, :]
    mask = measurement.mask()
    if mask is not None:
        z2 = z2 * mask[..., None, None, :].to(z2.dtype)
    nu = 0.5 * z2.sum(-1).sqrt()  # [..., K, n]
    return nu.max(-1)


def entropy_nonlinearity(
    model: ContinuousModel, means: Tensor, covs: Tensor, u: Tensor | None
) -> tuple[Tensor, Tensor]:
    """How fast the linearised propagation misjudges each component's entropy (nats/s), and along which axis.

    For ``dx = f dt + G dW`` the entropy of the density changes at ``E[∇·f] + ½E[‖∇ log p‖²_{GQGᵀ}]``, the
    linearisation's at ``∇·f(m) + ½ tr(P⁻¹GQGᵀ)``; for a Gaussian the diffusion terms agree, and

    .. math:: |E[∇·f] - ∇·f(m)| ≈ ½ \\Big| Σ_k δ_k \\Big|,\\qquad
              δ_k = ∇·f(m + s_k) + ∇·f(m - s_k) - 2∇·f(m)

    (exact for a divergence quadratic in the state), ``∇·f = tr ∂f/∂x`` (``model.drift_divergence``).  The axis is
    ``argmax_k |δ_k|``.

    Args:
        means: ``[..., K, n]``; covs: ``[..., K, n, n]``; u: ``[..., m]`` or ``None``.

    Returns:
        ``(score [..., K]`` nats/s, ``axis [..., K]`` int64).
    """
    n = means.shape[-1]
    pts = cholesky_axes(means, covs)
    lead = pts.shape[:-3]
    K = pts.shape[-3]
    u_c = None if u is None else u.unsqueeze(-2)
    div = model.drift_divergence(pts.reshape(*lead, K * (2 * n + 1), n), u_c).reshape(*lead, K, 2 * n + 1)
    delta = div[..., 1 : n + 1] + div[..., n + 1 :] - 2.0 * div[..., :1]  # [..., K, n]
    return 0.5 * delta.sum(-1).abs(), delta.abs().argmax(-1)
