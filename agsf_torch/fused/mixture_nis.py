"""The moment-matched mixture NIS of the fused star update, from the square roots its kernel returns.

The kernel of :mod:`agsf_torch.fused.star_update` updates each component on its own lane; the mixture's
NIS (:func:`~agsf_torch.update.moment_matched_innovation`) couples a trajectory's components, so it is
formed here, batched per trajectory, from each component's innovation ``νᵢ`` and ``Hᵢ Lᵢ`` (``Lᵢ`` the
prior's Cholesky factor) without forming any ``Sᵢ``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..shapes import broadcast_shapes
from ..update import covariance_form_usable

__all__ = ["mixture_information_nis"]


def mixture_information_nis(
    log_weights: Tensor, nu: Tensor, HL: Tensor, sigma2: Tensor, valid: Tensor | None = None
) -> Tensor:
    r"""The moment-matched mixture NIS ``ν̄ᵀS̄⁻¹ν̄`` (:func:`~agsf_torch.update.moment_matched_innovation`) from
    square roots: ``S̄ = σ²I + AAᵀ``, ``A = [√wᵢ [Hᵢ Lᵢ, νᵢ − ν̄]]ᵢ`` (``[..., d, (k+1)N]``; the order of the
    columns does not change ``AAᵀ``), written once, by the products that scale its columns, straight
    into the layout the Gram product reads (no concatenated, scaled and transposed copies of the blocks).

    Where the Cholesky factor of ``S̄`` is fit for solves (:func:`~agsf_torch.update.covariance_form_usable`,
    the generic update's rule), with it; elsewhere (a precise sensor after a wide prior) in information form,

    .. math:: \bar ν^T \bar S^{-1} \bar ν = |\bar ν - A z|^2/σ^2 + |z|^2,\quad
              z = (I + A^T A/σ^2)^{-1} A^T \bar ν / σ^2,

    with the factor of ``I + AᵀA/σ² ⪰ I`` from a QR of ``[A/σ; I]``: accurate whatever the
    conditioning of ``S̄``.

    Args:
        log_weights: ``[..., N]``.
        nu: ``[..., N, d]`` (zero at masked entries).
        HL: ``Hᵢ Lᵢ`` ``[..., N, d, k]`` (zero rows at masked entries).
        sigma2: ``σ²``.
        valid: ``[..., d]`` entry validity (a masked entry's row of ``S̄`` is that of the identity);
            ``None``: every entry.

    Returns:
        ``[...]``.
    """
    N, d, k = HL.shape[-3:]
    batch = broadcast_shapes(log_weights.shape[:-1], nu.shape[:-2], HL.shape[:-3])
    # every input at the full batch (views): the products below write whole slices of A
    log_weights, nu, HL = log_weights.expand(*batch, N), nu.expand(*batch, N, d), HL.expand(*batch, N, d, k)
    sw = (0.5 * log_weights).exp()  # √wᵢ
    nu_bar = ((sw * sw).unsqueeze(-2) @ nu).squeeze(-2)  # Σ wᵢ νᵢ
    spread = (nu - nu_bar.unsqueeze(-2)).transpose(-1, -2)  # [..., d, N]
    if torch.is_grad_enabled() and any(t.requires_grad for t in (log_weights, nu, HL)):
        # autograd records no product with out=: the same entries through a concatenation
        A = (torch.cat((HL.transpose(-3, -2), spread.unsqueeze(-1)), -1) * sw[..., None, :, None]).flatten(-2)
    else:
        A = HL.new_empty(*batch, d, N * (k + 1))
        X = A.unflatten(-1, (N, k + 1))  # [..., d, N, k+1], a view of A
        torch.mul(HL.transpose(-3, -2), sw[..., None, :, None], out=X[..., :k])
        torch.mul(spread, sw[..., None, :], out=X[..., k])
    S = A @ A.transpose(-1, -2)
    diagonal = sigma2 if valid is None else valid.to(A.dtype) * sigma2 + (1.0 - valid.to(A.dtype))
    S.diagonal(dim1=-2, dim2=-1).add_(diagonal)
    L, info = torch.linalg.cholesky_ex(S)
    usable = covariance_form_usable(L, info, valid, S)
    z = torch.linalg.solve_triangular(L, nu_bar.unsqueeze(-1), upper=False)
    nis = (z * z).sum((-2, -1))
    if bool(usable.all()):
        return nis
    # information form where the covariance form is not accurate
    Af, nf = A[~usable], nu_bar[~usable]
    cols = A.shape[-1]
    eye = torch.eye(cols, dtype=A.dtype, device=A.device).expand(Af.shape[0], cols, cols)
    R = torch.linalg.qr(torch.cat((Af / sigma2.sqrt(), eye), -2)).R  # RᵀR = I + AᵀA/σ²
    rhs = Af.transpose(-1, -2) @ nf.unsqueeze(-1) / sigma2
    zf = torch.linalg.solve_triangular(
        R, torch.linalg.solve_triangular(R.transpose(-1, -2), rhs, upper=False), upper=True
    )
    e = nf - (Af @ zf).squeeze(-1)
    return nis.index_put((~usable).nonzero(as_tuple=True), (e * e).sum(-1) / sigma2 + (zf * zf).sum((-2, -1)))
