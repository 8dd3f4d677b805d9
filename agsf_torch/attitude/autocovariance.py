"""Autocovariance least squares (ALS): the gyro and star-camera noise from the autocovariances of innovations.

The baseline beside the maximum-likelihood fit through the filter (:mod:`.learning`): the method of Odelson,
Rajamani & Rawlings (*A new autocovariance least-squares method for estimating noise covariances*, Automatica
42, 2006) on the linearised attitude error, for the 3-state case (the gyro bias known).  It estimates the gyro's
angle random walk σ_v (rad/s^½) and the star camera's noise σ_s (rad per axis across the direction).

**Frame errors.**  A reference attitude ``A_ref(t)`` (inertial to body) is integrated from the attitude at row 0
with the bias-corrected gyro, one rotation by ``ω̃ Δt`` per gyro interval (the step of the simulator and of the
filters, :func:`~agsf_torch.rotations.rotvec_to_quat`):

.. math:: q_k = q(u_k (t_k - t_{k-1})) ⊗ q_{k-1},\\qquad u_k = ω̃_k - ½(b_{k-1} + b_k)

(``ω̃_k`` the reading over ``(t_{k-1}, t_k]``, ``b`` the known bias).  At each star frame ``k`` the stars alone
give ``A_star`` (Wahba's problem, :func:`~agsf_torch.attitude.star_fix.star_fix`), and the frame error is the
small rotation between the two, in the inertial frame:

.. math:: A_{star,k} = A_{ref,k}(I_3 - [z_k×]),\\qquad z_k = A_{ref,k}^T δθ_k

with ``δθ_k`` the body-frame error of :func:`~agsf_torch.rotations.attitude_error_vector`.  Gyro noise ``η``
over a step turns ``A_ref`` by ``(I − [ηΔt×])`` in the body frame, i.e. by ``A_trueᵀηΔt`` in the inertial frame:
an isotropic random walk there whatever the body does (in the body frame it would be rotated by the motion
between frames).  Star noise of σ_s per axis across each direction gives the Wahba solution the error
covariance ``σ_s² (Σ_j (I − b_j b_jᵀ))⁻¹`` in the body frame (the QUEST covariance), which is
``σ_s² M_k⁻¹``, ``M_k = Σ_j (I − r_j r_jᵀ)`` over the frame's catalogue vectors ``r_j = A_trueᵀ b_j``, in the
inertial frame.  A wrong start ``A_ref,0 = A_true,0 R₀`` stays the same inertial-frame rotation ``R₀`` at every
sample (the gyro turns both attitudes alike), so it adds a constant to ``z`` that the innovations below remove:
the true initial attitude is a convenience, not a need.

**Model** (frames ``k = 0 … K−1`` a uniform ``Δt_f`` apart):

.. math::
    θ_{k+1} = θ_k + w_k,\\quad w_k \\sim N(0, q I_3),\\quad q = σ_v^2 Δt_f;\\qquad
    z_k = θ_k + v_k,\\quad v_k \\sim N(0, r M_k^{-1}),\\quad r = σ_s^2.

(The simulated gyro's reading noise also holds a rate-random-walk part, ``q = (σ_v² + σ_u²Δt²/12) Δt_f`` for
gyro steps ``Δt``: below 1e-9 of σ_v² for the paper's gyro, and ignored.)

**Innovations with the deadbeat gain.**  ALS runs a fixed, stable filter and takes the autocovariances of its
innovations.  Here ``A = C = I₃``, and the gain ``L = I₃`` makes ``Ā = A − ALC = 0``: the predicted state is
the last measurement and the innovations are the differences

.. math:: e_k = z_{k+1} - z_k = w_k + v_{k+1} - v_k,\\qquad k = 0 … K-2,

which depend on no prior and have no transient.  Their autocovariances are linear in ``(q, r)``:

.. math::
    E[e_k e_k^T] = q I_3 + r (M_k^{-1} + M_{k+1}^{-1}),\\qquad
    E[e_{k+1} e_k^T] = -r M_{k+1}^{-1},\\qquad E[e_{k+j} e_k^T] = 0 \\;(j ≥ 2).

**Least squares.**  Odelson et al. stack the sample autocovariances of lags ``0 … N−1`` of a stationary
innovation sequence, ``Ĉ_j = (1/(n−j)) Σ_k e_{k+j} e_kᵀ``, and solve the unweighted least-squares problem
``min Σ_j |vec Ĉ_j − vec(q Q_j + r R_j)|²`` for the noise covariances.  The star geometry changes from frame to
frame, so the coefficients differ from product to product; each product is therefore its own regression row,
with its own known coefficient matrices:

.. math::
    \\min_{q, r} Σ_{j=0}^{N-1} Σ_k \\| e_{k+j} e_k^T - q\\, Q_{kj} - r\\, R_{kj} \\|_F^2,\\qquad
    Q_{k0} = I_3,\\; R_{k0} = M_k^{-1} + M_{k+1}^{-1},\\; R_{k1} = -M_{k+1}^{-1},

all other ``Q_{kj}, R_{kj}`` zero (summed over the trajectories of a data set too).  With constant geometry this
is Odelson's problem up to the weights ``n − j`` of the lags.  With the deadbeat gain the rows of lags ``j ≥ 2``
have zero coefficients: they change neither the solution nor anything but the residual, so ``N = 2`` is the
whole estimate and a larger ``N`` is accepted for the form's sake.  The problem is solved by
:func:`torch.linalg.lstsq` for every data set at once.

**Limits.**  The unweighted problem weighs every entry alike, so the large entries of the poorly observed axis
(the roll about the boresight, ``M_k``'s small eigenvalue) dominate it; ``q`` shows only as a small
addition to the lag-0 products and is weakly determined when ``q ≪ r |M_k⁻¹|``.  The least-squares solution
may then be negative.  It is returned as it is (``q``, ``r``), and the σ of a non-positive solution as NaN
with a flag; this baseline adds no semidefinite constraint (Rajamani & Rawlings, Automatica 45, 2009, constrain
the ALS solution to positive semidefinite covariances) and no weighting (Odelson et al.'s weighted form uses
the covariance of the sample autocovariances).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..rotations import attitude_error_vector, mrp_to_quat, quat_multiply, quat_to_dcm, quat_to_mrp, rotvec_to_quat
from .recordings import Recording
from .star_fix import star_fix

__all__ = [
    "FrameErrors",
    "ALSEstimate",
    "frame_errors",
    "innovation_products",
    "autocovariance_coefficients",
    "solve_autocovariance_ls",
    "autocovariance_least_squares",
]

F64 = torch.float64


@dataclass(frozen=True)
class FrameErrors:
    """The measurements of the ALS model (module docstring), ``B`` trajectories of ``K`` frames.

    Attributes:
        z: ``[B, K, 3]`` frame errors ``z_k`` (rad, inertial frame).
        information: ``[B, K, 3, 3]`` ``M_k = Σ_j (I − r_j r_jᵀ)`` over the frame's valid stars (dimensionless;
            the frame error's covariance is ``σ_s² M_k⁻¹``).
        rows: ``[K]`` the frames' sample indices in the recording.
        frame_period: ``Δt_f`` (s), the uniform time between frames.
    """

    z: Tensor
    information: Tensor
    rows: np.ndarray
    frame_period: float


@dataclass(frozen=True)
class ALSEstimate:
    """:func:`autocovariance_least_squares`'s result for ``D`` data sets.

    Attributes:
        sigma_v: ``[D]`` gyro angle random walk σ_v = √(q/Δt_f) (rad/s^½); NaN where ``q ≤ 0``.
        sigma_s: ``[D]`` star noise σ_s = √r (rad); NaN where ``r ≤ 0``.
        q: ``[D]`` the least-squares ``q`` (rad² per frame interval), any sign.
        r: ``[D]`` the least-squares ``r`` (rad²), any sign.
        q_positive / r_positive: ``[D]`` bool, the solution is positive (its σ is defined).
        frame_period: ``Δt_f`` (s); frames: ``K`` per trajectory; lags: ``N``.
    """

    sigma_v: Tensor
    sigma_s: Tensor
    q: Tensor
    r: Tensor
    q_positive: Tensor
    r_positive: Tensor
    frame_period: float
    frames: int
    lags: int


def _gyro_reference(q0: Tensor, steps: Tensor, rows: np.ndarray) -> Tensor:
    """The gyro-propagated attitude at the frame rows: ``q_k = s_k ⊗ q_{k−1}``, renormalised after each step
    as the simulator does (the one loop is over time).

    Args:
        q0: ``[B, 4]`` start (scalar-last unit quaternions, inertial to body).
        steps: ``[T−1, B, 4]`` step rotations ``s_k = q(u_k Δt_k)`` (time-major).
        rows: ``[K]`` increasing sample indices.

    Returns:
        ``[B, K, 4]``.
    """
    wanted = set(rows.tolist())
    kept = [q0] if 0 in wanted else []
    q = q0
    for k in range(1, int(rows[-1]) + 1):
        q = quat_multiply(steps[k - 1], q)
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        if k in wanted:
            kept.append(q)
    return torch.stack(kept, 1)


def _start_attitude(rec: Recording, initial_mrp: Tensor | None) -> Tensor:
    """The attitude at row 0 ``[B, 3]`` (MRP): ``initial_mrp``, else the recording's ``truth_mrp[:, 0]``, else
    its ``initial_mrp`` column."""
    B = rec.num_trajectories
    if initial_mrp is None:
        if rec.truth_mrp is not None:
            return torch.as_tensor(rec.truth_mrp[:, 0], dtype=F64)
        if rec.initial_mrp is not None:
            return torch.as_tensor(rec.initial_mrp, dtype=F64)
        raise ValueError(
            "autocovariance_least_squares needs the attitude at row 0 to start the gyro reference: pass initial_mrp "
            "[B, 3] or give the recording a truth_mrp or initial_mrp column"
        )
    p0 = torch.as_tensor(initial_mrp, dtype=F64)
    if p0.shape != (B, 3):
        raise ValueError(f"initial_mrp must have shape [{B}, 3] (MRP per trajectory), got {tuple(p0.shape)}")
    if not bool(torch.isfinite(p0).all()):
        raise ValueError("initial_mrp must be finite")
    return p0


def _interval_bias(rec: Recording, bias: Tensor | None) -> Tensor:
    """The bias to remove from each gyro interval ``[B, T−1, 3]`` (rad/s): ``½(b_{k−1} + b_k)`` of the
    recording's ``truth_bias`` (the 3-state filter's known bias), or a constant ``bias [B, 3]``."""
    B, T = rec.num_trajectories, rec.num_samples
    if bias is None:
        if rec.truth_bias is None:
            raise ValueError(
                "autocovariance_least_squares needs the gyro bias as known: the recording has no truth_bias column; "
                "pass bias [B, 3] (rad/s)"
            )
        b = torch.as_tensor(rec.truth_bias, dtype=F64)
        return 0.5 * (b[:, :-1] + b[:, 1:])
    b = torch.as_tensor(bias, dtype=F64)
    if b.shape != (B, 3):
        raise ValueError(f"bias must have shape [{B}, 3] (rad/s per trajectory), got {tuple(b.shape)}")
    if not bool(torch.isfinite(b).all()):
        raise ValueError("bias must be finite")
    return b[:, None].expand(B, T - 1, 3)


def _frame_rows(rec: Recording) -> tuple[np.ndarray, float]:
    """The frame rows ``[K]`` shared by every trajectory and their uniform spacing ``Δt_f`` (s).

    A frame is a sample with any valid star.  The timestamps' precision sets the tolerance on the spacing, as
    for the samples of a replay: ``4 ε max|t| + 10⁻⁹ Δt_f``.
    """
    has = rec.star_mask.any(-1)  # [B, T]
    differ = has != has[:1]
    if differ.any():
        b, t = (int(i) for i in np.argwhere(differ)[0])
        raise ValueError(
            f"the star frames differ between trajectories: trajectory {b} {'has' if has[b, t] else 'lacks'} a frame "
            f"at row {t} (time {rec.time[t]:g} s) that trajectory 0 {'lacks' if has[b, t] else 'has'}; ALS needs "
            "the same frame times in every trajectory"
        )
    rows = np.flatnonzero(has[0])
    if rows.size < 3:
        raise ValueError(
            f"ALS needs at least 3 star frames per trajectory (two innovations, lags 0 and 1), got {rows.size}"
        )
    times = rec.time[rows]
    gaps = np.diff(times)
    period = float((times[-1] - times[0]) / (rows.size - 1))
    tol = 4.0 * float(np.finfo(np.float64).eps) * float(np.abs(times).max()) + 1e-9 * period
    worst = int(np.argmax(np.abs(gaps - period)))
    if abs(gaps[worst] - period) > tol:
        raise ValueError(
            f"the star frames are not uniformly spaced: frames at rows {rows[worst]} and {rows[worst + 1]} are "
            f"{gaps[worst]:g} s apart against a mean of {period:g} s; ALS needs one frame period (q = σ_v² Δt_f)"
        )
    return rows, period


def frame_errors(rec: Recording, *, initial_mrp: Tensor | None = None, bias: Tensor | None = None) -> FrameErrors:
    """The frame errors ``z_k`` and star information ``M_k`` of a recording (module docstring).

    Args:
        rec: ``B`` trajectories; every gyro sample valid, the same uniformly spaced star frames (samples with any
            valid star) in every trajectory, each with at least two non-parallel stars.
        initial_mrp: ``[B, 3]`` the attitude at row 0 (MRP) the gyro reference starts from; default the
            recording's ``truth_mrp[:, 0]``, else its ``initial_mrp`` column.
        bias: ``[B, 3]`` a constant gyro bias to remove (rad/s); default the recording's ``truth_bias``, removed
            as ``½(b_{k−1} + b_k)`` over each interval as the 3-state filter does.

    Returns:
        :class:`FrameErrors` (``z [B, K, 3]`` rad, ``information [B, K, 3, 3]``).

    Raises:
        ValueError: naming what is missing or wrong: no bias or start attitude, an invalid gyro sample, fewer than
        3 frames, frames differing between trajectories or not uniformly spaced, a frame determining no attitude,
        a bad ``initial_mrp`` / ``bias`` shape.
    """
    if rec.gyro_valid is not None and not rec.gyro_valid.all():
        b, t = (int(i) for i in np.argwhere(~rec.gyro_valid)[0])
        raise ValueError(
            f"gyro sample invalid at trajectory {b}, row {t} (column 'gyro_valid'): the ALS reference integrates "
            "every gyro reading and bridges no gap"
        )
    rows, period = _frame_rows(rec)
    p0 = _start_attitude(rec, initial_mrp)
    b_interval = _interval_bias(rec, bias)
    gyro = torch.as_tensor(rec.gyro, dtype=F64)
    dt = torch.as_tensor(np.diff(rec.time), dtype=F64)
    steps = rotvec_to_quat(((gyro[:, 1:] - b_interval) * dt[:, None]).transpose(0, 1).contiguous())
    q_ref = _gyro_reference(mrp_to_quat(p0), steps, rows)  # [B, K, 4]

    body = torch.as_tensor(rec.star_body[:, rows], dtype=F64)
    inertial = torch.as_tensor(rec.star_inertial[:, rows], dtype=F64)
    mask = torch.as_tensor(rec.star_mask[:, rows])
    p_star, ok = star_fix(body, inertial, mask)
    if not bool(ok.all()):
        b, k = (int(i) for i in (~ok).nonzero()[0])
        raise ValueError(
            f"the star frame at row {rows[k]} (time {rec.time[rows[k]]:g} s) of trajectory {b} determines no "
            f"attitude ({int(mask[b, k].sum())} valid star(s), fewer than two non-parallel ones)"
        )
    dtheta = attitude_error_vector(p_star, quat_to_mrp(q_ref))  # body frame of the reference
    z = (quat_to_dcm(q_ref).transpose(-1, -2) @ dtheta[..., None]).squeeze(-1)
    r = torch.where(mask[..., None], inertial, 0.0)
    eye = torch.eye(3, dtype=F64)
    information = mask.sum(-1).to(F64)[..., None, None] * eye - r.transpose(-1, -2) @ r
    return FrameErrors(z=z, information=information, rows=rows, frame_period=period)


def _check_lags(lags: int, innovations: int) -> None:
    if isinstance(lags, bool) or not isinstance(lags, int) or not 1 <= lags <= innovations:
        raise ValueError(
            f"lags must be an integer in [1, {innovations}] (the innovations of {innovations + 1} frames), got {lags!r}"
        )


def innovation_products(z: Tensor, lags: int) -> Tensor:
    """The products ``e_{k+j} e_kᵀ`` of the deadbeat innovations ``e_k = z_{k+1} − z_k``.

    Args:
        z: ``[..., K, 3]`` frame errors (rad).
        lags: ``N``, lags ``j = 0 … N−1`` (``N ≤ K − 1``).

    Returns:
        ``[..., N, K−1, 3, 3]`` (rad²): entry ``[j, k]`` is ``e_{k+j} e_kᵀ``, zero where ``k + j > K − 2``.
    """
    e = z[..., 1:, :] - z[..., :-1, :]
    n = e.shape[-2]
    _check_lags(lags, n)
    out = torch.zeros(*e.shape[:-2], lags, n, 3, 3, dtype=e.dtype, device=e.device)
    for j in range(lags):
        out[..., j, : n - j, :, :] = e[..., j:, :, None] * e[..., : n - j, None, :]
    return out


def autocovariance_coefficients(information: Tensor, lags: int) -> Tensor:
    """The known coefficient matrices of ``(q, r)`` in each product's expectation,
    ``E[e_{k+j} e_kᵀ] = q Q_{kj} + r R_{kj}`` (module docstring).

    ``M_k⁻¹`` comes from a Cholesky solve.

    Args:
        information: ``[..., K, 3, 3]`` ``M_k`` (symmetric positive definite).
        lags: ``N``, lags ``j = 0 … N−1`` (``N ≤ K − 1``).

    Returns:
        ``[..., N, K−1, 2, 3, 3]``: ``[j, k, 0]`` is ``Q_{kj}`` (``I₃`` at lag 0, else 0), ``[j, k, 1]`` is
        ``R_{kj}`` (``M_k⁻¹ + M_{k+1}⁻¹`` at lag 0, ``−M_{k+1}⁻¹`` at lag 1, else 0); zero where
        ``k + j > K − 2``.
    """
    eye = torch.eye(3, dtype=information.dtype, device=information.device)
    chol = torch.linalg.cholesky(information)
    N = torch.cholesky_solve(eye.expand_as(information), chol)  # M_k⁻¹ [..., K, 3, 3]
    n = N.shape[-3] - 1
    _check_lags(lags, n)
    out = torch.zeros(*N.shape[:-3], lags, n, 2, 3, 3, dtype=N.dtype, device=N.device)
    out[..., 0, :, 0, :, :] = eye
    out[..., 0, :, 1, :, :] = N[..., :-1, :, :] + N[..., 1:, :, :]
    if lags > 1:
        out[..., 1, : n - 1, 1, :, :] = -N[..., 1:-1, :, :]
    return out


def solve_autocovariance_ls(products: Tensor, coefficients: Tensor, *, datasets: int) -> tuple[Tensor, Tensor]:
    """The unweighted least-squares ``(q, r)`` of each data set (module docstring), batched over data sets.

    Every entry of every product is one row: ``vec(e_{k+j} e_kᵀ) ≈ q vec Q_{kj} + r vec R_{kj}``.  The ``B``
    trajectories are grouped consecutively into ``D = datasets`` data sets, each solved on its own rows by one
    batched :func:`torch.linalg.lstsq`.

    Args:
        products: ``[B, N, K−1, 3, 3]`` (:func:`innovation_products`, or their expectations).
        coefficients: ``[B, N, K−1, 2, 3, 3]`` (:func:`autocovariance_coefficients`).
        datasets: ``D``, dividing ``B``.

    Returns:
        ``(q [D], r [D])`` (rad² per frame interval, rad²).
    """
    B = products.shape[0]
    if products.shape[-2:] != (3, 3) or coefficients.shape != (*products.shape[:-2], 2, 3, 3):
        raise ValueError(
            f"products [B, N, K−1, 3, 3] and coefficients [B, N, K−1, 2, 3, 3] must agree, got "
            f"{tuple(products.shape)} and {tuple(coefficients.shape)}"
        )
    if isinstance(datasets, bool) or not isinstance(datasets, int) or datasets < 1 or B % datasets:
        raise ValueError(f"datasets must be a positive integer dividing B = {B}, got {datasets!r}")
    rows_y = products.reshape(datasets, -1, 1)
    rows_a = coefficients.movedim(-3, -1).reshape(datasets, -1, 2)
    x = torch.linalg.lstsq(rows_a, rows_y).solution[..., 0]
    return x[:, 0], x[:, 1]


def autocovariance_least_squares(
    rec: Recording,
    *,
    datasets: int = 1,
    lags: int = 2,
    initial_mrp: Tensor | None = None,
    bias: Tensor | None = None,
) -> ALSEstimate:
    """σ_v and σ_s of each data set by autocovariance least squares (module docstring), in one batched program.

    .. math:: \\hat σ_v = \\sqrt{\\hat q / Δt_f},\\qquad \\hat σ_s = \\sqrt{\\hat r}

    Args:
        rec: ``B`` trajectories (see :func:`frame_errors` for what they must hold).
        datasets: ``D``: the trajectories are grouped consecutively into ``D`` data sets of ``B / D``, each
            estimated on its own.
        lags: ``N ≥ 2`` autocovariance lags ``0 … N−1`` (at most ``K − 1``; lags ≥ 2 do not move the solution).
        initial_mrp, bias: as :func:`frame_errors`.

    Returns:
        :class:`ALSEstimate` (``[D]`` each): a non-positive ``q`` or ``r`` is kept as it is and its σ is NaN,
        flagged by ``q_positive`` / ``r_positive``.

    Raises:
        ValueError: ``datasets`` not a positive integer dividing ``B``, ``lags`` not an integer in
        ``[2, K − 1]``, and whatever :func:`frame_errors` refuses.
    """
    B = rec.num_trajectories
    if isinstance(datasets, bool) or not isinstance(datasets, int) or datasets < 1:
        raise ValueError(f"datasets must be a positive integer, got {datasets!r}")
    if B % datasets:
        raise ValueError(f"{B} trajectories do not split into {datasets} data sets of equal size")
    if isinstance(lags, bool) or not isinstance(lags, int) or lags < 2:
        raise ValueError(f"lags must be an integer ≥ 2 (lag 1 separates q from r), got {lags!r}")
    errors = frame_errors(rec, initial_mrp=initial_mrp, bias=bias)
    K = errors.z.shape[1]
    if lags > K - 1:
        raise ValueError(f"lags must be at most K − 1 = {K - 1} (the innovations of {K} frames), got {lags}")
    q, r = solve_autocovariance_ls(
        innovation_products(errors.z, lags),
        autocovariance_coefficients(errors.information, lags),
        datasets=datasets,
    )
    nan = torch.full_like(q, float("nan"))
    q_pos, r_pos = q > 0, r > 0
    return ALSEstimate(
        sigma_v=torch.where(q_pos, torch.sqrt(q.clamp_min(0.0) / errors.frame_period), nan),
        sigma_s=torch.where(r_pos, torch.sqrt(r.clamp_min(0.0)), nan),
        q=q,
        r=r,
        q_positive=q_pos,
        r_positive=r_pos,
        frame_period=errors.frame_period,
        frames=K,
        lags=lags,
    )
