"""FPKE residual: zero for exact linear-Gaussian propagation, equal to a finite-difference
evaluation of ∂p/∂t − L_FP(p) for nonlinear models; closed forms equal torch.func."""

from __future__ import annotations

import warnings

import pytest
import torch

from agsf_torch.fpke import ComponentRates, fpke_matrix, fpke_residual, galerkin_matrices
from agsf_torch.models import AttitudeModel, ContinuousModel
from agsf_torch.propagation import moment_derivatives
from agsf_torch.quadrature import gauss_hermite
from tests import linear_system as ls
from tests.helpers import F64, assert_within, relative_bound
from tests.models.test_base import Pendulum


class GenericAttitude(ContinuousModel):
    """The attitude model seen only through drift / noise_gain / noise_psd (all derivatives by torch.func)."""

    def __init__(self, inner: AttitudeModel):
        super().__init__()
        self.inner = inner
        self.state_dim = inner.state_dim

    def drift(self, x, u):
        return self.inner.drift(x, u)

    def noise_gain(self, x):
        return self.inner.noise_gain(x)

    def noise_psd(self):
        return self.inner.noise_psd()


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_attitude_closed_forms_match_torch_func(gen, estimate_bias):
    model = AttitudeModel(estimate_bias=estimate_bias, sigma_v=3e-4, sigma_u=2e-5)
    x = 0.6 * torch.randn(40, 6, generator=gen, dtype=F64)[:, : model.state_dim]
    u = torch.randn(40, 3, generator=gen, dtype=F64)
    a, g = model.fokker_planck_terms(x, u), GenericAttitude(model).fokker_planck_terms(x, u)
    for name in a.__dataclass_fields__:
        A, G = getattr(a, name), getattr(g, name)
        if name == "diffusion":  # the closed form returns the diagonal of a diagonal D
            A = torch.diag_embed(A)
        scale = max(float(G.abs().max()), 1e-300)
        assert_within(A, G, 1e-10 * scale, f"Fokker–Planck term {name}: closed form against torch.func")


def _rates(model, mean, cov, u):
    r = moment_derivatives(model, mean, cov, u)
    return ComponentRates(mean, torch.linalg.cholesky(cov), r.mean_rate, r.cov_rate)


def test_linear_sde_exact_moments_have_zero_residual(gen):
    model = ls.model()
    mean = torch.randn(4, 2, 3, generator=gen, dtype=F64)
    A = torch.randn(4, 2, 3, 3, generator=gen, dtype=F64)
    cov = A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=F64)
    u = torch.randn(4, 1, generator=gen, dtype=F64)
    rates = _rates(model, mean, cov, u.unsqueeze(-2))
    x = mean[:, :1] + 2.0 * torch.randn(4, 50, 3, generator=gen, dtype=F64)
    e = fpke_residual(model, x, u, torch.log(torch.tensor([[0.3, 0.7]] * 4, dtype=F64)), rates)
    assert float(e.abs().max()) < 1e-13  # pdf values here are O(1e-2): the residual is rounding


def _fd_residual(model, x, u, mean, cov):
    """∂p/∂t − L_FP(p) for p = N(μ, P) by central finite differences (time via μ̇, Ṗ; space via x),
    Richardson-extrapolated in the spatial step: error O((h/σ)⁴) ≈ 1e-8 with h = 0.01σ, rounding
    ε(σ/h)² ≈ 1e-12."""
    h = 1e-2 * float(cov.diagonal().sqrt().min())
    return (4.0 * _fd_residual_at(model, x, u, mean, cov, h / 2) - _fd_residual_at(model, x, u, mean, cov, h)) / 3.0


def _fd_residual_at(model, x, u, mean, cov, h):
    r = moment_derivatives(model, mean, cov, u)
    n = x.shape[-1]

    def pdf(z, m=mean, P=cov):
        return torch.exp(torch.distributions.MultivariateNormal(m, P).log_prob(z))

    eps = 1e-6
    dp_dt = (
        pdf(x, mean + eps * r.mean_rate, cov + eps * r.cov_rate)
        - pdf(x, mean - eps * r.mean_rate, cov - eps * r.cov_rate)
    ) / (2 * eps)
    eye = torch.eye(n, dtype=F64)

    def fp(z):
        return model.drift(z, u) * pdf(z)[..., None]

    def Dp(z):
        return model.diffusion(z) * pdf(z)[..., None, None]

    div = sum((fp(x + h * eye[j])[..., j] - fp(x - h * eye[j])[..., j]) / (2 * h) for j in range(n))
    second = 0.0
    for j in range(n):
        for k in range(n):
            second = second + (
                Dp(x + h * eye[j] + h * eye[k])[..., j, k]
                - Dp(x + h * eye[j] - h * eye[k])[..., j, k]
                - Dp(x - h * eye[j] + h * eye[k])[..., j, k]
                + Dp(x - h * eye[j] - h * eye[k])[..., j, k]
            ) / (4 * h * h)
    return dp_dt - (-div + second)


@pytest.mark.parametrize("which", ["pendulum", "attitude3", "attitude6"])
def test_residual_matches_finite_differences(gen, which):
    if which == "pendulum":
        model, n = Pendulum(), 2
        u = torch.tensor([0.3], dtype=F64)
        mean = torch.tensor([0.4, -0.2], dtype=F64)
        cov = torch.tensor([[0.2, 0.05], [0.05, 0.1]], dtype=F64)
    else:
        model = AttitudeModel(estimate_bias=which == "attitude6", sigma_v=0.05, sigma_u=0.02)
        n = model.state_dim
        u = torch.tensor([0.3, -0.2, 0.5], dtype=F64)
        mean = torch.tensor([0.1, -0.2, 0.15, 0.01, 0.02, -0.01], dtype=F64)[:n]
        cov = torch.diag(torch.tensor([0.01, 0.02, 0.015, 0.004, 0.003, 0.005], dtype=F64)[:n])
    x = mean + 1.5 * cov.diagonal().sqrt() * torch.randn(20, n, generator=gen, dtype=F64)
    e = fpke_residual(model, x, u, torch.zeros(1, dtype=F64), _rates(model, mean[None], cov[None], u))
    ref = _fd_residual(model, x, u, mean, cov)
    bound = relative_bound(ref, 1e-6, 1e-7 * float(ref.abs().max()))
    assert_within(e, ref, bound, "FPKE residual against finite differences")


def test_residual_matches_autograd_operator(gen):
    """The same identity with exact derivatives (torch.func) instead of differences: to rounding."""
    model = Pendulum()
    u = torch.tensor([0.3], dtype=F64)
    mean = torch.tensor([0.4, -0.2], dtype=F64)
    cov = torch.tensor([[0.2, 0.05], [0.05, 0.1]], dtype=F64)
    x = mean + 0.5 * torch.randn(10, 2, generator=gen, dtype=F64)
    e = fpke_residual(model, x, u, torch.zeros(1, dtype=F64), _rates(model, mean[None], cov[None], u))
    r = moment_derivatives(model, mean, cov, u)

    def pdf(z, m=mean, P=cov):
        return torch.exp(torch.distributions.MultivariateNormal(m, P).log_prob(z))

    def operator(z):
        """The operator's three terms ∂p/∂t, ∇·(fp) and ∇∇:(Dp)."""
        dp_dt = torch.func.jvp(lambda m, P: pdf(z, m, P), (mean, cov), (r.mean_rate, r.cov_rate))[1]
        div = torch.func.jacfwd(lambda v: model.drift(v, u) * pdf(v))(z).diagonal().sum()
        Hs = torch.func.jacfwd(torch.func.jacfwd(lambda v: model.diffusion(v) * pdf(v)))(z)
        return torch.stack((dp_dt, div, -torch.einsum("jkjk->", Hs)))

    terms = torch.stack([operator(z) for z in x])
    ref = terms.sum(-1)
    # both sides round to a few ε of the terms that cancel in the residual (≲ 10 here, the residual ≳ 1e-4)
    bound = relative_bound(ref, 1e-12, 16 * torch.finfo(F64).eps * terms.abs().sum(-1))
    assert_within(e, ref, bound, "FPKE residual against the autograd operator")


def _grid_residuals(gen):
    """Three attitude components and their pointwise residuals ``Lⱼ(x)`` on a fine grid covering ±7σ."""
    model = AttitudeModel(sigma_v=0.05)
    N = 3
    mean = 0.05 * torch.randn(N, 3, generator=gen, dtype=F64)
    cov = torch.diag_embed(0.002 + 0.002 * torch.rand(N, 3, generator=gen, dtype=F64))
    u = torch.tensor([0.3, -0.2, 0.5], dtype=F64)
    rates = _rates(model, mean, cov, u)
    g = torch.linspace(-0.4, 0.4, 121, dtype=F64)
    X = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    dv = float(g[1] - g[0]) ** 3
    one = lambda i: ComponentRates(
        *(t[i : i + 1] for t in (rates.means, rates.chol, rates.mean_rates, rates.cov_rates))
    )  # noqa: E731
    Ls = torch.stack([fpke_residual(model, X, u, torch.zeros(1, dtype=F64), one(i)) for i in range(N)])
    return model, mean, cov, u, rates, X, dv, Ls


def test_fpke_matrix_equals_brute_force_integral(gen):
    """L_ij by the product-Gaussian identity + exact Gauss–Hermite equals a dense grid integral."""
    model, mean, cov, u, rates, X, dv, Ls = _grid_residuals(gen)
    nodes, w = gauss_hermite(7, 3)
    Lm = fpke_matrix(model, u, rates, nodes, w).full()
    ref = (Ls[:, None, :] * Ls[None, :, :]).sum(-1) * dv
    assert_within(Lm, ref, relative_bound(ref, 1e-4, 1e-6 * float(ref.abs().max())), "L against the grid integral")


def _six_state_rates(gen):
    model = AttitudeModel(estimate_bias=True, sigma_v=0.05, sigma_u=0.02)
    N = 3
    mean = torch.cat(
        (0.1 * torch.randn(2, N, 3, generator=gen, dtype=F64), 0.01 * torch.randn(2, N, 3, generator=gen, dtype=F64)),
        -1,
    )
    A = torch.randn(2, N, 6, 6, generator=gen, dtype=F64)
    cov = 0.003 * (A @ A.transpose(-1, -2) / 6 + 0.2 * torch.eye(6, dtype=F64))
    u = torch.tensor([[0.3, -0.2, 0.5], [0.1, 0.4, -0.3]], dtype=F64)
    return model, u, _rates(model, mean, cov, u.unsqueeze(-2))


def test_six_state_rule_against_dense_quadrature(gen):
    """The exact 9261-node rule (7,7,7,3,3,3) against a dense 91,125-node (9,9,9,5,5,5) reference
    with correlated MRP/bias covariances: both integrate ℓᵢℓⱼ exactly, so they agree to rounding."""
    model, u, rates = _six_state_rates(gen)
    fast = fpke_matrix(model, u, rates, *gauss_hermite(model.fpke_quadrature_points())).full()
    dense = fpke_matrix(model, u, rates, *gauss_hermite((9, 9, 9, 5, 5, 5))).full()
    rel = float(((fast - dense).abs() / dense.abs().amax((-2, -1), keepdim=True)).max())
    print(f"6-D exact rule vs dense reference: max relative difference {rel:.2e}")
    bound = 1e-6 * dense.abs().amax((-2, -1), keepdim=True)  # 1e-6 of each matrix's largest entry
    assert_within(fast, dense, bound, "L by the exact 6-D rule against the dense rule")
    # one point fewer per bias axis is no longer exact: the test can tell
    coarse = fpke_matrix(model, u, rates, *gauss_hermite((7, 7, 7, 2, 2, 2))).full()
    with pytest.raises(AssertionError, match="entries outside the bound"):
        assert_within(coarse, dense, bound, "L by the inexact 6-D rule against the dense rule")


def test_smolyak_rule_for_generic_six_state(gen):
    """The generic 6-D default (Smolyak level 7, exact to total degree 13) on the same integrals."""
    from agsf_torch.quadrature import smolyak_gauss_hermite

    model, u, rates = _six_state_rates(gen)
    dense = fpke_matrix(model, u, rates, *gauss_hermite((9, 9, 9, 5, 5, 5))).full()
    sparse = fpke_matrix(model, u, rates, *smolyak_gauss_hermite(6, 7)).full()
    rel = float(((sparse - dense).abs() / dense.abs().amax((-2, -1), keepdim=True)).max())
    print(f"6-D Smolyak level 7 vs dense reference: max relative difference {rel:.2e}")
    bound = 1e-6 * dense.abs().amax((-2, -1), keepdim=True)  # 1e-6 of each matrix's largest entry
    assert_within(sparse, dense, bound, "L by the Smolyak rule against the dense rule")


def test_three_state_rule_against_dense_quadrature(gen):
    model = AttitudeModel(sigma_v=0.05)
    mean = 0.1 * torch.randn(2, 4, 3, generator=gen, dtype=F64)
    cov = torch.diag_embed(0.005 + 0.01 * torch.rand(2, 4, 3, generator=gen, dtype=F64))
    u = torch.tensor([[0.3, -0.2, 0.5], [0.1, 0.4, -0.3]], dtype=F64)
    rates = _rates(model, mean, cov, u.unsqueeze(-2))
    exact = fpke_matrix(model, u, rates, *gauss_hermite(7, 3)).full()
    dense = fpke_matrix(model, u, rates, *gauss_hermite(15, 3)).full()
    bound = relative_bound(dense, 1e-10, 1e-12 * float(dense.abs().max()))
    assert_within(exact, dense, bound, "L by the exact 3-D rule against a 15-point rule")


# ------------------------------------------------------------- Galerkin matrices (method.md §3b)


def test_galerkin_matrices_equal_brute_force_integrals(gen):
    """M_ij = ∫pᵢpⱼ and K_ij = ∫pᵢLⱼ by the product-Gaussian identity and the exact 4-point rule
    equal dense grid integrals of the pointwise densities and residuals."""
    model, mean, cov, u, rates, X, dv, Ls = _grid_residuals(gen)
    G = galerkin_matrices(model, u, rates, *gauss_hermite(model.fpke_quadrature_points(1)))
    scale = torch.exp(G.log_scale)
    dens = torch.stack([torch.distributions.MultivariateNormal(mean[i], cov[i]).log_prob(X).exp() for i in range(3)])
    M_ref = (dens[:, None, :] * dens[None, :, :]).sum(-1) * dv
    K_ref = (dens[:, None, :] * Ls[None, :, :]).sum(-1) * dv
    # M_ij = ∫pᵢpⱼ > 0: the grid integral's error is relative to it
    assert_within(G.mass * scale, M_ref, 1e-6 * M_ref, "mass matrix against the grid integral")
    bound = relative_bound(K_ref, 1e-4, 1e-6 * float(K_ref.abs().max()))
    assert_within(G.drift * scale, K_ref, bound, "drift matrix against the grid integral")


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_galerkin_rule_is_exact_for_attitude(gen, estimate_bias):
    """The declared rule for ℓⱼ — (4,4,4) / (4,4,4,2,2,2), 64 / 512 nodes — equals the closed-form route
    (Gaussian moments, no quadrature) to rounding, and one point fewer per axis is measurably inexact.

    Rounding: ℓ at a node ``x = m + Lξ`` sums terms of size ``‖Π‖‖Ṗ‖ n|ξ|²`` (``zᵀṖz``, ``tr ΠṖ``, …),
    the scale of ``max |K|``; over ``K`` nodes the quadrature rounds to ``K n ξ²_max ε`` of it, and the
    tolerance is 64× that.  The components' covariances span one decade (P ~ 1e-3 … 1e-2), where the
    rule's truncation error, were it inexact, is orders of magnitude above rounding (P ~ 1e-10 would
    hide it under the rounding of ``Π ~ 1e10``)."""
    if estimate_bias:
        model, u, rates = _six_state_rates(gen)
        coarse_pts = (3, 3, 3, 2, 2, 2)
    else:
        model = AttitudeModel(sigma_v=0.05)
        mean = 0.1 * torch.randn(2, 4, 3, generator=gen, dtype=F64)
        A = torch.randn(2, 4, 3, 3, generator=gen, dtype=F64)
        scale = 10.0 ** (-3 + torch.rand(2, 4, 1, 1, generator=gen, dtype=F64))  # P ~ 1e-3 … 1e-2
        cov = scale * (A @ A.transpose(-1, -2) / 3 + 0.2 * torch.eye(3, dtype=F64))
        cov = 0.5 * (cov + cov.transpose(-1, -2))
        u = torch.tensor([[0.3, -0.2, 0.5], [0.1, 0.4, -0.3]], dtype=F64)
        rates = _rates(model, mean, cov, u.unsqueeze(-2))
        coarse_pts = (3, 3, 3)
    closed = galerkin_matrices(model, u, rates, fused=False)
    exact_pts = model.fpke_quadrature_points(1)
    nodes, _ = gauss_hermite(exact_pts)
    K = {
        name: galerkin_matrices(model, u, rates, *gauss_hermite(pts))
        for name, pts in (("exact", exact_pts), ("coarse", coarse_pts))
    }
    rel = lambda a: float(((K[a].drift - closed.drift).abs() / closed.drift.abs().amax((-2, -1), keepdim=True)).max())  # noqa: E731
    n = model.state_dim
    tol = 64 * nodes.shape[0] * n * float((nodes * nodes).sum(-1).max()) * torch.finfo(F64).eps
    print(
        f"Galerkin K against the closed form: exact rule {rel('exact'):.2e} (tolerance {tol:.1e}), one point fewer {rel('coarse'):.2e}"
    )
    bound = tol * closed.drift.abs().amax((-2, -1), keepdim=True)  # relative to each matrix's largest entry
    assert_within(K["exact"].drift, closed.drift, bound, "K by the declared rule against the closed form")
    with pytest.raises(AssertionError, match="entries outside the bound"):
        assert_within(K["coarse"].drift, closed.drift, 100 * bound, "K by one point fewer against the closed form")
    assert torch.equal(K["exact"].mass, closed.mass)  # closed form, no quadrature


@pytest.mark.slow  # compiles ahead of time
def test_galerkin_matrices_compiled_equal_eager(gen, monkeypatch, tmp_path):
    """The generic node kernel compiled ahead of time (agsf_torch.compiled_kernels, keyed by its exported graph):
    no fallback to the eager kernel (a warning would fail the test), one package written, the eager numbers."""
    monkeypatch.setenv("AGSF_TORCH_KERNEL_CACHE", str(tmp_path))
    model, u, rates = _six_state_rates(gen)
    rule = gauss_hermite(model.fpke_quadrature_points(1))
    eager = galerkin_matrices(model, u, rates, *rule)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        comp = galerkin_matrices(model, u, rates, *rule, compile=True, chunk_size=4000)  # 9261 nodes: a padded tail
    assert [p.name.split("-")[0] for p in tmp_path.glob("*.pt2")] == ["fpke_galerkin"]
    bound = relative_bound(eager.drift, 1e-12, 1e-12 * float(eager.drift.abs().max()))
    assert_within(comp.drift, eager.drift, bound, "compiled drift matrix against eager")
