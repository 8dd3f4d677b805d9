"""The paper's ``E[ℓᵢℓⱼ]`` of the 6-state attitude model with the bias block integrated in closed form, batched:
the route of :meth:`~agsf_torch.models.AttitudeModel.fpke_pair_products` for few pairs (the generic FPKE core,
:mod:`agsf_torch.fpke`, reaches it only through that hook; the same mathematics on lanes:
:mod:`agsf_torch.fused.pair_products`).

Under a pair's product Gaussian ``N(m, S)`` (``S = LLᵀ``, ``L`` lower-triangular, MRP first), a point is
``x = m + Lξ``: the MRP ``p = m_p + L_pp ξ_p`` and the bias ``b = β + L_bb ξ_b`` with ``β = m_b + L_bp ξ_p``.
The attitude model's drift is affine in the bias (``ω = ω̃ − b``) and its ``D``, ``a`` and ``Σ∂²D`` do not
depend on it, so at fixed ``ξ_p`` the residual factor of a component (:mod:`agsf_torch.fpke.residual`) is a
quadratic in ``ξ_b``, with the rate's coefficients ``¼B(p)`` and ``(3/2)p``
(:func:`~agsf_torch.attitude.physics.rate_derivatives`):

.. math::

    ℓ = c_0 + g^Tξ_b + ξ_b^T G ξ_b,\\qquad z = z_0 + Zξ_b,\\quad Z = Π_{:,b} L_{bb},\\quad
    f = f_0 + Fξ_b,\\quad F = \\begin{bmatrix}−¼B(p)L_{bb}\\\\ 0\\end{bmatrix},

    c_0 = ℓ(x_0),\\quad g = Z^T(v_0 + \\dot P z_0 − 2 D z_0) − F^T z_0 − \\tfrac32 L_{bb}^T p,\\quad
    G = Z^T(½\\dot P − D)Z − \\operatorname{sym}(Z^T F),

with ``x₀ = (p, β)``, ``z₀ = Π(x₀ − μ)`` and ``v₀ = μ̇ − f(x₀) + 2a``.  In the orthonormal Hermite basis of
``ξ_b ~ N(0, I₃)`` its ten coefficients are ``c₀ + tr G``, ``g``, ``√2 G_kk`` and ``2 G_kl`` (``k < l``), so
``E_{ξ_b}[ℓᵢℓⱼ]`` is the dot product of the two sides' coefficients — exactly.  Each coefficient is a
polynomial of degree ≤ 6 in ``ξ_p``: its Hermite coefficients in ``ξ_p`` come from its values at the 84
nodes of :func:`~agsf_torch.quadrature.product_rule` for total degree 6 in three dimensions, and
``E[ℓᵢℓⱼ]`` is the sum of the products of the two sides' coefficients.  The result equals that of the
840-node product rule on ``P₆(ξ_p) ⊗ P₂(ξ_b)`` (the model's ``fpke_polynomial_space``) in exact arithmetic,
from a tenth of the nodes.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..attitude import physics
from ..fpke.pairs import ProductGaussians
from ..fpke.residual import ComponentRates
from ..fused.algebra import as_entries, as_tensor
from ..quadrature import ProductRule, product_rule

__all__ = ["attitude_pair_products"]

_RULES: dict[tuple, ProductRule] = {}


def _mrp_rule(dtype: torch.dtype, device: torch.device) -> ProductRule:
    key = (dtype, device)
    if key not in _RULES:
        _RULES[key] = product_rule((((0, 1, 2), 6),), 3, dtype=dtype, device=device)
    return _RULES[key]


#: Row and column of the six entries of a symmetric 3×3 matrix: the diagonal, then (0, 1), (0, 2), (1, 2).
_SYM = ([0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2])


def _side_coefficients(
    side: ComponentRates, x0: Tensor, terms, L_bb: Tensor, rate_matrix: Tensor, div_grad: Tensor
) -> Tensor:
    """The ten Hermite coefficients in ``ξ_b`` of ``ℓ`` of one side of every pair at every MRP node,
    ``[Q, 10, K]`` (module docstring), with ``z = Π(x − μ)`` as :func:`~agsf_torch.fpke.residual.residual_factor`
    forms it; ``rate_matrix`` ``¼B(p)`` ``[Q, K, 3, 3]`` and ``div_grad`` ``(3/2)p`` ``[Q, K, 3]`` at the nodes
    (:func:`~agsf_torch.attitude.physics.rate_derivatives`)."""
    Pi = side.precision  # [Q, 6, 6]
    Pdot = side.cov_rates
    z0 = (x0 - side.means.unsqueeze(-2)) @ Pi  # [Q, K, 6] (Π symmetric)
    d = terms.diffusion  # [Q, K, 6]: D is diagonal
    v0 = side.mean_rates.unsqueeze(-2) - terms.drift + 2.0 * terms.diffusion_divergence
    Pz = z0 @ Pdot  # Ṗz₀ (Ṗ symmetric)
    # c₀ = ℓ(x₀) as in residual_factor: zᵀ(v + ½Ṗz − Dz) + tr(DΠ) + div f − Σ∂²D − ½ tr(ΠṖ)
    tr_D_Pi = (d * Pi.diagonal(dim1=-2, dim2=-1).unsqueeze(-2)).sum(-1)
    scalars = terms.drift_divergence - terms.diffusion_second_divergence - 0.5 * (Pi * Pdot).sum((-2, -1)).unsqueeze(-1)
    c0 = ((v0 + 0.5 * Pz - d * z0) * z0).sum(-1) + tr_D_Pi + scalars  # [Q, K]
    Z = Pi[..., :, 3:] @ L_bb  # Π L_{:,b} (L lower-triangular) [Q, 6, 3]
    # g = Zᵀ(v₀ + Ṗz₀ − 2Dz₀) − Fᵀz₀ − (3/2)L_bbᵀp, with −Fᵀz₀ = L_bbᵀ ¼B(p)ᵀz₀,p
    g = (v0 + Pz - 2.0 * d * z0) @ Z  # [Q, K, 3]
    g = g + ((z0[..., :3].unsqueeze(-1) * rate_matrix).sum(-2) - div_grad) @ L_bb
    # G = Zᵀ(½Ṗ − D)Z − sym(ZᵀF), as its six entries (00, 11, 22, 01, 02, 12).  Per node only D and ¼B(p) change,
    # so the rest is formed once per pair: ZᵀDZ = Σ_a d_a Z_aᵀZ_a, and −ZᵀF = Z_pᵀ ¼B(p) L_bb = Σ_ab ¼B_ab O_ab
    # with O_ab = Z_p[a]ᵀ L_bb[b] (rows a and b)
    r, c = _SYM
    ZPZ = 0.5 * (Z.transpose(-1, -2) @ Pdot @ Z)[..., r, c]  # [Q, 6]
    outer = 0.5 * (Z[..., :, r] * Z[..., :, c] + Z[..., :, c] * Z[..., :, r])  # [Q, 6 rows a, 6 entries]
    O = (Z[..., :3, None, :, None] * L_bb[..., None, :, None, :]).flatten(1, 2)  # [Q, 9 (a, b), 3, 3]
    G = ZPZ.unsqueeze(-2) - d @ outer + rate_matrix.flatten(-2) @ (0.5 * (O[..., r, c] + O[..., c, r]))  # [Q, K, 6]
    coeffs = torch.cat(
        ((c0 + G[..., :3].sum(-1)).unsqueeze(-1), g, math.sqrt(2.0) * G[..., :3], 2.0 * G[..., 3:]), -1
    )  # [Q, K, 10]
    return coeffs.transpose(-1, -2)


def attitude_pair_products(model, u: Tensor | None, prod: ProductGaussians, max_chunk_elements: int = 2**24) -> Tensor:
    """``E_{N(m_ij, S_ij)}[ℓᵢℓⱼ]`` ``[..., P]`` for every pair of the 6-state attitude model (module
    docstring): the bias block in closed form, the MRP block by interpolation at 84 nodes; in chunks of
    pairs that keep a ``[pairs, 84, 3, 3]`` tensor under ``max_chunk_elements``.

    Args:
        model: an :class:`~agsf_torch.models.AttitudeModel` with ``estimate_bias=True``.
        u: the gyro rate ``[..., 3]`` (rad/s), broadcast against the trajectory dims.
        prod: the pairs' product Gaussians, their sides with precisions formed
            (:meth:`~agsf_torch.fpke.ComponentRates.with_precision` before :func:`~.pairs.product_gaussians`).
    """
    lead, flat = prod.mean.shape[:-1], prod.flat
    m, L = flat(prod.mean, 1), flat(prod.chol, 2)
    first, second = (r.map(lambda t, dim: flat(t, -dim - 1)) for r in (prod.first, prod.second))
    uf = None if u is None else flat(u.unsqueeze(-2), 1)  # [Q, 3]
    rule = _mrp_rule(m.dtype, m.device)
    chunk = max(1, max_chunk_elements // (rule.nodes.shape[0] * 9))
    out = [
        _chunk_products(
            model,
            None if uf is None else uf[a : a + chunk],
            m[a : a + chunk],
            L[a : a + chunk],
            first.map(lambda t, dim: t[a : a + chunk]),
            second.map(lambda t, dim: t[a : a + chunk]),
            rule,
        )
        for a in range(0, m.shape[0], chunk)
    ]
    if not out:  # no pairs: an empty batch
        return m.new_zeros(lead)
    return torch.cat(out).reshape(lead)


def _chunk_products(
    model,
    u: Tensor | None,
    m: Tensor,
    L: Tensor,
    first: ComponentRates,
    second: ComponentRates,
    rule: ProductRule,
) -> Tensor:
    """:func:`attitude_pair_products` of ``Q`` flattened pairs: ``m [Q, 6]``, ``L [Q, 6, 6]``, ``u [Q, 3]``."""
    xi = rule.nodes  # [K, 3]
    L_pp, L_bp, L_bb = L[..., :3, :3], L[..., 3:, :3], L[..., 3:, 3:]
    p = m[..., None, :3] + xi @ L_pp.transpose(-1, -2)  # [Q, K, 3]
    beta = m[..., None, 3:] + xi @ L_bp.transpose(-1, -2)
    x0 = torch.cat((p, beta), -1)  # [Q, K, 6]
    terms = model.fokker_planck_terms(x0, None if u is None else u[..., None, :])
    B4, div_grad = physics.rate_derivatives(as_entries(p, (3,)))
    B4, div_grad = as_tensor(B4), as_tensor(div_grad)  # ¼B(p) [Q, K, 3, 3], (3/2)p [Q, K, 3]
    ci = rule.coefficients(_side_coefficients(first, x0, terms, L_bb, B4, div_grad))  # [Q, 10, K]
    cj = rule.coefficients(_side_coefficients(second, x0, terms, L_bb, B4, div_grad))
    return (ci * cj).sum((-2, -1))
