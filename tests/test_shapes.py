"""agsf_torch.shapes: broadcasting of plain shapes, checked against torch's own rules."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from agsf_torch.shapes import broadcast_shapes

sizes = st.integers(0, 4)
shape = st.lists(sizes, max_size=4).map(tuple)


@settings(max_examples=300, deadline=None)  # torch.broadcast_shapes imports sympy on its first call
@given(st.lists(shape, min_size=1, max_size=4))
def test_broadcast_shapes_agrees_with_torch_whether_or_not_the_shapes_broadcast(shapes):
    try:
        expected = torch.broadcast_shapes(*shapes)
    except RuntimeError:
        with pytest.raises(RuntimeError, match="cannot be broadcast"):
            broadcast_shapes(*shapes)
    else:
        got = broadcast_shapes(*shapes)
        assert got == expected and isinstance(got, torch.Size)


def test_broadcast_shapes_names_the_two_shapes_that_clash_and_takes_torch_sizes():
    with pytest.raises(RuntimeError, match=r"\(3, 2\) and \(4,\)"):
        broadcast_shapes((3, 2), (1, 1), (4,))
    assert broadcast_shapes(torch.Size([5, 1]), torch.Size([4])) == (5, 4)
    assert broadcast_shapes() == torch.Size([])
    assert broadcast_shapes((1,), (0,)) == (0,)
