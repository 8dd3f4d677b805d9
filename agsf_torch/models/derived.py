"""What a model derives from its physics holds only for that physics.

A model states its physics in a few methods (a :class:`~agsf_torch.models.base.ContinuousModel`'s ``drift``,
``noise_gain`` and ``noise_psd``; a :class:`~agsf_torch.models.base.MeasurementModel`'s ``predict`` and
``noise_cov``) and may add what it derives from them: closed forms (``drift_jacobian``, ``fokker_planck_terms``,
…) and fused kernels (``fused_propagation``, ``fused_update``, …).  A user's subclass that changes the physics
and keeps the parent's derivations would otherwise run the parent's equations, and only where a derivation is
taken (a fused kernel from some batch size on): different numbers for the same model at different sizes.

:func:`derived_from` marks such a method with the physics it was derived from.  The physics is recorded as the
functions the first model class holding the method resolves those names to (:func:`record_derivations`, called
by the model bases for every subclass); on a model whose class resolves any of them to another function (or
that sets one on the instance) the method gives way to the generic one of the model base (``torch.func``
derivatives, the generic quadrature, the unfused path).  A subclass that overrides a derived method itself
declares it for its own physics, and it applies.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import Any

__all__ = ["derived_from", "record_derivations", "follows_physics", "provides"]

#: Attribute of a derived method: the physics names it was derived from.
_NAMES = "__derived_from__"
#: Attribute of a derived method: ``{name: function}`` the first class holding it resolved those names to.
_SNAPSHOT = "__derived_against__"


def derived_from(*physics: str, generic: Callable[..., Any]) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Mark a method as derived from the methods named ``physics``; where a model's class resolves any of them
    to another function than the class the method was first declared for, the call goes to ``generic`` (the
    model base's method of the same contract) instead.

    Args:
        physics: method names, e.g. ``("drift", "noise_gain", "noise_psd")``.
        generic: the implementation that follows any physics, called with the same arguments.
    """

    def mark(method: Callable[..., Any]) -> Callable[..., Any]:
        valid: dict[type, bool] = {}  # per class: its resolution of the physics is fixed once it is created
        names = frozenset(physics)

        @functools.wraps(method)
        def dispatch(self, *args, **kwargs):
            cls = type(self)
            ok = valid.get(cls)
            if ok is None:
                ok = valid[cls] = _resolves_as_recorded(cls, dispatch)
            if ok and not (self.__dict__.keys() & names):
                return method(self, *args, **kwargs)
            return generic(self, *args, **kwargs)

        setattr(dispatch, _NAMES, tuple(physics))
        return dispatch

    return mark


def record_derivations(cls: type) -> None:
    """Record, for every derived method ``cls`` holds that no class recorded before, the functions its physics
    names resolve to on ``cls`` (called by the model bases' ``__init_subclass__``)."""
    for name in dir(cls):
        method = inspect.getattr_static(cls, name, None)
        names = getattr(method, _NAMES, None)
        if names is None or hasattr(method, _SNAPSHOT):
            continue
        setattr(method, _SNAPSHOT, {p: inspect.getattr_static(cls, p, None) for p in names})


def _resolves_as_recorded(cls: type, method: Callable[..., Any]) -> bool:
    snapshot = getattr(method, _SNAPSHOT, None)
    if snapshot is None:  # held by a class that is not a model: nothing to compare with
        return False
    return all(inspect.getattr_static(cls, p, None) is f for p, f in snapshot.items())


def follows_physics(model: Any, name: str) -> bool:
    """Whether ``model``'s method ``name`` applies as written: ``True`` for a method that derives nothing, or one
    whose physics ``model`` resolves as the class it was derived for."""
    method = inspect.getattr_static(type(model), name, None)
    names = getattr(method, _NAMES, None)
    if names is None:
        return True
    return _resolves_as_recorded(type(model), method) and not (model.__dict__.keys() & set(names))


def provides(model: Any, name: str, base: type) -> bool:
    """Whether ``model``'s method ``name`` is one of its own that applies: not ``base``'s default, and derived (if
    at all) for the physics ``model`` has."""
    return getattr(type(model), name) is not getattr(base, name) and follows_physics(model, name)
