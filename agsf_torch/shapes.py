"""Broadcasting of shapes (tuples of sizes), without tensors.

:func:`torch.broadcast_shapes` runs through the reference implementation's symbolic-size guards, a large part of
a one-spacecraft filter step; the filters call :func:`broadcast_shapes` instead, which follows the same rules in
plain Python.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["broadcast_shapes"]


def broadcast_shapes(*shapes: Sequence[int]) -> torch.Size:
    """The shape that ``shapes`` broadcast to, by NumPy's rules (as :func:`torch.broadcast_shapes`).

    Shapes are aligned at their last dimension; in each dimension the sizes must be equal or 1 (a size
    of 1 stretches, so ``1`` and ``0`` give ``0``).

    Raises:
        RuntimeError: as :func:`torch.broadcast_shapes`, naming the two shapes that do not broadcast.
    """
    ndim = max((len(s) for s in shapes), default=0)
    out = [1] * ndim
    owner = [-1] * ndim  # which shape set each size, for the error message
    for k, shape in enumerate(shapes):
        for i, size in enumerate(shape, ndim - len(shape)):
            size = int(size)
            if size < 0:
                raise RuntimeError(f"Trying to create tensor with negative dimension {size}: {tuple(shape)}")
            if size == 1:
                continue
            if out[i] == 1:
                out[i], owner[i] = size, k
            elif out[i] != size:
                raise RuntimeError(
                    f"Shape mismatch: objects cannot be broadcast to a single shape: "
                    f"{tuple(shapes[owner[i]])} and {tuple(shape)}"
                )
    return torch.Size(out)
