"""Rotations against scipy's Rotation, round trips and identities."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from agsf_torch import rotations as rot
from tests.helpers import assert_within, relative_bound

#: Entries of rotation matrices, unit quaternions, canonical MRPs and angles are O(1), computed in a few tens of
#: roundings (scipy's side likewise): 1e-12 absolute is ~4500 units in the last place of that scale.
ROUNDING = 1e-12
EPS = torch.finfo(torch.float64).eps


def test_cross_matrix(gen):
    a, b = torch.randn(2, 50, 3, generator=gen, dtype=torch.float64)
    # each entry is a difference of two products aᵢbⱼ − aⱼbᵢ: each side rounds to ~2ε of their sizes |aᵢbⱼ| + |aⱼbᵢ|
    scale = rot.cross_matrix(a).abs() @ b.abs()[..., None]
    assert_within(
        rot.cross_matrix(a) @ b[..., None], torch.linalg.cross(a, b)[..., None], 16 * EPS * scale, "cross product"
    )


def test_mrp_to_dcm_matches_scipy(mrps):
    C = rot.mrp_to_dcm(mrps)
    C_ref = Rotation.from_mrp(mrps.numpy()).as_matrix().transpose(0, 2, 1)  # scipy's matrix is Cᵀ
    assert_within(C, C_ref, ROUNDING, "rotation matrix of an MRP against scipy")


def test_mrp_to_quat_and_quat_to_dcm_match_scipy(mrps):
    q = rot.mrp_to_quat(mrps)
    q_ref = Rotation.from_mrp(mrps.numpy()).as_quat()
    sign = np.sign((q.numpy() * q_ref).sum(-1, keepdims=True))
    assert_within(q, sign * q_ref, ROUNDING, "quaternion of an MRP against scipy")
    assert_within(rot.quat_to_dcm(q), rot.mrp_to_dcm(mrps), ROUNDING, "rotation matrix of the quaternion")


def test_dcm_to_quat_matches_scipy(mrps):
    C = rot.mrp_to_dcm(mrps)
    q = rot.dcm_to_quat(C)
    q_ref = Rotation.from_matrix(C.transpose(-1, -2).numpy()).as_quat()
    sign = np.sign((q.numpy() * q_ref).sum(-1, keepdims=True))
    assert_within(q, sign * q_ref, ROUNDING, "quaternion of a rotation matrix against scipy")


def test_round_trips(mrps):
    p_short = rot.mrp_canonical(mrps)
    assert bool(((p_short**2).sum(-1) <= 1.0 + 1e-15).all())
    assert_within(rot.quat_to_mrp(rot.mrp_to_quat(mrps)), p_short, ROUNDING, "MRP → quaternion → MRP")
    assert_within(rot.dcm_to_mrp(rot.mrp_to_dcm(mrps)), p_short, ROUNDING, "MRP → matrix → MRP")
    C = rot.mrp_to_dcm(mrps)
    assert_within(rot.quat_to_dcm(rot.dcm_to_quat(C)), C, ROUNDING, "matrix → quaternion → matrix")


def test_dcm_is_proper_orthogonal(mrps):
    C = rot.mrp_to_dcm(mrps)
    eye = torch.eye(3, dtype=torch.float64).expand_as(C)
    assert_within(C @ C.transpose(-1, -2), eye, ROUNDING, "C Cᵀ")
    assert_within(torch.linalg.det(C), 1.0, ROUNDING, "det C")


def test_quat_multiply_composes_matrices(gen):
    from tests.helpers import random_mrps

    pa, pb = random_mrps(1000, gen), random_mrps(1000, gen)
    qa, qb = rot.mrp_to_quat(pa), rot.mrp_to_quat(pb)
    product = rot.mrp_to_dcm(pa) @ rot.mrp_to_dcm(pb)
    assert_within(rot.quat_to_dcm(rot.quat_multiply(qa, qb)), product, ROUNDING, "matrix of the quaternion product")
    assert_within(rot.mrp_to_dcm(rot.mrp_compose(pa, pb)), product, ROUNDING, "matrix of the composed MRP")
    # scipy: as_matrix() is Cᵀ, so C(a)C(b) = (R_b R_a)ᵀ
    R = Rotation.from_mrp(pb.numpy()) * Rotation.from_mrp(pa.numpy())
    assert_within(
        rot.mrp_to_dcm(rot.mrp_compose(pa, pb)), R.as_matrix().transpose(0, 2, 1), ROUNDING, "composition vs scipy"
    )


def test_shadow_set_same_attitude_and_jacobian(mrps):
    p = mrps[(mrps.norm(dim=-1) > 1e-3)]
    ps = rot.mrp_shadow(p)
    assert_within(rot.mrp_to_dcm(ps), rot.mrp_to_dcm(p), 1e-11, "matrix of the shadow MRP")
    J = rot.mrp_shadow_jacobian(p[:500])
    J_ad = torch.func.vmap(torch.func.jacrev(rot.mrp_shadow))(p[:500])
    assert_within(J, J_ad, relative_bound(J_ad, 1e-10, 1e-10), "shadow-set Jacobian against autograd")


def test_kinematics_matrix_identity(mrps):
    B = rot.mrp_kinematics_matrix(mrps)
    s = (mrps**2).sum(-1)
    eye = torch.eye(3, dtype=torch.float64)
    assert_within(B @ B.transpose(-1, -2) / ((1 + s) ** 2)[:, None, None], eye, ROUNDING, "B Bᵀ / (1 + |p|²)²")


def test_attitude_error_angle(gen, mrps):
    from tests.helpers import random_mrps

    pa = random_mrps(len(mrps), gen)
    ang = rot.attitude_error_angle(pa, mrps)
    ra, rb = Rotation.from_mrp(pa.numpy()), Rotation.from_mrp(mrps.numpy())
    ref = (ra * rb.inv()).magnitude()
    assert_within(ang, ref, ROUNDING, "attitude error angle against scipy")
    # same attitude through the shadow set: zero error
    big = mrps[mrps.norm(dim=-1) > 1e-3]
    # q(p) and q(p_s) = −q(p) each to ~4ε per entry, δq_v = q_a ⊗ q_b⁻¹'s vector part a sum of 4 products of
    # them: |δq_v| ≤ 16ε, and θ = 2 atan(|δq_v|/|δq₄|) ≤ 2|δq_v| (|δq₄| ≈ 1)
    eps = torch.finfo(torch.float64).eps
    angle = rot.attitude_error_angle(big, rot.mrp_shadow(big))
    assert_within(angle, 0.0, 32 * eps, "angle between an MRP and its shadow")


def test_attitude_error_vector_small_angle(gen):
    from tests.helpers import random_mrps

    p_true = random_mrps(200, gen)
    dtheta = 1e-4 * torch.randn(200, 3, generator=gen, dtype=torch.float64)
    q_est = rot.quat_multiply(rot.rotvec_to_quat(dtheta), rot.mrp_to_quat(p_true))
    err = rot.attitude_error_vector(rot.quat_to_mrp(q_est), p_true)
    # C(q_est) = exp(−[δθ×]) C(p_true) ⇒ error vector is δθ up to O(|δθ|³)
    # its magnitude is 2 sin(θ/2) = θ − θ³/24: ≲ 6e-12 from θ ≲ 5e-4 (|δθ| of 1e-4 per axis), rounding ~1e-16
    assert_within(err, dtheta, 1e-11, "small-angle error vector")


def test_rotvec_to_quat_matches_scipy(gen):
    phi = torch.randn(500, 3, generator=gen, dtype=torch.float64)
    phi[:10] *= 1e-12
    q = rot.rotvec_to_quat(phi)
    # scipy's rotation vector is active: C(q) = R(φ)ᵀ
    C_ref = Rotation.from_rotvec(phi.numpy()).as_matrix().transpose(0, 2, 1)
    assert_within(rot.quat_to_dcm(q), C_ref, ROUNDING, "rotation matrix of a rotation vector against scipy")


def test_batched_over_leading_dims(gen):
    from tests.helpers import random_mrps

    p = random_mrps(24, gen).reshape(2, 3, 4, 3)
    flat = rot.mrp_to_dcm(p.reshape(24, 3))
    assert_within(rot.mrp_to_dcm(p).reshape(24, 3, 3), flat, relative_bound(flat, 1e-7, 1e-7), "batched matrices")
    assert rot.dcm_to_quat(rot.mrp_to_dcm(p)).shape == torch.Size((2, 3, 4, 4))


def test_attitude_error_angle_does_not_depend_on_the_batch(gen):
    """Trajectory i's error angle is the same bits whether computed alone or in a batch of any size
    (torch's atan2 takes a SIMD path for full vectors and a scalar one for the tail, which differ
    in the last bit for a few per cent of arguments)."""
    from tests.helpers import random_mrps

    pa, pb = random_mrps(4099, gen), random_mrps(4099, gen)
    batch = rot.attitude_error_angle(pa, pb)
    alone = torch.cat([rot.attitude_error_angle(pa[i : i + 1], pb[i : i + 1]) for i in range(len(pa))])
    assert torch.equal(batch, alone)
    assert torch.equal(rot.attitude_error_angle(pa[:7], pb[:7]), batch[:7])


def test_attitude_error_jacobian_is_the_derivative_of_the_error_vector():
    from agsf_torch.rotations import attitude_error_jacobian, attitude_error_vector

    gen = torch.Generator().manual_seed(4)
    for p in (torch.zeros(3, dtype=torch.float64), 0.7 * torch.randn(3, generator=gen, dtype=torch.float64)):
        J = torch.autograd.functional.jacobian(lambda pe: attitude_error_vector(pe, p), p)
        assert_within(attitude_error_jacobian(p), J, relative_bound(J, 1e-12, 1e-12), "error-vector Jacobian")
    four = 4.0 * torch.eye(3, dtype=torch.float64)
    assert_within(
        attitude_error_jacobian(torch.zeros(3, dtype=torch.float64)),
        four,
        relative_bound(four, 1e-7, 1e-7),
        "error-vector Jacobian at p = 0",
    )


def test_uniform_mrp_is_haar_distributed():
    """Uniform attitudes: short MRPs (|p| ≤ 1) whose attitude matrices average to zero entrywise (E[C] = 0 under the
    Haar measure; each entry has variance 1/3) and whose rotation angle has E[cos θ] = −1/2 (density
    (1 − cos θ)/π on [0, π], so E[trace C] = E[1 + 2 cos θ] = 0)."""
    from tests.helpers import assert_statistic

    N = 20000
    p = rot.uniform_mrp(N, torch.Generator().manual_seed(5))
    assert p.shape == (N, 3) and bool((p.norm(dim=-1) <= 1.0 + 1e-15).all())
    C = rot.mrp_to_dcm(p).reshape(N, 9).numpy()
    assert_statistic(C.mean(0), np.zeros(9), np.full(9, np.sqrt(1.0 / 3.0 / N)), "E[C]", false_failure=1e-4)
    cos = (C[:, 0] + C[:, 4] + C[:, 8] - 1.0) / 2.0
    # Var cos θ = E[cos²θ] − ¼ = ½ − ¼ = ¼ under the density (1 − cos θ)/π
    assert_statistic(cos.mean(), -0.5, np.sqrt(0.25 / N), "E[cos θ]", false_failure=1e-4)
