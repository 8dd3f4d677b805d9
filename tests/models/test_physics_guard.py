"""A model's closed forms and fused kernels hold only for the physics they were derived from
(:mod:`agsf_torch.models.derived`): a user's subclass that changes the dynamics or the camera gets the generic
path at every batch size, never its parent's equations from some batch size on."""

from __future__ import annotations

import math

import pytest
import torch

from agsf_torch import GaussianMixture
from agsf_torch.filters import AdaptiveGaussianSumFilter, GaussianSumFilter
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.models.derived import follows_physics
from agsf_torch.rotations import mrp_to_dcm
from tests.helpers import F64, assert_within, random_mrps, random_spd, random_unit_vectors

#: A rate the user's model adds to the gyro input (rad/s): 10⁴ times the step's rounding, easily told apart.
EXTRA_RATE = 0.05
#: The user's camera's misalignment about its boresight x axis (rad).
MISALIGNMENT = 0.01


class SpinningAttitude(AttitudeModel):
    """A user's model: the body turns at an extra ``EXTRA_RATE`` about every axis beyond what the gyro reads."""

    def drift(self, x, u):
        return super().drift(x, u + EXTRA_RATE)

    def drift_jacobian(self, x, u):
        return super().drift_jacobian(x, u + EXTRA_RATE)


def _rotation_x(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=F64)


class MisalignedCamera(StarVectorMeasurement):
    """A user's camera, rotated by ``MISALIGNMENT`` about its x axis: ``h(x) = R_c C(p) r``, ``H = R_c H₀``."""

    def predict(self, x):
        b = super().predict(x).unflatten(-1, (-1, 3))
        return (b @ _rotation_x(MISALIGNMENT).T.to(b)).flatten(-2)

    def jacobian(self, x):
        H = super().jacobian(x).unflatten(-2, (-1, 3))  # [..., M, 3, n]
        return (_rotation_x(MISALIGNMENT).to(H) @ H).flatten(-3, -2)


def _mixture(gen, B, N, n):
    truth = random_mrps(B, gen, max_norm=0.8)
    means = truth[:, None, :] + 1e-2 * torch.randn(B, N, 3, generator=gen, dtype=F64)
    if n == 6:
        means = torch.cat((means, 1e-6 * torch.randn(B, N, 3, generator=gen, dtype=F64)), -1)
    scale = torch.tensor([1e-4] * 3 + [1e-12] * 3, dtype=F64)[:n].sqrt()
    covs = scale[:, None] * random_spd(gen, B, N, n=n) * scale[None, :]
    log_w = torch.log_softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    return GaussianMixture(log_weights=log_w, means=means, covs=covs), truth


def _filters(model, fused, n, B):
    """The filters whose predict would run a kernel of the parent's at this size: the GSF's propagation from
    1,024 lanes, the Galerkin pairs' from 1,024 pairs (the penalty's pair products:
    :func:`test_the_derivations_give_way_where_the_physics_is_the_users`)."""
    filters = {"GSF": GaussianSumFilter(model, fused=fused)}
    if n == 3 and B == 256:
        filters["AGSF-galerkin"] = AdaptiveGaussianSumFilter(model, weight_update="galerkin", fused=fused)
    return filters


def test_the_derivations_give_way_where_the_physics_is_the_users():
    parent, child = AttitudeModel(estimate_bias=True), SpinningAttitude(estimate_bias=True)
    derived = (
        "drift_jacobian",
        "drift_divergence",
        "fokker_planck_terms",
        "fokker_planck_moments",
        "fpke_polynomial_space",
    )
    kernels = ("fused_propagation", "fused_galerkin_pairs", "fused_penalty_pairs", "fpke_pair_products")
    assert all(follows_physics(parent, name) for name in derived + kernels + ("process_noise",))
    # the user overrode drift_jacobian: theirs applies; the closed forms and kernels derived from drift do not
    assert follows_physics(child, "drift_jacobian") and follows_physics(child, "process_noise")
    assert not any(follows_physics(child, name) for name in derived[1:] + kernels)
    assert child.fpke_polynomial_space() is None and child.fpke_quadrature_points() is None
    # the child's divergence is the trace of its own Jacobian (the generic route), not the parent's closed form
    x, u = torch.tensor([[0.1, -0.2, 0.3, 0.0, 0.0, 0.0]], dtype=F64), torch.tensor([[0.01, 0.02, -0.03]], dtype=F64)
    own = child.drift_jacobian(x, u).diagonal(dim1=-2, dim2=-1).sum(-1)
    assert torch.equal(child.drift_divergence(x, u), own)
    assert not torch.equal(own, parent.drift_divergence(x, u))
    camera = MisalignedCamera(torch.eye(3, dtype=F64))
    assert follows_physics(camera, "jacobian") and not follows_physics(camera, "fused_update")


def test_a_user_kernel_for_the_users_physics_applies():
    class OwnKernel(SpinningAttitude):
        def fused_propagation(self, mean, cov, u, dt, substeps=1, *, compile=False):
            return "the user's own kernel"

    assert OwnKernel().fused_propagation(None, None, None, 0.1) == "the user's own kernel"


def test_physics_set_on_the_instance_takes_the_generic_path():
    model = AttitudeModel()
    model.drift = lambda x, u: torch.zeros_like(x)
    assert not follows_physics(model, "fused_propagation")
    x = torch.zeros(2, 3, dtype=F64)
    assert model.fused_propagation(x, torch.eye(3, dtype=F64).expand(2, 3, 3), x, 0.1) is None


@pytest.mark.parametrize("B", [8, 256])
@pytest.mark.parametrize("n", [3, 6])
def test_a_subclass_that_changes_the_drift_gets_its_own_physics_at_every_batch_size(gen, B, n):
    """At B = 256, N = 5 (1,280 lanes) the fused kernels would run; they evaluate the parent's equations, 1e-2
    away from the subclass's: every filter's predict must give the generic path's numbers for the subclass."""
    N, dt = 5, 0.1
    mix, _ = _mixture(gen, B, N, n)
    u = 1e-3 * torch.randn(B, 3, generator=gen, dtype=F64)
    child = SpinningAttitude(estimate_bias=n == 6)
    parent = AttitudeModel(estimate_bias=n == 6)
    fused, generic = _filters(child, True, n, B), _filters(child, False, n, B)
    differ = []
    for name in fused:
        # the Galerkin pairs run on lanes from 1,024 pairs: 72 trajectories × 15 pairs suffice, and spare the
        # generic quadrature that the subclass now takes a fourth of the work of B = 256
        T = 72 if name == "AGSF-galerkin" else B
        m = GaussianMixture(log_weights=mix.log_weights[:T], means=mix.means[:T], covs=mix.covs[:T])
        got = fused[name].predict(m, u[:T], dt)
        want = generic[name].predict(m, u[:T], dt)
        # the same generic arithmetic on the same data: identical numbers
        pairs = ((got.means, want.means), (got.covs, want.covs), (got.log_weights, want.log_weights))
        if not all(torch.equal(a, b) for a, b in pairs):
            differ.append(name)
        if name == "GSF":
            gsf = got
    assert not differ, f"{differ} ran other physics than the subclass's with fused=True"
    parents = GaussianSumFilter(parent, fused=True).predict(mix, u, dt)
    moved = (parents.means[..., :3] - gsf.means[..., :3]).norm(dim=-1)
    # the subclass's physics is not the parent's: ¼·0.05 rad/s·0.1 s ≈ 1.25e-3 per axis in the MRP
    assert bool((moved > 1e-3).all())


def _star_problem(gen, B, N, n, M=5):
    mix, truth = _mixture(gen, B, N, n)
    r = random_unit_vectors(gen, B, M)
    y = (mrp_to_dcm(truth)[:, None] @ r.unsqueeze(-1)).squeeze(-1) @ _rotation_x(MISALIGNMENT).T
    y = y + 1e-5 * torch.randn(B, M, 3, generator=gen, dtype=F64)
    return mix, (y / y.norm(dim=-1, keepdim=True)).flatten(-2), r


@pytest.mark.parametrize("B", [8, 256])
@pytest.mark.parametrize("n", [3, 6])
def test_a_subclass_that_changes_the_camera_gets_its_own_update_at_every_batch_size(gen, B, n):
    N = 5
    mix, y, r = _star_problem(gen, B, N, n)
    model = AttitudeModel(estimate_bias=n == 6)
    camera = MisalignedCamera(r, sigma=1e-5)
    got = GaussianSumFilter(model, fused=True).update(mix, y, camera)
    want = GaussianSumFilter(model, fused=False).update(mix, y, camera)
    for a, b in ((got.means, want.means), (got.covs, want.covs), (got.log_weights, want.log_weights)):
        assert torch.equal(a, b)
    parents = GaussianSumFilter(model, fused=True).update(mix, y, StarVectorMeasurement(r, sigma=1e-5))
    # the misaligned camera's update is its own: the parent's would be ~MISALIGNMENT away (here, for 5 stars, O(1e-3))
    assert bool(((parents.means[..., :3] - got.means[..., :3]).norm(dim=-1) > 1e-4).any())


def test_the_parents_kernels_still_run_for_the_parent(gen, monkeypatch):
    """The guard must not switch the library's own model off its kernels: at 1,280 lanes the parent's predict
    goes through its fused propagation."""
    import agsf_torch.fused.propagation as propagation

    calls = []
    real = propagation.propagation_kernel
    monkeypatch.setattr(propagation, "propagation_kernel", lambda s: calls.append(s) or real(s))
    mix, _ = _mixture(gen, 256, 5, 6)
    u = torch.zeros(256, 3, dtype=F64)
    out = GaussianSumFilter(AttitudeModel(estimate_bias=True), fused=True).predict(mix, u, 0.1)
    assert calls and out.means.shape == mix.means.shape
    generic = GaussianSumFilter(AttitudeModel(estimate_bias=True), fused=False).predict(mix, u, 0.1)
    # the kernel's RK4 against the generic one: the same arithmetic in another order, a few ulps of the
    # mean's entries and of the propagated covariance's scale (1e-4)
    assert_within(out.means, generic.means, 64 * torch.finfo(F64).eps * (1 + out.means.abs()), "propagated means")
    assert_within(out.covs, generic.covs, 64 * torch.finfo(F64).eps * 1e-4, "propagated covariances")


def test_a_subclass_that_changes_the_camera_reads_every_state_entry():
    r = torch.eye(3, dtype=F64)[None]
    assert StarVectorMeasurement(r, sigma=1e-5).state_entries() == (0, 1, 2)
    assert MisalignedCamera(r, sigma=1e-5).state_entries() is None  # its predict is its own: no declaration
