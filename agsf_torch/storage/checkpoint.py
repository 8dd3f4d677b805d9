"""Checkpoints: a filter run's full state saved and restored, safely.

A checkpoint is a ``torch.save`` file holding only tensors, numbers, strings,
lists and dicts, so it loads with ``torch.load(weights_only=True)`` (no code
execution).  It holds, per filter, the mixture (log-weights, means, covariances),
the filter's run state (``filter.state_dict()``: the adaptive filter's
weight-update counter and reference weights) and its options (``filter.checkpoint_options()``: the filter's and its
weight update's), plus any caller state (for example an environment's ``state_dict()`` and a
:class:`~agsf_torch.attitude.gyro_hold.GyroHold`'s).  Restoring it into filters of the same options
and continuing gives the same numbers, bit for bit, as never stopping.  A filter whose options differ is refused,
naming each option and its two values, but for :data:`MAY_DIFFER`: the options that choose how the same arithmetic
runs (compiled or eager, fused or generic, in chunks: the numbers then agree to rounding) and the Galerkin update's
residual diagnostics (which change no number).
"""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Mapping
from pathlib import Path, PurePath
from typing import Any

import torch

from ..filters.base import Filter
from ..mixture import GaussianMixture
from .files import atomic_open

__all__ = ["save_checkpoint", "load_checkpoint", "FORMAT", "MAY_DIFFER"]

FORMAT = "agsf-checkpoint-3"
#: The format before checkpoints recorded their filters' options: still read, with a warning that they go unchecked.
_FORMAT_WITHOUT_OPTIONS = "agsf-checkpoint-2"
#: The options a checkpoint may be loaded under with other values than it was saved with: how the same arithmetic
#: runs (compiled or eager, the fused path or the generic one, the quadrature in chunks), which moves the numbers at
#: most by rounding, and the Galerkin update's residual diagnostics, which move none.
MAY_DIFFER = ("fused", "compile_fused", "compile", "chunk_size", "residual_diagnostics")


def _mixture_state(m: GaussianMixture) -> dict[str, Any]:
    return {"log_weights": m.log_weights, "means": m.means, "covs": m.covs}


def save_checkpoint(
    path: str | Path,
    mixtures: Mapping[str, GaussianMixture],
    filters: Mapping[str, Filter],
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write a checkpoint atomically (:func:`agsf_torch.storage.files.atomic_open`: a temporary file, flushed
    to disk and renamed into place).

    Args:
        mixtures / filters: name → the current belief / the filter that owns it.
        extra: further state (tensors, Python numbers, strings, ``None``, lists, tuples and dicts with string
            keys), e.g. ``env.state_dict()``; anything else (a NumPy array or scalar, a path) is refused,
            naming its key, before any file changes.
    """
    if set(mixtures) != set(filters):
        raise ValueError(f"mixtures {sorted(mixtures)} and filters {sorted(filters)} must name the same filters")
    _check_storable(dict(extra or {}), "extra")
    state = {
        "format": FORMAT,
        "filters": {
            name: {
                "mixture": _mixture_state(mixtures[name]),
                "filter": filters[name].state_dict(),
                "options": _options(filters[name]),
            }
            for name in mixtures
        },
        "extra": dict(extra or {}),
    }
    path = Path(path)
    with atomic_open(path) as fh:
        torch.save(state, fh)
    return path


#: Python types a checkpoint stores as they are (and reads back with ``torch.load(weights_only=True)``).
_PLAIN = (bool, int, float, str, type(None))
#: An option one side has and the other has not (filters of different kinds).
_ABSENT = object()


def _options(filt: Filter) -> dict[str, Any]:
    """The filter's options as a checkpoint stores them (:func:`_option_value`); none for a filter that declares no
    ``checkpoint_options``."""
    declared = getattr(filt, "checkpoint_options", None)
    return {} if declared is None else {str(k): _option_value(v) for k, v in declared().items()}


def _option_value(value: Any) -> Any:
    """An option in a form :func:`torch.load` reads back with ``weights_only=True``: a 0-d tensor (a learned λ) as
    its number, another tensor (a quadrature rule's nodes) detached on the CPU, sequences as tuples; an object of any
    other kind (a user's weight update's option) by its ``repr``."""
    if torch.is_tensor(value):
        value = value.detach().cpu()
        return value.item() if value.dim() == 0 else value.clone()
    if type(value) in _PLAIN:
        return value
    if isinstance(value, (list, tuple)):
        return tuple(_option_value(v) for v in value)
    if isinstance(value, dict) and all(type(k) is str for k in value):
        return {k: _option_value(v) for k, v in value.items()}
    return repr(value)


def _same(a: Any, b: Any) -> bool:
    """Whether two stored options are the same: tensors of one dtype, shape and value; sequences and dicts entry by
    entry; numbers by value (``2`` and ``2.0`` are one cadence), but a bool only as a bool."""
    if torch.is_tensor(a) or torch.is_tensor(b):
        return (
            torch.is_tensor(a)
            and torch.is_tensor(b)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and torch.equal(a, b)
        )
    if isinstance(a, (list, tuple)) or isinstance(b, (list, tuple)):
        sequences = isinstance(a, (list, tuple)) and isinstance(b, (list, tuple))
        return sequences and len(a) == len(b) and all(map(_same, a, b))
    if isinstance(a, dict) or isinstance(b, dict):
        return (
            isinstance(a, dict) and isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
        )
    if a is _ABSENT or b is _ABSENT or isinstance(a, bool) != isinstance(b, bool):
        return a is b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return a == b
    return type(a) is type(b) and a == b


def _shown(value: Any) -> str:
    """An option as a refusal shows it: small tensors by value, larger ones by dtype, shape and a digest."""
    if value is _ABSENT:
        return "absent"
    if torch.is_tensor(value):
        if value.numel() <= 8:
            return f"tensor({value.tolist()})"
        digest = hashlib.sha256(repr(value.flatten().tolist()).encode()).hexdigest()[:12]
        return f"a {value.dtype} tensor of shape {tuple(value.shape)} (sha256 {digest}…)"
    if isinstance(value, tuple):
        return "(" + ", ".join(map(_shown, value)) + ("," if len(value) == 1 else "") + ")"
    return repr(value)


def _check_options(saved: Any, current: dict[str, Any]) -> None:
    """Refuse a filter whose options differ from those its checkpoint entry was saved with (but :data:`MAY_DIFFER`),
    naming each such option with its two values."""
    if not isinstance(saved, dict):
        raise ValueError(f"filter options must be a dict, got {type(saved).__name__}")
    names = [*saved, *(name for name in current if name not in saved)]
    differ = [
        f"{name} is {_shown(saved.get(name, _ABSENT))} in the checkpoint, {_shown(current.get(name, _ABSENT))} in "
        "this filter"
        for name in names
        if name not in MAY_DIFFER and not _same(saved.get(name, _ABSENT), current.get(name, _ABSENT))
    ]
    if differ:
        may = f"{', '.join(MAY_DIFFER[:-1])} and {MAY_DIFFER[-1]}"
        raise ValueError(
            f"{'; '.join(differ)}: a run resumes only under the options it was saved with ({may} may differ)"
        )


def _check_storable(value: Any, where: str) -> None:
    """Refuse, naming the key, a value that :func:`load_checkpoint` could not read back (NumPy arrays and
    scalars, paths, arbitrary objects): tensors, Python numbers, strings, ``None`` and lists, tuples and
    dicts (string keys) of them are stored."""
    if torch.is_tensor(value) or type(value) in _PLAIN:
        return
    if type(value) in (list, tuple):
        for i, v in enumerate(value):
            _check_storable(v, f"{where}[{i}]")
        return
    if type(value) is dict:
        for k, v in value.items():
            if type(k) is not str:
                raise ValueError(f"{where}: checkpoint keys must be strings, got {type(k).__name__} {k!r}")
            _check_storable(v, f"{where}[{k!r}]")
        return
    kind = f"{type(value).__module__}.{type(value).__qualname__}"
    hint = (
        " (convert it with torch.as_tensor or .item())"
        if type(value).__module__ == "numpy"
        else " (store str(path))"
        if isinstance(value, PurePath)
        else ""
    )
    raise ValueError(
        f"{where} is a {kind}, which a checkpoint cannot store{hint}: use tensors, numbers, strings, lists and dicts"
    )


def _mixture(m: Any) -> GaussianMixture:
    """The mixture of a checkpoint entry ``{"log_weights", "means", "covs"}``, validated in full.

    The three fields must be floating-point tensors of one dtype (as :func:`save_checkpoint`
    writes them: no conversion on load, so a resumed run is bit-identical).
    """
    if not isinstance(m, dict) or not {"log_weights", "means", "covs"} <= set(m):
        got = sorted(m) if isinstance(m, dict) else type(m).__name__
        raise ValueError(f"mixture must be a dict with log_weights, means and covs, got {got}")
    for key in ("means", "covs", "log_weights"):
        t = m[key]
        if not torch.is_tensor(t) or not t.is_floating_point():
            what = f"a {t.dtype} tensor" if torch.is_tensor(t) else type(t).__name__
            raise ValueError(f"mixture '{key}' must be a floating-point tensor, got {what}")
        if t.dtype != m["means"].dtype:
            raise ValueError(f"mixture '{key}' is {t.dtype} but 'means' is {m['means'].dtype}")
    return GaussianMixture(log_weights=m["log_weights"], means=m["means"], covs=m["covs"])


def _check_reference(state: Any, mixture: GaussianMixture) -> None:
    """A weight update's reference log-weights, if the state holds any, must match the mixture's ``[..., N]``."""
    update = state.get("weight_update") if isinstance(state, dict) else None
    ref = update.get("ref_log_weights") if isinstance(update, dict) else None
    if torch.is_tensor(ref) and ref.shape != mixture.log_weights.shape:
        raise ValueError(
            f"weight-update state 'ref_log_weights' has shape {tuple(ref.shape)}, the mixture's weights "
            f"{tuple(mixture.log_weights.shape)}"
        )


#: Errors a malformed checkpoint's content can raise while it is read or handed to a filter.
_CONTENT_ERRORS = (ValueError, KeyError, TypeError, AttributeError, IndexError, RuntimeError)


def _read(path: Path) -> Any:
    """``torch.load(path, weights_only=True)``; a file that is not a readable torch archive
    (corrupt, truncated, a pickle of other objects) is a ``ValueError`` naming it."""
    if not path.exists():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    if path.is_dir():
        raise IsADirectoryError(f"checkpoint {path} is a directory, not a file")
    try:
        return torch.load(path, weights_only=True)
    except OSError:
        raise
    except Exception as exc:  # noqa: BLE001 - torch/pickle raise many types for a corrupt archive
        raise ValueError(f"{path} is not a readable torch checkpoint ({type(exc).__name__}: {exc})") from None


def load_checkpoint(
    path: str | Path, filters: Mapping[str, Filter]
) -> tuple[dict[str, GaussianMixture], dict[str, Any]]:
    """Read a checkpoint (``weights_only=True``), restore the filters' run state, return
    ``(mixtures, extra)``.

    Every mixture is validated in full (floating-point tensors of one dtype, shapes,
    finite means, symmetric positive definite covariances, log-weights) and against its
    filter (:meth:`~agsf_torch.filters.base.Filter.check_mixture`: the state dimension, the
    number of components), and every filter's options against those its entry was saved with (the module
    docstring: each option that differs is named with both values, but :data:`MAY_DIFFER`; a checkpoint of the
    format before options, ``agsf-checkpoint-2``, loads with a warning that they go unchecked).  The filters'
    states are then loaded one by one; if any filter refuses its state (whatever the
    error), every filter is put back as it was before the call: a failed load changes
    nothing.

    Raises:
        ValueError: naming the file (and the filter) for any malformed or mismatched content,
            and for a file that is not a readable torch archive (corrupt, truncated).
        FileNotFoundError, IsADirectoryError: naming the path.
    """
    path = Path(path)
    state = _read(path)
    fmt = state.get("format") if isinstance(state, dict) else None
    if fmt not in (FORMAT, _FORMAT_WITHOUT_OPTIONS):
        raise ValueError(f"{path} is not an {FORMAT} file (format {fmt!r})")
    if fmt == _FORMAT_WITHOUT_OPTIONS:
        warnings.warn(
            f"{path} records no filter options (format {fmt!r}, written before checkpoints recorded them): the "
            "filters' options go unchecked, and the run resumes bit for bit only under the options it was saved with",
            RuntimeWarning,
            stacklevel=2,
        )
    name = None
    try:
        entries, extra = state["filters"], state["extra"]
        if not isinstance(entries, dict) or set(entries) != set(filters):
            got = sorted(entries) if isinstance(entries, dict) else type(entries).__name__
            raise ValueError(f"checkpoint holds filters {got}, got {sorted(filters)}")
        mixtures, restored = {}, {}
        for name, s in entries.items():
            if not isinstance(s, dict):
                raise ValueError(f"entry must be a dict, got {type(s).__name__}")
            mixtures[name] = _mixture(s["mixture"])
            filters[name].check_mixture(mixtures[name])  # state dimension, components: fits its filter
            if fmt == FORMAT:
                _check_options(s["options"], _options(filters[name]))
            restored[name] = s["filter"]
            _check_reference(restored[name], mixtures[name])
        name = None
    except _CONTENT_ERRORS as exc:
        where = "" if name is None else f"filter {name!r}: "
        if isinstance(exc, ValueError):
            raise ValueError(f"{path}: {where}{exc}") from None
        raise ValueError(f"{path}: malformed checkpoint ({where}{type(exc).__name__}: {exc})") from None
    previous = {name: filt.state_dict() for name, filt in filters.items()}
    loaded: list[str] = []
    current = None
    try:
        for current, filt in filters.items():
            filt.load_state_dict(restored[current])
            loaded.append(current)
    except BaseException as exc:  # put every filter back as it was, whatever went wrong
        for name in loaded:
            filters[name].load_state_dict(previous[name])
        try:  # the failing filter too, should it have changed anything before refusing
            filters[current].load_state_dict(previous[current])
        except Exception:  # noqa: BLE001 - it refuses states altogether; its own error is raised below
            pass
        if isinstance(exc, _CONTENT_ERRORS):
            raise ValueError(f"{path}: filter {current!r}: {exc}") from None
        raise
    return mixtures, extra
