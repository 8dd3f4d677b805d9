"""Model protocol: torch.func defaults, FunctionMeasurement, LinearModel."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.models import ContinuousModel, FunctionMeasurement, LinearModel, MeasurementModel, batched_jacobian
from tests.helpers import assert_within, relative_bound


class Pendulum(ContinuousModel):
    """A user model with no closed forms: θ̈ = −sin θ − c θ̇ + u."""

    state_dim = 2

    def drift(self, x, u):
        return torch.stack((x[..., 1], -torch.sin(x[..., 0]) - 0.3 * x[..., 1] + u[..., 0]), -1)

    def noise_gain(self, x):
        return torch.stack((torch.zeros_like(x[..., 0]), 1.0 + 0.1 * x[..., 0] ** 2), -1)[..., None]

    def noise_psd(self):
        return torch.tensor([[0.5]], dtype=torch.float64)


def test_generic_jacobian_of_user_model(gen):
    model = Pendulum()
    x = torch.randn(7, 5, 2, generator=gen, dtype=torch.float64)
    u = torch.randn(5, 1, generator=gen, dtype=torch.float64)
    A = model.drift_jacobian(x, u)
    assert A.shape == (7, 5, 2, 2)
    ref = torch.zeros(7, 5, 2, 2, dtype=torch.float64)
    ref[..., 0, 1] = 1.0
    ref[..., 1, 0] = -torch.cos(x[..., 0])
    ref[..., 1, 1] = -0.3
    assert_within(A, ref, 1e-15, "torch.func Jacobian of the pendulum's drift")
    g = model.noise_gain(x)
    D = 0.5 * 0.5 * g @ g.transpose(-1, -2)
    assert_within(model.diffusion(x), D, relative_bound(D, 1e-7, 1e-7), "diffusion ½ g Q gᵀ of the pendulum")


def test_batched_jacobian_broadcasts_parameters(gen):
    W = torch.randn(4, 3, 2, generator=gen, dtype=torch.float64)  # parameters with their own batch dim
    x = torch.randn(6, 1, 2, generator=gen, dtype=torch.float64)
    J = batched_jacobian(lambda z: torch.tanh((W @ z[..., None]).squeeze(-1)), x)
    assert J.shape == (6, 4, 3, 2)
    y = (W @ x[..., None]).squeeze(-1)
    assert_within(J, (1 - torch.tanh(y) ** 2)[..., None] * W, 1e-14, "batched Jacobian of tanh(W z)")


def test_function_measurement(gen):
    meas = FunctionMeasurement(lambda x: x[..., :1] ** 2, torch.eye(1, dtype=torch.float64))
    x = torch.randn(10, 1, generator=gen, dtype=torch.float64)
    assert_within(meas.jacobian(x), 2 * x[..., None], relative_bound(2 * x[..., None], 1e-7, 1e-7), "Jacobian of x²")
    assert meas.mask() is None
    closed = FunctionMeasurement(lambda x: x**2, torch.eye(1, dtype=torch.float64), jacobian=lambda x: 2 * x[..., None])
    generic = meas.jacobian(x)
    assert_within(closed.jacobian(x), generic, relative_bound(generic, 1e-7, 1e-7), "a Jacobian given in closed form")


@pytest.mark.parametrize(
    "R, match",
    [
        (torch.ones(3), "square"),
        (torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=torch.float64), "symmetric"),
        (torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64), "positive definite"),
        (torch.tensor([[float("nan")]], dtype=torch.float64), "finite"),
    ],
)
def test_function_measurement_rejects_bad_noise(R, match):
    with pytest.raises(ValueError, match=match):
        FunctionMeasurement(lambda x: x, R)


def test_linear_model(gen):
    A = torch.tensor([[0.0, 1.0], [-2.0, -0.5]], dtype=torch.float64)
    G = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    model = LinearModel(A, G, torch.tensor([[0.3]], dtype=torch.float64), B=G)
    x = torch.randn(8, 2, generator=gen, dtype=torch.float64)
    u = torch.randn(8, 1, generator=gen, dtype=torch.float64)
    f = x @ A.T + u @ G.T
    assert_within(model.drift(x, u), f, relative_bound(f, 1e-7, 1e-7), "linear drift A x + B u")
    A_ad = ContinuousModel.drift_jacobian(model, x, u)
    assert_within(model.drift_jacobian(x, u), A_ad, relative_bound(A_ad, 1e-7, 1e-7), "linear drift Jacobian")
    with pytest.raises(ValueError, match="A must be square"):
        LinearModel(torch.ones(2, 3), G, torch.eye(1))
    with pytest.raises(ValueError, match="Q must be"):
        LinearModel(A, G, torch.eye(2))


@pytest.mark.parametrize(
    "mask, match",
    [
        (torch.ones(2, dtype=torch.bool), r"mask must have shape \[\.\.\., 3\] \(d = noise_cov's size\), got \(2,\)"),
        (torch.ones(4, 1, dtype=torch.bool), r"mask must have shape \[\.\.\., 3\]"),
        (torch.full((3,), 0.5), r"mask must be bool \(or 0/1 integers\)"),
        (torch.tensor([0, 2, 1]), r"mask must be bool \(or 0/1 integers\)"),
    ],
)
def test_function_measurement_checks_the_mask_at_construction(mask, match):
    with pytest.raises(ValueError, match=match):
        FunctionMeasurement(lambda x: x, torch.eye(3, dtype=torch.float64), mask=mask)
    ok = FunctionMeasurement(lambda x: x, torch.eye(3, dtype=torch.float64), mask=torch.tensor([1, 0, 1]))
    assert ok.mask().tolist() == [True, False, True]


def test_function_measurement_of_the_wrong_size_is_refused_before_the_update():
    """R is 1×1 but y and h(x) have 3 entries: refused at the update, naming y, before anything changes."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter

    model = LinearModel(torch.zeros(3, 3), torch.eye(3), torch.eye(3))
    mix = GaussianMixture.from_gaussian(
        torch.zeros(2, 3, dtype=torch.float64), torch.eye(3, dtype=torch.float64).expand(2, 3, 3), 2
    )
    filt = GaussianSumFilter(model)
    small_R = FunctionMeasurement(lambda x: x, torch.eye(1, dtype=torch.float64))
    with pytest.raises(
        ValueError,
        match=r"y has shape \(2, 3\): 3 entries but the measurement model predicts 1 \(d = noise_cov's size\)",
    ):
        filt.update(mix, torch.zeros(2, 3, dtype=torch.float64), small_R)
    with pytest.raises(ValueError, match=r"fn must return \[2, 1\] for states x \[2, n\]: .*d = 1 .*got \(2, 3\)"):
        small_R.predict(torch.zeros(2, 3, dtype=torch.float64))
    closed = FunctionMeasurement(
        lambda x: x, torch.eye(3, dtype=torch.float64), jacobian=lambda x: torch.ones(*x.shape[:-1], 3, 2)
    )
    with pytest.raises(ValueError, match=r"jacobian must return \[2, 3, 3\]"):
        closed.jacobian(torch.zeros(2, 3, dtype=torch.float64))


@pytest.mark.parametrize("batch", [2, 4])
def test_a_measurement_function_that_indexes_the_batch_dim_is_refused_even_where_the_shapes_agree(batch):
    """``x[:, i]`` instead of ``x[..., i]``: the filters pass ``[N, B, n]``, so with ``B = n`` the wrong function
    returns the right shape (and had given posterior means off by 1.5, silently); a probe at leading dims no state
    size can be mistaken for refuses it, before the update changes anything, whatever ``B``."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter

    model = LinearModel(torch.zeros(2, 2), torch.eye(2), torch.eye(2))
    mix = GaussianMixture.from_gaussian(
        torch.full((batch, 2), 3.0, dtype=torch.float64), 0.1 * torch.eye(2, dtype=torch.float64).expand(batch, 2, 2), 3
    )
    filt = GaussianSumFilter(model)
    wrong = FunctionMeasurement(
        lambda x: torch.atan2(x[:, 1], x[:, 0]).unsqueeze(-1), 1e-2 * torch.eye(1, dtype=torch.float64)
    )
    y = torch.full((batch, 1), 0.5, dtype=torch.float64)
    # B = 4: the filters' own shapes tell; B = 2 = n: only the probe does
    probe = r"act on every state of x \[\.\.\., n\] alike .*on states \[1, 2, 3, 2, n\] it returned \(1, 3, 2, 2, 1\)"
    message = r"return \[3, 4, 1\] for states x \[3, 4, n\]" if batch == 4 else probe
    with pytest.raises(ValueError, match=rf"fn must {message}.*index the state as x\[\.\.\., i\], not x\[:, i\]"):
        filt.update(mix, y, wrong)
    right = FunctionMeasurement(lambda x: torch.atan2(x[..., 1], x[..., 0]).unsqueeze(-1), wrong.R)
    posterior = filt.update(mix, y, right)  # the same function written elementwise is accepted
    assert torch.isfinite(posterior.means).all()


def test_model_input_size_is_checked_when_declared():
    class Driven(Pendulum):
        input_dim = 1

    x = torch.zeros(4, 2, dtype=torch.float64)
    Driven().check_input(torch.zeros(4, 1))
    with pytest.raises(ValueError, match=r"u must have shape \[\.\.\., 1\] \(Driven's input\), got \(4, 2\)"):
        Driven().check_input(torch.zeros(4, 2))
    with pytest.raises(ValueError, match=r"Driven needs an input u \[\.\.\., 1\], got None"):
        Driven().check_input(None)
    Pendulum().check_input(torch.zeros(4, 7))  # not declared: the model's own business
    assert Pendulum().drift(x, torch.zeros(4, 1)).shape == (4, 2)


def _broken(**overrides):
    """The test helpers' CubicDrift with methods replaced (a user's mistakes)."""
    from tests.helpers import CubicDrift

    return type("Broken", (CubicDrift,), overrides)()


@pytest.mark.parametrize(
    ("overrides", "error", "match"),
    [
        (
            {"drift": lambda self, x, u=None: x.sum(-1)},
            ValueError,
            r"Broken\.drift must return \[\.\.\., n\] = \(2, 3, 1\)",
        ),
        ({"drift": lambda self, x, u=None: "f"}, ValueError, r"Broken\.drift must return .* got str"),
        (
            {"noise_gain": lambda self, x: torch.ones_like(x)},
            ValueError,
            r"Broken\.noise_gain must return \[\.\.\., n, q\]",
        ),
        (
            {"noise_psd": lambda self: torch.ones(2, 2, dtype=torch.float64)},
            ValueError,
            r"noise_psd must return \[q, q\] = \(1, 1\)",
        ),
        (
            {"noise_psd": lambda self: torch.full((1, 1), -0.25, dtype=torch.float64)},
            ValueError,
            r"positive semidefinite",
        ),
        (
            {"noise_psd": lambda self: torch.full((1, 1), float("nan"), dtype=torch.float64)},
            ValueError,
            r"Broken\.noise_psd has non-finite entries",
        ),
        ({"noise_psd": ContinuousModel.noise_psd}, NotImplementedError, r"Broken must implement noise_psd\(\)"),
        ({"noise_gain": ContinuousModel.noise_gain}, NotImplementedError, r"Broken must implement noise_gain\(x\)"),
    ],
)
@pytest.mark.parametrize("kind", ["gsf", "penalty"])
def test_a_model_breaking_its_contract_is_refused_at_the_first_predict_naming_the_method(overrides, error, match, kind):
    """A user's model whose drift, noise gain or noise density has the wrong shape (a raw broadcasting error
    deep in the propagation), a negative density (accepted and integrated) or a missing method (a bare
    NotImplementedError) is refused at the first predict, naming the method and the shapes, before anything
    changes."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import AdaptiveGaussianSumFilter, GaussianSumFilter

    model = _broken(**overrides)
    filt = GaussianSumFilter(model) if kind == "gsf" else AdaptiveGaussianSumFilter(model)
    mix = GaussianMixture.from_gaussian(
        torch.zeros(2, 1, dtype=torch.float64), 0.1 * torch.ones(2, 1, 1, dtype=torch.float64), 3
    )
    before = filt.state_dict() if kind != "gsf" else None
    with pytest.raises(error, match=match):
        filt.predict(mix, None, 0.1)
    if before is not None:
        assert filt.state_dict() == before


@pytest.mark.parametrize("state_dim", [None, 0, -1, 1.5, True, "3"])
def test_a_model_without_a_positive_integer_state_dim_is_refused_at_construction(state_dim):
    from agsf_torch.filters import GaussianSumFilter
    from tests.helpers import CubicDrift

    if state_dim is None:  # no attribute at all: the subclass forgot it (the base class only annotates it)
        methods = {k: getattr(CubicDrift, k) for k in ("drift", "noise_gain", "noise_psd")}
        model = type("Broken", (ContinuousModel,), methods)()
    else:
        model = _broken(state_dim=state_dim)
    with pytest.raises(ValueError, match=r"Broken\.state_dim must be a positive integer"):
        GaussianSumFilter(model)


class _Direct(MeasurementModel):
    """A user's measurement subclass ``y = x + v`` with the noise covariance ``R`` given."""

    def __init__(self, R):
        super().__init__()
        self.R = R

    def predict(self, x):
        return x

    def noise_cov(self):
        return self.R


@pytest.mark.parametrize(
    ("R", "match"),
    [
        (
            torch.full((1, 1), -0.01, dtype=torch.float64),
            r"_Direct\.noise_cov must be a covariance, with a non-negative diagonal, got diagonal \[-0\.01\]",
        ),
        (torch.full((1, 1), float("nan"), dtype=torch.float64), r"_Direct\.noise_cov has non-finite entries"),
        (torch.eye(2, dtype=torch.float64), r"_Direct\.noise_cov must be \[d, d\] or \[\.\.\., d, d\] with d = 1"),
        (torch.ones(1, dtype=torch.float64), r"_Direct\.noise_cov must be \[d, d\]"),
    ],
)
def test_a_measurement_subclass_with_a_bad_noise_covariance_is_refused_naming_it(R, match):
    """A negative variance was reported as 'covariance is not positive definite in the measurement update', a
    wrong size as a raw cholesky_solve error: the filters' check of the measurement names noise_cov."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter
    from tests.helpers import CubicDrift

    mix = GaussianMixture.from_gaussian(
        torch.zeros(2, 1, dtype=torch.float64), 0.1 * torch.ones(2, 1, 1, dtype=torch.float64), 3
    )
    with pytest.raises(ValueError, match=match):
        GaussianSumFilter(CubicDrift()).update(mix, torch.zeros(2, 1, dtype=torch.float64), _Direct(R))


def test_an_indefinite_noise_covariance_with_a_non_negative_diagonal_is_refused_and_a_singular_one_accepted():
    """``R`` with eigenvalues −0.06 and 0.14 (variances 0.04 and 0.04, covariance 0.1): blamed on the state covariance
    ('not positive definite in the measurement update … repair_covariance'), and with the repair accepted, returning
    a posterior eigenvalue of 1e-13.  It is refused, naming noise_cov and its eigenvalue, before the state moves; a
    positive semidefinite singular R (an exact measurement of one combination) and R = 0 still pass the check."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter

    model = LinearModel(torch.zeros(2, 2), torch.eye(2), torch.eye(2))
    mix = GaussianMixture.from_gaussian(torch.zeros(2, 2, dtype=torch.float64), torch.eye(2).expand(2, 2, 2), 2)
    y = torch.zeros(2, 2, dtype=torch.float64)
    indefinite = torch.tensor([[0.04, 0.1], [0.1, 0.04]], dtype=torch.float64)
    for repair in (False, True):
        with pytest.raises(
            ValueError, match=r"_Direct\.noise_cov must be a covariance, positive semidefinite, .* -0\.06"
        ):
            GaussianSumFilter(model, repair_covariance=repair).update(mix, y, _Direct(indefinite))
    for dtype in (torch.float64, torch.float32):  # R = 0 in float32 too (a floor of tiny had been flushed to 0)
        for R in (
            torch.tensor([[1.0, 1.0], [1.0, 1.0]]),
            torch.zeros(2, 2),
            torch.zeros(2, 2, 2),
            1e-30 * torch.eye(2),
        ):
            assert torch.equal(_Direct(R.to(dtype)).check_measurement(y.to(dtype)), y.to(dtype))
    with pytest.raises(ValueError, match=r"positive semidefinite"):  # a zero diagonal with off-diagonal entries
        _Direct(torch.tensor([[0.0, 1e-3], [1e-3, 0.0]], dtype=torch.float64)).check_measurement(y)


def test_a_noise_covariance_symmetric_to_rounding_is_accepted_and_one_that_is_not_refused(gen):
    """``R = AAᵀ`` as a user computes it is symmetric only to rounding: accepted; an asymmetric one is not."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter
    from tests.helpers import CubicDrift

    A = torch.randn(2, 2, generator=gen, dtype=torch.float64)
    R = A @ A.T + 0.1 * torch.eye(2, dtype=torch.float64)
    R[0, 1] = R[0, 1] * (1 + 1e-15)  # rounding
    mix = GaussianMixture.from_gaussian(
        torch.zeros(3, 2, dtype=torch.float64), 0.1 * torch.eye(2, dtype=torch.float64).expand(3, 2, 2), 2
    )

    class Plane(CubicDrift):
        state_dim = 2

    y = torch.zeros(3, 2, dtype=torch.float64)
    GaussianSumFilter(Plane()).update(mix, y, _Direct(R))
    R[0, 1] += 0.5
    with pytest.raises(ValueError, match=r"_Direct\.noise_cov is not symmetric"):
        GaussianSumFilter(Plane()).update(mix, y, _Direct(R))


@pytest.mark.parametrize("components", [2, 3])
def test_a_drift_that_indexes_the_component_dim_is_refused_even_where_the_shapes_agree(components):
    """Van der Pol written with ``x[:, i]``: the filters pass means ``[B, N, n]``, so with ``N = n`` the wrong drift
    returns the right shape (and had propagated means off by 1.6, silently); the contract check's probe refuses it
    at the first ``predict``, before anything changes, for every ``N``."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter

    class VanDerPol(ContinuousModel):
        state_dim = 2

        def __init__(self, index) -> None:
            super().__init__()
            self.index = index

        def drift(self, x, u=None):
            x1, x2 = self.index(x, 0), self.index(x, 1)
            return torch.stack([x2, (1 - x1**2) * x2 - x1], -1)

        def noise_gain(self, x):
            return torch.stack([torch.zeros_like(x[..., 0]), torch.ones_like(x[..., 0])], -1).unsqueeze(-1)

        def noise_psd(self):
            return torch.tensor([[0.2]], dtype=torch.float64)

    mix = GaussianMixture.from_gaussian(
        torch.full((4, 2), 2.0, dtype=torch.float64),
        0.1 * torch.eye(2, dtype=torch.float64).expand(4, 2, 2),
        components,
    )
    wrong = GaussianSumFilter(VanDerPol(lambda x, i: x[:, i]))
    with pytest.raises(
        ValueError, match=r"VanDerPol.drift must return .*index the state as x\[\.\.\., i\], not x\[:, i\]"
    ):
        wrong.predict(mix, None, 0.05)
    right = GaussianSumFilter(VanDerPol(lambda x, i: x[..., i])).predict(mix, None, 0.05)
    assert torch.isfinite(right.means).all()


def test_a_model_holding_float64_tensors_given_a_float32_mixture_is_refused_naming_the_dtypes():
    """A user's model with a float64 matrix and a mixture built in float32 (``torch.zeros`` without a dtype) failed
    inside torch ('expected m1 and m2 to have the same dtype'); the contract check names both dtypes and the two
    fixes.  The library's own models cast their parameters and run in float32 as before."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter

    class Matrix(ContinuousModel):
        state_dim = 2

        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("A", torch.tensor([[0.0, 1.0], [-1.0, -0.1]], dtype=torch.float64))

        def drift(self, x, u=None):
            return x @ self.A.T

        def noise_gain(self, x):
            return torch.ones(*x.shape[:-1], 2, 1, dtype=x.dtype)

        def noise_psd(self):
            return torch.eye(1, dtype=torch.float64)

    mix32 = GaussianMixture.from_gaussian(torch.zeros(3, 2), torch.eye(2).expand(3, 2, 2), 2)
    with pytest.raises(
        ValueError,
        match=r"Matrix failed on the mixture's torch\.float32 states while holding torch\.float64 tensors .*"
        r"build the mixture in float64 .* or convert the model \(model\.to\(torch\.float32\)\)",
    ):
        GaussianSumFilter(Matrix()).predict(mix32, None, 0.1)
    assert GaussianSumFilter(Matrix().to(torch.float32)).predict(mix32, None, 0.1).means.dtype == torch.float32
    linear = LinearModel(torch.tensor([[0.0, 1.0], [-1.0, -0.1]]), torch.ones(2, 1), torch.eye(1))
    assert GaussianSumFilter(linear).predict(mix32, None, 0.1).means.dtype == torch.float32


def test_the_linear_models_input_is_refused_without_b_and_checked_against_b():
    """Without an input matrix an input was ignored without a word (u = 100 moved nothing); with ``B [n, m]`` a
    wrong-sized input was a raw matmul error.  Now the first is refused, the second names ``m``, and ``B u`` is the
    drift's input term."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import ExtendedKalmanFilter

    A, G, Q = [[0.0, 1.0], [-4.0, -0.4]], [[0.0], [1.0]], [[0.5]]
    mix = GaussianMixture.from_gaussian(torch.zeros(3, 2, dtype=torch.float64), torch.eye(2).expand(3, 2, 2), 1)
    with pytest.raises(ValueError, match=r"LinearModel has no input matrix B, got an input u of shape \(3, 1\)"):
        ExtendedKalmanFilter(LinearModel(A, G, Q)).predict(mix, torch.full((3, 1), 100.0), 0.1)
    driven = LinearModel(A, G, Q, B=[[0.0], [1.0]])
    assert driven.input_dim == 1
    with pytest.raises(ValueError, match=r"u must have shape \[\.\.\., 1\] \(LinearModel's input\), got \(3, 2\)"):
        ExtendedKalmanFilter(driven).predict(mix, torch.ones(3, 2), 0.1)
    x, u = torch.tensor([[1.0, 2.0]], dtype=torch.float64), torch.tensor([[3.0]], dtype=torch.float64)
    expected = torch.tensor([[2.0, -4.0 - 0.8 + 3.0]], dtype=torch.float64)
    assert_within(driven.drift(x, u), expected, relative_bound(expected, 1e-15, 0.0), "drift A x + B u")


def test_a_drift_written_for_the_filters_exact_shapes_is_refused_naming_the_probe():
    """A drift that only works on ``[B, N, n]`` (an einsum over named dims with per-trajectory matrices) fails on the
    probe's states: a ``ValueError`` naming the method, the probe's shape and the rule, not a raw einsum error."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter

    class Exact(ContinuousModel):
        state_dim = 2

        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("A", -torch.eye(2, dtype=torch.float64).expand(4, 2, 2).clone())

        def drift(self, x, u=None):
            return torch.einsum("bij,bnj->bni", self.A, x)

        def noise_gain(self, x):
            return torch.ones(*x.shape[:-1], 2, 1, dtype=x.dtype)

        def noise_psd(self):
            return torch.eye(1, dtype=torch.float64)

    mix = GaussianMixture.from_gaussian(torch.zeros(4, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64), 3)
    with pytest.raises(
        ValueError, match=r"Exact\.drift failed on states \[1, 2, 4, 3, n\] \(RuntimeError: .*act on every state"
    ):
        GaussianSumFilter(Exact()).predict(mix, None, 0.1)


@pytest.mark.parametrize("batch", [2, 4])
def test_a_measurement_subclass_whose_predict_indexes_the_batch_dim_is_refused_once(batch):
    """A user's ``MeasurementModel`` subclass with ``predict`` written as ``x[:, 0]``: with ``B = n`` the filters' own
    call returns the right shape and wrong numbers; the first update probes ``predict`` once per measurement object
    and refuses it naming the fix, before anything changes; the elementwise one passes and is not probed again."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter

    class Position(MeasurementModel):
        def __init__(self, index) -> None:
            super().__init__()
            self.index = index

        def predict(self, x):
            return self.index(x).unsqueeze(-1)

        def noise_cov(self):
            return torch.full((1, 1), 0.01, dtype=torch.float64)

    model = LinearModel(torch.zeros(2, 2), torch.eye(2), torch.eye(2))
    mix = GaussianMixture.from_gaussian(torch.ones(batch, 2, dtype=torch.float64), torch.eye(2).expand(batch, 2, 2), 3)
    y = torch.zeros(batch, 1, dtype=torch.float64)
    filt = GaussianSumFilter(model)
    with pytest.raises(ValueError, match=r"Position\.predict (must act on every state|failed on states)"):
        filt.update(mix, y, Position(lambda x: x[:, 0]))
    right = Position(lambda x: x[..., 0])
    filt.update(mix, y, right)
    assert right.elementwise_checked is True


def test_closed_form_jacobians_are_probed_like_the_functions_they_differentiate():
    """A drift Jacobian or a measurement Jacobian written in closed form with ``x[:, i]`` (the functions themselves
    elementwise) linearised every component at the wrong state where the shapes coincide (``N = n``, ``B = n``);
    both are refused at their first use, before anything changes."""
    from agsf_torch import GaussianMixture
    from agsf_torch.filters import GaussianSumFilter

    class Pendulum2(ContinuousModel):
        state_dim = 2

        def drift(self, x, u=None):
            return torch.stack((x[..., 1], -torch.sin(x[..., 0])), -1)

        def drift_jacobian(self, x, u=None):
            zero, one = torch.zeros_like(x[:, 0]), torch.ones_like(x[:, 0])  # x[:, 0]: the wrong axis
            return torch.stack((zero, one, -torch.cos(x[:, 0]), zero), -1).unflatten(-1, (2, 2))

        def noise_gain(self, x):
            return torch.ones(*x.shape[:-1], 2, 1, dtype=x.dtype)

        def noise_psd(self):
            return torch.eye(1, dtype=torch.float64)

    class Angle(MeasurementModel):
        def predict(self, x):
            return x[..., :1]

        def jacobian(self, x):
            return torch.stack((torch.ones_like(x[:, 0]), torch.zeros_like(x[:, 0])), -1).unsqueeze(-2)

        def noise_cov(self):
            return torch.full((1, 1), 0.01, dtype=torch.float64)

    mix = GaussianMixture.from_gaussian(torch.ones(2, 2, dtype=torch.float64), torch.eye(2).expand(2, 2, 2), 2)
    with pytest.raises(ValueError, match=r"Pendulum2\.drift_jacobian"):
        GaussianSumFilter(Pendulum2()).predict(mix, None, 0.1)
    with pytest.raises(ValueError, match=r"Angle\.jacobian must act on every state"):
        GaussianSumFilter(LinearModel(torch.zeros(2, 2), torch.eye(2), torch.eye(2))).update(
            mix, torch.zeros(2, 1, dtype=torch.float64), Angle()
        )
