"""Innovation gating: the χ² threshold, the per-block NIS, the consistency rule, the filter option."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from agsf_torch import GaussianMixture
from agsf_torch.filters import AdaptiveGaussianSumFilter, GaussianSumFilter
from agsf_torch.gating import chi2_threshold, innovation_gate
from agsf_torch.models import AttitudeModel, FunctionMeasurement, StarVectorMeasurement
from agsf_torch.rotations import mrp_to_dcm
from tests.helpers import F64, assert_within, random_mrps, relative_bound

SIGMA = 1e-5


def test_chi2_thresholds():
    # χ²₃ quantile at 1 − 1e-4 (tabulated: 21.108), and the closed form for 2 dof: −2 ln(1 − p).
    assert_within(chi2_threshold(0.9999, 3), 21.1075, 1e-4, "χ²₃ quantile against its table (4 decimals)")
    two_dof = -2.0 * math.log(0.01)
    assert_within(chi2_threshold(0.99, 2), two_dof, 1e-12 * two_dof, "χ²₂ quantile against its closed form")
    for p in (0.0, 1.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="gate probability must lie in"):
            chi2_threshold(p, 3)
    with pytest.raises(ValueError, match="degrees of freedom"):
        chi2_threshold(0.9, 0)


def _frame(gen, B=4, N=3, M=5, bad_slot=None, offset=1e-3, prior_var=1e-11):
    """Converged attitude mixtures and a star frame; star ``bad_slot`` carries a wrong catalogue vector."""
    truth = random_mrps(B, gen, max_norm=0.8)
    r = torch.randn(B, M, 3, generator=gen, dtype=F64)
    r = r / r.norm(dim=-1, keepdim=True)
    y = StarVectorMeasurement(r, sigma=SIGMA).predict(truth) + SIGMA * torch.randn(B, 3 * M, generator=gen, dtype=F64)
    r_reported = r.clone()
    if bad_slot is not None:  # the catalogue vector turned by `offset` rad about a random axis ⊥ r
        good = r[:, bad_slot]
        across = torch.linalg.cross(good, torch.randn(B, 3, generator=gen, dtype=F64), dim=-1)
        wrong = good + offset * across / across.norm(dim=-1, keepdim=True)
        r_reported[:, bad_slot] = wrong / wrong.norm(dim=-1, keepdim=True)
    mean = truth + prior_var**0.5 * torch.randn(B, 3, generator=gen, dtype=F64)
    mix = GaussianMixture.from_gaussian(mean, prior_var * torch.eye(3, dtype=F64).expand(B, 3, 3), N)
    return mix, y, r_reported, truth


def test_block_nis_matches_an_independent_computation(gen):
    mix, y, r, truth = _frame(gen, N=1)
    meas = StarVectorMeasurement(r, sigma=SIGMA)
    accepted, nis, entry_mask, overridden = innovation_gate(mix.log_weights, mix.means, mix.covs, y, meas, 21.1)
    mu = mix.means[:, 0].numpy()
    P = mix.covs[:, 0].numpy()
    H = meas.jacobian(mix.means[:, 0]).numpy()
    C = mrp_to_dcm(mix.means[:, 0]).numpy()
    for b in range(mu.shape[0]):
        for j in range(5):
            nu = y[b, 3 * j : 3 * j + 3].numpy() - C[b] @ r[b, j].numpy()
            Hj = H[b, 3 * j : 3 * j + 3]
            S = Hj @ P[b] @ Hj.T + SIGMA**2 * np.eye(3)
            # ν ~ 1e-5 is a difference of unit vectors: each side rounds it to ~1e-11 of itself, and κ(S) < 3
            expected = nu @ np.linalg.solve(S, nu)
            assert_within(nis[b, j], expected, 1e-9 * expected, "per-star NIS")
    assert accepted.all() and entry_mask.all() and not overridden.any()


def test_a_wrong_catalogue_vector_is_rejected_and_the_update_ignores_it(gen):
    mix, y, r, truth = _frame(gen, bad_slot=2)
    model = AttitudeModel(estimate_bias=False)
    meas = StarVectorMeasurement(r, sigma=SIGMA)
    gated = GaussianSumFilter(model, gate_probability=0.9999)
    post = gated.update(mix, y, meas)
    d = gated.diagnostics
    assert d["gate_rejected"].tolist() == [1, 1, 1, 1]
    assert (~d["gate_accepted"]).nonzero()[:, 1].tolist() == [2, 2, 2, 2]
    assert (d["gate_nis"][:, 2] > 1e3).all() and not d["gate_overridden"].any()
    # exactly the update with that star masked out
    mask = torch.ones(4, 5, dtype=torch.bool)
    mask[:, 2] = False
    ref = GaussianSumFilter(model).update(mix, y, StarVectorMeasurement(r, mask, SIGMA))
    assert torch.equal(post.means, ref.means) and torch.equal(post.covs, ref.covs)
    assert torch.equal(post.log_weights, ref.log_weights)
    # with the star masked the estimate is consistent with its covariance; without the gate the outlier
    # (100 σ off) drags it far outside: the NEES of the estimate against the χ²₃ quantile of false-alarm
    # probability 5e-7 over the four trajectories
    plain = GaussianSumFilter(model).update(mix, y, meas)

    def estimate_nees(post):
        mean, cov = GaussianSumFilter(model).estimate(post)
        white = torch.linalg.solve_triangular(torch.linalg.cholesky(cov), (mean - truth).unsqueeze(-1), upper=False)
        return white.square().sum((-2, -1))

    limit = stats.chi2.isf(5e-7 / 4, 3)
    assert bool((estimate_nees(ref) <= limit).all())
    assert bool((estimate_nees(plain) > limit).all())


def test_consistency_rule_keeps_a_frame_that_disagrees_as_a_whole(gen):
    mix, y, r, truth = _frame(gen)
    # the prediction is off by ~12°: every star disagrees (a star hides a rotation δθ only within an angle
    # ~4.6σ/δθ ≈ 2e-4 rad of its axis: probability ~1e-8 per star for random stars)
    shifted = mix.replace(means=mix.means + 3e-2)
    meas = StarVectorMeasurement(r, sigma=SIGMA)
    threshold = chi2_threshold(0.9999, 3)
    accepted, nis, entry_mask, overridden = innovation_gate(
        shifted.log_weights, shifted.means, shifted.covs, y, meas, threshold
    )
    assert (nis > threshold).all() and overridden.all() and accepted.all() and entry_mask.all()
    # with two valid stars, one failing star is rejected only if the other passes
    mix2, y2, r2, _ = _frame(gen, M=2, bad_slot=1)
    acc2, _, _, ov2 = innovation_gate(
        mix2.log_weights, mix2.means, mix2.covs, y2, StarVectorMeasurement(r2, sigma=SIGMA), 21.1
    )
    assert acc2[:, 0].all() and not acc2[:, 1].any() and not ov2.any()


def test_masked_stars_are_neither_gated_nor_counted(gen):
    mix, y, r, truth = _frame(gen, bad_slot=2)
    mask = torch.ones(4, 5, dtype=torch.bool)
    mask[:, 2] = False  # the outlier is already invalid
    mask[0, 4] = False
    filt = GaussianSumFilter(AttitudeModel(estimate_bias=False), gate_probability=0.9999)
    filt.update(mix, y, StarVectorMeasurement(r, mask, SIGMA))
    assert filt.diagnostics["gate_rejected"].tolist() == [0, 0, 0, 0]
    assert (filt.diagnostics["gate_nis"][:, 2] == 0).all()


def test_single_block_measurements_are_gated_as_they_stand(gen):
    # a scalar measurement y = x with R = 1: NIS = (y − μ)² / (P + 1)
    mix = GaussianMixture.from_gaussian(torch.zeros(2, 1, dtype=F64), torch.eye(1, dtype=F64).expand(2, 1, 1), 1)
    meas = FunctionMeasurement(lambda x: x, torch.eye(1, dtype=F64))
    y = torch.tensor([[1.0], [10.0]], dtype=F64)
    accepted, nis, _, overridden = innovation_gate(
        mix.log_weights, mix.means, mix.covs, y, meas, chi2_threshold(0.999, 1)
    )
    expected = torch.tensor([0.5, 50.0], dtype=F64)
    assert_within(nis[:, 0], expected, relative_bound(expected, 1e-6, 1e-12), "scalar NIS")
    assert accepted[:, 0].tolist() == [True, False] and not overridden.any()


def test_gate_option_validation_and_adaptive_filter_passes_it_on():
    model = AttitudeModel(estimate_bias=False)
    for p in (0.0, 1.0, 2.0):
        with pytest.raises(ValueError, match="gate probability must lie in"):
            GaussianSumFilter(model, gate_probability=p)
    assert AdaptiveGaussianSumFilter(model, gate_probability=0.999).gate_probability == 0.999
    assert GaussianSumFilter(model).gate_probability is None
