"""The paper's ``E[ℓᵢℓⱼ]`` of the 6-state attitude model with the bias block integrated in closed form.

Under a pair's product Gaussian ``N(m, S)`` (``S = LLᵀ``, ``L`` lower-triangular, MRP first), a point is
``x = m + Lξ``: the MRP ``p = m_p + L_pp ξ_p`` and the bias ``b = β + L_bb ξ_b`` with ``β = m_b + L_bp ξ_p``.
The attitude model's drift is affine in the bias (``ω = ω̃ − b``) and its ``D``, ``a`` and ``Σ∂²D`` do not
depend on it, so at fixed ``ξ_p`` the residual factor of a component (:mod:`.residual`) is a quadratic in
``ξ_b``:

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

from ..quadrature import ProductRule, product_rule
from .pairs import ProductGaussians
from .residual import ComponentRates

__all__ = ["attitude_pair_products"]

_RULES: dict[tuple, ProductRule] = {}


def _mrp_rule(dtype: torch.dtype, device: torch.device) -> ProductRule:
    key = (dtype, device)
    if key not in _RULES:
        _RULES[key] = product_rule((((0, 1, 2), 6),), 3, dtype=dtype, device=device)
    return _RULES[key]


def _cross_matrix_t(p: Tensor, v: Tensor) -> Tensor:
    """``B(p)ᵀ v = (1 − s)v − 2 p×v + 2p(pᵀv)`` (``B(p) = (1 − s)I + 2[p×] + 2ppᵀ``, ``s = pᵀp``)."""
    s = (p * p).sum(-1, keepdim=True)
    return (1.0 - s) * v - 2.0 * torch.linalg.cross(p, v, dim=-1) + 2.0 * p * (p * v).sum(-1, keepdim=True)


#: Row and column of the six entries of a symmetric 3×3 matrix: the diagonal, then (0, 1), (0, 2), (1, 2).
_SYM = ([0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2])

#: ``[e_k×]`` for the three unit vectors: ``[p×] = Σ_k p_k [e_k×]``.
_E_CROSS = torch.tensor(
    [
        [[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
        [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]],
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
    ],
    dtype=torch.float64,
)


def _side_coefficients(side: ComponentRates, x0: Tensor, terms, L_bb: Tensor, p: Tensor) -> Tensor:
    """The ten Hermite coefficients in ``ξ_b`` of ``ℓ`` of one side of every pair at every MRP node,
    ``[Q, 10, K]`` (module docstring), with ``z = Π(x − μ)`` as :func:`~.residual.residual_factor` forms it."""
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
    Zp = Z[..., :3, :]
    # g = Zᵀ(v₀ + Ṗz₀ − 2Dz₀) − Fᵀz₀ − 1.5 L_bbᵀp, with −Fᵀz₀ = ¼ L_bbᵀ B(p)ᵀ z₀,p
    g = (v0 + Pz - 2.0 * d * z0) @ Z  # [Q, K, 3]
    g = g + (0.25 * _cross_matrix_t(p, z0[..., :3]) - 1.5 * p) @ L_bb
    # G = Zᵀ(½Ṗ − D)Z − sym(ZᵀF), as its six entries (00, 11, 22, 01, 02, 12).  Per node only scalars change,
    # so every 3×3 product is formed once per pair: ZᵀDZ = Σ_a d_a Z_aᵀZ_a, and with B(p) = (1 − s)I + 2[p×] + 2ppᵀ,
    # −ZᵀF = ¼ Z_pᵀB(p)L_bb = ¼[(1 − s)Z_pᵀL_bb + 2 Σ_k p_k Z_pᵀ[e_k×]L_bb + 2 (Z_pᵀp)(L_bbᵀp)ᵀ]
    r, c = _SYM
    ZPZ = 0.5 * (Z.transpose(-1, -2) @ Pdot @ Z)[..., r, c]  # [Q, 6]
    outer = 0.5 * (Z[..., :, r] * Z[..., :, c] + Z[..., :, c] * Z[..., :, r])  # [Q, 6 rows a, 6 entries]
    A0 = Zp.transpose(-1, -2) @ L_bb  # [Q, 3, 3]
    Mk = torch.stack([Zp.transpose(-1, -2) @ (_E_CROSS[k].to(Z) @ L_bb) for k in range(3)], 1)  # [Q, 3, 3, 3]
    sym = lambda A: 0.5 * (A[..., r, c] + A[..., c, r])  # noqa: E731 - the six entries of sym(A)
    zp, lb = p @ Zp, p @ L_bb  # Z_pᵀp, L_bbᵀp [Q, K, 3]
    s_node = (p * p).sum(-1, keepdim=True)
    G = (
        ZPZ.unsqueeze(-2)
        - d @ outer
        + 0.25
        * (
            (1.0 - s_node) * sym(A0).unsqueeze(-2)
            + 2.0 * p @ sym(Mk)
            + (zp[..., r] * lb[..., c] + zp[..., c] * lb[..., r])
        )
    )  # [Q, K, 6]
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
    lead = prod.mean.shape[:-1]

    def flat(t: Tensor, event: int) -> Tensor:
        tail = t.shape[t.dim() - event :]
        return t.expand(*lead, *tail).reshape(-1, *tail)

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
    ci = rule.coefficients(_side_coefficients(first, x0, terms, L_bb, p))  # [Q, 10, K]
    cj = rule.coefficients(_side_coefficients(second, x0, terms, L_bb, p))
    return (ci * cj).sum((-2, -1))
