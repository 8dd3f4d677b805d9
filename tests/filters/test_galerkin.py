"""The Galerkin weight update (method.md §3b) inside the adaptive filter: exact cases, the
authors' benchmarks against independent references, the weight update as a pluggable step,
and bad input."""

from __future__ import annotations

import math

import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.experiments.studies.sine_benchmark import run_sine_benchmark
from agsf_torch.filters import (
    AdaptiveGaussianSumFilter,
    GalerkinWeightUpdate,
    GaussianSumFilter,
    PenaltyWeightUpdate,
    WeightUpdate,
)
from agsf_torch.models import AttitudeModel, LinearModel, LorenzModel
from agsf_torch.models.benchmarks import SineDriftModel
from agsf_torch.quadrature import gauss_hermite, six_n_plus_one
from tests.filters.test_adaptive import _attitude_setup
from tests.helpers import F64, assert_within, random_mrps, relative_bound


def _linear_mixture(gen, B=4, N=3):
    A = torch.tensor([[-0.3, 1.0], [-0.5, -0.2]], dtype=F64)
    model = LinearModel(
        A, torch.eye(2, dtype=F64), torch.diag(torch.tensor([0.2, 0.1], dtype=F64)), B=torch.eye(2, dtype=F64)
    )
    mean = torch.randn(B, N, 2, generator=gen, dtype=F64)
    L = torch.randn(B, N, 2, 2, generator=gen, dtype=F64)
    covs = L @ L.transpose(-1, -2) + 0.3 * torch.eye(2, dtype=F64)
    w = torch.rand(B, N, generator=gen, dtype=F64) + 0.1
    return model, GaussianMixture(weights=w, means=mean, covs=0.5 * (covs + covs.transpose(-1, -2)))


def test_linear_model_keeps_its_weights(gen):
    """Each Gaussian propagated by its moment equations solves the FPKE of a linear SDE exactly:
    ℓ ≡ 0, K = 0, and the update returns w⁻ (to 1e-12) whatever the mixture."""
    model, mix = _linear_mixture(gen)
    filt = AdaptiveGaussianSumFilter(model, weight_update="galerkin")
    u = torch.randn(4, 2, generator=gen, dtype=F64)
    w0 = mix.weights
    for _ in range(5):
        mix = filt.predict(mix, u, 0.1)
        assert filt.diagnostics["weights_adapted"]
        assert_within(mix.weights, w0, 1e-12, "weights on a linear model")
        assert_within(filt.diagnostics["galerkin_residual_change"], 0.0, 1e-12, "residual change on a linear model")


def test_sine_forecast_against_the_grid_fpke():
    """method.md §5 without measurements, against a Crank–Nicolson FPKE solution on a fine grid:
    the Galerkin update brings the density far closer to the exact one than the classic GSF and
    than the paper's penalised update."""
    filters = {
        "gsf": GaussianSumFilter(SineDriftModel(), substeps=10),
        "penalty": AdaptiveGaussianSumFilter(
            SineDriftModel(), weight_update=PenaltyWeightUpdate(quadrature=40), substeps=10
        ),
        "galerkin": AdaptiveGaussianSumFilter(
            SineDriftModel(), weight_update=GalerkinWeightUpdate(quadrature=40), substeps=10
        ),
    }
    ise = {k: float(v[-1]) for k, v in run_sine_benchmark(filters).items() if k != "time"}
    print(f"ISE at t = 8: {ise}")
    # measured: GSF 0.1024, penalty 0.0211, Galerkin 0.00194
    assert ise["galerkin"] < 0.1 * ise["gsf"]
    assert ise["galerkin"] < 0.2 * ise["penalty"]


def _lorenz_prior() -> GaussianMixture:
    """The authors' Lorenz example (their main.m): weights [0.9, 0.1], means [∓0.2, ∓0.2, 8], covariances 0.5916·I."""
    return GaussianMixture(
        weights=torch.tensor([0.9, 0.1], dtype=F64),
        means=torch.tensor([[-0.2, -0.2, 8.0], [0.2, 0.2, 8.0]], dtype=F64),
        covs=0.5916 * torch.eye(3, dtype=F64).expand(2, 3, 3),
    )


def _lorenz_ensemble(model: LorenzModel, num: int, substeps: int, steps: int, seed: int) -> torch.Tensor:
    """Euler–Maruyama samples of the stochastic Lorenz system at t = steps · 0.01 (independent of the filters)."""
    g = torch.Generator().manual_seed(seed)
    prior = _lorenz_prior()
    comp = (torch.rand(num, generator=g, dtype=F64) < 0.1).long()
    x = prior.means[comp] + math.sqrt(0.5916) * torch.randn(num, 3, generator=g, dtype=F64)
    h = 0.01 / substeps
    sd = torch.sqrt(torch.tensor([1.0, 1.0, 2.0], dtype=F64) * h)
    s, r, b = 10.0, 28.0, 8.0 / 3.0
    for _ in range(steps * substeps):
        x1, x2, x3 = x.unbind(-1)
        f = torch.stack((s * (x2 - x1), x1 * (r - x3) - x2, x1 * x2 - b * x3), -1)
        x = x + f * h + sd * torch.randn(num, 3, generator=g, dtype=F64)
    return x


def _lorenz_scores(num: int, substeps: int):
    model = LorenzModel()
    filters = {
        "gsf": GaussianSumFilter(model),
        "penalty": AdaptiveGaussianSumFilter(model),
        "galerkin": AdaptiveGaussianSumFilter(model, weight_update="galerkin"),
        "galerkin_6n+1": AdaptiveGaussianSumFilter(
            model, weight_update=GalerkinWeightUpdate(quadrature=six_n_plus_one(3))
        ),
    }
    mixtures = {}
    for name, f in filters.items():
        mix = _lorenz_prior()
        for _ in range(51):
            mix = f.predict(mix, None, 0.01)
        mixtures[name] = mix
    x = _lorenz_ensemble(model, num, substeps, 51, seed=0)
    logp = {name: m.log_prob(x) for name, m in mixtures.items()}
    return mixtures, logp, x


def _check_lorenz(num: int, substeps: int) -> None:
    mixtures, logp, x = _lorenz_scores(num, substeps)
    lobe = float((x[:, 0] > 0).double().mean())

    def paired(a, b):
        d = logp[a] - logp[b]
        return float(d.mean()), float(d.std() / math.sqrt(d.numel()))

    gain_pen, se_pen = paired("penalty", "gsf")
    gain_gal, se_gal = paired("galerkin", "gsf")
    gal_vs_pen, se_gp = paired("galerkin", "penalty")
    w_pos = {k: float(m.weights[int(m.means[:, 0].argmax())]) for k, m in mixtures.items()}
    print(
        f"Lorenz t = 0.51, {num} samples: P(x1 > 0) = {lobe:.4f}; weight of the x1 > 0 component {w_pos}; "
        f"density score gain over GSF: penalty {gain_pen:.4f} ± {se_pen:.4f}, Galerkin {gain_gal:.4f} ± {se_gal:.4f} nats; "
        f"Galerkin − penalty {gal_vs_pen:.4f} ± {se_gp:.4f}"
    )
    # measured (2e5 samples): P(x1 > 0) 0.391; weights GSF 0.1, penalty 0.30, Galerkin 0.388;
    # gains penalty 0.275 ± 0.0015, Galerkin 0.294 ± 0.0019, Galerkin − penalty 0.018 ± 0.0004
    assert gain_gal > 10 * se_gal and gal_vs_pen > 5 * se_gp
    # the weights carry the mass of each lobe: 0.02 allows the Galerkin approximation (measured 0.003) and the
    # ensemble's sampling spread of P(x1 > 0) (√(p(1 − p)/num) ≈ 0.0011 at 2e5 samples)
    assert_within(w_pos["galerkin"], lobe, 0.02, "Galerkin weight of the x1 > 0 component against P(x1 > 0)")
    assert abs(w_pos["gsf"] - lobe) > 0.2
    # the authors' 6n+1-point rule is exact for the cubic ℓⱼ of the Lorenz drift: the same weights
    # after 51 steps up to the rounding of the two rules (measured 3e-12)
    assert_within(
        mixtures["galerkin_6n+1"].weights, mixtures["galerkin"].weights, 1e-10, "weights with the 6n+1-point rule"
    )


def test_lorenz_against_an_euler_maruyama_ensemble():
    """The authors' Lorenz example (σ=10, ρ=28, β=8/3, Q = diag(1,1,2), Δt = 0.01, 51 steps),
    scored by the mean log-density of 2·10⁵ Euler–Maruyama samples (step 1e-3)."""
    _check_lorenz(200_000, 10)


@pytest.mark.slow
def test_lorenz_against_a_million_sample_ensemble():
    """The same with 10⁶ samples and an Euler–Maruyama step of 2.5e-4."""
    _check_lorenz(1_000_000, 40)


# ------------------------------------------------------------------ attitude and the QP


def _attitude(gen, estimate_bias, B=16, N=4):
    return _attitude_setup(gen, estimate_bias, B=B, N=N)


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_attitude_weights_on_simplex_and_residual_reduced(gen, estimate_bias):
    """Weights on the simplex to 1e-12; the residual ∫e² never grows, and the cheap residual
    change equals the difference of the two full residuals (computed with the ℓᵢℓⱼ rule)."""
    model, mix, u, meas, y = _attitude(gen, estimate_bias)
    filt = AdaptiveGaussianSumFilter(model, weight_update=GalerkinWeightUpdate(residual_diagnostics=True))
    for k in range(4):
        mix = filt.predict(mix, u, 0.1)
        d = filt.diagnostics
        w = mix.weights
        assert bool((w >= 0).all())
        assert_within(w.sum(-1), torch.ones_like(w[:, 0]), 1e-12, "sum of the Galerkin weights")
        assert_within(d["qp_kkt_residual"], 0.0, 1e-9, "KKT residual of the Galerkin QP")
        before, after, change = d["fpke_error_before"], d["fpke_error_with_rate"], d["galerkin_residual_change"]
        # the change is ≤ 0 (the QP's minimiser against w⁻) and ∫e² ≥ 0, each up to rounding of their scale
        assert_within(change.clamp_min(0.0), 0.0, 1e-12 * before, "Galerkin residual change above 0")
        assert_within(after.clamp_max(0.0), 0.0, 1e-9 * before, "∫e² below 0")
        if k == 1:
            mix = filt.update(mix, y, meas)


def test_coincident_components_keep_the_nearest_weights(gen):
    """Identical components make M singular (rank one): every split of their weight is a
    minimiser, and the update returns the one nearest w⁻ — w⁻ itself."""
    model = AttitudeModel()
    p = random_mrps(3, gen, max_norm=0.5)
    mix = GaussianMixture(
        weights=torch.tensor([[0.2, 0.3, 0.5]] * 3, dtype=F64),
        means=p.unsqueeze(-2).expand(3, 3, 3),
        covs=(1e-4 * torch.eye(3, dtype=F64)).expand(3, 3, 3, 3),
    )
    filt = AdaptiveGaussianSumFilter(model, weight_update="galerkin")
    out = filt.predict(mix, torch.tensor([0.01, -0.02, 0.03], dtype=F64).expand(3, 3), 0.1)
    err = float((out.weights - mix.weights).abs().max())
    print(f"coincident components: max |w − w⁻| = {err:.1e}")
    # the proximal term's KKT solve is conditioned to ~1e9 (GalerkinWeightUpdate): ~1e9·ε ≈ 1e-7 on weights ≤ 1
    assert_within(out.weights, mix.weights, 1e-6, "weights of coincident components")


def test_gradcheck_through_the_galerkin_qp():
    """Gradients of a forecast statistic through the Galerkin QP (the KKT solve on the optimal
    support) with respect to the drift input and the prior spread, checked by finite differences."""
    model = SineDriftModel()
    filt = AdaptiveGaussianSumFilter(model, weight_update=GalerkinWeightUpdate(quadrature=20))

    def fn(shift, scale):
        filt.reset()
        mix = GaussianMixture(
            weights=torch.tensor([0.3, 0.7], dtype=F64),
            means=torch.stack((-0.4 + shift, 0.5 + 0 * shift)).reshape(2, 1),
            covs=(scale * torch.tensor([0.5, 0.8], dtype=F64)).reshape(2, 1, 1),
        )
        for _ in range(3):
            mix = filt.predict(mix, None, 0.1)
        return (mix.weights * torch.tensor([1.0, -2.0], dtype=F64)).sum()

    args = (torch.tensor(0.05, dtype=F64, requires_grad=True), torch.tensor(1.1, dtype=F64, requires_grad=True))
    assert fn(*args).requires_grad
    assert torch.autograd.gradcheck(fn, args, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_cadence_uses_the_time_since_the_last_adaptation(gen):
    """With cadence k the update integrates the weights' rate over k·dt: on a linear model nothing
    changes; on the sine model cadence 2 at dt equals cadence 1 at 2·dt for the first adaptation."""
    model = SineDriftModel()
    mix = GaussianMixture(
        weights=torch.tensor([0.1, 0.9], dtype=F64),
        means=torch.tensor([[-0.2], [0.2]], dtype=F64),
        covs=torch.ones(2, 1, 1, dtype=F64),
    )
    every2 = AdaptiveGaussianSumFilter(model, weight_update=GalerkinWeightUpdate(cadence=2, quadrature=30))
    once = AdaptiveGaussianSumFilter(model, weight_update=GalerkinWeightUpdate(quadrature=30))
    a = every2.predict(every2.predict(mix, None, 0.05), None, 0.05)
    b = GaussianSumFilter(model).predict(GaussianSumFilter(model).predict(mix, None, 0.05), None, 0.05)
    b = b.replace(log_weights=once.weight_update(model, mix, b, None, 0.1)[0])
    assert_within(a.weights, b.weights, 1e-14, "weights with cadence 2 against cadence 1 at 2·dt")
    assert every2.weight_update.state_dict() == {"kind": "galerkin", "step": 2, "elapsed": 0.0}


# ------------------------------------------------------------------ the step as a plug-in


class _HalfwayToUniform(WeightUpdate):
    """A user-written update: move the weights halfway to uniform."""

    name = "halfway"

    def compute(self, model, prior, propagated, u, elapsed):
        w = 0.5 * propagated.weights + 0.5 / propagated.num_components
        return torch.log(w), {"moved": (w - propagated.weights).abs().sum(-1)}


def test_a_user_weight_update_plugs_in(gen):
    model, mix, u, _, _ = _attitude(gen, False)
    filt = AdaptiveGaussianSumFilter(model, weight_update=_HalfwayToUniform(cadence=2))
    one = filt.predict(mix, u, 0.1)
    assert not filt.diagnostics["weights_adapted"]
    two = filt.predict(one, u, 0.1)
    assert filt.diagnostics["weights_adapted"] and "moved" in filt.diagnostics
    # log, the logsumexp normalisation over N = 4 and exp: ~(N + 4)·ε/2 relative to each weight (≥ 1/8)
    halfway = 0.5 * one.weights + 0.5 / 4
    bound = relative_bound(halfway, 16 * torch.finfo(F64).eps, 0.0)
    assert_within(two.weights, halfway, bound, "weights moved halfway to uniform")


def test_state_dict_round_trip_and_reset(gen):
    model, mix, u, meas, y = _attitude(gen, False)
    a = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(cadence=3))
    m = a.update(a.predict(mix, u, 0.1), y, meas)
    state = a.state_dict()
    assert state["weight_update"]["step"] == 1 and torch.equal(state["weight_update"]["ref_log_weights"], m.log_weights)
    b = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(cadence=3))
    b.load_state_dict(state)
    for _ in range(3):
        ma, mb = a.predict(m, u, 0.1), b.predict(m, u, 0.1)
        assert torch.equal(ma.log_weights, mb.log_weights)
        m = ma
    a.reset()
    assert a.state_dict()["weight_update"] == {"kind": "penalty", "step": 0, "elapsed": 0.0, "ref_log_weights": None}
    assert GaussianSumFilter(model).state_dict() == {}


# ------------------------------------------------------------------ bad input


def _galerkin(**options):
    return {"weight_update": GalerkinWeightUpdate(**options)}


@pytest.mark.parametrize(
    "make, error, match",
    [
        (lambda: {"weight_update": "fancy"}, ValueError, r"one of \['galerkin', 'penalty'\]"),
        (lambda: _galerkin(reg=0.5), TypeError, "unexpected keyword argument 'reg'"),
        (lambda: _galerkin(scaling="none"), TypeError, "unexpected keyword argument 'scaling'"),
        (
            lambda: {"weight_update": GalerkinWeightUpdate(), "cadence": 2},
            TypeError,
            r"cadence configures the weight update, not the filter: pass weight_update=GalerkinWeightUpdate\(cadence=",
        ),
        (lambda: {"weight_update": "galerkin", "reg": 0.5}, TypeError, r"weight_update=PenaltyWeightUpdate\(reg="),
        (lambda: _galerkin(chunk_size=0), ValueError, "chunk_size must be a positive integer"),
        (lambda: _galerkin(chunk_size=-3), ValueError, "chunk_size must be a positive integer"),
        (lambda: _galerkin(cadence=0), ValueError, "cadence must be a positive integer"),
        (lambda: _galerkin(quadrature=(torch.zeros(5, 2), torch.full((5,), 0.2))), ValueError, r"nodes \[K, 3\]"),
        (lambda: _galerkin(quadrature=(torch.zeros(4, 3), torch.full((5,), 0.2))), ValueError, r"shapes"),
        (
            lambda: _galerkin(quadrature=(torch.full((5, 3), float("nan")), torch.full((5,), 0.2))),
            ValueError,
            "nodes must be finite",
        ),
        (
            lambda: _galerkin(quadrature=(torch.zeros(5, 3), torch.full((5,), float("inf")))),
            ValueError,
            "weights must be finite",
        ),
        (lambda: _galerkin(quadrature=(torch.zeros(5, 3), torch.full((5,), 0.3))), ValueError, "sum to 1"),
        (lambda: _galerkin(quadrature=(3, 3)), ValueError, "one point count per state axis"),
        (lambda: _galerkin(quadrature="dense"), ValueError, "quadrature must be"),
        (lambda: _galerkin(quadrature=0), ValueError, "must be ≥ 1"),
    ],
)
def test_bad_options_raise(make, error, match):
    """Bad options are refused when the update or the filter is built, naming the option; options of the
    weight update given to the filter are refused with the call that sets them."""
    with pytest.raises(error, match=match):
        AdaptiveGaussianSumFilter(AttitudeModel(), **make())


def test_bad_update_objects_raise():
    with pytest.raises(ValueError, match="tikhonov"):
        GalerkinWeightUpdate(tikhonov=-1.0)
    with pytest.raises(ValueError, match="reg must be"):
        PenaltyWeightUpdate(reg=-1.0)
    with pytest.raises(ValueError, match="residual_diagnostics"):
        GalerkinWeightUpdate(residual_diagnostics="yes")
    with pytest.raises(ValueError, match="tikhonov must be a finite number > 0"):
        GalerkinWeightUpdate(tikhonov=0.0)


def test_error_in_a_step_changes_no_state(gen):
    """A non-finite K (a NaN input reaching the drift) raises before the counter moves."""
    model = SineDriftModel()
    filt = AdaptiveGaussianSumFilter(model, weight_update=GalerkinWeightUpdate(quadrature=10))
    mix = GaussianMixture(
        weights=torch.tensor([0.5, 0.5], dtype=F64),
        means=torch.tensor([[0.0], [1.0]], dtype=F64),
        covs=torch.ones(2, 1, 1, dtype=F64),
    )
    prop = GaussianSumFilter(model).predict(mix, None, 0.1)
    bad = prop.replace(means=torch.tensor([[float("nan")], [1.0]], dtype=F64), validate=False)
    with pytest.raises((ValueError, RuntimeError)):
        filt.weight_update(model, mix, bad, None, 0.1)
    assert filt.weight_update.state_dict() == {"kind": "galerkin", "step": 0, "elapsed": 0.0}


def test_bad_state_dict_is_refused_without_change(gen):
    filt = AdaptiveGaussianSumFilter(AttitudeModel(), weight_update="galerkin")
    penalty_state = AdaptiveGaussianSumFilter(AttitudeModel()).state_dict()
    for bad in (
        {"weight_update": {"kind": "galerkin", "step": -1, "elapsed": 0.0}},
        {"weight_update": {"kind": "galerkin", "step": 1}},
        {"weight_update": {"kind": "galerkin", "step": 1, "elapsed": 0.0, "extra": 2}},
        penalty_state,  # another kind of update: refused, not half-loaded
        {"other": 1},
    ):
        with pytest.raises(ValueError):
            filt.load_state_dict(bad)
        assert filt.state_dict() == {"weight_update": {"kind": "galerkin", "step": 0, "elapsed": 0.0}}
    with pytest.raises(ValueError, match="not this 'penalty'"):
        AdaptiveGaussianSumFilter(AttitudeModel()).load_state_dict(
            {"weight_update": {"kind": "galerkin", "step": 0, "elapsed": 0.0, "ref_log_weights": None}}
        )


def test_six_n_plus_one_rule_moments():
    """The authors' rule: 6n + 1 nodes, weights summing to 1, exact moments to degree 3 and
    unit variances, but not the fourth moments (2.94 instead of 3)."""
    nodes, w = six_n_plus_one(4)
    assert nodes.shape == (25, 4) and w.shape == (25,)
    # a sum of K = 25 rounded terms is off by at most ~K·ε/2 of the sum of their magnitudes (the origin's weight is
    # −1.41: Σ|wᵢ| = 3.8), and each weight carries a few roundings of its own: K·ε·Σ|terms| holds both
    K, eps = nodes.shape[0], torch.finfo(F64).eps
    assert_within(w.sum(), 1.0, K * eps * w.abs().sum(), "sum of the 6n+1 weights")
    first_bound = K * eps * (w.abs()[:, None] * nodes.abs()).sum(0)
    assert_within((w[:, None] * nodes).sum(0), torch.zeros(4, dtype=F64), first_bound, "first moments of the 6n+1 rule")
    second = (w[:, None, None] * nodes[:, :, None] * nodes[:, None, :]).sum(0)
    assert_within(second, torch.eye(4, dtype=F64), 1e-14, "second moments of the 6n+1 rule")
    fourth = float((w * nodes[:, 0] ** 4).sum())
    ref = gauss_hermite(3, 1)
    assert_within(float((ref[1] * ref[0][:, 0] ** 4).sum()), 3.0, 1e-12, "fourth moment of 3-point Gauss–Hermite")
    assert abs(fourth - 3.0) > 0.05
    with pytest.raises(ValueError, match="dim"):
        six_n_plus_one(0)


def test_a_measurement_update_restarts_the_galerkin_interval(gen):
    """With cadence 2 and an update in between, the adaptation integrates the weights' rate over
    the time since the update (one interval), not since the last adaptation (two)."""
    model, mix, u, meas, y = _attitude(gen, False, B=4, N=3)
    seen = {}

    class Spy(GalerkinWeightUpdate):
        def compute(self, model, prior, propagated, u, elapsed):
            seen["elapsed"] = elapsed
            return super().compute(model, prior, propagated, u, elapsed)

    filt = AdaptiveGaussianSumFilter(model, weight_update=Spy(cadence=2))
    one = filt.update(filt.predict(mix, u, 0.1), y, meas)
    assert filt.weight_update.state_dict()["elapsed"] == 0.0
    filt.predict(one, u, 0.1)
    assert_within(seen["elapsed"], 0.1, 1e-15, "time since the measurement update")
