"""Star-camera unit-vector measurement ``b_j = C(p) r_j + v_j`` (method.md §1).

Valid star vectors must have unit norm.  Catalogue vectors (``r_inertial``) and the
camera's observed directions (``body``, an observation's ``star_body``): off by at most
``1e-12`` they are taken as they are, by at most :data:`UNIT_TOLERANCE` they are
normalised with a warning, beyond it they are refused, naming the vector, its index and
its norm (:func:`unit_vectors`; the same rule as recorded sensor logs,
:mod:`agsf_torch.attitude.recordings`).  A measurement ``y`` handed to a filter is ``C r + v``
with the model's noise ``v``, unit only up to that noise: it is used as it is, and
refused only beyond ``max(UNIT_TOLERANCE, 10 σ)`` of the unit sphere (σ the radial noise
of the noise model; a larger radial draw has probability < 1e-22), which catches zero,
unnormalised or mis-scaled vectors (:meth:`StarVectorMeasurement.check_measurement`).
Vectors of masked-out stars are ignored (they must only be finite).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping

import numpy as np
import torch
from torch import Tensor

from ..attitude import physics
from ..fused.algebra import as_entries, as_tensor
from ..shapes import broadcast_shapes
from .base import MeasurementModel, check_finite, check_measurement_batch
from .derived import derived_from

__all__ = ["StarVectorMeasurement", "UNIT_TOLERANCE", "UNIT_ROUNDING", "unit_vectors"]

#: Largest |‖v‖ − 1| of a valid star vector that is normalised (with a warning) instead of refused.
UNIT_TOLERANCE = 1e-3
#: Below this |‖v‖ − 1| a vector is taken as it is (the rounding of a float64 normalisation).
UNIT_ROUNDING = 1e-12


#: A measured vector's radial noise beyond this many σ is taken for a malformed vector.
_RADIAL_NOISE_BOUND = 10.0


def _off_unit(name: str, v: Tensor, mask: Tensor | None, tolerance: float) -> tuple[Tensor, Tensor]:
    """``(‖v‖, |‖v‖ − 1|)`` of ``v [..., M, 3]`` (0 off the ``mask``); ``ValueError`` naming ``name``,
    the star, its batch index and its norm where ``|‖v‖ − 1| > tolerance``."""
    norm = torch.linalg.vector_norm(v.detach(), dim=-1)
    off = (norm - 1.0).abs()
    if mask is not None:
        off = torch.where(mask, off, torch.zeros_like(off))
    bad = off > tolerance
    if bool(bad.any()):
        idx = bad.nonzero()[0].tolist()
        value = float(torch.broadcast_to(norm, bad.shape)[tuple(idx)])
        raise ValueError(
            f"{name}: star {idx[-1]} at batch index {tuple(idx[:-1])} is not a unit vector (norm {value:.6g}); "
            f"valid star vectors must have unit norm within {tolerance:.3g}"
        )
    return norm, off


def unit_vectors(name: str, v: Tensor, mask: Tensor | None = None) -> Tensor:
    """``v [..., M, 3]`` with the valid rows (``mask [..., M]``, broadcasting; ``None``: all) checked
    to be unit vectors.

    ``|‖v‖ − 1| ≤ max(UNIT_ROUNDING, 100 ε)``: kept bit for bit; ``≤ UNIT_TOLERANCE``: normalised (``v/‖v‖``)
    with a warning; beyond (zero vectors included): ``ValueError`` naming ``name``, the star,
    its batch index and its norm.  Masked-out rows are returned unchanged.
    """
    norm, off = _off_unit(name, v, mask, UNIT_TOLERANCE)
    fix = off > max(UNIT_ROUNDING, 100.0 * torch.finfo(v.dtype).eps)  # rounding of the dtype
    if not bool(fix.any()):
        return v
    warnings.warn(
        f"{name}: star vectors off unit norm by up to {float(off.max()):.2e} (first at "
        f"{tuple(fix.nonzero()[0].tolist())}); normalised",
        stacklevel=3,
    )
    scale = torch.where(fix, torch.broadcast_to(norm, fix.shape), torch.ones_like(off)).to(v)
    return v / scale.unsqueeze(-1)


class StarVectorMeasurement(MeasurementModel):
    """``M`` star directions in one frame, stacked: ``h(x) = [C(p) r_1; …; C(p) r_M]``.

    The MRP is taken from the first three state entries, so the same measurement
    serves the 3-state and the 6-state attitude model.

    Noise models (``noise_model``):

    * ``"isotropic"`` (default, method.md): ``R = σ_s² I_{3M}``;
    * ``"tangent"``: per star ``R_j = σ_s² (I − b̃_j b̃_jᵀ) + σ_r² b̃_j b̃_jᵀ`` with the
      measured unit vector ``b̃_j`` (``body``): a camera's noise lies across the
      star direction (2 degrees of freedom per star); ``σ_r`` (``radial_sigma``,
      fixed, not scaled with σ_s) only keeps ``R`` invertible.

    The log-likelihood a filter reports (and learning maximises) is the data's under either model,
    2 degrees of freedom per star (:meth:`data_log_likelihood`).

    Args:
        r_inertial: catalogue unit vectors ``[..., M, 3]`` (leading dims are the
            trajectory batch).
        mask: ``[..., M]`` bool, ``True`` for a valid star (``None``: all valid).
            Masked stars contribute nothing to an update.
        sigma: σ_s, per-axis unit-vector noise (rad), > 0: a number, or ``[B]``, one per trajectory of the
            measurement ``y [B, 3M]`` (learning fits independent data sets this way; the fused update takes one).
        body: the measured unit vectors ``[..., M, 3]`` (needed by ``"tangent"``).

    Valid vectors of ``r_inertial`` and ``body`` must be unit vectors (:func:`unit_vectors`),
    and those of the measurement ``y`` handed to a filter unit up to the noise
    (:meth:`check_measurement`; module docstring).
    """

    #: Not probed by :func:`~agsf_torch.models.contract.check_measurement_elementwise` (checked otherwise).
    elementwise_checked = True

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
        try:  # one real, positive, finite number: bools, strings and complex numbers are refused alike
            sig = torch.as_tensor(sigma, dtype=torch.float64) if not isinstance(sigma, Tensor) else sigma
            real = not (isinstance(sigma, (bool, np.bool_)) or sig.dtype == torch.bool or sig.is_complex())
        except (TypeError, ValueError, RuntimeError):
            sig, real = None, False
        if not real or sig.dim() > 1 or not bool((sig > 0).all()) or not bool(sig.isfinite().all()):
            raise ValueError(f"sigma must be a positive finite scalar or [B] (rad), got {sigma!r}")
        if mask is not None:
            mask = torch.as_tensor(mask, dtype=torch.bool, device=r.device)
            if mask.shape != r.shape[:-1]:
                raise ValueError(
                    f"mask must have shape {tuple(r.shape[:-1])} (r_inertial[..., M]), got {tuple(mask.shape)}"
                )
        if body is not None:
            body = torch.as_tensor(body, dtype=r.dtype, device=r.device)
            if body.shape != r.shape:
                raise ValueError(f"body must have the shape of r_inertial {tuple(r.shape)}, got {tuple(body.shape)}")
            check_finite("body", body)
            body = unit_vectors("body", body, mask)
        r = unit_vectors("r_inertial", r, mask)
        self.num_stars = r.shape[-2]
        self.register_buffer("r_inertial", r)
        self.register_buffer("star_mask", mask)
        self.register_buffer("sigma", sig.to(r.dtype))
        self.register_buffer("body", body)

    @classmethod
    def from_observation(
        cls, obs: Mapping[str, Tensor], sigma: float | Tensor, **kwargs
    ) -> tuple[Tensor, StarVectorMeasurement]:
        """Build the measurement and the stacked vector ``y`` from an observation dict.

        Args:
            obs: with ``star_body [..., M, 3]``, ``star_inertial [..., M, 3]``,
                ``star_mask [..., M]`` (the environment's observation keys).
            sigma: σ_s (rad).

        Returns:
            ``(y [..., 3M], measurement)``; valid star vectors are checked (and, within
            :data:`UNIT_TOLERANCE`, normalised) as :func:`unit_vectors`.
        """
        missing = [key for key in ("star_body", "star_inertial", "star_mask") if key not in obs]
        if missing:
            raise ValueError(
                f"the observation has no {', '.join(missing)}: a star frame needs star_body, star_inertial and "
                f"star_mask (the environment's keys), got keys {sorted(obs)}"
            )
        body = torch.as_tensor(obs["star_body"])
        inertial = torch.as_tensor(obs["star_inertial"])
        if body.shape != inertial.shape:
            raise ValueError(
                f"star_body {tuple(body.shape)} and star_inertial {tuple(inertial.shape)} must have equal shapes"
            )
        if kwargs.get("noise_model") == "tangent":
            kwargs.setdefault("body", body)
        meas = cls(inertial, torch.as_tensor(obs["star_mask"]), sigma, **kwargs)
        if meas.body is not None and kwargs.get("body") is body:
            body = meas.body.to(body.dtype)  # checked (and normalised) by the constructor
        else:
            check_finite("star_body", body)
            body = unit_vectors("star_body", body, meas.star_mask)
        return body.flatten(-2), meas

    def check_measurement(self, y: Tensor) -> Tensor:
        """``y [..., 3M]`` (returned unchanged): the valid stars' measured vectors ``C r + v`` must lie
        within ``max(UNIT_TOLERANCE, 10 σ)`` of the unit sphere, σ the radial noise (σ_s, or
        ``radial_sigma`` for the tangent model) — a zero, unnormalised or mis-scaled vector is
        refused, naming the star, its batch index and its norm.  The catalogue vectors and the mask are one per
        trajectory of ``y`` or one for all (:func:`~agsf_torch.models.base.check_measurement_batch`)."""
        M = self.num_stars
        if y.dim() < 1 or y.shape[-1] != 3 * M:
            raise ValueError(
                f"y has shape {tuple(y.shape)}: {y.shape[-1] if y.dim() else 0} entries but the measurement model predicts {3 * M} (3 for each of {M} stars)"
            )
        check_measurement_batch("r_inertial (catalogue vectors)", self.r_inertial.shape[:-2], y)
        if self.star_mask is not None:
            check_measurement_batch("star_mask", self.star_mask.shape[:-1], y)
        check_measurement_batch("sigma", self.sigma.shape, y)
        radial = float(self.sigma.detach().max()) if self.noise_model == "isotropic" else self.radial_sigma
        _off_unit(
            "y (measured star vectors)",
            y.unflatten(-1, (M, 3)),
            self.star_mask,
            max(UNIT_TOLERANCE, _RADIAL_NOISE_BOUND * radial),
        )
        return y

    def _body_vectors(self, x: Tensor) -> tuple[list, list]:
        """``(bⱼ = C(p) rⱼ, p)`` as entries ``[..., M]`` and ``[..., 1]`` (:mod:`agsf_torch.attitude.physics`)."""
        p = as_entries(x[..., :3].unsqueeze(-2), (3,))  # [..., 1] against the stars [..., M]
        r = as_entries(self.r_inertial.to(x), (3,))
        return physics.star_vector(physics.attitude_matrix(p), r), p

    def predict(self, x: Tensor) -> Tensor:
        """``h(x) = vec(C(p) r_j)`` (:func:`~agsf_torch.attitude.physics.star_vector`): ``x [..., n]`` → ``[..., 3M]``."""
        return as_tensor(self._body_vectors(x)[0], like=x).flatten(-2)

    @derived_from("predict", "_body_vectors", generic=MeasurementModel.state_entries)
    def state_entries(self) -> tuple[int, ...] | None:
        """The MRP ``p``, entries 0–2: the star directions do not depend on the gyro bias."""
        return (0, 1, 2)

    @derived_from("predict", "_body_vectors", generic=MeasurementModel.jacobian)
    def jacobian(self, x: Tensor) -> Tensor:
        """Closed form ``∂(C(p) r)/∂p = [(C r)×] E``, ``E = 4B(p)ᵀ/(1+s)²``; zero on bias states
        (:func:`~agsf_torch.attitude.physics.star_jacobian`).

        From ``Ċ = −[ω×]C`` and ``ω = 4 B(p)ᵀ ṗ / (1+s)²``.

        Returns:
            ``[..., 3M, n]``.
        """
        b, p = self._body_vectors(x)
        H = physics.star_jacobian(b, physics.chart_map(p))
        return as_tensor([row + [None] * (x.shape[-1] - 3) for row in H], like=x).flatten(-3, -2)

    @derived_from("predict", "_body_vectors", "jacobian", "noise_cov", "mask", generic=MeasurementModel.fused_update)
    def fused_update(
        self,
        log_weights: Tensor,
        means: Tensor,
        covs: Tensor,
        y: Tensor,
        iterations: int = 1,
        *,
        mask: Tensor | None = None,
        mixture_nis: bool = True,
        compile: bool = False,
    ):
        """The star update in information form on lanes (:func:`agsf_torch.fused.star_update.fused_star_update`)
        for the isotropic noise model on a state whose first three entries are the MRP; ``None`` (the
        generic path) for the tangent model and for an eager call on fewer lanes than it pays for
        (:func:`~agsf_torch.fused.lanes.worth_fusing`)."""
        from ..fused.lanes import worth_fusing
        from ..fused.star_update import fused_star_update

        lanes = math.prod(broadcast_shapes(means.shape[:-1], y.shape[:-1] + (1,)))
        if (
            self.noise_model != "isotropic"
            or self.sigma.dim()
            or means.shape[-1] < 3
            or not worth_fusing(lanes, compile)
        ):
            return None
        return fused_star_update(
            log_weights, means, covs, y, self, iterations, mask=mask, mixture_nis=mixture_nis, compile=compile
        )

    @derived_from("noise_cov", generic=MeasurementModel.data_log_likelihood)
    def data_log_likelihood(self, log_weights: Tensor, nu: Tensor, HL: Tensor, y: Tensor, valid: Tensor) -> Tensor:
        """The log-likelihood of the measured directions, two degrees of freedom per valid star, under either
        noise model: the innovations across each measured unit vector ``b̃ⱼ``,

        .. math:: \\log Σ_i w_i N(T^T ν_i; 0, T^T H_i P_i H_i^T T + σ_s^2 I_{2m}),

        ``T`` block-diagonal with an orthonormal basis ``Tⱼ [3, 2]`` of the plane across ``b̃ⱼ`` (``Tⱼᵀ R Tⱼ =
        σ_s² I₂`` for both noise models: the noise of a unit vector lies across it).  The isotropic model's
        update spreads σ_s² over the third, radial axis too, where the data has no noise to show: its own
        ``log Σ wᵢβᵢ`` makes the maximum-likelihood σ_s √(2/3) of the camera's.  Evaluated in information form,
        ``A = TᵀHL`` (``[2m, k]``), ``G = I + AᵀA/σ²``, ``z = G⁻¹Aᵀν_t/σ²``:
        ``ν_tᵀS_t⁻¹ν_t = |ν_t − Az|²/σ² + |z|²`` and ``log det S_t = 2m log σ² + log det G``.

        Args: as :meth:`~agsf_torch.models.base.MeasurementModel.data_log_likelihood` (``d = 3M``).

        Returns:
            ``[...]``: 0 where no star is valid.
        """
        M = self.num_stars
        star_valid = valid.unflatten(-1, (M, 3))[..., 0].to(nu.dtype)  # [..., N, M]
        b = y.unflatten(-1, (M, 3))
        # an invalid star's vector may be anything (zeros between frames): a unit vector in its place, which
        # keeps the basis and its gradients finite, and its rows are zeroed below
        b = torch.where(star_valid.amax(-2).unsqueeze(-1) > 0, b, torch.tensor([0.0, 0.0, 1.0]).to(b))
        b = b / torch.linalg.vector_norm(b, dim=-1, keepdim=True)
        T = tangent_basis(b).unsqueeze(-4)  # [..., 1, M, 3, 2]
        nu_t = (T.transpose(-1, -2) @ nu.unflatten(-1, (M, 3)).unsqueeze(-1)).squeeze(-1)  # [..., N, M, 2]
        nu_t = nu_t * star_valid[..., None]
        A = T.transpose(-1, -2) @ HL.unflatten(-2, (M, 3))  # [..., N, M, 2, k]
        A = (A * star_valid[..., None, None]).flatten(-3, -2)  # [..., N, 2M, k]
        sigma2 = self.sigma.to(nu)[..., None] ** 2  # [..., 1] against the components [..., N]
        k = A.shape[-1]
        G = torch.eye(k, dtype=nu.dtype, device=nu.device) + A.transpose(-1, -2) @ A / sigma2[..., None, None]
        g = (A.transpose(-1, -2) @ nu_t.flatten(-2).unsqueeze(-1)) / sigma2[..., None, None]  # [..., N, k, 1]
        L = torch.linalg.cholesky(G)
        z = torch.cholesky_solve(g, L)  # [..., N, k, 1]: the minimiser below
        m = star_valid.sum(-1)  # [..., N]
        # ν_tᵀS_t⁻¹ν_t = min_z |ν_t − Az|²/σ² + |z|², a sum of squares at its minimiser (the difference
        # |ν_t|²/σ² − gᵀG⁻¹g cancels digits where a precise camera sees a wide prior)
        resid = nu_t.flatten(-2) - (A @ z).squeeze(-1)
        nis = (resid * resid).sum(-1) / sigma2 + (z * z).sum((-2, -1))
        log_det = 2.0 * m * torch.log(sigma2) + 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
        log_beta = -0.5 * (nis + log_det + 2.0 * m * math.log(2.0 * math.pi))
        log_lik = torch.logsumexp(log_weights + log_beta, -1)
        return torch.where(m[..., 0] > 0, log_lik, torch.zeros_like(log_lik))

    def noise_cov(self) -> Tensor:
        """``R``: ``σ_s² I_{3M}`` (isotropic) or block-diagonal ``[..., 3M, 3M]`` (tangent)."""
        eye = torch.eye(3 * self.num_stars, dtype=self.r_inertial.dtype, device=self.r_inertial.device)
        sigma = self.sigma.to(eye)[..., None, None]  # one per trajectory: [B, 1, 1], in the vectors' dtype
        if self.noise_model == "isotropic":
            return sigma**2 * eye
        b = self.body / torch.linalg.vector_norm(self.body, dim=-1, keepdim=True).clamp_min(1e-300)
        bbT = b.unsqueeze(-1) * b.unsqueeze(-2)  # [..., M, 3, 3]
        eye3 = torch.eye(3, dtype=b.dtype, device=b.device)
        blocks = sigma[..., None] ** 2 * (eye3 - bbT) + self.radial_sigma**2 * bbT
        return _block_diag(blocks)

    def mask(self) -> Tensor | None:
        """Entry validity ``[..., 3M]`` (each star's mask repeated for its 3 axes)."""
        if self.star_mask is None:
            return None
        return self.star_mask.repeat_interleave(3, dim=-1)


def tangent_basis(b: Tensor) -> Tensor:
    """An orthonormal basis ``[..., 3, 2]`` of the plane across each unit vector ``b [..., 3]``, continuous except
    where ``b_z`` changes sign (Duff et al., *Building an orthonormal basis, revisited*, JCGT 2017): with
    ``s = sign(b_z)``, ``a = −1/(s + b_z)``, ``c = b_x b_y a``, the columns are
    ``(1 + s b_x² a, s c, −s b_x)`` and ``(c, s + b_y² a, −b_y)``."""
    x, y, z = b.unbind(-1)
    s = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (s + z)
    c = x * y * a
    t1 = torch.stack((1.0 + s * x * x * a, s * c, -s * x), -1)
    t2 = torch.stack((c, s + y * y * a, -y), -1)
    return torch.stack((t1, t2), -1)


def _block_diag(blocks: Tensor) -> Tensor:
    """``[..., M, 3, 3]`` → block-diagonal ``[..., 3M, 3M]`` (batched)."""
    M = blocks.shape[-3]
    eye_m = torch.eye(M, dtype=blocks.dtype, device=blocks.device)
    # out[..., 3i + a, 3j + b] = δ_ij blocks[..., i, a, b]
    out = eye_m[:, None, :, None] * blocks.unsqueeze(-2)  # [..., M, 3, M, 3]
    return out.reshape(*blocks.shape[:-3], 3 * M, 3 * M)
