"""Mixture management (agsf_torch.filters.management): the split, merge and prune steps against their formulas,
inactive slots that change nothing, the nonlinearity scores against closed forms, the filters and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.filters import (
    AdaptiveGaussianSumFilter,
    ExtendedKalmanFilter,
    GalerkinWeightUpdate,
    GaussianSumFilter,
    MixtureManagement,
    MultiplicativeEKF,
)
from agsf_torch.filters.management import (
    MANAGEMENT_DIAGNOSTICS,
    SPLIT_OFFSETS,
    SPLIT_VARIANCE,
    SPLIT_WEIGHTS,
    active_slots,
    entropy_nonlinearity,
    gather_slots,
    measurement_nonlinearity,
    merged_moments,
    pad_mixture,
    runnalls_bound,
    slot_count,
    spread_slots,
)
from agsf_torch.filters.registry import CONFIG_OPTIONS, make_filter
from agsf_torch.filters.weight_updates.base import MANAGED_WEIGHT_KEPT, WeightUpdateRun, solve_weight_qp
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.models.benchmarks import SineDriftModel
from agsf_torch.models.function_measurement import FunctionMeasurement
from agsf_torch.models.linear import LinearModel
from agsf_torch.update import kalman_update
from tests.helpers import F64, assert_within, random_mrps, random_spd, random_unit_vectors, relative_bound

EPS = float(np.finfo(np.float64).eps)

#: Management that never acts: the mixture is only padded, and updated with the EKF update.
IDLE = dict(prune_weight=0.0, merge_bound=0.0, split_measurement=0.0, split_entropy_rate=0.0, second_order_update=False)


def _np_moments(w, m, P):
    """Mixture moments in numpy, ``w [N]``, ``m [N, n]``, ``P [N, n, n]``."""
    w = np.asarray(w, dtype=np.float64)
    mean = (w[:, None] * m).sum(0)
    d = m - mean
    return mean, (w[:, None, None] * (P + d[:, :, None] * d[:, None, :])).sum(0)


def _linear_model(n=3):
    return LinearModel(A=0.1 * torch.eye(n, dtype=F64), G=torch.eye(n, dtype=F64), Q=1e-3 * torch.eye(n, dtype=F64))


def test_the_split_table_keeps_a_unit_gaussians_moments():
    w, mu = np.array(SPLIT_WEIGHTS), np.array(SPLIT_OFFSETS)
    # three constants rounded to ½ ulp each and two additions: under 2ε in any order; 8ε leaves room for the few
    # ulps another machine's summation may round differently (pytest --jitter-ulps moves the sum by up to 4 ulps)
    assert_within(w.sum(), 1.0, 8 * EPS, "split weights sum")
    assert_within((w * mu).sum(), 0.0, 4 * EPS, "split mean")
    assert_within((w * (SPLIT_VARIANCE + mu**2)).sum(), 1.0, 8 * EPS, "split variance")
    assert 0.0 < SPLIT_VARIANCE < 1.0


def test_a_split_keeps_the_mixtures_mean_and_covariance(gen):
    B, K, n = 5, 8, 3
    model = _linear_model(n)
    means = torch.randn(B, 2, n, generator=gen, dtype=F64)
    covs = random_spd(gen, B, 2, n=n)
    mix = pad_mixture(
        GaussianMixture(weights=torch.tensor([0.7, 0.3], dtype=F64).expand(B, 2), means=means, covs=covs), K
    )
    score = torch.zeros(B, K, dtype=F64)
    score[:, 0] = 2.0
    axis = torch.randint(0, n, (B, K), generator=gen)
    out = MixtureManagement(capacity=K, **{**IDLE, "split_measurement": 1.0}).apply(mix, model, score, axis, 1.0)
    assert out.counts["splits"].tolist() == [1] * B
    assert out.counts["active_components"].tolist() == [4] * B
    w = out.mixture.weights.numpy()
    for b in range(B):
        m0, P0 = _np_moments([0.7, 0.3], means[b].numpy(), covs[b].numpy())
        m1, P1 = _np_moments(w[b], out.mixture.means[b].numpy(), out.mixture.covs[b].numpy())
        scale = float(np.abs(P0).max())
        assert_within(m1, m0, 32 * EPS * (np.abs(means[b].numpy()).max() + math.sqrt(scale)), "mean after a split")
        assert_within(P1, P0, 64 * EPS * scale, "covariance after a split")
    # the children sit along column k of the parent's Cholesky factor
    L = torch.linalg.cholesky(covs[:, 0])
    d = L[torch.arange(B), :, axis[:, 0]]
    active = torch.isfinite(out.mixture.log_weights)
    for b in range(B):
        offsets = out.mixture.means[b][active[b]] - means[b, 0]
        along = offsets @ d[b] / (d[b] @ d[b])
        expected = sorted([0.0, SPLIT_OFFSETS[0], SPLIT_OFFSETS[2]])
        got = sorted(along[[0, 2, 3]].tolist())  # slot 1 is the other component
        assert_within(got, expected, 64 * EPS * (1 + float(means[b].abs().max() / d[b].norm())), "offsets")


def test_runnalls_bound_and_merged_moments_follow_the_formulas(gen):
    n = 3
    model = _linear_model(n)
    w = torch.tensor([[0.5, 0.3, 0.2, 0.0]], dtype=F64)  # slot 3 inactive
    means = torch.randn(1, 4, n, generator=gen, dtype=F64)
    covs = random_spd(gen, 1, 4, n=n)
    bound = runnalls_bound(w.log(), means, covs)
    wn, mn, Pn = w[0].numpy(), means[0].numpy(), covs[0].numpy()
    for i, j in ((0, 1), (0, 2), (1, 2)):
        ws = wn[i] + wn[j]
        mm = (wn[i] * mn[i] + wn[j] * mn[j]) / ws
        d = mn[i] - mn[j]
        PP = (wn[i] * Pn[i] + wn[j] * Pn[j]) / ws + wn[i] * wn[j] / ws**2 * np.outer(d, d)
        half = 0.5 * (Pn[i] + Pn[j]) + 0.25 * np.outer(d, d)  # Runnalls' pair bound at equal weights
        expected = 0.5 * (
            np.linalg.slogdet(half)[1] - 0.5 * np.linalg.slogdet(Pn[i])[1] - 0.5 * np.linalg.slogdet(Pn[j])[1]
        )
        logdets = abs(np.linalg.slogdet(half)[1]) + abs(np.linalg.slogdet(Pn[i])[1]) + abs(np.linalg.slogdet(Pn[j])[1])
        assert_within(bound[0, i, j], expected, 64 * EPS * (1 + logdets), f"bound of ({i}, {j})")
        assert_within(bound[0, j, i], expected, 64 * EPS * (1 + logdets), f"bound of ({j}, {i})")
        m, P = merged_moments(w[0, i].log(), means[0, i], covs[0, i], w[0, j].log(), means[0, j], covs[0, j], model)
        assert_within(m, mm, 16 * EPS * np.abs(mn).max(), f"merged mean ({i}, {j})")
        assert_within(P, PP, 32 * EPS * np.abs(PP).max(), f"merged covariance ({i}, {j})")
    assert bool(torch.isinf(bound[0].diagonal()).all())
    assert bool(torch.isinf(bound[0, 3]).all()) and bool(torch.isinf(bound[0, :, 3]).all())  # the inactive slot


def test_runnalls_bound_of_scattered_active_slots_is_the_bound_of_those_pairs(gen):
    # 8 slots, 3 active in each trajectory at different slots: the pairs are computed on 3 gathered slots
    # (active_slots) and put back; each active pair's bound is the one of the same pair among all slots active
    K, n = 8, 3
    means = torch.randn(2, K, n, generator=gen, dtype=F64)
    covs = random_spd(gen, 2, K, n=n)
    log_w = torch.full((2, K), -math.inf, dtype=F64)
    log_w[0, [1, 4, 6]] = math.log(1 / 3)
    log_w[1, [0, 2, 7]] = math.log(1 / 3)
    bound = runnalls_bound(log_w, means, covs)
    every = runnalls_bound(torch.zeros(2, K, dtype=F64), means, covs)  # no slot inactive: all 28 pairs
    active = torch.isfinite(log_w)
    pair = active[:, :, None] & active[:, None, :] & ~torch.eye(K, dtype=torch.bool)
    assert int(pair.sum()) == 12
    scale = 64 * EPS * (1 + every[pair].abs() + torch.logdet(covs).abs().amax())
    assert_within(bound[pair], every[pair], scale, "bound of the active pairs")
    assert bool(torch.isinf(bound[~pair]).all())


def test_runnalls_bound_is_infinite_where_a_covariance_is_not_positive_definite(gen):
    means = torch.randn(2, 3, 2, generator=gen, dtype=F64)
    covs = random_spd(gen, 2, 3, n=2).clone()
    covs[1, 2] = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=F64)  # indefinite
    bound = runnalls_bound(torch.zeros(2, 3, dtype=F64), means, covs)
    assert bool(torch.isinf(bound[1, 2]).all()) and bool(torch.isfinite(bound[1, 0, 1]))
    off_diagonal = ~torch.eye(3, dtype=torch.bool)
    assert bool(torch.isfinite(bound[0][off_diagonal]).all())


def test_the_merge_is_taken_in_the_heavier_components_chart():
    # two components of nearly the same attitude from opposite MRP sets (a rotation of 180° ± 0.1° about x): the
    # lighter is moved to the heavier's set before the moments are matched, so the merged mean is an attitude of
    # the pair, not their average across the sphere
    model = AttitudeModel(estimate_bias=False)
    m_a = torch.tensor([math.tan(math.radians(179.9) / 4), 0.0, 0.0], dtype=F64)  # |p| < 1: canonical
    m_b = torch.tensor([math.tan(math.radians(-179.8) / 4), 0.0, 0.0], dtype=F64)  # 180.2°, canonical
    P = 1e-8 * torch.eye(3, dtype=F64)
    m, _ = merged_moments(torch.tensor(-0.1, dtype=F64), m_a, P, torch.tensor(-2.0, dtype=F64), m_b, P, model)
    assert m[0] > 0.99 and abs(float(m[1])) < 1e-12 and abs(float(m[2])) < 1e-12


def test_a_light_component_is_not_merged_for_being_light():
    # the dissimilarity is weight-free: a component of weight e^-800 (0 in float64) 5 standard deviations away has
    # b = ½ log(1 + 5²/4) whatever its weight, and merges only with a bound that large
    model = _linear_model(1)
    means = torch.tensor([[[0.0], [5.0]]], dtype=F64)
    covs = torch.ones(1, 2, 1, 1, dtype=F64)
    for lw in (-800.0, -1.0, 0.0):
        log_w = torch.tensor([[0.0, lw]], dtype=F64)
        bound = runnalls_bound(log_w - torch.logsumexp(log_w, -1, keepdim=True), means, covs)
        assert_within(bound[0, 0, 1], 0.5 * math.log(1 + 25 / 4), 8 * EPS, f"b at log-weight {lw}")
        out = MixtureManagement(capacity=2, **{**IDLE, "merge_bound": 0.5}).apply(
            GaussianMixture(log_weights=log_w, means=means, covs=covs), model
        )
        assert out.counts["merges"].tolist() == [0]


def test_mutual_nearest_pairs_merge_in_one_round_and_keep_the_moments(gen):
    n = 2
    model = _linear_model(n)
    base = torch.randn(2, n, generator=gen, dtype=F64) * 10
    means = torch.stack((base[0], base[0] + 1e-3, base[1], base[1] - 1e-3))[None]
    covs = torch.eye(n, dtype=F64).expand(1, 4, n, n)
    mix = pad_mixture(
        GaussianMixture(weights=torch.tensor([[0.4, 0.1, 0.3, 0.2]], dtype=F64), means=means, covs=covs), 6
    )
    out = MixtureManagement(capacity=6, **{**IDLE, "merge_bound": 1e-3, "merge_rounds": 1}).apply(mix, model)
    assert out.counts["merges"].tolist() == [2]
    assert out.counts["active_components"].tolist() == [2]
    active = torch.isfinite(out.mixture.log_weights[0])
    assert active.tolist() == [True, False, True, False, False, False]  # merged into the heavier's slots
    m0, P0 = _np_moments([0.4, 0.1, 0.3, 0.2], means[0].numpy(), covs[0].numpy())
    m1, P1 = _np_moments(out.mixture.weights[0].numpy(), out.mixture.means[0].numpy(), out.mixture.covs[0].numpy())
    assert_within(m1, m0, 64 * EPS * float(means.abs().max()), "mean after merging")
    assert_within(P1, P0, 64 * EPS * float(means.abs().max()) ** 2, "covariance after merging")


def test_prune_drops_light_components_but_never_the_heaviest():
    model = _linear_model(1)
    means = torch.tensor([[[0.0], [5.0], [9.0]]], dtype=F64)
    covs = torch.ones(1, 3, 1, 1, dtype=F64)
    mix = GaussianMixture(weights=torch.tensor([[0.99995, 4e-5, 1e-5]], dtype=F64), means=means, covs=covs)
    out = MixtureManagement(capacity=3, **{**IDLE, "prune_weight": 1e-4}).apply(mix, model)
    assert out.counts["prunes"].tolist() == [2]
    assert torch.isfinite(out.mixture.log_weights[0]).tolist() == [True, False, False]
    assert_within(out.mixture.log_weights[0, 0], 0.0, 4 * EPS, "the survivor's log-weight")
    # the inactive slots hold a copy of the heaviest
    assert torch.equal(out.mixture.means[0, 1], means[0, 0])
    # a lone heaviest below the threshold is kept
    lone = GaussianMixture(weights=torch.tensor([[1 / 3] * 3], dtype=F64), means=means, covs=covs)
    kept = MixtureManagement(capacity=3, **{**IDLE, "prune_weight": 0.4}).apply(lone, model)
    assert kept.counts["active_components"].tolist() == [1]


def test_the_weight_map_carries_the_old_weights_to_the_new(gen):
    n = 2
    model = _linear_model(n)
    means = torch.stack(
        (torch.zeros(3, n, dtype=F64), torch.zeros(3, n, dtype=F64) + 1e-4, torch.ones(3, n, dtype=F64) * 5), 1
    )
    covs = torch.eye(n, dtype=F64).expand(3, 3, n, n)
    w = torch.tensor([0.5, 0.3, 0.2], dtype=F64).expand(3, 3)
    mix = pad_mixture(GaussianMixture(weights=w, means=means, covs=covs), 8)
    score = torch.zeros(3, 8, dtype=F64)
    score[:, 2] = 5.0
    out = MixtureManagement(capacity=8, prune_weight=0.0, merge_bound=1e-3, split_measurement=1.0).apply(
        mix, model, score, torch.zeros(3, 8, dtype=torch.int64), 1.0
    )
    mapped = (out.weight_map @ mix.weights.unsqueeze(-1)).squeeze(-1)
    assert_within(mapped / mapped.sum(-1, keepdim=True), out.mixture.weights, 8 * EPS, "T w against the new weights")


def test_measurement_nonlinearity_of_a_quadratic_measurement_is_its_closed_form():
    sigma = 0.2
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, torch.tensor([[sigma**2]], dtype=F64))
    means = torch.tensor([[[0.3], [-2.0]]], dtype=F64)
    covs = torch.tensor([[[[0.5]], [[0.01]]]], dtype=F64)
    score, axis = measurement_nonlinearity(means, covs, meas)
    # h(m + s) + h(m − s) − 2h(m) = 2s² = 2P: ν = ½ · 2P / σ = P / σ
    expected = covs[0, :, 0, 0] / sigma
    assert_within(score[0], expected, 16 * EPS * (1 + means.abs().max() ** 2) / sigma, "ν of x²")
    assert axis.tolist() == [[0, 0]]


def test_entropy_nonlinearity_of_the_sine_drift_is_its_closed_form():
    model = SineDriftModel()
    means = torch.tensor([[[0.0], [1.0], [math.pi / 2]]], dtype=F64)
    var = torch.tensor([4.0, 0.25, 1.0], dtype=F64)
    covs = var.reshape(1, 3, 1, 1)
    score, _ = entropy_nonlinearity(model, means, covs, None)
    # ∇·f = cos x: ½|cos(m + s) + cos(m − s) − 2 cos m| = |cos m (cos s − 1)|
    s = var.sqrt()
    expected = (torch.cos(means[0, :, 0]) * (torch.cos(s) - 1.0)).abs()
    assert_within(score[0], expected, 16 * EPS, "entropy rate of the sine drift")


def _attitude_problem(gen, B=4, N=5, sigma=1e-4, var=1e-3, stars=3):
    model = AttitudeModel(estimate_bias=True)
    truth = random_mrps(B, gen, max_norm=0.5)
    prior_var = torch.tensor([var] * 3 + [1e-10] * 3, dtype=F64)
    mean0 = torch.cat(
        (truth + var**0.5 * torch.randn(B, 3, generator=gen, dtype=F64), torch.zeros(B, 3, dtype=F64)), -1
    )
    mix = GaussianMixture.from_gaussian(mean0, torch.diag(prior_var).expand(B, 6, 6), N)
    r = random_unit_vectors(gen, B, stars)
    y = StarVectorMeasurement(r, sigma=sigma).predict(truth) + sigma * torch.randn(
        B, 3 * stars, generator=gen, dtype=F64
    )
    u = 1e-3 * torch.randn(B, 3, generator=gen, dtype=F64)
    return model, mix, StarVectorMeasurement(r, sigma=sigma), y, u


@pytest.mark.parametrize("fused", [False, True])
def test_idle_management_only_pads_and_changes_no_estimate(gen, fused):
    model, mix, meas, y, u = _attitude_problem(gen)
    plain = GaussianSumFilter(model, fused=fused)
    managed = GaussianSumFilter(model, fused=fused, management=MixtureManagement(capacity=8, **IDLE))
    a, b = mix, mix
    for _ in range(3):
        a = plain.update(plain.predict(a, u, 0.1), y, meas)
        b = managed.update(managed.predict(b, u, 0.1), y, meas)
    assert b.num_components == 8
    assert bool(torch.isinf(b.log_weights[:, 5:]).all())
    ma, Pa = plain.estimate(a)
    mb, Pb = managed.estimate(b)
    assert_within(mb, ma, relative_bound(ma, 1e-12, 1e-12 * float(ma.abs().max())), "estimate with idle slots")
    assert_within(Pb, Pa, relative_bound(Pa, 1e-10, 1e-12 * float(Pa.abs().max())), "covariance with idle slots")
    assert_within(b.log_weights[:, :5], a.log_weights, relative_bound(a.log_weights, 1e-10, 1e-12), "log-weights")
    assert set(MANAGEMENT_DIAGNOSTICS) <= set(managed.diagnostics)
    assert set(managed.diagnostic_keys("update")) == set(managed.diagnostics)
    assert managed.diagnostics["active_components"].tolist() == [5] * 4


@pytest.mark.parametrize(
    ("active", "slots"),
    [(1, 1), (2, 2), (3, 3), (4, 4), (5, 6), (6, 6), (7, 8), (8, 8), (9, 12), (12, 12), (13, 16), (25, 32), (33, 48)],
)
def test_slot_count_is_the_next_power_of_two_or_three_halves_of_one(active, slots):
    assert slot_count(active) == slots


def test_active_slots_come_first_and_their_count_is_the_slot_count():
    inf = -math.inf
    log_w = torch.full((2, 16), inf, dtype=F64)
    log_w[0, [2, 5, 9]] = math.log(1 / 3)
    log_w[1, [0, 1, 3, 4, 7, 15, 11]] = math.log(1 / 7)
    index = active_slots(log_w)
    assert index.shape == (2, 8)  # seven active at most: eight slots
    assert index[0, :3].tolist() == [2, 5, 9] and index[1, :7].tolist() == [0, 1, 3, 4, 7, 11, 15]
    picked = torch.gather(log_w, -1, index)
    assert bool(torch.isinf(picked[0, 3:]).all()) and bool(torch.isinf(picked[1, 7:]).all())
    assert len(set(index[0].tolist())) == 8 and len(set(index[1].tolist())) == 8  # distinct slots
    assert active_slots(torch.zeros(3, 5, dtype=F64)) is None  # every slot active
    assert active_slots(log_w[:, :8].clone().fill_(0.0)) is None
    one = torch.full((1, 4), inf, dtype=F64)
    one[0, 3] = 0.0
    assert active_slots(one).tolist() == [[3]]
    five = torch.tensor([[0.0, inf, -1.0, -2.0, inf, -3.0, inf, -4.0]], dtype=F64)
    assert active_slots(five).tolist() == [[0, 2, 3, 5, 7, 1]]  # five active of eight: six slots


def test_spread_slots_puts_computed_components_back_and_fills_inactive_slots_with_the_heaviest(gen):
    inf = -math.inf
    K, n = 8, 2
    log_w = torch.full((2, K), inf, dtype=F64)
    log_w[0, [1, 3, 4, 6, 7]] = torch.log(torch.tensor([0.2, 0.05, 0.5, 0.2, 0.05], dtype=F64))
    log_w[1, [0, 7]] = torch.log(torch.tensor([0.6, 0.4], dtype=F64))
    mix = GaussianMixture(
        log_weights=log_w, means=torch.randn(2, K, n, generator=gen, dtype=F64), covs=random_spd(gen, 2, K, n=n)
    )
    index = active_slots(log_w)
    assert index.shape == (2, 6)  # five active at most: six slots, one inactive among them in each
    computed = gather_slots(mix, index)
    computed = computed.replace(means=computed.means + 1.0, covs=2.0 * computed.covs, validate=False)
    per_slot = torch.arange(6, dtype=F64).expand(2, 6) + 10.0
    spread, (nis,) = spread_slots(mix, computed, index, per_slot)
    assert spread.num_components == K
    assert torch.equal(torch.isfinite(spread.log_weights), torch.isfinite(log_w))
    active = torch.isfinite(log_w)
    # gather_slots normalises the gathered weights again: a logsumexp of weights that sum to one (a few eps), then
    # log w − lse rounded to |log w| (a few eps of it, and the inputs' jitter is relative to it too)
    expected = mix.log_weights[active]
    assert_within(spread.log_weights[active], expected, relative_bound(expected, 8 * EPS, 8 * EPS), "log-weights")
    assert torch.equal(spread.means[active], mix.means[active] + 1.0)
    assert torch.equal(spread.covs[active], 2.0 * mix.covs[active])
    for b, heaviest in ((0, 4), (1, 0)):  # every inactive slot: a copy of the heaviest computed component
        idle = ~active[b]
        assert torch.equal(spread.means[b, idle], (mix.means[b, heaviest] + 1.0).expand(int(idle.sum()), n))
        assert torch.equal(spread.covs[b, idle], (2.0 * mix.covs[b, heaviest]).expand(int(idle.sum()), n, n))
        position = int((index[b] == heaviest).nonzero())
        assert bool((nis[b, idle] == 10.0 + position).all())
        assert nis[b, index[b, 0]] == 10.0


@pytest.mark.parametrize("weight_update", [None, "galerkin"])
def test_a_managed_step_computes_on_the_active_slots_and_matches_computing_every_slot(gen, weight_update):
    # five active components in 16 slots: propagation and update see the 6 slots they need; the active
    # components come out as when every slot is computed (the same arithmetic per component), the inactive
    # slots as copies of the heaviest
    seen = []

    class EverySlot:
        def _computed_slots(self, mixture):
            return None

    class Recorded:
        def _propagate(self, mixture, u, dt):
            seen.append(("propagate", mixture.num_components))
            return super()._propagate(mixture, u, dt)

        def _kalman_step(self, frame, y, mask):
            seen.append(("update", frame.log_weights.shape[-1]))
            return super()._kalman_step(frame, y, mask)

    model, mix, meas, y, u = _attitude_problem(gen, var=1e-2, stars=1)
    base = GaussianSumFilter if weight_update is None else AdaptiveGaussianSumFilter
    kwargs = {} if weight_update is None else {"weight_update": weight_update}
    opts = dict(IDLE, second_order_update=True)
    sliced = type("Sliced", (Recorded, base), {})(model, management=MixtureManagement(capacity=16, **opts), **kwargs)
    whole = type("Whole", (EverySlot, base), {})(model, management=MixtureManagement(capacity=16, **opts), **kwargs)
    a = sliced.update(sliced.predict(mix, u, 0.5), y, meas)
    b = whole.update(whole.predict(mix, u, 0.5), y, meas)
    assert seen == [("propagate", 6), ("update", 6)]
    assert torch.equal(torch.isfinite(a.log_weights), torch.isfinite(b.log_weights))
    live = torch.isfinite(b.log_weights)
    assert_within(a.log_weights[live], b.log_weights[live], relative_bound(b.log_weights[live], 1e-10, 1e-12), "log-w")
    ma, Pa = sliced.estimate(a)
    mb, Pb = whole.estimate(b)
    assert_within(ma, mb, relative_bound(mb, 1e-12, 1e-12 * float(mb.abs().max())), "estimate")
    assert_within(Pa, Pb, relative_bound(Pb, 1e-10, 1e-12 * float(Pb.abs().max())), "covariance")
    heaviest = a.log_weights.argmax(-1)
    idle = ~live
    for t in range(a.log_weights.shape[0]):
        assert torch.equal(a.means[t, idle[t]], a.means[t, heaviest[t]].expand(int(idle[t].sum()), -1))
    assert sliced.diagnostics["nis"].shape == b.log_weights.shape


def test_a_managed_weight_update_computes_on_the_active_slots_only(gen):
    # 5 active components in 16 slots: the Galerkin update sees 6 slots (5 active, 1 held at zero), and its
    # weights come back to the active slots, −inf at the others
    seen = []

    class Recorded(GalerkinWeightUpdate):
        def compute(self, model, prior, propagated, u, elapsed):
            seen.append(propagated.num_components)
            return super().compute(model, prior, propagated, u, elapsed)

    model, mix, meas, y, u = _attitude_problem(gen, var=1e-2)
    managed = AdaptiveGaussianSumFilter(
        model, weight_update=Recorded(), management=MixtureManagement(capacity=16, **IDLE)
    )
    out = managed.predict(mix, u, 0.5)
    assert seen == [6]
    assert out.num_components == 16 and bool(torch.isinf(out.log_weights[:, 5:]).all())
    assert bool(torch.isfinite(out.log_weights[:, :5]).all())


def test_a_managed_weight_qp_keeps_every_active_component_and_holds_the_inactive_at_zero():
    # H = I, c = (10, 0, 0, 0, 0): on the simplex the minimiser drops the first component (w = (0, ¼, ¼, ¼, ¼));
    # a managed mixture's zero weight would free that slot for good, so the component keeps κ·w⁰ of its weight,
    # and the fifth slot, inactive, stays at zero
    H = torch.eye(5, dtype=F64)
    c = torch.tensor([10.0, 0.0, 0.0, 0.0, 0.0], dtype=F64)
    log_w0 = torch.tensor([math.log(0.25)] * 4 + [-math.inf], dtype=F64)
    plain, _ = solve_weight_qp(WeightUpdateRun(), H, c, torch.zeros(5, dtype=F64))
    assert plain[0] == 0.0
    w, res = solve_weight_qp(WeightUpdateRun(hold_inactive=True), H, c, log_w0)
    kept = MANAGED_WEIGHT_KEPT * 0.25
    # the rest share 1 − κ/4 equally: (1 − κ/4)/3 each
    expected = torch.tensor([kept, *[(1.0 - kept) / 3.0] * 3, 0.0], dtype=F64)
    assert_within(w, expected, 4 * EPS, "weights with the first component kept")
    assert w[4] == 0.0
    assert_within(res.kkt_residual, 0.0, 1e-12, "KKT residual of the problem solved")


@pytest.mark.parametrize("weight_update", ["penalty", "galerkin"])
def test_idle_management_leaves_the_adaptive_weights_as_they_were(gen, weight_update):
    model, mix, meas, y, u = _attitude_problem(gen, var=1e-2)
    plain = AdaptiveGaussianSumFilter(model, weight_update=weight_update)
    managed = AdaptiveGaussianSumFilter(
        model, weight_update=weight_update, management=MixtureManagement(capacity=16, **IDLE)
    )
    a = plain.update(plain.predict(mix, u, 0.5), y, meas)
    b = managed.update(managed.predict(mix, u, 0.5), y, meas)
    a, b = plain.predict(a, u, 0.5), managed.predict(b, u, 0.5)
    # the QPs differ in method (an interior point above 12 components): they agree to their KKT accuracy, 1e-9
    assert_within(b.weights[:, :5], a.weights, 1e-9, "adapted weights with idle slots")
    assert bool(torch.isinf(b.log_weights[:, 5:]).all())


def test_a_wide_prior_splits_before_the_update_and_the_mixture_stays_consistent(gen):
    model, mix, meas, y, u = _attitude_problem(gen, N=3, var=0.05, sigma=1e-4, stars=1)
    filt = GaussianSumFilter(model, management=MixtureManagement(capacity=12))
    post = filt.update(filt.predict(mix, u, 0.1), y, meas)
    d = filt.diagnostics
    assert bool((d["splits"] > 0).all())
    assert d["active_components"].tolist() == torch.isfinite(post.log_weights).sum(-1).tolist()
    assert_within(post.weights.sum(-1), 1.0, 16 * EPS, "normalised weights")
    assert bool(torch.linalg.cholesky_ex(post.covs).info.eq(0).all())


def test_registry_builds_the_managed_filters_with_their_options():
    model = AttitudeModel()
    filt = make_filter("AGSF-galerkin-managed", model, capacity=8, merge_bound=0.01)
    assert filt.management == MixtureManagement(capacity=8, merge_bound=0.01)
    assert make_filter("GSF", model).management is None
    for name in ("capacity", "prune_weight", "merge_bound", "merge_rounds", "split_measurement", "split_entropy_rate"):
        assert name in CONFIG_OPTIONS
    assert make_filter("GSF-managed", model).checkpoint_options()["management"] == MixtureManagement().as_dict()
    assert "management" not in make_filter("GSF", model).checkpoint_options()


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"capacity": 0}, "capacity"),
        ({"prune_weight": -1e-3}, "prune_weight"),
        ({"prune_weight": 0.5}, "prune_weight"),
        ({"merge_bound": float("nan")}, "merge_bound"),
        ({"merge_bound": 1.0}, "merge_bound"),
        ({"merge_rounds": 0}, "merge_rounds"),
        ({"split_measurement": float("inf")}, "split_measurement"),
        ({"split_entropy_rate": -1.0}, "split_entropy_rate"),
        ({"second_order_update": 1}, "second_order_update"),
    ],
)
def test_bad_options_are_refused_by_name(options, match):
    with pytest.raises(ValueError, match=match):
        MixtureManagement(**options)


def test_management_on_the_wrong_filter_or_mixture_is_refused(gen):
    model, mix, meas, y, u = _attitude_problem(gen, N=5)
    with pytest.raises(ValueError, match="management"):
        ExtendedKalmanFilter(model, management=MixtureManagement())
    with pytest.raises(ValueError, match="management"):
        MultiplicativeEKF(model, management=MixtureManagement())
    with pytest.raises(TypeError, match="management"):
        GaussianSumFilter(model, management={"capacity": 4})
    filt = GaussianSumFilter(model, management=MixtureManagement(capacity=4))
    with pytest.raises(ValueError, match="capacity"):
        filt.predict(mix, u, 0.1)
    # the weight QP's limit binds the adaptive filters only; the GSF takes more slots
    for weight_update in ("penalty", "galerkin"):
        with pytest.raises(ValueError, match="capacity must be ≤ 64 for an adaptive filter"):
            AdaptiveGaussianSumFilter(model, weight_update=weight_update, management=MixtureManagement(capacity=65))
    wide = GaussianSumFilter(model, management=MixtureManagement(capacity=65))
    assert wide.predict(mix, u, 0.1).num_components == 65
    with pytest.raises(ValueError, match="capacity"):
        pad_mixture(mix, 4)


def test_the_managed_update_is_the_second_order_one():
    # h = x² on one component N(0.7, 0.3) with splitting and merging off: the managed GSF's update is
    # kalman_update's second-order update (tests/test_update.py checks that update against
    # its closed form), and with second_order_update=False the EKF update
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, torch.tensor([[0.04]], dtype=F64))
    model = _linear_model(1)
    belief = GaussianMixture.from_gaussian(torch.tensor([[0.7]], dtype=F64), torch.tensor([[[0.3]]], dtype=F64))
    y = torch.tensor([[0.9]], dtype=F64)
    still = {**IDLE, "second_order_update": True}
    got = GaussianSumFilter(model, management=MixtureManagement(capacity=1, **still)).update(belief, y, meas)
    want = kalman_update(belief.log_weights, belief.means, belief.covs, y, meas, second_order=True)
    assert torch.equal(got.means, want.means) and torch.equal(got.covs, want.covs)
    ekf = GaussianSumFilter(model, management=MixtureManagement(capacity=1, **IDLE)).update(belief, y, meas)
    plain = kalman_update(belief.log_weights, belief.means, belief.covs, y, meas)
    assert torch.equal(ekf.means, plain.means) and torch.equal(ekf.covs, plain.covs)
    assert not torch.equal(ekf.covs, got.covs)
