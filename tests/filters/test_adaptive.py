"""Adaptive GSF: the scalar benchmark against grid references, batched attitude runs, bad input."""

from __future__ import annotations

import math
import re

import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.experiments.studies.sine_benchmark import run_sine_benchmark
from agsf_torch.filters import AdaptiveGaussianSumFilter, GaussianSumFilter, PenaltyWeightUpdate
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.models.benchmarks import SineDriftModel
from tests.helpers import F64, CubicDrift, assert_within, random_mrps, relative_bound


def _sine_filters():
    return {
        "gsf": GaussianSumFilter(SineDriftModel(), substeps=10),
        "agsf": AdaptiveGaussianSumFilter(
            SineDriftModel(), weight_update=PenaltyWeightUpdate(quadrature=40), substeps=10
        ),
    }


def test_sine_benchmark_without_measurements():
    ise = run_sine_benchmark(_sine_filters())
    ratio = ise["agsf"][-1] / ise["gsf"][-1]
    print(f"ISE at t=8: GSF {ise['gsf'][-1]:.4f}, AGSF {ise['agsf'][-1]:.4f}, ratio {ratio:.3f}")
    # measured: GSF 0.1024, AGSF 0.0211 (ratio 0.206)
    assert ratio < 0.25


def test_sine_benchmark_with_ambiguous_measurements():
    ise = run_sine_benchmark(_sine_filters(), measure_every=10, seed=0)
    g, a = ise["gsf"].mean(), ise["agsf"].mean()
    print(f"run-averaged ISE with y = x²: GSF {g:.4f}, AGSF {a:.4f}, ratio {a / g:.3f}")
    # measured: GSF 0.168, AGSF 0.020 (ratio 0.12)
    assert a <= g
    assert a / g < 0.2


def _attitude_setup(gen, estimate_bias, B=256, N=5):
    model = AttitudeModel(estimate_bias=estimate_bias)
    n = model.state_dim
    p = random_mrps(B, gen, max_norm=0.9)
    mean = torch.cat((p, torch.zeros(B, 3, dtype=F64)), -1)[:, :n]
    prior = torch.diag(torch.tensor([1e-3] * 3 + [1e-12] * 3, dtype=F64)[:n])
    mix = GaussianMixture.from_gaussian(mean, prior.expand(B, n, n), N)
    u = (2 * torch.pi / 100) * torch.tensor([1.0, 1.0, 0.0], dtype=F64).expand(B, 3)
    r = torch.randn(B, 5, 3, generator=gen, dtype=F64)
    r = r / r.norm(dim=-1, keepdim=True)
    return model, mix, u, StarVectorMeasurement(r, sigma=1e-5), StarVectorMeasurement(r, sigma=1e-5).predict(p)


@pytest.mark.parametrize("estimate_bias, B", [(False, 256), (True, 256)])
def test_batched_attitude_weights_stay_on_simplex(gen, estimate_bias, B):
    model, mix, u, meas, y = _attitude_setup(gen, estimate_bias, B=B)
    agsf = AdaptiveGaussianSumFilter(model)
    for k in range(3):
        mix = agsf.predict(mix, u, 0.1)
        w = mix.weights
        assert bool((w >= 0).all())
        # exp of log-weights normalised by logsumexp: their sum is 1 to a few N·ε, far inside 1e-12
        assert_within(w.sum(-1), torch.ones(B, dtype=F64), 1e-12, "sum of the adapted weights")
        d = agsf.diagnostics
        assert d["weights_adapted"]
        assert_within(d["qp_kkt_residual"], 0.0, 1e-9, "KKT residual of the weight QP")
        assert bool(torch.isfinite(d["fpke_error_after"]).all())
        if k == 1:
            mix = agsf.update(mix, y, meas)
    assert bool(torch.isfinite(mix.means).all())


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_switched_off_equals_gsf_exactly(gen, estimate_bias):
    model, mix, u, meas, y = _attitude_setup(gen, estimate_bias, B=32)
    off = AdaptiveGaussianSumFilter(model, adapt=False)
    gsf = GaussianSumFilter(model)
    a, b = mix, mix
    for k in range(3):
        a, b = off.predict(a, u, 0.1), gsf.predict(b, u, 0.1)
        if k == 1:
            a, b = off.update(a, y, meas), gsf.update(b, y, meas)
    assert torch.equal(a.means, b.means) and torch.equal(a.covs, b.covs) and torch.equal(a.log_weights, b.log_weights)


def test_fpke_error_is_reduced_without_penalty(gen):
    """With λ → 0 the QP minimises wᵀLw itself: the FPKE error can only go down."""
    model, mix, u, meas, y = _attitude_setup(gen, False, B=64)
    agsf = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(reg=1e-9))
    agsf.predict(mix, u, 0.1)
    d = agsf.diagnostics
    assert bool((d["fpke_error_after"] <= d["fpke_error_before"] * (1 + 1e-6)).all())
    assert float((d["fpke_error_after"] / d["fpke_error_before"]).min()) < 0.99


def test_unscaled_paper_form_runs(gen):
    model, mix, u, meas, y = _attitude_setup(gen, False, B=16)
    agsf = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(scaling="none"))
    out = agsf.predict(mix, u, 0.1)
    assert_within(out.weights.sum(-1), torch.ones(16, dtype=F64), 1e-12, "sum of the weights (unscaled QP)")


def test_singular_covariance_is_named_or_repaired(gen):
    model, mix, u, meas, y = _attitude_setup(gen, False, B=4, N=3)
    covs = mix.covs.clone()
    covs[2, 0] = torch.diag(torch.tensor([1e-3, 1e-3, -1e-6], dtype=F64))
    broken = mix.replace(covs=covs, validate=False)  # the filter's own check is under test
    with pytest.raises(ValueError, match=r"trajectory index \(2,\), component 0"):
        AdaptiveGaussianSumFilter(model).predict(broken, u[:4], 0.1)
    agsf = AdaptiveGaussianSumFilter(model, repair_covariance=True)
    out = agsf.predict(broken, u[:4], 0.1)
    assert agsf.diagnostics["covariance_repairs"] >= 1
    assert bool(torch.isfinite(out.weights).all())


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"reg": -1.0}, "reg"),
        ({"reg": float("nan")}, "reg"),
        ({"scaling": "log"}, "scaling"),
        ({"weight_ref": "first"}, "weight_ref"),
        ({"cadence": 0}, "cadence"),
        ({"quadrature": (7, 7)}, "quadrature"),
    ],
)
def test_bad_options_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        AdaptiveGaussianSumFilter(AttitudeModel(), weight_update=PenaltyWeightUpdate(**kwargs))


@pytest.mark.slow
def test_compiled_kernel_equals_eager(gen):
    model, mix, u, meas, y = _attitude_setup(gen, False, B=32)
    eager = AdaptiveGaussianSumFilter(model).predict(mix, u, 0.1)
    compiled = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(compile=True)).predict(mix, u, 0.1)
    assert_within(
        compiled.log_weights, eager.log_weights, relative_bound(eager.log_weights, 1e-10, 1e-12), "compiled log-weights"
    )


class Broken(AttitudeModel):
    """Fokker–Planck terms that turn NaN wherever the gyro reads the marker rate 0.123 (elementwise)."""

    def fokker_planck_terms(self, x, u):
        from agsf_torch.models.base import FokkerPlanckTerms

        t = super().fokker_planck_terms(x, u)
        div = torch.where(u[..., 0] == 0.123, float("nan"), t.drift_divergence)
        return FokkerPlanckTerms(t.drift, div, t.diffusion, t.diffusion_divergence, t.diffusion_second_divergence)


def test_non_finite_fpke_matrix_names_the_trajectory(gen):
    """A model whose Fokker–Planck terms turn NaN for one trajectory: a clear error, never a NaN weight."""
    model, mix, u, meas, y = _attitude_setup(gen, False, B=4, N=3)
    u = u[:4].clone()
    u[2, 0] = 0.123  # trajectory 2
    before = mix.log_weights.clone()
    with pytest.raises(ValueError, match=r"FPKE matrix L is not finite at trajectory index \(2,\)"):
        AdaptiveGaussianSumFilter(Broken()).predict(mix, u, 0.1)
    assert torch.equal(mix.log_weights, before)


def test_components_beyond_the_qp_limit_are_refused_before_any_work():
    """N > 64 names the limit at the first predict, before the state changes; the config refuses it up front."""
    from agsf_torch.experiments.config.loader import load_preset
    from agsf_torch.mixture import GaussianMixture
    from agsf_torch.qp import MAX_COMPONENTS

    filt = AdaptiveGaussianSumFilter(AttitudeModel(), weight_update="galerkin")
    mix = GaussianMixture.from_gaussian(
        torch.zeros(2, 3, dtype=torch.float64),
        1e-3 * torch.eye(3, dtype=torch.float64).expand(2, 3, 3),
        MAX_COMPONENTS + 1,
    )
    before = filt.weight_update.state_dict()
    with pytest.raises(ValueError, match=r"N ≤ 64 components, got a mixture of 65"):
        filt.predict(mix, torch.zeros(2, 3, dtype=torch.float64), 0.1)
    assert filt.weight_update.state_dict() == before
    with pytest.raises(ValueError, match=r"'components' must be ≤ 64 with an adaptive filter"):
        load_preset("case1").replace(components=65)
    assert load_preset("case1").replace(components=65, filters=["GSF"]).components == 65


@pytest.mark.parametrize("bad", [0, -1, -3, 2.5, True, "4", [4], float("inf"), float("nan")])
@pytest.mark.parametrize("weight_update", ["penalty", "galerkin"])
def test_bad_chunk_size_is_refused_and_options_are_frozen(weight_update, bad):
    """One check (chunks.check_chunk_size) for every path: the update and the matrices; the options
    of a built update cannot change."""
    from dataclasses import FrozenInstanceError

    from agsf_torch.chunks import check_chunk_size
    from agsf_torch.filters.weight_updates import WEIGHT_UPDATES

    with pytest.raises(ValueError, match="chunk_size must be a positive integer or None"):
        WEIGHT_UPDATES[weight_update](chunk_size=bad)
    filt = AdaptiveGaussianSumFilter(AttitudeModel(), weight_update=WEIGHT_UPDATES[weight_update](chunk_size=8))
    with pytest.raises(FrozenInstanceError):
        filt.weight_update.chunk_size = bad
    assert filt.weight_update.chunk_size == 8
    with pytest.raises(ValueError, match="chunk_size must be a positive integer or None"):
        check_chunk_size(bad)
    assert check_chunk_size(4.0) == 4 and check_chunk_size(None) is None


@pytest.mark.parametrize("kind", ["penalty", "galerkin"])
def test_counter_does_not_move_when_the_update_refuses_the_mixture(kind):
    """N > 64 is refused on the first interval, adapted or not: the cadence counter stays where it was."""
    from agsf_torch.filters.weight_updates import WEIGHT_UPDATES
    from agsf_torch.qp import MAX_COMPONENTS

    model = AttitudeModel()
    update = WEIGHT_UPDATES[kind](cadence=2)
    update.bind(model)
    mix = GaussianMixture.from_gaussian(
        torch.zeros(2, 3, dtype=F64), 1e-3 * torch.eye(3, dtype=F64).expand(2, 3, 3), MAX_COMPONENTS + 1
    )
    u = torch.zeros(2, 1, 3, dtype=F64)
    for _ in range(2):
        with pytest.raises(ValueError, match=r"the weight QP handles N ≤ 64 components, got a mixture of 65"):
            update(model, mix, mix, u, 0.1)
        assert update.state_dict()["step"] == 0 and update.state_dict()["elapsed"] == 0.0
    update(model, mix, mix, u, 0.1, enabled=False)  # switched off: a plain GSF, any N
    assert update.state_dict()["step"] == 1


def test_counter_does_not_move_when_the_fpke_matrix_is_not_finite(gen):
    """The off-cadence interval counts; the adapting one that fails does not, and can be retried."""
    model, mix, u, meas, y = _attitude_setup(gen, False, B=4, N=3)
    u = u[:4].clone()
    u[1, 0] = 0.123
    filt = AdaptiveGaussianSumFilter(Broken(), weight_update=PenaltyWeightUpdate(cadence=2))
    filt.predict(mix, u, 0.1)
    assert filt.weight_update.state_dict()["step"] == 1
    before = filt.state_dict()
    for _ in range(2):
        with pytest.raises(ValueError, match=r"FPKE matrix L is not finite at trajectory index \(1,\)"):
            filt.predict(mix, u, 0.1)
        assert filt.state_dict()["weight_update"] == before["weight_update"]


@pytest.mark.parametrize("estimate_bias", [False, True])
@pytest.mark.parametrize("kind", ["penalty", "galerkin"])
@pytest.mark.parametrize("compiled", [False, True])
def test_an_empty_batch_gives_an_empty_mixture(estimate_bias, kind, compiled):
    """B = 0 trajectories: both adaptive filters return an empty mixture, as the GSF does (the paper's update
    failed in torch.cat on no pairs), also on their compiled fused routes (which failed reshaping no pairs)."""
    from agsf_torch.filters.registry import make_filter

    n = 6 if estimate_bias else 3
    model = AttitudeModel(estimate_bias=estimate_bias)
    mix = GaussianMixture.from_gaussian(torch.zeros(0, n, dtype=F64), 1e-4 * torch.eye(n, dtype=F64).expand(0, n, n), 3)
    if compiled:  # nothing is compiled for no lanes
        filt = make_filter("AGSF", model, compile=True) if kind == "penalty" else None
        filt = filt or make_filter("AGSF-galerkin", model, compile_fused=True)
    else:
        filt = AdaptiveGaussianSumFilter(model, weight_update=kind)
    out = filt.predict(mix, torch.zeros(0, 3, dtype=F64), 0.1)
    assert out.means.shape == (0, 3, n) and out.log_weights.shape == (0, 3)


@pytest.mark.parametrize("kind", ["gsf", "galerkin", "penalty"])
@pytest.mark.parametrize(("dt", "rate"), [(1e5, 0.02), (1e7, 0.02), (0.1, 1e3)])
def test_an_interval_the_propagation_cannot_follow_is_refused_naming_the_rotation(kind, dt, rate):
    """An interval that turns the body by more than a radian (dt = 1e7 s, or 1e3 rad/s) is refused before
    anything changes (the Galerkin update returned NaN weights); split as the message says, it runs."""
    model = AttitudeModel(estimate_bias=True)
    mean = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=F64).expand(2, 6)
    cov = torch.diag(torch.tensor([1e-4] * 3 + [1e-10] * 3, dtype=F64)).expand(2, 6, 6)
    mix = GaussianMixture.from_gaussian(mean, cov, 3)
    u = torch.tensor([rate, 0.0, 0.0], dtype=F64).expand(2, 3)
    filt = {
        "gsf": lambda: GaussianSumFilter(model),
        "galerkin": lambda: AdaptiveGaussianSumFilter(model, weight_update="galerkin"),
        "penalty": lambda: AdaptiveGaussianSumFilter(model),
    }[kind]()
    before = filt.state_dict() if kind != "gsf" else None
    with pytest.raises(
        ValueError, match=r"turns [0-9.e+]+ rad, more than the 1 rad .* at least (\d+) intervals"
    ) as exc:
        filt.predict(mix, u, dt)
    if before is not None:
        assert filt.state_dict() == before  # the cadence counter did not move
    if rate * dt <= 100:  # split into the intervals the message names, the same span runs: finite weights
        intervals = int(re.search(r"at least (\d+) intervals", str(exc.value)).group(1))
        for _ in range(intervals):
            mix = filt.predict(mix, u, dt / intervals)
        assert bool(torch.isfinite(mix.log_weights).all())


@pytest.mark.parametrize("kind", ["gsf", "galerkin", "penalty"])
def test_a_step_rk4_cannot_follow_on_a_users_model_is_refused_before_anything_changes(kind):
    """A user's stiff model on the generic path (``dx = (x − x³)dt + dβ``, a component at x = 16.4, one RK4 step of
    0.1 s): the GSF returned means of 1e45 and covariances of 1e95 without a word, the adaptive filters a raw
    ``LinAlgError`` naming a 'batch element'.  Now every filter refuses the step naming the component and the
    substeps that can take it, before its weight update's counter moves; with those substeps it runs."""
    model = CubicDrift()
    means = torch.tensor([[[-1.0], [1.0], [16.4]], [[0.0], [0.5], [-0.5]]], dtype=F64)  # [B = 2, N = 3, 1]
    mix = GaussianMixture(
        log_weights=torch.full((2, 3), -math.log(3), dtype=F64),
        means=means,
        covs=torch.full((2, 3, 1, 1), 0.05, dtype=F64),
    )

    def build(substeps):
        return {
            "gsf": lambda: GaussianSumFilter(model, substeps=substeps),
            "galerkin": lambda: AdaptiveGaussianSumFilter(model, weight_update="galerkin", substeps=substeps),
            "penalty": lambda: AdaptiveGaussianSumFilter(model, substeps=substeps),
        }[kind]()

    filt = build(1)
    before = filt.state_dict() if kind != "gsf" else None
    with pytest.raises(ValueError, match=r"at batch index \(0, 2\).*use at least substeps=81 for dt=0\.1 s") as exc:
        filt.predict(mix, None, 0.1)
    if before is not None:
        assert filt.state_dict() == before
    substeps = int(re.search(r"substeps=(\d+)", str(exc.value)).group(1))
    out = build(substeps).predict(mix, None, 0.1)
    assert bool(torch.isfinite(out.means).all() and torch.isfinite(out.covs).all())
    assert bool(torch.isfinite(out.log_weights).all()) and float(out.means[0, 2, 0]) < 3.0  # 16.4 falls to 2.33


def test_one_weight_update_object_serves_one_filter():
    """A second filter given the same update had shared the first's reference weights and counter (its weights off
    by 0.12 from a fresh filter's) and rebound the update to its own model; it is refused, naming the fix, and a
    copy by ``dataclasses.replace`` (a fresh run state) or a filter that is gone frees the way."""
    import dataclasses
    import gc

    from tests.helpers import CubicDrift

    update = PenaltyWeightUpdate(reg=0.5)
    first = AdaptiveGaussianSumFilter(CubicDrift(), weight_update=update)
    with pytest.raises(
        ValueError, match=r"this PenaltyWeightUpdate already serves another filter .*dataclasses\.replace"
    ):
        AdaptiveGaussianSumFilter(CubicDrift(), weight_update=update)
    copy = dataclasses.replace(update)
    assert copy.reg == 0.5 and copy.run is not update.run
    AdaptiveGaussianSumFilter(CubicDrift(), weight_update=copy)
    # a filter pickles and deep-copies with its own update (the owner is not state); a shallow copy shares the
    # update and is refused at its first step
    import copy as copying
    import pickle

    mix = GaussianMixture.from_gaussian(
        torch.tensor([[0.2], [1.0]], dtype=F64), torch.full((2, 1, 1), 0.05, dtype=F64), 3
    )
    first.predict(mix, None, 0.05)
    for make in (lambda f: pickle.loads(pickle.dumps(f)), copying.deepcopy):
        clone = make(first)  # the same run state: the same next step
        assert clone.weight_update is not update
        assert torch.equal(clone.predict(mix, None, 0.05).weights, first.predict(mix, None, 0.05).weights)
    with pytest.raises(ValueError, match="already serves another filter"):
        copying.copy(first).predict(mix, None, 0.05)
    del first
    gc.collect()
    AdaptiveGaussianSumFilter(CubicDrift(), weight_update=update)


class _KernelCalled(Exception):
    """Raised by a stand-in for the FPKE matrices: the call and its ``compile`` flag are all the test needs."""


@pytest.mark.parametrize("update", ["penalty", "galerkin"])
@pytest.mark.parametrize(
    ("compile_fused", "own", "compiled"),
    [(True, None, True), (False, None, False), (True, False, False), (False, True, True)],
)
def test_the_filter_switch_compiles_the_weight_updates_kernels_unless_the_update_says_otherwise(
    update, compile_fused, own, compiled, monkeypatch
):
    """One switch: ``compile_fused=True`` compiles the weight update's FPKE kernels too (before, a user who set it
    alone got the penalty update's L eagerly, many times the fused GSF's step); the update's own ``compile``, when
    given, overrides it.  The matrices are asked for with the resolved flag."""
    from agsf_torch.filters import GalerkinWeightUpdate
    from agsf_torch.filters.weight_updates import galerkin, penalty

    flags = []

    def stand_in(*args, compile, **kwargs):
        flags.append(compile)
        raise _KernelCalled

    if update == "penalty":
        weight_update = PenaltyWeightUpdate(compile=own)
        monkeypatch.setattr(penalty, "fpke_matrix", stand_in)
    else:
        weight_update = GalerkinWeightUpdate(compile=own)
        monkeypatch.setattr(galerkin, "galerkin_matrices", stand_in)
    filt = AdaptiveGaussianSumFilter(
        AttitudeModel(estimate_bias=False), weight_update=weight_update, compile_fused=compile_fused, fused=False
    )
    cov = 0.01 * torch.eye(3, dtype=F64).expand(1, 2, 3, 3).clone()
    mix = GaussianMixture(
        log_weights=torch.full((1, 2), -math.log(2), dtype=F64), means=torch.zeros(1, 2, 3, dtype=F64), covs=cov
    )
    with pytest.raises(_KernelCalled):
        filt.predict(mix, torch.zeros(1, 3, dtype=F64), 0.1)
    assert flags == [compiled]


def test_a_weight_update_compile_of_another_type_is_refused():
    with pytest.raises(
        ValueError, match=r"compile must be True, False or None \(as the filter's compile_fused\), got 1"
    ):
        PenaltyWeightUpdate(compile=1)
