"""A filter step's diagnostics: a plain dict that prints as a short summary.

``filt.diagnostics`` holds one step's numbers as tensors of shape ``[...]`` (one per
trajectory) or ``[..., N]`` (one per component); printing them raw dumps every entry.
:class:`StepDiagnostics` is a ``dict`` (keys, values, ``**``, ``==`` and ``json`` work as
before) whose ``repr``/``str`` is one line per key::

    log_likelihood  [256]     float64  min -12.3  mean -8.41  max -5.02
    nis             [256, 5]  float64  min 0.0132  mean 2.11  max 9.87  (3 NaN)
    weights_adapted           bool     True
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["StepDiagnostics", "summarize_value"]


def _number(x: float) -> str:
    """``x`` in three significant digits (``nan``, ``inf`` as such)."""
    return f"{x:.3g}"


def summarize_value(value: Any) -> tuple[str, str, str]:
    """``(shape, dtype, statistics)`` of one diagnostics value, as text.

    Args:
        value: a tensor of any shape (numeric or bool; it may require grad or live on
            any device), or a Python scalar or other object.

    Returns:
        ``shape``: ``"[B, N]"`` for a tensor (``""`` for a 0-d tensor or a non-tensor);
        ``dtype``: the tensor's dtype without ``torch.`` or the Python type's name;
        ``statistics``: for a 0-d tensor or a scalar its value; for a numeric tensor
        ``min … mean … max …`` over its finite and infinite entries, ignoring NaN (and
        counting them, ``(k NaN)``; a complex tensor: of its magnitudes, dtype marked ``|·|``);
        for a bool tensor ``true k/n``; ``empty`` for a tensor without entries.
    """
    if not torch.is_tensor(value):
        return "", type(value).__name__, repr(value)
    t = value.detach()
    shape = "" if t.dim() == 0 else "[" + ", ".join(str(s) for s in t.shape) + "]"
    dtype = str(t.dtype).removeprefix("torch.")
    if t.numel() == 0:
        return shape, dtype, "empty"
    if t.dtype == torch.bool:
        if t.dim() == 0:
            return shape, dtype, str(bool(t))
        return shape, dtype, f"true {int(t.sum())}/{t.numel()}"
    if t.is_complex():
        t = t.abs()
        dtype += " |·|"
    if t.dim() == 0:
        v = t.item()
        return shape, dtype, str(v) if isinstance(v, int) else _number(v)
    t = t.to(torch.float64) if not t.is_floating_point() else t
    nan = torch.isnan(t)
    n_nan = int(nan.sum())
    if n_nan == t.numel():
        return shape, dtype, "all NaN"
    valid = t[~nan]
    lo, mean, hi = float(valid.min()), float(valid.mean()), float(valid.max())
    stats = f"min {_number(lo)}  mean {_number(mean)}  max {_number(hi)}"
    if n_nan:
        stats += f"  ({n_nan} NaN)"
    return shape, dtype, stats


class StepDiagnostics(dict):
    """One filter step's diagnostics ``{name: tensor or number}``; a ``dict`` in every respect
    except that ``repr``/``str`` summarise each value on one line (name, shape, dtype and
    ``min``/``mean``/``max`` ignoring NaN; :func:`summarize_value`) instead of printing it whole."""

    def summary(self) -> str:
        """The one-line-per-key text of ``repr``/``str`` (columns aligned)."""
        if not self:
            return "StepDiagnostics({})"
        rows = [(str(k), *summarize_value(v)) for k, v in self.items()]
        widths = [max(len(r[i]) for r in rows) for i in range(3)]
        return "\n".join(
            f"{name:<{widths[0]}}  {shape:<{widths[1]}}  {dtype:<{widths[2]}}  {stats}".rstrip()
            for name, shape, dtype, stats in rows
        )

    __repr__ = summary
    __str__ = summary

    def _repr_pretty_(self, printer: Any, cycle: bool) -> None:  # IPython / Jupyter
        printer.text(self.summary())
