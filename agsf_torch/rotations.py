"""Attitude parametrisations: MRP, quaternion, attitude matrix, shadow set.

Conventions (the package's, stated in the user guide's *Conventions*, docs/guide/filters.md):

* The attitude matrix ``C`` maps inertial to body coordinates, ``b = C r``.
  It is the *transpose* of scipy's ``Rotation.as_matrix()`` for the same
  quaternion / MRP.
* Quaternions are scalar-last ``[x, y, z, w]`` (as scipy), with the product
  ``⊗`` defined so that ``C(q_a ⊗ q_b) = C(q_a) C(q_b)``.
* Modified Rodrigues parameters ``p = e tan(θ/4)``; the shadow set
  ``pˢ = −p/|p|²`` describes the same attitude and is used when ``|p| > 1``.

Every function is batched over arbitrary leading dimensions and follows the
dtype/device of its input.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .attitude import physics
from .fused import algebra
from .fused.algebra import as_entries, as_tensor

__all__ = [
    "cross_matrix",
    "mrp_to_dcm",
    "dcm_to_mrp",
    "mrp_to_quat",
    "quat_to_mrp",
    "uniform_mrp",
    "quat_to_dcm",
    "dcm_to_quat",
    "quat_multiply",
    "quat_conjugate",
    "rotvec_to_quat",
    "mrp_compose",
    "mrp_kinematics_matrix",
    "mrp_shadow",
    "mrp_shadow_jacobian",
    "mrp_canonical",
    "attitude_error_angle",
    "attitude_error_vector",
    "attitude_error_jacobian",
]


def cross_matrix(v: Tensor) -> Tensor:
    """Skew-symmetric cross-product matrix ``[v×]`` (:func:`agsf_torch.fused.algebra.cross_matrix`).

    Args:
        v: ``[..., 3]``.

    Returns:
        ``[..., 3, 3]`` with ``[v×] u = v × u``.
    """
    return as_tensor(algebra.cross_matrix(as_entries(v, (3,))), like=v)


def mrp_to_dcm(p: Tensor) -> Tensor:
    """Attitude matrix (inertial → body) of an MRP.

    .. math:: C(p) = I_3 + \\frac{8[p×]^2 - 4(1 - s)[p×]}{(1 + s)^2},\\quad s = p^T p

    (:func:`agsf_torch.attitude.physics.attitude_matrix`).

    Args:
        p: MRP ``[..., 3]``.

    Returns:
        ``[..., 3, 3]``.
    """
    return as_tensor(physics.attitude_matrix(as_entries(p, (3,))), like=p)


def mrp_to_quat(p: Tensor) -> Tensor:
    """Quaternion (scalar-last) of an MRP: ``q = [2p, 1 − s] / (1 + s)``.

    Args:
        p: ``[..., 3]``.

    Returns:
        Unit quaternion ``[..., 4]``.
    """
    s = (p * p).sum(-1, keepdim=True)
    return torch.cat((2.0 * p, 1.0 - s), -1) / (1.0 + s)


def uniform_mrp(count: int, gen: torch.Generator, dtype: torch.dtype = torch.float64) -> Tensor:
    """``count`` attitudes drawn uniformly over the rotation group (Haar measure), as short MRPs ``[count, 3]``.

    A normalised 4-D standard normal is uniform on the unit sphere of quaternions, whose double cover of the
    rotations carries the Haar measure (Shoemake, "Uniform random rotations", Graphics Gems III, 1992);
    :func:`quat_to_mrp` maps it to ``|p| ≤ 1``.
    """
    return quat_to_mrp(torch.randn(count, 4, generator=gen, dtype=dtype))


def quat_to_mrp(q: Tensor) -> Tensor:
    """MRP of a quaternion, choosing the sign of ``q`` so that ``|p| ≤ 1``.

    .. math:: p = q_{1:3} / (1 + |q_4|) \\cdot \\operatorname{sign}(q_4)

    Args:
        q: quaternion ``[..., 4]`` (normalised here).

    Returns:
        ``[..., 3]``.
    """
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    sign = torch.where(q[..., 3:] < 0, -1.0, 1.0).to(q.dtype)
    q = q * sign
    return q[..., :3] / (1.0 + q[..., 3:])


def quat_to_dcm(q: Tensor) -> Tensor:
    """Attitude matrix of a quaternion.

    .. math:: C(q) = (q_4^2 - |q_v|^2) I_3 + 2 q_v q_v^T - 2 q_4 [q_v×]

    Args:
        q: ``[..., 4]`` scalar-last (normalised here).

    Returns:
        ``[..., 3, 3]``.
    """
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    qv, q4 = q[..., :3], q[..., 3:]
    eye = torch.eye(3, dtype=q.dtype, device=q.device)
    return (
        (q4 * q4 - (qv * qv).sum(-1, keepdim=True))[..., None] * eye
        + 2.0 * qv[..., :, None] * qv[..., None, :]
        - 2.0 * q4[..., None] * cross_matrix(qv)
    )


def dcm_to_quat(C: Tensor) -> Tensor:
    """Quaternion of an attitude matrix (Shepperd's method, batched).

    Of the four algebraically equivalent extractions the one with the largest
    pivot is used, which keeps the result accurate for every rotation angle.

    Args:
        C: ``[..., 3, 3]`` proper orthogonal.

    Returns:
        Unit quaternion ``[..., 4]`` (sign arbitrary).
    """
    c11, c22, c33 = C[..., 0, 0], C[..., 1, 1], C[..., 2, 2]
    tr = c11 + c22 + c33
    d23 = C[..., 1, 2] - C[..., 2, 1]
    d31 = C[..., 2, 0] - C[..., 0, 2]
    d12 = C[..., 0, 1] - C[..., 1, 0]
    s12 = C[..., 0, 1] + C[..., 1, 0]
    s13 = C[..., 0, 2] + C[..., 2, 0]
    s23 = C[..., 1, 2] + C[..., 2, 1]
    cand = torch.stack(
        (
            torch.stack((1.0 + 2.0 * c11 - tr, s12, s13, d23), -1),
            torch.stack((s12, 1.0 + 2.0 * c22 - tr, s23, d31), -1),
            torch.stack((s13, s23, 1.0 + 2.0 * c33 - tr, d12), -1),
            torch.stack((d23, d31, d12, 1.0 + tr), -1),
        ),
        -2,
    )  # [..., 4, 4]
    pivot = torch.stack((c11, c22, c33, tr), -1).argmax(-1)
    idx = pivot[..., None, None].expand(*pivot.shape, 1, 4)
    q = torch.gather(cand, -2, idx).squeeze(-2)
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)


def dcm_to_mrp(C: Tensor) -> Tensor:
    """MRP (``|p| ≤ 1``) of an attitude matrix ``[..., 3, 3]`` → ``[..., 3]``."""
    return quat_to_mrp(dcm_to_quat(C))


def quat_multiply(q_a: Tensor, q_b: Tensor) -> Tensor:
    """Quaternion product with ``C(q_a ⊗ q_b) = C(q_a) C(q_b)``.

    .. math:: q_a ⊗ q_b = [q_{a4} q_{bv} + q_{b4} q_{av} - q_{av} × q_{bv};\\;
              q_{a4} q_{b4} - q_{av} · q_{bv}]

    Args:
        q_a, q_b: ``[..., 4]`` (broadcast).
    """
    av, a4 = q_a[..., :3], q_a[..., 3:]
    bv, b4 = q_b[..., :3], q_b[..., 3:]
    v = a4 * bv + b4 * av - torch.linalg.cross(av, bv, dim=-1)
    w = a4 * b4 - (av * bv).sum(-1, keepdim=True)
    return torch.cat((v, w), -1)


def quat_conjugate(q: Tensor) -> Tensor:
    """Inverse rotation of a unit quaternion ``[..., 4]``."""
    return torch.cat((-q[..., :3], q[..., 3:]), -1)


def rotvec_to_quat(phi: Tensor) -> Tensor:
    """Quaternion of the rotation vector ``φ = θ e``: ``[sin(θ/2) e, cos(θ/2)]``.

    Used for the exact attitude step under a constant body rate ``ω`` held over
    ``Δt``: ``q_{k+1} = rotvec_to_quat(ω Δt) ⊗ q_k``.

    Args:
        phi: ``[..., 3]`` (rad).
    """
    theta = torch.linalg.vector_norm(phi, dim=-1, keepdim=True)
    # sin(θ/2)/θ = ½ sinc(θ / 2π), smooth through θ = 0.
    return torch.cat((0.5 * torch.sinc(theta / (2.0 * torch.pi)) * phi, torch.cos(0.5 * theta)), -1)


def mrp_compose(p_a: Tensor, p_b: Tensor) -> Tensor:
    """MRP ``p`` with ``C(p) = C(p_a) C(p_b)`` (short set, ``|p| ≤ 1``)."""
    return quat_to_mrp(quat_multiply(mrp_to_quat(p_a), mrp_to_quat(p_b)))


def mrp_kinematics_matrix(p: Tensor) -> Tensor:
    """MRP kinematics matrix, ``ṗ = ¼ B(p) ω`` (:func:`agsf_torch.attitude.physics.kinematics_matrix`).

    .. math:: B(p) = (1 - s) I_3 + 2 [p×] + 2 p p^T,\\qquad B B^T = (1 + s)^2 I_3

    Args:
        p: ``[..., 3]``.

    Returns:
        ``[..., 3, 3]``.
    """
    return as_tensor(physics.kinematics_matrix(as_entries(p, (3,))), like=p)


def mrp_shadow(p: Tensor) -> Tensor:
    """Shadow MRP ``pˢ = −p / |p|²`` (the same attitude; :func:`agsf_torch.attitude.physics.shadow`), ``[..., 3]``.
    ``p`` must be non-zero."""
    return as_tensor(physics.shadow(as_entries(p, (3,))), like=p)


def mrp_shadow_jacobian(p: Tensor) -> Tensor:
    """Jacobian of the shadow map, ``J = ∂pˢ/∂p = (2 p pᵀ − s I₃) / s²``
    (:func:`agsf_torch.attitude.physics.shadow_jacobian`).

    Args:
        p: ``[..., 3]`` non-zero.

    Returns:
        ``[..., 3, 3]``.
    """
    return as_tensor(physics.shadow_jacobian(as_entries(p, (3,))), like=p)


def mrp_canonical(p: Tensor) -> Tensor:
    """Map every MRP with ``|p| > 1`` to its shadow set, leaving the others."""
    s = (p * p).sum(-1, keepdim=True)
    return torch.where(s > 1.0, -p / s.clamp_min(1.0), p)


def attitude_error_vector(p_est: Tensor, p_true: Tensor) -> Tensor:
    """Small-angle attitude error ``δθ`` (rad, body frame of the truth), ``[..., 3]``.

    ``δq = q_est ⊗ q_true⁻¹`` and ``δθ = 2 δq_v sign(δq_4)``, so that
    ``C(p_est) ≈ (I − [δθ×]) C(p_true)``.  Exact direction; magnitude is
    ``2 sin(θ/2)`` (use :func:`attitude_error_angle` for the exact angle).
    """
    dq = quat_multiply(mrp_to_quat(p_est), quat_conjugate(mrp_to_quat(p_true)))
    sign = torch.where(dq[..., 3:] < 0, -1.0, 1.0).to(dq.dtype)
    return 2.0 * dq[..., :3] * sign


def attitude_error_jacobian(p: Tensor) -> Tensor:
    """Jacobian of :func:`attitude_error_vector` in its first argument, at ``p_est = p_true = p``:
    how an additive MRP perturbation ``δp`` of the estimate turns into the small-angle error,
    ``δθ ≈ J δp``.

    .. math:: J = \\frac{4}{(1 + |p|^2)^2} B(p)^T

    (:func:`agsf_torch.attitude.physics.chart_map`; ``J = 4 I`` at ``p = 0``).  Maps an MRP covariance ``P`` to
    the covariance ``J P Jᵀ`` of the rotation error (rad²).

    Args:
        p: ``[..., 3]``.

    Returns:
        ``[..., 3, 3]``.
    """
    return as_tensor(physics.chart_map(as_entries(p, (3,))), like=p)


def attitude_error_angle(p_a: Tensor, p_b: Tensor) -> Tensor:
    """Rotation angle (rad, in ``[0, π]``) between the attitudes of two MRPs.

    .. math:: θ = 2 \\arctan(|δq_v| / |δq_4|),\\quad δq = q_a ⊗ q_b^{-1}

    Written with operations whose result for one element does not depend on the
    batch it is computed in (a trajectory's error is the same bits alone or among
    10⁵): torch's ``atan2`` evaluates full SIMD vectors and the remainder with two
    routines that differ in the last bit for a few per cent of arguments, while
    ``atan`` of a contiguous tensor takes one path for every element.  ``|δq_4| = 0``
    gives ``atan(∞) = π/2``, θ = π.

    Args:
        p_a, p_b: ``[..., 3]`` (broadcast).

    Returns:
        ``[...]``.
    """
    dq = quat_multiply(mrp_to_quat(p_a), quat_conjugate(mrp_to_quat(p_b)))
    x, y, z, w = dq.unbind(-1)
    n = torch.sqrt(x * x + y * y + z * z)
    return 2.0 * torch.atan((n / w.abs()).contiguous())
