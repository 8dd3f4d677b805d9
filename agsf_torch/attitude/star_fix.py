"""An attitude from one star frame: Wahba's problem, batched (a start for a replay without the truth).

Given the valid stars' measured body vectors ``b_j`` and catalogue vectors ``r_j`` of a frame, the attitude
matrix ``C`` (``b = C r``, inertial to body) minimising ``Σ_j w_j |b_j − C r_j|²`` over rotations is, with
the attitude profile matrix ``B = Σ_j w_j b_j r_jᵀ = U S Vᵀ`` (singular value decomposition),

.. math:: C = U \\,\\mathrm{diag}(1, 1, \\det U \\det V)\\, V^T

(Markley's SVD solution of Wahba's problem).  It is unique when the stars span two directions, i.e. when
``B``'s second singular value is not negligible against the first; a frame with fewer than two valid stars
or with parallel stars determines no attitude and is reported as such.  Every trajectory is solved in one
batched decomposition (``scipy.spatial.transform.Rotation.align_vectors`` solves one frame).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..rotations import dcm_to_mrp

__all__ = ["star_fix", "MIN_SPREAD"]

#: The smallest ratio of ``B``'s second to first singular value taken as two directions: for two stars an angle
#: θ apart the ratio is ``tan²(θ/2) ≈ θ²/4``, so stars within ~2e-3 rad (0.1°) of parallel determine no attitude.
MIN_SPREAD = 1e-6


def star_fix(body: Tensor, inertial: Tensor, mask: Tensor, min_spread: float = MIN_SPREAD) -> tuple[Tensor, Tensor]:
    """The attitude of one star frame per trajectory (module docstring), equal weights.

    Args:
        body: measured star unit vectors ``[..., M, 3]`` (body frame).
        inertial: their catalogue unit vectors ``[..., M, 3]`` (inertial frame).
        mask: ``[..., M]`` bool, the valid stars (others are ignored).
        min_spread: the smallest ratio of ``B``'s second to first singular value that counts as two directions.

    Returns:
        ``(mrp [..., 3], ok [...])``: the attitude as an MRP (``|p| ≤ 1``, inertial to body) and whether the frame
        determines it (≥ 2 valid, non-parallel stars); where ``ok`` is false the MRP is meaningless.

    Raises:
        ValueError: mismatched shapes or non-finite valid vectors.
    """
    body, inertial = torch.as_tensor(body), torch.as_tensor(inertial)
    mask = torch.as_tensor(mask, dtype=torch.bool, device=body.device)
    if body.dim() < 2 or body.shape[-1] != 3 or body.shape != inertial.shape or mask.shape != body.shape[:-1]:
        raise ValueError(
            f"star_fix needs body and inertial [..., M, 3] and mask [..., M] alike, got {tuple(body.shape)}, "
            f"{tuple(inertial.shape)} and {tuple(mask.shape)}"
        )
    b = torch.where(mask[..., None], body, 0.0)  # the invalid stars' entries are ignored, whatever they hold
    r = torch.where(mask[..., None], inertial, 0.0)
    if not (bool(torch.isfinite(b).all()) and bool(torch.isfinite(r).all())):
        raise ValueError("star_fix: a valid star vector is not finite")
    profile = b.transpose(-1, -2) @ r  # B = Σ_j b_j r_jᵀ over the valid stars, [..., 3, 3]
    U, S, Vh = torch.linalg.svd(profile)
    d = torch.linalg.det(U) * torch.linalg.det(Vh)
    D = torch.ones(*d.shape, 3, dtype=body.dtype, device=body.device)
    D[..., 2] = d
    C = U @ (D[..., None] * Vh)
    ok = (mask.sum(-1) >= 2) & (S[..., 1] > min_spread * S[..., 0])
    return dcm_to_mrp(C), ok
