"""A measurement model from a plain function (``y = h(x) + v``, ``v ~ N(0, R)``): the
:class:`~agsf_torch.models.base.MeasurementModel` a user writes in one line, its Jacobian by ``torch.func``
unless given in closed form."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..finite import check_finite
from ..shapes import broadcast_shapes
from .base import MeasurementModel, check_measurement_batch

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
        self.register_buffer("R", R)
        self.register_buffer("_mask", mask)

    @property
    def measurement_dim(self) -> int:
        """``d``, the size of ``y`` (``noise_cov``'s)."""
        return self.R.shape[-1]

    def _check_output(self, name: str, value: Tensor, trailing: tuple[int, ...]) -> Tensor:
        if (
            not torch.is_tensor(value)
            or value.dim() < len(trailing)
            or tuple(value.shape[-len(trailing) :]) != trailing
        ):
            got = tuple(value.shape) if torch.is_tensor(value) else type(value).__name__
            want = ", ".join(map(str, trailing))
            raise ValueError(
                f"{name} must return [..., {want}] (d = {self.measurement_dim}, noise_cov's size), got {got}"
            )
        return value

    def predict(self, x: Tensor) -> Tensor:
        return self._check_output("fn", self.fn(x), (self.measurement_dim,))

    def noise_cov(self) -> Tensor:
        return self.R

    def jacobian(self, x: Tensor) -> Tensor:
        if self._jacobian is not None:
            return self._check_output("jacobian", self._jacobian(x), (self.measurement_dim, x.shape[-1]))
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
