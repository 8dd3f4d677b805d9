"""Measurement update of every mixture component (method.md §2).

For each component, with ``H = ∂h/∂x`` at the predicted mean:

.. math::

    S = H P H^T + R,\\quad K = P H^T S^{-1},\\quad μ^+ = μ + K(\\tilde y - h(μ)),

    P^+ = (I - KH) P (I - KH)^T + K R K^T \\quad\\text{(Joseph form)},

    \\log w^+ = \\log w + \\log N(\\tilde y; h(μ), S) - \\operatorname{logsumexp}(\\cdot).

Solves go through Cholesky factors; no inverse is formed.  Invalid measurement
entries (a mask) are removed exactly: their rows of ``H`` and of the innovation
are zeroed and their block of ``R`` is replaced by the identity, so they change
neither the state nor the likelihood; a trajectory with no valid entry is
returned unchanged.

**Two forms of the gain.**  The covariance form above solves with the Cholesky
factor of ``S``.  A unit-vector measurement makes ``H P Hᵀ`` singular along each
star direction, so ``cond(S) ≈ λ_max(HPHᵀ)/σ²`` (≈ 4·10⁸ for σ = 10 µrad after a
1e-3 prior, ≈ 4·10¹⁶ for σ = 1 nrad): the gain's rounding error grows like
``ε·cond(S)`` and beyond ``1/ε`` the factorisation fails.  Where the Cholesky
factor of ``S`` shows ``(max ℓᵢ / min ℓᵢ)² > COVARIANCE_FORM_MAX_CONDITION``
(``ℓᵢ = Lᵢᵢ/√Sᵢᵢ``: a lower bound of the condition of ``S`` scaled to unit diagonal;
the limit scales with the dtype's ε) or the factorisation fails, the same gain is formed
in information form (push-through identity), which never factors ``S``:

.. math::

    P = L_P L_P^T,\\; R = L_R L_R^T,\\; G = L_R^{-1} H L_P,\\;
    M = I + G^T G = R_M^T R_M \\;(\\text{QR of } [G; I]),

    K = L_P M^{-1} G^T L_R^{-1} \\;(= P H^T S^{-1}),\\qquad
    \\log\\det S = \\log\\det R + \\log\\det M,

    ν^T S^{-1} ν = \\lVert L_R^{-1}(ν - H δx)\\rVert^2 + \\lVert L_P^{-1} δx\\rVert^2,\\quad δx = Kν.

``M ⪰ I`` whatever the conditioning, and its QR factor is backward stable, so the
gain stays accurate to rounding; the Joseph form then keeps ``P⁺`` symmetric
positive definite.  Below the threshold the covariance form is used unchanged.

**Input checks** (:func:`check_innovation`, one batched reduction): the update
refuses a non-finite mean, measurement or prediction, and an innovation entry
more than ``1/ε`` of its predicted standard deviations ``√Sᵢᵢ`` — a value no
float64 update can resolve (wrong units, a corrupted value) — naming it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from .models.base import MeasurementModel
from .models.derived import provides
from .shapes import broadcast_shapes

__all__ = [
    "COVARIANCE_FORM_MAX_CONDITION",
    "LINEAR_POSTERIOR",
    "PLAIN_POSTERIOR_PROBABILITY",
    "ComponentUpdate",
    "check_innovation",
    "cholesky_axes",
    "covariance_form_usable",
    "evaluate_measurement",
    "gram_factor",
    "kalman_update",
    "measurement_curvature",
    "measurement_second_differences",
    "moment_matched_factor",
    "moment_matched_innovation",
    "second_order_size",
]

#: Largest lower bound ``(max ℓᵢ / min ℓᵢ)²`` of the condition of the correlation matrix
#: ``D^{-½} S D^{-½}`` (``ℓᵢ = Lᵢᵢ/√Sᵢᵢ``, over valid entries) at which a gain or NIS is computed
#: with the Cholesky factor ``L`` of ``S`` in float64; above it the square-root / information form
#: is used.  ``ε·10¹⁰ ≈ 2·10⁻⁶``: the covariance form's relative error bound.  Other dtypes scale
#: it by ``ε_float64 / ε`` (the same error bound: about 18 in float32).
COVARIANCE_FORM_MAX_CONDITION = 1e10

#: The second-order update of an iterated update keeps its plain posterior for a mixture where, for every active
#: component, the measurement's second-order part over that component's posterior, :func:`second_order_size` (the
#: expected squared size of ``h − h_lin`` in noise units, dimensionless), is at most this: a tenth of one noise
#: variance summed over the entries, where the Gaussian posterior of the iterated update's Laplace approximation
#: is accurate.
LINEAR_POSTERIOR = 0.1

#: ... and where the frame agrees with the mixture's prediction: its moment-matched NIS at most the ``χ²_d``
#: quantile at this probability (``d`` the frame's valid entries).  A posterior that is narrow about a mode the
#: data contradict (every component far from the truth) is no evidence that the iterates found the posterior;
#: there the prior's terms keep the frame's weight down, as they do for a component still wide.
PLAIN_POSTERIOR_PROBABILITY = 0.999


@dataclass(frozen=True)
class ComponentUpdate:
    """Result of :func:`kalman_update`.

    Attributes:
        means: ``[..., N, n]``; covs: ``[..., N, n, n]``; log_weights: ``[..., N]`` (normalised).
        log_likelihood: ``log Σᵢ wᵢ βᵢ``, the measurement log-likelihood of the mixture, ``[...]``.
        nis: normalised innovation squared of each component, ``νᵀS⁻¹ν``, ``[..., N]``.
        dof: number of valid measurement entries, ``[...]``.
        innovation: ``ν = ỹ − h(μ)`` ``[..., N, d]`` (zero at masked entries).
        innovation_cov: ``S`` ``[..., N, d, d]``.
        nis_mixture: NIS of the moment-matched mixture prediction ``ν̄ᵀ S̄⁻¹ ν̄``
            (:func:`moment_matched_innovation` with the prior weights), ``[...]``; ``None`` when
            not asked for (``kalman_update(..., mixture_nis=False)``).
    """

    means: Tensor
    covs: Tensor
    log_weights: Tensor
    log_likelihood: Tensor
    nis: Tensor
    dof: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    nis_mixture: Tensor | None


def moment_matched_innovation(log_weights: Tensor, nu: Tensor, S: Tensor) -> tuple[Tensor, Tensor]:
    """The mixture's predicted innovation, moment-matched over its components:

    .. math:: \\bar ν = \\sum_i w_i ν_i,\\qquad
              \\bar S = \\sum_i w_i \\left(S_i + (ν_i - \\bar ν)(ν_i - \\bar ν)^T\\right).

    Used for the mixture NIS of an update and by the innovation gate (per block).

    Args:
        log_weights: ``[..., N]``; nu: component innovations ``[..., N, k]``;
        S: their covariances ``[..., N, k, k]``.

    Returns:
        ``(ν̄ [..., k], S̄ [..., k, k])``.
    """
    w = log_weights.exp()
    nu_bar = (w[..., None] * nu).sum(-2)
    dn = nu - nu_bar.unsqueeze(-2)
    # Σ wᵢSᵢ and Σ wᵢ dnᵢdnᵢᵀ = dnᵀ diag(w) dn as contractions, without an [..., N, k, k] temporary
    spread = (w[..., None] * dn).transpose(-1, -2) @ dn
    S_bar = torch.einsum("...i,...ijk->...jk", w, S) + 0.5 * (spread + spread.transpose(-1, -2))
    return nu_bar, S_bar


def gram_factor(A: Tensor) -> Tensor:
    """Lower-triangular ``L`` with ``L Lᵀ = A Aᵀ`` and ``Lᵢᵢ ≥ 0``, from a QR of ``Aᵀ`` (``Aᵀ = QU``, ``L = Uᵀ``).

    Backward stable: ``L`` is the exact factor of ``(A + E)(A + E)ᵀ`` with ``|E| = O(ε|A|)``,
    so it is nonsingular whenever ``A``'s smallest singular value exceeds ``O(ε|A|)`` — e.g.
    ``A = [H L_P, L_R]`` (``S = AAᵀ``) with ``R`` positive definite — however ill-conditioned ``AAᵀ`` is.

    Args:
        A: ``[..., d, k]`` with ``k ≥ d``.

    Returns:
        ``L [..., d, d]``.
    """
    U = torch.linalg.qr(A.transpose(-1, -2)).R  # [..., d, d] upper
    sign = torch.where(U.diagonal(dim1=-2, dim2=-1) < 0, -1.0, 1.0).to(U)
    return (sign[..., :, None] * U).transpose(-1, -2)


def covariance_form_usable(L: Tensor, info: Tensor, valid: Tensor | None, S: Tensor) -> Tensor:
    """Whether the Cholesky factor ``L`` of ``S`` (from ``torch.linalg.cholesky_ex``) is fit for solves:
    the factorisation succeeded and ``(max ℓᵢ / min ℓᵢ)² ≤ COVARIANCE_FORM_MAX_CONDITION·ε₆₄/ε`` with
    ``ℓᵢ = Lᵢᵢ / √Sᵢᵢ`` (the pivots of the correlation matrix ``D^{-½} S D^{-½}``, so entries in
    different units do not count as ill-conditioning) over the valid entries (masked entries have
    decoupled unit pivots and are left out).

    Args:
        L: ``[..., d, d]``; info: ``[...]``; valid: ``[..., d]`` (bool or 0/1), or ``None`` (every entry);
            S: ``[..., d, d]``.

    Returns:
        ``[...]`` bool.
    """
    piv = L.diagonal(dim1=-2, dim2=-1) / S.diagonal(dim1=-2, dim2=-1).clamp_min(torch.finfo(S.dtype).tiny).sqrt()
    if valid is None:
        big, small = piv.amax(-1), piv.amin(-1)
    else:
        v = valid.to(torch.bool)
        big = torch.where(v, piv, torch.zeros_like(piv)).amax(-1)
        small = torch.where(v, piv, torch.full_like(piv, math.inf)).amin(-1)
    limit = COVARIANCE_FORM_MAX_CONDITION * torch.finfo(torch.float64).eps / torch.finfo(S.dtype).eps
    return (info == 0) & (big <= small * math.sqrt(limit))


def moment_matched_factor(log_weights: Tensor, nu: Tensor, HL: Tensor, L_R: Tensor) -> tuple[Tensor, Tensor]:
    """``ν̄`` and a lower Cholesky factor of ``S̄`` (:func:`moment_matched_innovation`) from square roots,
    never forming ``S̄``:

    .. math:: \\bar S = A A^T,\\quad A = \\left[\\sqrt{w_i}\\, H_i L_{P,i}\\;(i = 1..N),\\;
              \\sqrt{w_i}\\,(ν_i - \\bar ν)\\;(i = 1..N),\\; \\sqrt{\\textstyle\\sum_i w_i}\\, L_R\\right],

    factored by :func:`gram_factor` (``S_i = H_i P_i H_iᵀ + R`` with one ``R`` for all components).

    Args:
        log_weights: ``[..., N]``; nu: ``[..., N, k]``; HL: ``H_i L_{P,i}`` ``[..., N, k, n]``;
        L_R: a lower factor of ``R`` ``[..., k, k]``.

    Returns:
        ``(ν̄ [..., k], L̄ [..., k, k])``.
    """
    w = log_weights.exp()
    nu_bar = (w[..., None] * nu).sum(-2)
    sw = w.sqrt()
    dn = (sw[..., None] * (nu - nu_bar.unsqueeze(-2))).transpose(-1, -2)  # [..., k, N]
    spread = (sw[..., None, None] * HL).movedim(-3, -2)  # [..., k, N, n]
    spread = spread.reshape(*spread.shape[:-2], -1)  # [..., k, N n]
    rn = w.sum(-1).sqrt()[..., None, None] * L_R
    batch = broadcast_shapes(spread.shape[:-2], dn.shape[:-2], rn.shape[:-2])
    k = nu.shape[-1]
    A = torch.cat([t.expand(*batch, k, t.shape[-1]) for t in (spread, dn, rn)], -1)
    return nu_bar, gram_factor(A)


def _first_index(bad: Tensor) -> list[int]:
    return bad.nonzero()[0].tolist()


def check_innovation(y: Tensor, means: Tensor, h: Tensor, S_diag: Tensor, valid: Tensor) -> None:
    """Refuse an update that no float64 arithmetic can carry out, naming the cause (before anything changes).

    Passes when every innovation entry ``νⱼ = ỹⱼ − hⱼ(μ)`` is finite and, on the valid entries,
    ``ε |νⱼ| ≤ √Sⱼⱼ`` (an innovation of more than ``1/ε ≈ 4.5·10¹⁵`` predicted standard deviations
    is below the rounding of ``ν`` itself).  One batched reduction on success; on failure the
    first cause is named in this order: a non-finite state mean, measurement, prediction
    ``h(μ)`` or innovation variance ``Sⱼⱼ``, then the out-of-range innovation.

    Args:
        y: ``[..., 1, d]`` (broadcast over components); means: ``[..., N, n]``;
        h: ``[..., N, d]``; S_diag: ``diag(S)`` ``[..., N, d]``; valid: ``[..., N, d]`` (bool or 0/1).

    Raises:
        ValueError: naming the quantity, the trajectory index, the component and the entry.
    """
    nu = y - h
    eps = torch.finfo(nu.dtype).eps
    v = valid.to(torch.bool)
    ok = torch.isfinite(nu) & (~v | (eps * nu.abs() <= S_diag.sqrt()))
    if bool(ok.all()):
        return
    if not bool(torch.isfinite(means).all()):
        idx = _first_index(~torch.isfinite(means))
        raise ValueError(
            f"the state mean is not finite at trajectory index {tuple(idx[:-2])}, component {idx[-2]} "
            f"(entry {idx[-1]}): the update needs a finite prior mean"
        )
    yb = y.expand(h.shape)
    if not bool(torch.isfinite(yb).all()):
        idx = _first_index(~torch.isfinite(yb))
        raise ValueError(f"the measurement y is not finite at trajectory index {tuple(idx[:-2])}, entry {idx[-1]}")
    if not bool(torch.isfinite(h).all()):
        idx = _first_index(~torch.isfinite(h))
        raise ValueError(
            f"the measurement model's prediction h(μ) is not finite at trajectory index {tuple(idx[:-2])}, "
            f"component {idx[-2]}, entry {idx[-1]} (the model is undefined at this mean)"
        )
    bad_S = v & ~(S_diag > 0)  # NaN or non-positive
    if bool(bad_S.any()):
        idx = _first_index(bad_S)
        raise ValueError(
            f"the innovation variance S = H P Hᵀ + R is {float(S_diag[tuple(idx)]):.3g} at trajectory index "
            f"{tuple(idx[:-2])}, component {idx[-2]}, entry {idx[-1]}: the component covariance, the model's "
            "Jacobian or its noise covariance is not finite or not positive"
        )
    idx = _first_index(~ok)
    at = tuple(idx)
    z = float(nu[at].abs() / S_diag[at].sqrt())
    raise ValueError(
        f"measurement entry {idx[-1]} at trajectory index {tuple(idx[:-2])}, component {idx[-2]} is absurd: "
        f"ỹ = {float(yb[at]):.6g} against the prediction h(μ) = {float(h[at]):.6g} with √S = {float(S_diag[at].sqrt()):.3g}, "
        f"{z:.3g} standard deviations away (more than 1/ε = {1.0 / eps:.3g}): a measurement in the wrong units or a corrupted value"
    )


def cholesky_axes(means: Tensor, covs: Tensor) -> Tensor:
    """The points ``m``, ``m + s_k``, ``m − s_k`` of each component (``s_k = L e_k``, ``P = LLᵀ``, ``k = 1…n``):
    ``[..., N, 2n + 1, n]`` from ``means [..., N, n]`` and ``covs [..., N, n, n]``."""
    return _axis_points(means, torch.linalg.cholesky(covs).transpose(-1, -2))


def _axis_points(means: Tensor, s: Tensor) -> Tensor:
    """``m``, ``m + s_k``, ``m − s_k``: ``[..., N, 2r + 1, n]`` from ``means [..., N, n]`` and the axes
    ``s [..., N, r, n]`` (row ``k``: ``s_k``)."""
    m = means.unsqueeze(-2)
    return torch.cat((m, m + s, m - s), -2)


def measurement_curvature(means: Tensor, covs: Tensor, measurement: MeasurementModel) -> Tensor:
    """The measurement's second differences along each component's axes, ``[..., N, n, d]``:

    .. math:: c_k = h(μ + s_k) + h(μ − s_k) − 2h(μ),\\qquad s_k = L e_k,\\; P = LL^T

    (``≈ s_kᵀ∇²h s_k``, exact for a quadratic ``h``), in the measurement's units.

    Args:
        means: ``[..., N, n]``; covs: ``[..., N, n, n]``.
    """
    return _second_differences(means, covs, measurement, mixed=False)[0]


def measurement_second_differences(means: Tensor, covs: Tensor, measurement: MeasurementModel) -> tuple[Tensor, Tensor]:
    """The measurement's second differences along each component's axes and across each pair of them:
    ``c [..., N, r, d]`` (:func:`measurement_curvature`'s where ``r = n``) and, for the ``r(r − 1)/2`` pairs
    ``k < l`` (in the order of ``torch.triu_indices(r, r, 1)``), ``[..., N, r(r − 1)/2, d]``

    .. math:: M_{kl} = h(μ + s_k + s_l) − h(μ + s_k) − h(μ + s_l) + h(μ)

    (``≈ s_kᵀ∇²h s_l``, exact for a quadratic ``h``).  With them the second-order covariance of ``h`` under
    ``N(μ, P)`` is ``½ tr(∇²hₐ P ∇²h_b P) = ½Σ_k c_k c_kᵀ + Σ_{k<l} M_kl M_klᵀ`` (exact for a quadratic ``h``).
    Where the measurement reads only ``r < n`` state entries
    (:meth:`~agsf_torch.models.base.MeasurementModel.state_entries`), the axes are those of the marginal
    covariance of those entries, ``P_rr = L_r L_rᵀ`` (``r`` axes, ``r(r − 1)/2`` pairs): the same terms, since ``h``
    does not vary along the rest (with the read entries first in the state, the first ``r`` axes of ``P``'s own
    factor are these and the others' terms are exactly zero).

    Args:
        means: ``[..., N, n]``; covs: ``[..., N, n, n]``.
    """
    return _second_differences(means, covs, measurement, mixed=True)


def _second_differences(
    means: Tensor, covs: Tensor, measurement: MeasurementModel, mixed: bool
) -> tuple[Tensor, Tensor | None]:
    """``(c, M or None)`` of :func:`measurement_second_differences` (``mixed``) or :func:`measurement_curvature`,
    ``h`` evaluated once at every point (the component dim moved to the front for the call, as
    :func:`evaluate_measurement`).  With ``mixed`` and a measurement that reads only some state entries
    (:meth:`~agsf_torch.models.base.MeasurementModel.state_entries`) the axes are those of the marginal covariance
    of those entries: the terms of the other axes vanish exactly, and so are not evaluated."""
    n = means.shape[-1]
    entries = measurement.state_entries() if mixed else None
    if entries is None or len(entries) >= n:
        s = torch.linalg.cholesky(covs).transpose(-1, -2)  # [..., N, n, n], row k: s_k
    else:
        idx = torch.as_tensor(entries, device=means.device)
        L = torch.linalg.cholesky(covs[..., idx[:, None], idx[None, :]])  # the read entries' marginal
        s = means.new_zeros(*L.shape[:-1], n)  # [..., N, r, n]
        s[..., idx] = L.transpose(-1, -2)
    r = s.shape[-2]
    pts = _axis_points(means, s)  # [..., N, 2r + 1, n]: μ, μ + s_k, μ − s_k
    if mixed:
        k, l = torch.triu_indices(r, r, 1, device=means.device)
        pts = torch.cat((pts, pts[..., :1, :] + s[..., k, :] + s[..., l, :]), -2)  # μ + s_k + s_l
    lead, N, Q = pts.shape[:-3], pts.shape[-3], pts.shape[-2]
    x = pts.reshape(*lead, N * Q, n).movedim(-2, 0)
    h = measurement.predict(x).movedim(0, -2)
    h = h.reshape(*lead, N, Q, h.shape[-1])
    centre, plus = h[..., :1, :], h[..., 1 : r + 1, :]
    c = plus + h[..., r + 1 : 2 * r + 1, :] - 2.0 * centre
    if not mixed:
        return c, None
    return c, h[..., 2 * r + 1 :, :] - plus[..., k, :] - plus[..., l, :] + centre


def evaluate_measurement(measurement: MeasurementModel, means: Tensor) -> tuple[Tensor, Tensor]:
    """``h(μᵢ)`` and ``Hᵢ`` for every component.

    The component dim is moved to the front for the call, so a measurement whose
    own tensors carry only the trajectory dims (``[..., M, 3]``) broadcasts
    against ``[N, ..., n]``.

    Args:
        means: ``[..., N, n]``.

    Returns:
        ``(h [..., N, d], H [..., N, d, n])``.
    """
    x = means.movedim(-2, 0)
    h = measurement.predict(x).movedim(0, -2)
    H = measurement.jacobian(x).movedim(0, -3)
    return h, H


def _cholesky_or_raise(A: Tensor, need: Tensor, what: str, components: bool = True) -> Tensor:
    """Cholesky factor of ``A [..., k, k]``; ``ValueError`` naming ``what`` where it fails and ``need`` holds
    (``components``: the last batch dim of ``need`` is the component)."""
    L, info = torch.linalg.cholesky_ex(A)
    bad = (info != 0) & need
    if bool(bad.any()):
        idx = _first_index(bad)
        at = (
            f"trajectory index {tuple(idx[:-1])}, component {idx[-1]}"
            if components
            else f"trajectory index {tuple(idx)}"
        )
        raise ValueError(f"{what} is not positive definite at {at}")
    return L


def _information_gain(covs: Tensor, H: Tensor, R_eff: Tensor, need: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The gain in information form (module docstring): ``(K [..., N, n, d], L_P, L_R, log det S [..., N])``."""
    L_P = _cholesky_or_raise(covs, need, "the component covariance P")
    L_R = _cholesky_or_raise(R_eff, need, "the measurement noise covariance R")
    G = torch.linalg.solve_triangular(L_R, H @ L_P, upper=False)  # [..., N, d, n]
    n = G.shape[-1]
    eye = torch.eye(n, dtype=G.dtype, device=G.device).expand(*G.shape[:-2], n, n)
    R_M = torch.linalg.qr(torch.cat((G, eye), -2)).R  # R_Mᵀ R_M = I + GᵀG
    W = torch.linalg.solve_triangular(L_R.transpose(-1, -2), G, upper=True)  # L_R⁻ᵀ G
    K = L_P @ torch.cholesky_solve(W.transpose(-1, -2), R_M, upper=True)  # L_P M⁻¹ Gᵀ L_R⁻¹
    log_det = 2.0 * (
        L_R.diagonal(dim1=-2, dim2=-1).abs().log().sum(-1) + R_M.diagonal(dim1=-2, dim2=-1).abs().log().sum(-1)
    )
    return K, L_P, L_R, log_det


def kalman_update(
    log_weights: Tensor,
    means: Tensor,
    covs: Tensor,
    y: Tensor,
    measurement: MeasurementModel,
    iterations: int = 1,
    mask: Tensor | None = None,
    mixture_nis: bool = True,
    second_order: bool = False,
) -> ComponentUpdate:
    """Joseph-form EKF update of all components and Bayes' rule on the weights.

    With ``iterations = 1`` this is the EKF update of method.md §2 (``H`` and
    ``βᵢ`` at the predicted mean).  With ``iterations > 1`` it is the iterated
    EKF (Gauss–Newton on the MAP problem of each component): the measurement is
    relinearised at the current iterate ``xⱼ``,

    .. math:: x_{j+1} = μ + K_j\\left(\\tilde y - h(x_j) - H_j(μ - x_j)\\right),

    and the covariance, the innovation and ``βᵢ`` use the last linearisation.
    It removes the linearisation error of the first star frame after a wide
    prior, where one EKF step leaves errors many σ outside its covariance.

    The gain of each component is formed in covariance form, or in information
    form where ``S`` is too ill-conditioned for it (module docstring: a precise
    sensor after a wide prior); both are the same gain up to rounding.

    Args:
        log_weights: ``[..., N]`` normalised.
        means: ``[..., N, n]``.
        covs: ``[..., N, n, n]``.
        y: measurement ``[..., d]``.
        measurement: the measurement model (``h``, ``H``, ``R``, mask).
        iterations: linearisations (≥ 1).
        mask: entry validity ``[..., d]`` bool to use instead of the model's
            ``measurement.mask()`` (e.g. after innovation gating).
        mixture_nis: compute :attr:`ComponentUpdate.nis_mixture` (a single-Gaussian caller
            that does not report it saves its factorisation).
        second_order: the second-order update: with the measurement's second differences along the prior's axes
            and across each pair of them (:func:`measurement_second_differences`: ``c_k ≈ s_kᵀ∇²h s_k``,
            ``M_kl ≈ s_kᵀ∇²h s_l``, ``s_k = L e_k``, ``P = LLᵀ``), the prediction is ``h + ½Σ_k c_k`` and its
            covariance gains ``½Σ_k c_k c_kᵀ + Σ_{k<l} M_kl M_klᵀ``: the second-order terms of a Gaussian,
            ``½tr(∇²h P)`` and ``½tr(∇²hₐ P ∇²h_b P)``, exact for a quadratic ``h`` (the divided-difference
            filter of Nørgaard, Poulsen & Ravn 2000 keeps only the ``c_k``), so a component wide against the
            noise is not updated as if ``h`` were linear over it.  With ``iterations > 1`` the plain iterated
            update runs first, and a mixture keeps its posterior where ``h`` is linear over the posterior of every
            active component (:func:`second_order_size` ``≤`` :data:`LINEAR_POSTERIOR`) and the frame agrees with
            the mixture's prediction (NIS within :data:`PLAIN_POSTERIOR_PROBABILITY`): the Gauss–Newton iterates
            have then found the modes and the Gaussians about them are the posterior.  The choice is the
            mixture's, not each component's, so that the components' likelihoods ``βᵢ``, which set the weights,
            come from one approximation.  Elsewhere every relinearisation keeps the terms of the prior: taken
            over each iterate's posterior instead (iterated posterior linearisation) they cost the managed
            filters their consistency with one star per frame (``docs/results/management.md``).

    Returns:
        :class:`ComponentUpdate`.

    Raises:
        ValueError: ``y`` of the wrong size; a non-finite mean, measurement or prediction, or an
            absurd innovation (:func:`check_innovation`); a component covariance or ``R`` that is
            not positive definite where the information form needs its factor.
    """
    R = measurement.noise_cov().to(means)
    if mask is None:
        mask = measurement.mask()
    y = y.unsqueeze(-2)  # [..., 1, d]
    R = R.unsqueeze(-3) if R.dim() > 2 else R
    part = _component_updates(means, covs, y, measurement, R, mask, iterations, prior_terms=False)
    part_nis_mixture = None  # the mixture NIS of `part`, where it was needed before the end
    if second_order:
        keep = None
        if int(iterations) > 1:  # the iterated posterior stands where h is linear over it (the docstring)
            # (a posterior that rounding left without a Cholesky factor is not judged: the prior's terms there)
            factored = torch.linalg.cholesky_ex(part.covs).info == 0
            judged = torch.where(factored[..., None, None], part.covs, covs)
            size = second_order_size(part.means, judged, measurement, part.R_eff, part.valid)
            linear = (factored & (size <= LINEAR_POSTERIOR)) | (log_weights == -math.inf)  # inactive: no say
            # the whole mixture or none of it: its components' likelihoods are then one approximation's; and only
            # where the frame agrees with the mixture's prediction (a narrow posterior about a mode the data
            # contradict is no evidence: there the prior's terms keep the frame's weight down)
            valid0 = part.valid[..., 0, :]
            part_nis_mixture = _mixture_nis(log_weights, part.nu, part.S, part.H, covs, part.R_eff, valid0)
            keep = linear.all(-1) & _frame_agrees(part_nis_mixture, valid0)  # [...]
        if keep is None or not bool(keep.all()):
            second = _component_updates(means, covs, y, measurement, R, mask, iterations, prior_terms=True)
            part = second if keep is None else _select_components(keep, part, second)
            part_nis_mixture = None
    nu, S, H, R_eff, valid = part.nu, part.S, part.H, part.R_eff, part.valid
    new_means, new_covs, nis = part.means, part.covs, part.nis
    dof = valid.sum(-1)  # [..., N]
    log_beta = -0.5 * (nis + part.log_det + dof * math.log(2.0 * math.pi))
    joint = log_weights + log_beta
    log_lik = torch.logsumexp(joint, -1)
    new_log_weights = joint - log_lik.unsqueeze(-1)
    nis_mixture = None
    if mixture_nis:
        nis_mixture = part_nis_mixture
        if nis_mixture is None:
            nis_mixture = _mixture_nis(log_weights, nu, S, H, covs, R_eff, valid[..., 0, :])
    if provides(measurement, "data_log_likelihood", MeasurementModel):
        # the data's own degrees of freedom (a unit vector's two), whatever R the gain spreads the noise over
        HL = H @ torch.linalg.cholesky(0.5 * (covs + covs.transpose(-1, -2)))
        log_lik = measurement.data_log_likelihood(log_weights, nu, HL, y.squeeze(-2), valid)

    # trajectories without a valid entry are left exactly as they were
    any_valid = dof[..., 0] > 0
    new_means = torch.where(any_valid[..., None, None], new_means, means)
    new_covs = torch.where(any_valid[..., None, None, None], new_covs, covs)
    new_log_weights = torch.where(any_valid[..., None], new_log_weights, log_weights)
    log_lik = torch.where(any_valid, log_lik, torch.zeros_like(log_lik))
    return ComponentUpdate(new_means, new_covs, new_log_weights, log_lik, nis, dof[..., 0], nu, S, nis_mixture)


class _Components(NamedTuple):
    """Every component's update before Bayes' rule on the weights (:func:`_component_updates`): the posterior
    ``means [..., N, n]`` and ``covs [..., N, n, n]``, ``nis`` and ``log_det`` (of ``S``) ``[..., N]``, the last
    linearisation's ``nu [..., N, d]``, ``S`` and ``R_eff [..., N, d, d]``, ``H [..., N, d, n]``, and the entry
    validity ``valid [..., N, d]`` (0/1 in the means' dtype)."""

    means: Tensor
    covs: Tensor
    nis: Tensor
    log_det: Tensor
    nu: Tensor
    S: Tensor
    H: Tensor
    R_eff: Tensor
    valid: Tensor


def _component_updates(
    means: Tensor,
    covs: Tensor,
    y: Tensor,
    measurement: MeasurementModel,
    R: Tensor,
    mask: Tensor | None,
    iterations: int,
    prior_terms: bool,
) -> _Components:
    """The (iterated) Joseph-form update of every component (:func:`kalman_update`), ``y [..., 1, d]``, with the
    second-order terms over the prior where ``prior_terms``."""
    n = means.shape[-1]
    eye_n = torch.eye(n, dtype=means.dtype, device=means.device)
    shift = None
    if prior_terms:  # over the prior N(μ, P), for every linearisation (kalman_update's docstring says why)
        c, M = measurement_second_differences(means, covs, measurement)  # [..., N, r, d], [..., N, r(r−1)/2, d]
        shift = 0.5 * c.sum(-2)  # [..., N, d]
        R = R + 0.5 * c.transpose(-1, -2) @ c + M.transpose(-1, -2) @ M  # [..., N, d, d]
    every_entry_valid = mask is None or bool(mask.all())
    x = means
    for j in range(int(iterations)):
        h, H = evaluate_measurement(measurement, x)
        if shift is not None:
            h = h + shift
        d = h.shape[-1]
        if y.shape[-1] != d:
            raise ValueError(
                f"y has {y.shape[-1]} entries but the measurement model predicts {d} (h: {tuple(h.shape)})"
            )
        if mask is None:
            valid = torch.ones(h.shape[:-1] + (d,), dtype=means.dtype, device=means.device)
        else:
            valid = mask.to(means.dtype).unsqueeze(-2).expand(h.shape)
        if every_entry_valid:  # the masking below would change nothing
            R_eff = R.expand(*h.shape, d)
        else:
            R_eff = valid[..., :, None] * valid[..., None, :] * R + torch.diag_embed(1.0 - valid)
            H = valid[..., None] * H
        PHt = covs @ H.transpose(-1, -2)  # [..., N, n, d]
        S = H @ PHt + R_eff
        if j == 0:
            check_innovation(y, means, h, S.diagonal(dim1=-2, dim2=-1), valid)
        nu = y - h
        if x is not means:
            nu = nu - (H @ (means - x).unsqueeze(-1)).squeeze(-1)
        nu = valid * nu

        S = 0.5 * (S + S.transpose(-1, -2))
        L, info = torch.linalg.cholesky_ex(S)
        need = ~covariance_form_usable(L, info, valid, S)
        robust = bool(need.any())
        if robust:  # ill-conditioned S somewhere: information form there (module docstring)
            eye_d = torch.eye(d, dtype=S.dtype, device=S.device)
            L = torch.linalg.cholesky_ex(torch.where(need[..., None, None], eye_d, S)).L
            K_info, L_P, L_R, log_det_info = _information_gain(covs, H, R_eff, need)
        K = torch.cholesky_solve(PHt.transpose(-1, -2), L).transpose(-1, -2)  # [..., N, n, d]
        if robust:
            K = torch.where(need[..., None, None], K_info, K)
        x = means + (K @ nu.unsqueeze(-1)).squeeze(-1)
    IKH = eye_n - K @ H
    new_covs = IKH @ covs @ IKH.transpose(-1, -2) + K @ R_eff @ K.transpose(-1, -2)
    new_covs = 0.5 * (new_covs + new_covs.transpose(-1, -2))

    z = torch.linalg.solve_triangular(L, nu.unsqueeze(-1), upper=False).squeeze(-1)
    nis = (z * z).sum(-1)
    log_det = 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
    if robust:
        dx = x - means
        e = torch.linalg.solve_triangular(L_R, (nu - (H @ dx.unsqueeze(-1)).squeeze(-1)).unsqueeze(-1), upper=False)
        f = torch.linalg.solve_triangular(L_P, dx.unsqueeze(-1), upper=False)
        nis = torch.where(need, (e * e).sum((-2, -1)) + (f * f).sum((-2, -1)), nis)
        log_det = torch.where(need, log_det_info, log_det)
    return _Components(x, new_covs, nis, log_det, nu, S, H, R_eff, valid)


def _frame_agrees(nis_mixture: Tensor, valid: Tensor) -> Tensor:
    """Whether the frame agrees with the mixture's prediction, ``[...]``: its moment-matched NIS ``[...]``
    (:func:`moment_matched_innovation`, prior weights) at most the ``χ²_d`` quantile at
    :data:`PLAIN_POSTERIOR_PROBABILITY`, ``d`` the frame's valid entries (``valid [..., d]``, 0/1)."""
    from .quantiles import chi2_quantile

    dof = valid.sum(-1)
    bound = torch.full_like(nis_mixture, math.inf)
    for d in torch.unique(dof).tolist():  # the frames' few distinct entry counts
        if d > 0:
            bound = torch.where(dof == d, chi2_quantile(PLAIN_POSTERIOR_PROBABILITY, d), bound)
    return nis_mixture <= bound


def _select_components(keep: Tensor, first: _Components, second: _Components) -> _Components:
    """``first``'s update of the mixtures where ``keep [...]`` holds, ``second``'s elsewhere."""
    picked = []
    for a, b in zip(first, second):
        k = keep.reshape(keep.shape + (1,) * (max(a.dim(), b.dim()) - keep.dim()))
        picked.append(torch.where(k, a, b))
    return _Components(*picked)


def second_order_size(means: Tensor, covs: Tensor, measurement: MeasurementModel, R: Tensor, valid: Tensor) -> Tensor:
    """The expected squared size, in the noise's units, of the measurement's second-order part over each
    component ``N(μ, P)``, ``[..., N]``:

    .. math:: E\\lVert R^{-½}(h(x) - h(μ) - H(x - μ))\\rVert^2 ≈ \\operatorname{tr}(R^{-1}Σ_2) + b_2^T R^{-1} b_2,
              \\quad b_2 = ½Σ_k c_k,\\; Σ_2 = ½Σ_k c_k c_k^T + Σ_{k<l} M_{kl} M_{kl}^T

    (:func:`measurement_second_differences`; exact for a quadratic ``h``), over the valid entries: zero for a
    measurement linear over the component, about ``d`` where its curvature over it is as large as the noise.

    Args:
        means: ``[..., N, n]``; covs: ``[..., N, n, n]``; R: ``[..., N, d, d]`` or ``[d, d]`` (positive definite:
            invalid entries' blocks replaced by the identity, as :func:`kalman_update` does); valid: ``[..., N, d]``
            0/1 in the means' dtype.
    """
    c, M = measurement_second_differences(means, covs, measurement)  # [..., N, r, d], [..., N, p, d]
    A = torch.cat((math.sqrt(0.5) * c, M, 0.5 * c.sum(-2, keepdim=True)), -2) * valid.unsqueeze(-2)
    L_R = torch.linalg.cholesky(R)
    Z = torch.linalg.solve_triangular(L_R, A.transpose(-1, -2), upper=False)  # [..., N, d, r + p + 1]
    return (Z * Z).sum((-2, -1))


def _mixture_nis(
    log_weights: Tensor, nu: Tensor, S: Tensor, H: Tensor, covs: Tensor, R_eff: Tensor, valid: Tensor
) -> Tensor:
    """``ν̄ᵀ S̄⁻¹ ν̄`` of :func:`moment_matched_innovation`, ``[...]``: with the Cholesky factor of ``S̄``,
    or, where that is unfit (:func:`covariance_form_usable`), with :func:`moment_matched_factor`."""
    nu_bar, S_bar = moment_matched_innovation(log_weights, nu, S)
    L, info = torch.linalg.cholesky_ex(S_bar)
    need = ~covariance_form_usable(L, info, valid, S_bar)
    if bool(need.any()):
        eye = torch.eye(S_bar.shape[-1], dtype=S_bar.dtype, device=S_bar.device)
        L = torch.linalg.cholesky_ex(torch.where(need[..., None, None], eye, S_bar)).L
        L_P = _cholesky_or_raise(covs, need.unsqueeze(-1), "the component covariance P")
        L_R = _cholesky_or_raise(R_eff[..., 0, :, :], need, "the measurement noise covariance R", components=False)
        _, L_rob = moment_matched_factor(log_weights, nu, H @ L_P, L_R)
        L = torch.where(need[..., None, None], L_rob, L)
    z = torch.linalg.solve_triangular(L, nu_bar.unsqueeze(-1), upper=False).squeeze(-1)
    return (z * z).sum(-1)
