"""Fokker–Planck residual of a Gaussian mixture and the weight-update matrices (method.md §3, §3b).

* :mod:`.residual` — the residual factor ``ℓᵢ`` and the pointwise residual;
* :mod:`.pairs` — the product Gaussians ``pᵢpⱼ = z_ij N(m_ij, S_ij)``;
* :mod:`.matrices` — ``L_ij = ∫LᵢLⱼ`` and ``K_ij = ∫pᵢLⱼ`` by quadrature;
* :mod:`.rules` — which quadrature rule;
* :mod:`.rounding` — which components' residual is zero to rounding.
"""

from .matrices import (
    FPKEMatrix,
    GalerkinMatrices,
    fpke_matrix,
    fused_fpke_matrix,
    fused_galerkin_matrices,
    galerkin_matrices,
)
from .pairs import ProductGaussians, product_gaussians
from .residual import ComponentRates, fpke_residual, log_normal, residual_factor
from .rules import residual_rule

__all__ = [
    "ComponentRates",
    "residual_factor",
    "fpke_residual",
    "log_normal",
    "ProductGaussians",
    "product_gaussians",
    "fpke_matrix",
    "FPKEMatrix",
    "galerkin_matrices",
    "fused_galerkin_matrices",
    "fused_fpke_matrix",
    "GalerkinMatrices",
    "residual_rule",
]
