"""The star-vector measurement update in information form, one component per lane.

For a unit-vector camera the noise covariance is block diagonal per star, ``R = σ²I``, and each
star's Jacobian acts on the attitude only, ``Hⱼ = [bⱼ×] E`` with ``bⱼ = C rⱼ`` the predicted body
vector and ``E`` the chart's ``3×3`` map (the MRP chart: ``E = 4Bᵀ(p)/(1+s)²``).  With the
Cholesky factor of the prior split by blocks,

.. math::

    P = L Lᵀ,\\quad L = \\begin{bmatrix} L_{pp} & 0 \\\\ L_{bp} & L_{bb} \\end{bmatrix},\\quad
    W = \\begin{bmatrix} L_{pp} \\\\ L_{bp} \\end{bmatrix},

the information-form gain of :mod:`agsf_torch.update` (``G = R^{-1/2} H L``, ``M = I + GᵀG``) has
``G`` zero outside its first three columns, so ``M = blockdiag(I + A, I)`` and every solve is
``3×3``, whatever the number of stars:

.. math::

    A = L_{pp}^T E^T T E L_{pp} / σ^2,\\quad T = \\sum_j m_j (|b_j|^2 I - b_j b_j^T),\\qquad
    g = L_{pp}^T E^T \\sum_j m_j (ν_j × b_j) / σ^2,

    I + A = U U^T,\\quad z = (I + A)^{-1} g,\\quad δx = W z,\\quad
    P^+ = Y Y^T + \\operatorname{blockdiag}(0, L_{bb} L_{bb}^T),\\; Y = W U^{-T},

    \\log\\det S = d \\log σ^2 + 2 \\sum_k \\log U_{kk},\\qquad
    ν^T S^{-1} ν = \\sum_j m_j |ν_j - [b_j×] E\\,δp|^2 / σ^2 + |z|^2,

with ``mⱼ ∈ {0, 1}`` the star mask and ``d = 3 Σ mⱼ``.  This is the same gain as the covariance
form ``K = PHᵀS⁻¹`` (push-through identity), but ``I + A ⪰ I`` is never ill-conditioned however
precise the sensor or wide the prior, ``P⁺`` is a sum of outer products (symmetric positive
definite by construction, as the Joseph form), and the cost is ``O(M + n²)`` per component
instead of the ``O(M³)`` factorisation of the ``3M×3M`` innovation covariance.

Every function here works on *entries*: a matrix is a list of rows of tensors that all
broadcast to the lanes ``[C]`` (components), so the ``3×3`` algebra is unrolled at trace time
and runs eagerly or compiled as one loop (:mod:`agsf_torch.fused.lanes`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..attitude import physics
from ..finite import all_finite
from ..shapes import broadcast_shapes
from ..update import ComponentUpdate, check_innovation
from .algebra import (
    Entry,
    add,
    cholesky,
    cholesky_solve,
    cross,
    div,
    dot,
    forward_substitution,
    matmul,
    matvec,
    mul,
    sub,
    zeros,
)
from .lanes import entries, run_in_chunks, stack_entries
from .mixture_nis import mixture_information_nis
from .propagation import positive_pivots

if TYPE_CHECKING:  # the measurement calls this kernel; the kernel never imports the model
    from ..models.star_vectors import StarVectorMeasurement

__all__ = ["FusedUpdate", "information_star_update", "star_kernel", "fused_star_update"]

Mat = list[list[Entry]]


@dataclass(frozen=True)
class FusedUpdate(ComponentUpdate):
    """:class:`~agsf_torch.update.ComponentUpdate` with the kernel's own definiteness check.

    Attributes:
        positive_definite: every pivot of the Cholesky factorisation of ``P⁺`` is positive, ``[..., N]``.
    """

    positive_definite: Tensor | None = None


def information_star_update(
    mean: list[Tensor],
    P: Mat,
    body: list[list[Tensor]],
    nu: list[list[Tensor]],
    E: Mat,
    mask: list[Tensor],
    sigma2: Tensor,
) -> tuple[list[Tensor], Mat, Tensor, Tensor, Tensor, Mat]:
    """One star-vector update of every lane in information form (module docstring).

    Args:
        mean: the prior mean, ``n`` entries (MRP first, then any other states).
        P: the prior covariance, ``n×n`` entries (the lower triangle is read).
        body: the predicted body vectors ``bⱼ = C rⱼ`` at the linearisation point, ``M`` lists of 3.
        nu: the innovations ``νⱼ`` (``ỹⱼ − h(x)`` with the relinearisation term of an iterated
            update), ``M`` lists of 3.
        E: the chart's ``3×3`` map (``Hⱼ = [bⱼ×] E``, :func:`~agsf_torch.attitude.physics.chart_map`).
        mask: ``M`` entries, 1.0 for a valid star, 0.0 for a masked one.
        sigma2: ``σ²`` (rad²), an entry.

    Returns:
        ``(mean⁺ (n entries), P⁺ (n×n, symmetric), log N(ỹ; h, S), NIS νᵀS⁻¹ν, d, F = E L_pp (3×3))``
        per lane (``Hⱼ L = [bⱼ×] F`` on the attitude columns; ``log N`` NaN where a pivot of ``P`` or ``I + A``
        is not positive); lanes without a valid star are *not* special-cased here (the caller keeps them).
    """
    n = len(mean)
    L, _, prior_ok = cholesky(P)
    inv_s2 = div(1.0, sigma2)
    # T = Σ mⱼ (|bⱼ|² I − bⱼbⱼᵀ) (symmetric) and u = Σ mⱼ νⱼ × bⱼ
    T: Mat = zeros(3)
    u: list[Entry] = [None] * 3
    count = None
    for b, v, m in zip(body, nu, mask):
        bb = dot((b[k], b[k]) for k in range(3))
        for i in range(3):
            for j in range(i + 1):
                T[i][j] = add(T[i][j], mul(m, sub(bb if i == j else None, mul(b[i], b[j]))))
        u = [add(u[k], mul(m, w)) for k, w in enumerate(cross(v, b))]
        count = add(count, m)
    T = [[T[i][j] if j <= i else T[j][i] for j in range(3)] for i in range(3)]
    W = [row[:3] for row in L]  # the first three columns of L (n×3), its upper triangle structural zeros
    F = matmul(E, W[:3])  # the chart map applied to the attitude columns of L
    TF = matmul(T, F)
    A = [
        [mul(dot((F[k][i], TF[k][j]) for k in range(3)), inv_s2) if j <= i else None for j in range(3)]
        for i in range(3)
    ]
    g = [mul(dot((F[k][i], u[k]) for k in range(3)), inv_s2) for i in range(3)]
    U, U_inv, gain_ok = cholesky([[add(1.0, A[i][j]) if i == j else A[i][j] for j in range(3)] for i in range(3)])
    z = cholesky_solve(U, U_inv, g)
    delta = matvec(W, z)  # δx = W z
    Y = [forward_substitution(U, U_inv, w) for w in W]  # Y = W U⁻ᵀ
    post: Mat = zeros(n)
    for i in range(n):
        for j in range(i + 1):
            # the bias block's own factor, L_bb L_bbᵀ
            v = add(dot((Y[i][k], Y[j][k]) for k in range(3)), dot((L[i][k], L[j][k]) for k in range(3, j + 1)))
            post[i][j] = post[j][i] = v
    new_mean = [add(mean[i], delta[i]) for i in range(n)]
    # NIS = Σ mⱼ |νⱼ − [bⱼ×] E δp|² / σ² + |z|²
    Edp = matvec(E, delta[:3])
    resid = None
    for b, v, m in zip(body, nu, mask):
        e = [sub(v[k], hb) for k, hb in enumerate(cross(b, Edp))]
        resid = add(resid, mul(m, dot((e[k], e[k]) for k in range(3))))
    nis = add(dot((z[k], z[k]) for k in range(3)), mul(resid, inv_s2))
    dof = mul(3.0, count)
    log_det = dof * torch.log(sigma2) + 2.0 * (torch.log(U[0][0]) + torch.log(U[1][1]) + torch.log(U[2][2]))
    log_beta = -0.5 * (nis + log_det + dof * math.log(2.0 * math.pi))
    log_beta = torch.where(prior_ok & gain_ok, log_beta, torch.nan)  # beyond the kernel's range: the generic update
    return new_mean, post, log_beta, nis, dof, F


def _star_step(mean, P, x_lin, r, y, mask, sigma2):
    """One linearisation at ``x_lin`` (``None``: the prior mean), batch-first lanes in and out; ``h`` and ``H`` from
    :mod:`agsf_torch.attitude.physics`.

    Args:
        mean, x_lin: ``[c, n]``; P: ``[c, n, n]``; r, y: ``[c, M, 3]`` catalogue and measured unit
        vectors; mask: ``[c, M]`` (1.0 valid); sigma2: ``[c]``.

    Returns:
        ``(mean⁺ [c, n], P⁺ [c, n, n], log β [c], NIS [c], d [c], ν [c, M, 3], H L [c, M, 3, 3],
        P⁺ positive definite [c] bool)``.
    """
    c, n = mean.shape
    M = r.shape[1]
    mu = entries(mean, (n,))
    x = mu if x_lin is None else entries(x_lin, (n,))
    Pe = entries(P, (n, n))
    re, ye, me = entries(r, (M, 3)), entries(y, (M, 3)), entries(mask, (M,))
    C, E = physics.attitude_matrix(x[:3]), physics.chart_map(x[:3])
    Edp = None if x_lin is None else matvec(E, [sub(mu[k], x[k]) for k in range(3)])
    body, nu = [], []
    for j in range(M):
        b = physics.star_vector(C, re[j])
        v = [sub(ye[j][k], b[k]) for k in range(3)]
        if Edp is not None:  # ν = ỹ − h(x) − H (μ − x)
            v = [sub(v[k], hb) for k, hb in enumerate(cross(b, Edp))]
        body.append(b)
        nu.append([mul(me[j], v[k]) for k in range(3)])
    new_mean, post, log_beta, nis, dof, F = information_star_update(mu, Pe, body, nu, E, me, sigma2)
    # Hⱼ L = [bⱼ×] F on the attitude columns (masked): the square root of each star's H P Hᵀ
    HL = [[[mul(me[j], v) for v in row] for row in physics.star_jacobian(body[j], F)] for j in range(M)]
    return (
        stack_entries(new_mean, c),
        stack_entries(post, c),
        log_beta,
        nis,
        dof,
        stack_entries(nu, c),
        stack_entries(HL, c),
        positive_pivots(post),
    )


def star_kernel(mean, P, r, y, mask, sigma2):
    """The update linearised at the prior mean (a kernel for :func:`~agsf_torch.fused.lanes.run_in_chunks`)."""
    return _star_step(mean, P, None, r, y, mask, sigma2)


def star_kernel_relinearised(mean, P, x_lin, r, y, mask, sigma2):
    """The update relinearised at ``x_lin`` (an iterated update's later iterations)."""
    return _star_step(mean, P, x_lin, r, y, mask, sigma2)


def fused_star_update(
    log_weights: Tensor,
    means: Tensor,
    covs: Tensor,
    y: Tensor,
    measurement: StarVectorMeasurement,
    iterations: int = 1,
    mask: Tensor | None = None,
    mixture_nis: bool = True,
    compile: bool = False,
) -> ComponentUpdate:
    """:func:`agsf_torch.update.kalman_update` for a :class:`~agsf_torch.models.StarVectorMeasurement`
    with isotropic noise on an attitude state (MRP first), in information form (module docstring).

    Same arguments and result as :func:`~agsf_torch.update.kalman_update` (``mask``: entry validity
    ``[..., 3M]``, e.g. the gate's; else the measurement's star mask) and the same checks before
    anything changes (:func:`~agsf_torch.update.check_innovation`); ``innovation_cov`` is not formed
    (``None``).  ``compile`` runs the kernel compiled ahead of time
    (:func:`~agsf_torch.fused.lanes.run_in_chunks`).  Where the kernel's result is not finite (a problem
    beyond its range, e.g. a pivot of ``I + A`` clamped), the whole call takes the generic update: never a
    wrong number.
    """
    n, N, M = means.shape[-1], means.shape[-2], measurement.num_stars
    lead = broadcast_shapes(means.shape[:-1], y.shape[:-1] + (1,))
    C = math.prod(lead)
    if mask is not None:
        star_valid = mask.reshape(*mask.shape[:-1], M, 3)[..., 0]
    elif measurement.star_mask is not None:
        star_valid = measurement.star_mask
    else:
        star_valid = None  # every star
    m = (
        means.new_ones(C, M)
        if star_valid is None
        else star_valid.to(means.dtype).unsqueeze(-2).expand(*lead, M).reshape(C, M)
    )
    r = measurement.r_inertial.to(means).unsqueeze(-3).expand(*lead, M, 3).reshape(C, M, 3)
    y3 = y.reshape(*y.shape[:-1], 1, M, 3).expand(*lead, M, 3).reshape(C, M, 3)
    mu = means.expand(*lead, n).reshape(C, n)
    P = covs.expand(*lead, n, n).reshape(C, n, n)
    sigma2 = (measurement.sigma.to(means) ** 2).expand(C).contiguous()
    out = run_in_chunks(star_kernel, (mu, P, r, y3, m, sigma2), compile=compile, key=("star", n, M))
    # the innovation at the prior mean, checked before anything is returned (the kernel changed nothing):
    # ε|ν| ≤ σ ≤ √Sⱼⱼ suffices (false for a NaN or infinite ν); where it fails, the exact check names the cause
    nu0, sigma = out[5], measurement.sigma.to(means)
    if not bool((torch.finfo(nu0.dtype).eps * nu0.abs() <= sigma).all()):
        _check_innovation(y, means, covs, measurement, star_valid)
    x_last = mu  # the linearisation point of the last iteration (H, ν and S are taken there)
    for _ in range(int(iterations) - 1):
        x_last = out[0]
        out = run_in_chunks(
            star_kernel_relinearised, (mu, P, x_last, r, y3, m, sigma2), compile=compile, key=("star-relin", n, M)
        )
    new_means, new_covs = out[0].reshape(*lead, n), out[1].reshape(*lead, n, n)
    log_beta, nis, dof = (t.reshape(lead) for t in out[2:5])
    if not all_finite(
        new_covs, new_means, log_beta, nis
    ):  # beyond the kernel's range (a pivot clamped to overflow): the generic update
        from ..update import kalman_update

        generic = kalman_update(log_weights, means, covs, y, measurement, iterations, mask, mixture_nis)
        return FusedUpdate(**{f.name: getattr(generic, f.name) for f in dataclasses.fields(generic)})
    nu = out[5].reshape(*lead, 3 * M)
    HL = out[6].reshape(*lead, 3 * M, 3)
    positive_definite = out[7].reshape(lead)
    joint = log_weights + log_beta
    log_lik = torch.logsumexp(joint, -1)
    new_log_weights = joint - log_lik.unsqueeze(-1)
    entry = None if star_valid is None else star_valid.to(means.dtype).repeat_interleave(3, dim=-1)
    nis_mixture = None
    if mixture_nis:
        valid = None if entry is None else entry.expand(*lead[:-1], 3 * M)
        nis_mixture = nis[..., 0] if N == 1 else mixture_information_nis(log_weights, nu, HL, sigma**2, valid)
    entry = torch.ones_like(nu) if entry is None else entry.unsqueeze(-2).expand(nu.shape)
    log_lik = measurement.data_log_likelihood(log_weights, nu, HL, y, entry)  # the data's: two dof per star
    any_valid = dof[..., 0] > 0
    if not bool(any_valid.all()):  # trajectories without a valid star keep their prior
        new_means = torch.where(any_valid[..., None, None], new_means, means)
        new_covs = torch.where(any_valid[..., None, None, None], new_covs, covs)
        new_log_weights = torch.where(any_valid[..., None], new_log_weights, log_weights)
        log_lik = torch.where(any_valid, log_lik, torch.zeros_like(log_lik))
        positive_definite = positive_definite | ~any_valid[..., None]
    return FusedUpdate(
        new_means, new_covs, new_log_weights, log_lik, nis, dof[..., 0], nu, None, nis_mixture, positive_definite
    )


def _check_innovation(
    y: Tensor, means: Tensor, covs: Tensor, measurement: StarVectorMeasurement, star_valid: Tensor | None
) -> None:
    """:func:`~agsf_torch.update.check_innovation` with the exact innovation variances (called where the
    sufficient test ``ε|νⱼ| ≤ σ ≤ √Sⱼⱼ`` on the kernel's innovations failed; it names the cause or passes)."""
    x = means.movedim(-2, 0)
    h = measurement.predict(x).movedim(0, -2)  # [..., N, d]
    nu = y.unsqueeze(-2) - h
    if star_valid is None:  # every star
        star_valid = torch.ones(measurement.num_stars, dtype=torch.bool, device=nu.device)
    valid = star_valid.repeat_interleave(3, dim=-1).unsqueeze(-2).expand(nu.shape)
    sigma = measurement.sigma.to(means)
    eps = torch.finfo(nu.dtype).eps
    if bool((torch.isfinite(nu) & (~valid | (eps * nu.abs() <= sigma))).all()):
        return
    H = measurement.jacobian(x).movedim(0, -3)
    S_diag = (H @ covs @ H.transpose(-1, -2)).diagonal(dim1=-2, dim2=-1) + sigma**2
    check_innovation(y.unsqueeze(-2), means, h, S_diag, valid)
