"""Finiteness checks by extremes (agsf_torch.finite)."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from agsf_torch.finite import all_finite, check_finite
from tests.helpers import F64


@settings(max_examples=200, deadline=None)
@given(
    shape=st.lists(st.integers(0, 5), min_size=0, max_size=4),
    bad=st.sampled_from([math.nan, math.inf, -math.inf, None]),
    where=st.floats(0.0, 1.0, exclude_max=True),
    dtype=st.sampled_from([torch.float64, torch.float32, torch.float16, torch.bfloat16]),
    seed=st.integers(0, 2**31 - 1),
)
def test_the_extremes_answer_as_a_mask_does(shape, bad, where, dtype, seed):
    """Against ``torch.isfinite(t).all()`` on random tensors with one NaN or ``±inf`` (or none) anywhere."""
    t = torch.randn(tuple(shape), generator=torch.Generator().manual_seed(seed), dtype=F64).to(dtype)
    if bad is not None and t.numel():
        t.view(-1)[int(where * t.numel())] = bad
    assert all_finite(t) == bool(torch.isfinite(t).all())


def test_several_tensors_and_the_types_without_extremes():
    ok = torch.ones(3, dtype=F64)
    assert all_finite(ok, torch.arange(4), torch.ones(2, dtype=torch.bool), torch.empty(0, dtype=F64))
    assert not all_finite(ok, torch.tensor([1.0, math.inf]))
    assert all_finite(torch.tensor([1 + 2j]))
    assert not all_finite(torch.tensor([complex(math.nan, 0.0)]))


def test_check_finite_names_the_tensor_and_the_first_bad_entry():
    value = torch.zeros(2, 3, dtype=F64)
    value[1, 2] = math.nan
    with pytest.raises(ValueError, match=r"gyro must be finite; non-finite entry at index \(1, 2\)"):
        check_finite("gyro", value)
    check_finite("gyro", torch.zeros(2, dtype=F64))
