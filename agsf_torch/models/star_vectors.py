"""Star-camera unit-vector measurement ``b_j = C(p) r_j + v_j`` (method.md §1)."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

from ..rotations import cross_matrix, mrp_kinematics_matrix, mrp_to_dcm
from .base import MeasurementModel, check_finite, check_nonnegative

__all__ = ["StarVectorMeasurement"]


class StarVectorMeasurement(MeasurementModel):
    """``M`` star directions in one frame, stacked: ``h(x) = [C(p) r_1; …; C(p) r_M]``.

    The MRP is taken from the first three state entries, so the same measurement
    serves the 3-state and the 6-state attitude model.

    Noise models (``noise_model``):

    * ``"isotropic"`` (default, method.md): ``R = σ_s² I_{3M}``;
    * ``"tangent"``: per star ``R_j = σ_s² (I − b̃_j b̃_jᵀ) + σ_r² b̃_j b̃_jᵀ`` with the
      measured unit vector ``b̃_j`` (``body``): a camera's noise lies across the
      star direction (2 degrees of freedom per star); ``σ_r`` (``radial_sigma``,
      fixed, not scaled with σ_s) only keeps ``R`` invertible.  Under this model the
      likelihood's dependence on σ_s counts 2 degrees of freedom per star, so σ_s
      is identifiable by maximum likelihood; under the isotropic one the ML σ_s is
      √(2/3) of the camera's per-axis noise.

    Args:
        r_inertial: catalogue unit vectors ``[..., M, 3]`` (leading dims are the
            trajectory batch).
        mask: ``[..., M]`` bool, ``True`` for a valid star (``None``: all valid).
            Masked stars contribute nothing to an update.
        sigma: σ_s, per-axis unit-vector noise (rad), > 0.
    """

    block_size = 3  # one star: gated as a whole

    def __init__(
        self,
        r_inertial: Tensor,
        mask: Tensor | None = None,
        sigma: float | Tensor = 10e-6,
        *,
        noise_model: str = "isotropic",
        body: Tensor | None = None,
        radial_sigma: float = 1e-3,
    ) -> None:
        super().__init__()
        if noise_model not in ("isotropic", "tangent"):
            raise ValueError(f"noise_model must be 'isotropic' or 'tangent', got {noise_model!r}")
        if noise_model == "tangent":
            if body is None:
                raise ValueError("noise_model='tangent' needs the measured body vectors (body=)")
            if not radial_sigma > 0:
                raise ValueError(f"radial_sigma must be > 0, got {radial_sigma}")
        self.noise_model = noise_model
        self.radial_sigma = float(radial_sigma)
        r = torch.as_tensor(r_inertial)
        if r.dim() < 2 or r.shape[-1] != 3:
            raise ValueError(f"r_inertial must have shape [..., M, 3], got {tuple(r.shape)}")
        check_finite("r_inertial", r)
        sig = check_nonnegative("sigma", sigma)
        if sig.dim() != 0 or bool(sig <= 0):
            raise ValueError(f"sigma must be a positive scalar, got {sig.tolist()}")
        if mask is not None:
            mask = torch.as_tensor(mask, dtype=torch.bool, device=r.device)
            if mask.shape != r.shape[:-1]:
                raise ValueError(f"mask must have shape {tuple(r.shape[:-1])} (r_inertial[..., M]), got {tuple(mask.shape)}")
        self.num_stars = r.shape[-2]
        self.register_buffer("r_inertial", r)
        self.register_buffer("star_mask", mask)
        self.register_buffer("sigma", sig.to(r.dtype))
        if body is not None:
            body = torch.as_tensor(body, dtype=r.dtype, device=r.device)
            if body.shape != r.shape:
                raise ValueError(f"body must have the shape of r_inertial {tuple(r.shape)}, got {tuple(body.shape)}")
            check_finite("body", body)
        self.register_buffer("body", body)

    @classmethod
    def from_observation(
        cls, obs: Mapping[str, Tensor], sigma: float | Tensor, **kwargs
    ) -> tuple[Tensor, "StarVectorMeasurement"]:
        """Build the measurement and the stacked vector ``y`` from an observation dict.

        Args:
            obs: with ``star_body [..., M, 3]``, ``star_inertial [..., M, 3]``,
                ``star_mask [..., M]`` (the environment's observation keys).
            sigma: σ_s (rad).

        Returns:
            ``(y [..., 3M], measurement)``.
        """
        body = torch.as_tensor(obs["star_body"])
        if kwargs.get("noise_model") == "tangent":
            kwargs.setdefault("body", body)
        meas = cls(torch.as_tensor(obs["star_inertial"]), torch.as_tensor(obs["star_mask"]), sigma, **kwargs)
        if body.shape != meas.r_inertial.shape:
            raise ValueError(
                f"star_body {tuple(body.shape)} and star_inertial {tuple(meas.r_inertial.shape)} must have equal shapes"
            )
        return body.flatten(-2), meas

    def predict(self, x: Tensor) -> Tensor:
        """``h(x) = vec(C(p) r_j)``: ``x [..., n]`` → ``[..., 3M]``."""
        C = mrp_to_dcm(x[..., :3])
        b = (C.unsqueeze(-3) @ self.r_inertial.to(x).unsqueeze(-1)).squeeze(-1)  # [..., M, 3]
        return b.flatten(-2)

    def jacobian(self, x: Tensor) -> Tensor:
        """Closed form ``∂(C(p) r)/∂p = 4/(1+s)² [(C r)×] B(p)ᵀ``; zero on bias states.

        From ``Ċ = −[ω×]C`` and ``ω = 4 B(p)ᵀ ṗ / (1+s)²``.

        Returns:
            ``[..., 3M, n]``.
        """
        p = x[..., :3]
        s = (p * p).sum(-1)[..., None, None, None]
        C = mrp_to_dcm(p)
        b = (C.unsqueeze(-3) @ self.r_inertial.to(x).unsqueeze(-1)).squeeze(-1)  # [..., M, 3]
        Bt = mrp_kinematics_matrix(p).transpose(-1, -2).unsqueeze(-3)
        Hp = 4.0 / (1.0 + s) ** 2 * (cross_matrix(b) @ Bt)  # [..., M, 3, 3]
        Hp = Hp.flatten(-3, -2)
        n = x.shape[-1]
        if n == 3:
            return Hp
        return torch.cat((Hp, Hp.new_zeros(*Hp.shape[:-1], n - 3)), -1)

    def noise_cov(self) -> Tensor:
        """``R``: ``σ_s² I_{3M}`` (isotropic) or block-diagonal ``[..., 3M, 3M]`` (tangent)."""
        eye = torch.eye(3 * self.num_stars, dtype=self.r_inertial.dtype, device=self.r_inertial.device)
        if self.noise_model == "isotropic":
            return self.sigma**2 * eye
        b = self.body / torch.linalg.vector_norm(self.body, dim=-1, keepdim=True).clamp_min(1e-300)
        bbT = b.unsqueeze(-1) * b.unsqueeze(-2)  # [..., M, 3, 3]
        eye3 = torch.eye(3, dtype=b.dtype, device=b.device)
        blocks = self.sigma**2 * (eye3 - bbT) + self.radial_sigma**2 * bbT
        return _block_diag(blocks)

    def mask(self) -> Tensor | None:
        """Entry validity ``[..., 3M]`` (each star's mask repeated for its 3 axes)."""
        if self.star_mask is None:
            return None
        return self.star_mask.repeat_interleave(3, dim=-1)


def _block_diag(blocks: Tensor) -> Tensor:
    """``[..., M, 3, 3]`` → block-diagonal ``[..., 3M, 3M]`` (batched)."""
    M = blocks.shape[-3]
    eye_m = torch.eye(M, dtype=blocks.dtype, device=blocks.device)
    # out[..., 3i + a, 3j + b] = δ_ij blocks[..., i, a, b]
    out = eye_m[:, None, :, None] * blocks.unsqueeze(-2)  # [..., M, 3, M, 3]
    return out.reshape(*blocks.shape[:-3], 3 * M, 3 * M)
