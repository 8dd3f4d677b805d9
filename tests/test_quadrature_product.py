"""The interpolatory product rule: E[fg] and E[f] exact for f, g in the declared polynomial space."""

from __future__ import annotations

import itertools

import pytest
import torch

from agsf_torch.quadrature import gauss_hermite, product_rule
from tests.helpers import F64, assert_within, relative_bound


def _random_polynomial(gen, groups):
    """A random polynomial in the tensor product of the groups' total-degree spaces, as a function of x [K, n]."""
    per_group = [[a for a in itertools.product(range(d + 1), repeat=len(ax)) if sum(a) <= d] for ax, d in groups]
    terms = list(itertools.product(*per_group))
    coef = torch.randn(len(terms), generator=gen, dtype=F64)

    def f(x):
        out = torch.zeros(x.shape[0], dtype=F64)
        for c, exps in zip(coef, terms):
            term = torch.full((x.shape[0],), float(c), dtype=F64)
            for (ax, _), a in zip(groups, exps):
                for axis, power in zip(ax, a):
                    term = term * x[:, axis] ** power
            out = out + term
        return out

    return f


@pytest.mark.parametrize("groups", [(((0, 1, 2), 6),), (((0, 1, 2), 4), ((3, 4), 2)), (((0,), 5),)])
def test_products_and_means_are_exact(gen, groups):
    n = sum(len(ax) for ax, _ in groups)
    rule = product_rule(groups, n)
    f, g = _random_polynomial(gen, groups), _random_polynomial(gen, groups)
    cf, cg = rule.coefficients(f(rule.nodes)), rule.coefficients(g(rule.nodes))
    # a tensor Gauss–Hermite rule exact for the product: degree ≤ 2d per axis needs d + 1 points
    points = [0] * n
    for ax, d in groups:
        for a in ax:
            points[a] = d + 1
    nodes, w = gauss_hermite(tuple(points))
    ref_fg, ref_f = float((f(nodes) * g(nodes) * w).sum()), float((f(nodes) * w).sum())
    # E[fg] and E[f] are sums over nodes in which random signs cancel: both sides round relative to the norms
    # ‖f‖ = E[f²]^½ and ‖g‖ (|E[fg]| ≤ ‖f‖‖g‖, |E[f]| ≤ ‖f‖), not only to the results, which may be small
    # (1e-12 is ~4500 ε: the degree-6 polynomials at the outer nodes are far larger than their norms)
    norm_f, norm_g = float((f(nodes) ** 2 * w).sum()) ** 0.5, float((g(nodes) ** 2 * w).sum()) ** 0.5
    assert_within((cf * cg).sum(), ref_fg, relative_bound(ref_fg, 1e-11, 1e-12 * norm_f * norm_g), "E[fg]")
    assert_within(cf[0], ref_f, relative_bound(ref_f, 1e-11, 1e-12 * norm_f), "E[f]")


def test_node_counts_and_bad_groups():
    assert product_rule((((0, 1, 2), 6), ((3, 4, 5), 2)), 6).nodes.shape == (840, 6)
    assert product_rule((((0, 1, 2), 6),), 3).nodes.shape == (84, 3)
    with pytest.raises(ValueError, match="partition the 3 axes"):
        product_rule((((0, 1), 2),), 3)
    with pytest.raises(ValueError, match="degrees must be integers ≥ 0"):
        product_rule((((0, 1, 2), -1),), 3)


def test_a_tensor_product_rule_too_large_to_build_is_refused_before_allocating():
    """40 points per axis in 6 dimensions (4.1e9 nodes) had tried to allocate 30 GiB; it is refused naming the size,
    and an adaptive filter given it is refused when built."""
    from agsf_torch.filters import AdaptiveGaussianSumFilter, PenaltyWeightUpdate
    from agsf_torch.models import AttitudeModel
    from agsf_torch.quadrature import MAX_PRODUCT_NODES, gauss_hermite

    with pytest.raises(ValueError, match=r"has 4,096,000,000 nodes, more than 2,000,000: use fewer points per axis"):
        AdaptiveGaussianSumFilter(AttitudeModel(estimate_bias=True), weight_update=PenaltyWeightUpdate(quadrature=40))
    assert gauss_hermite(11, 6)[0].shape == (11**6, 6) and 11**6 <= MAX_PRODUCT_NODES
