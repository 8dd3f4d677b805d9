"""A measurement model from a plain function (``y = h(x) + v``, ``v ~ N(0, R)``): the
:class:`~agsf_torch.models.base.MeasurementModel` a user writes in one line, its Jacobian by ``torch.func``
unless given in closed form."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..finite import check_finite
from ..shapes import broadcast_shapes
from .base import MeasurementModel
from .contract import check_elementwise, check_measurement_batch

__all__ = ["FunctionMeasurement"]


class FunctionMeasurement(MeasurementModel):
    """A measurement model from a plain function.

    Args:
        fn: ``h``, mapping ``[..., n]`` to ``[..., d]`` elementwise over leading dims.
        noise_cov: ``R``, ``[d, d]`` (or batched), symmetric positive definite; its size
            fixes ``d``.
        jacobian: optional closed form of ``∂h/∂x`` (``[..., n]`` → ``[..., d, n]``).
        mask: optional ``[..., d]`` bool validity of the entries (``d`` as ``noise_cov``'s,
            leading dims broadcasting with its own).

    Shapes are checked against ``d``: the mask at construction, ``y`` before each update
    (:meth:`check_measurement`), ``fn``'s and ``jacobian``'s outputs at every call — a
    mismatch is a ``ValueError`` naming the argument, never a broadcast.
    """

    #: Not probed by :func:`~agsf_torch.models.contract.check_measurement_elementwise` (checked otherwise).
    elementwise_checked = True

    def __init__(
        self,
        fn: Callable[[Tensor], Tensor],
        noise_cov: Tensor,
        jacobian: Callable[[Tensor], Tensor] | None = None,
        mask: Tensor | None = None,
    ) -> None:
        super().__init__()
        R = torch.as_tensor(noise_cov)
        if R.dim() < 2 or R.shape[-1] != R.shape[-2]:
            raise ValueError(f"noise_cov must be a square matrix [..., d, d], got shape {tuple(R.shape)}")
        check_finite("noise_cov", R)
        if not torch.allclose(R, R.transpose(-1, -2)):
            raise ValueError("noise_cov must be symmetric")
        if bool((torch.linalg.cholesky_ex(R).info != 0).any()):
            raise ValueError("noise_cov must be positive definite")
        d = R.shape[-1]
        if mask is not None:
            mask = torch.as_tensor(mask)
            if mask.dtype != torch.bool:
                if mask.is_floating_point() or mask.is_complex() or bool(((mask != 0) & (mask != 1)).any()):
                    raise ValueError(f"mask must be bool (or 0/1 integers) [..., {d}], got a {mask.dtype} tensor")
                mask = mask.to(torch.bool)
            if mask.dim() < 1 or mask.shape[-1] != d:
                raise ValueError(f"mask must have shape [..., {d}] (d = noise_cov's size), got {tuple(mask.shape)}")
            try:
                broadcast_shapes(mask.shape[:-1], R.shape[:-2])
            except RuntimeError:
                raise ValueError(
                    f"mask {tuple(mask.shape)} and noise_cov {tuple(R.shape)} have leading dims that do not broadcast"
                ) from None
        self.fn = fn
        self._jacobian = jacobian
        self._probed: set[tuple[str, int]] = set()  # (function, state size n) whose elementwise probe passed
        self.register_buffer("R", R)
        self.register_buffer("_mask", mask)

    @property
    def measurement_dim(self) -> int:
        """``d``, the size of ``y`` (``noise_cov``'s)."""
        return self.R.shape[-1]

    def _check_output(self, name: str, value: Tensor, lead: torch.Size, trailing: tuple[int, ...]) -> Tensor:
        """``value`` if it is ``[*lead, *trailing]``: the leading dims of the states it was called with (a function
        that indexes ``x[:, i]`` instead of ``x[..., i]`` returns other leading dims), else a ``ValueError``."""
        if not torch.is_tensor(value) or tuple(value.shape) != (*lead, *trailing):
            got = tuple(value.shape) if torch.is_tensor(value) else type(value).__name__
            want = ", ".join(map(str, (*lead, *trailing)))
            raise ValueError(
                f"{name} must return [{want}] for states x [{', '.join(map(str, (*lead, 'n')))}]: x's leading "
                f"dims, then d = {self.measurement_dim} (noise_cov's size){', n' if len(trailing) == 2 else ''}; "
                f"got {got} (index the state as x[..., i], not x[:, i]: the filters pass [..., n])"
            )
        return value

    def _probe(self, name: str, function: Callable[[Tensor], Tensor], x: Tensor, trailing: tuple[int, ...]) -> None:
        """Once per state size ``n``: call ``function`` on :func:`~.contract.elementwise_probe` states, whose leading dims no
        state size can be mistaken for (the filters' own, ``[N, B, n]``, are ``[N, n, n]`` when ``B = n``: a function
        indexing ``x[:, i]`` then returns the right shape and wrong numbers)."""
        n = x.shape[-1]
        if (name, n) in self._probed or x.numel() == 0:
            return
        check_elementwise(name, function, x, trailing)
        self._probed.add((name, n))

    def predict(self, x: Tensor) -> Tensor:
        h = self._check_output("fn", self.fn(x), x.shape[:-1], (self.measurement_dim,))
        self._probe("fn", self.fn, x, (self.measurement_dim,))
        return h

    def noise_cov(self) -> Tensor:
        return self.R

    def jacobian(self, x: Tensor) -> Tensor:
        if self._jacobian is not None:
            trailing = (self.measurement_dim, x.shape[-1])
            H = self._check_output("jacobian", self._jacobian(x), x.shape[:-1], trailing)
            self._probe("jacobian", self._jacobian, x, trailing)
            return H
        return super().jacobian(x)

    def check_measurement(self, y: Tensor) -> Tensor:
        """``y`` must have ``d`` entries (``noise_cov``'s size); ``noise_cov`` and the mask one per trajectory of
        ``y`` or one for all (:func:`~agsf_torch.models.base.check_measurement_batch`)."""
        if y.dim() < 1 or y.shape[-1] != self.measurement_dim:
            raise ValueError(
                f"y has shape {tuple(y.shape)}: {y.shape[-1] if y.dim() else 0} entries but the measurement model "
                f"predicts {self.measurement_dim} (d = noise_cov's size)"
            )
        check_measurement_batch("noise_cov", self.R.shape[:-2], y)
        if self._mask is not None:
            check_measurement_batch("mask", self._mask.shape[:-1], y)
        return y

    def mask(self) -> Tensor | None:
        return self._mask
