"""The 6-state attitude model's ``E[ℓᵢℓⱼ]`` with the bias block in closed form (:mod:`agsf_torch.models.attitude_bias_block`)
against the 840-node interpolatory rule and a dense Gauss–Hermite rule of higher degree than the integrand."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.fpke import fpke_matrix
from agsf_torch.fpke.rules import residual_rule
from agsf_torch.models import AttitudeModel
from agsf_torch.quadrature import gauss_hermite
from tests.fpke.test_exactness import _random_rates, _rounding, _within
from tests.helpers import assert_within


@pytest.mark.parametrize("N", [1, 3, 6])
def test_bias_block_route_equals_both_rules(gen, N):
    """In exact arithmetic all three are the same number; each differs from the dense rule by at most that rule's
    worst-case rounding (:func:`tests.fpke.test_exactness._rounding`, the fast routes rounding far less), so from
    each other by at most twice it."""
    model = AttitudeModel(estimate_bias=True)
    rule, _ = residual_rule(model, None, 2)
    tol = _rounding((9, 9, 9, 4, 4, 4), 2)
    for _ in range(3):
        rates, u = _random_rates(model, 4, N, gen, (-4.0, -2.0))
        closed = fpke_matrix(model, u, rates, rule, None)  # the model's route: bias block in closed form
        interpolated = fpke_matrix(model, u, rates, rule, None, pair_products=False)  # 840 nodes
        dense = fpke_matrix(model, u, rates, *gauss_hermite((9, 9, 9, 4, 4, 4)))  # degree 17 / 7 ≥ 12 / 4
        _within(closed.scaled, dense.scaled, tol, "L̃ with the bias block in closed form, against the dense rule")
        _within(interpolated.scaled, dense.scaled, tol, "L̃ by the 840-node rule, against the dense rule")
        _within(closed.scaled, interpolated.scaled, 2 * tol, "L̃ with the bias block in closed form, against 840 nodes")
        assert torch.equal(closed.log_scale, interpolated.log_scale)  # the same product Gaussians: the same log z


def test_chunks_and_an_empty_batch(gen):
    """Chunks of pairs give the numbers of one call to rounding (BLAS blocks a batch by its size; both within
    the rounding bound of the test above); an empty batch an empty result."""
    from agsf_torch.fpke.pairs import product_gaussians
    from agsf_torch.models.attitude_bias_block import attitude_pair_products

    model = AttitudeModel(estimate_bias=True)
    rates, u = _random_rates(model, 5, 4, gen, (-4.0, -2.0))
    prod = product_gaussians(rates.with_precision())
    whole = attitude_pair_products(model, u, prod)
    chunked = attitude_pair_products(model, u, prod, max_chunk_elements=84 * 9 * 3)  # 3 pairs per chunk
    scale = whole.abs().amax(-1, keepdim=True)
    assert_within(chunked, whole, _rounding((9, 9, 9, 4, 4, 4), 2) * scale, "E[ℓᵢℓⱼ] in chunks of 3 pairs")
    empty = product_gaussians(rates.with_precision().map(lambda t, dim: t[:0]))
    assert attitude_pair_products(model, u[:0], empty).shape == (0, 10)


def test_the_three_state_model_keeps_its_84_node_rule():
    assert AttitudeModel(estimate_bias=False).fpke_pair_products(None, None) is None
