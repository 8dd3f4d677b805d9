"""Options declared once: frozen, keyword-only dataclasses whose fields carry their help text.

A step's options (a weight update's λ, the filters' update iterations…) are the fields of
one dataclass that validates itself.  The registry builds filters from them, and the
experiment configuration, the command line's list of keys and the documentation read
their fields (:func:`option` metadata: the help line, and whether and how the option
appears in a configuration file), so a new option is written in one place.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from ..gating import chi2_threshold

__all__ = ["option", "config_options", "ConfigOption", "FilterOptions", "positive_int"]


def option(help: str, *, config: str | None = None, off: Any = None) -> dict[str, Any]:
    """Field metadata of an option.

    Args:
        help: one line for help texts and documentation.
        config: the option's type in a configuration file (``"int"``, ``"float"``, ``"str"``,
            ``"bool"``), or ``None`` when it is set through the API only (a tensor rule, say).
        off: the configuration value that stands for ``None`` (TOML has no null), if any.
    """
    return {"help": help, "config": config, "off": off}


@dataclass(frozen=True)
class ConfigOption:
    """An option as it appears in a configuration file.

    Attributes:
        name: the key (the dataclass field's name: one name in the API, the configuration and the CLI).
        kind: ``"int"``, ``"float"``, ``"str"`` or ``"bool"``.
        default: its default, in configuration form (``off`` for a ``None`` default).
        help: the help line.
        off: the configuration value that stands for ``None``, or ``None``.
        owners: the dataclasses that declare it.
    """

    name: str
    kind: str
    default: Any
    help: str
    off: Any
    owners: tuple[type, ...]

    def to_api(self, value: Any) -> Any:
        """The value as the dataclass takes it (``off`` → ``None``)."""
        return None if self.off is not None and value == self.off else value


def config_options(*classes: type) -> dict[str, ConfigOption]:
    """The configuration options of ``classes`` (fields with a ``config`` type), by name.

    A name declared by several classes (``cadence`` of both weight updates) is one option;
    its declarations must agree on type and default.
    """
    out: dict[str, ConfigOption] = {}
    for cls in classes:
        for f in dataclasses.fields(cls):
            kind = f.metadata.get("config")
            if kind is None:
                continue
            off = f.metadata.get("off")
            default = f.default if f.default is not None else off
            if f.name in out:
                known = out[f.name]
                if (known.kind, known.default) != (kind, default):
                    raise TypeError(
                        f"option {f.name!r} is declared differently by {known.owners[0].__name__} and {cls.__name__}"
                    )
                out[f.name] = dataclasses.replace(known, owners=known.owners + (cls,))
            else:
                out[f.name] = ConfigOption(f.name, kind, default, f.metadata["help"], off, (cls,))
    return out


def positive_int(name: str, value: Any) -> int:
    """``value`` as an ``int ≥ 1``; ``ValueError`` naming ``name`` otherwise (``bool`` refused)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or int(value) != value or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


@dataclass(frozen=True, kw_only=True)
class FilterOptions:
    """The options every registered filter takes (:class:`~agsf_torch.filters.base.BaseFilter`).

    Attributes:
        update_iterations: linearisations per measurement update (1: the EKF update).
        gate_probability: the innovation gate's ``p`` in (0, 1), or ``None`` (off).
        fused: use the fused (matrix-major) path of a model or measurement that declares one
            (:mod:`agsf_torch.fused`: the attitude model's propagation, the star-vector update);
            ``False``: the generic path (any model, ``torch.func``), the reference.
        compile_fused: the package's one compile switch: run its kernels compiled ahead of time
            (:mod:`agsf_torch.compiled_kernels`: the fused kernels of :mod:`agsf_torch.fused.lanes`, per kernel a
            threaded variant for calls of 1,024 lanes or more and a serial one below, and the adaptive filters'
            FPKE kernels, unless their weight update's ``compile`` overrides it), each compiled on first use, once
            per machine, and loaded by later processes; ``False`` runs the same code eagerly (the fused kernels from
            :data:`~agsf_torch.fused.lanes.EAGER_MIN_LANES` components on; fewer take the generic path, which is
            faster there).
    """

    update_iterations: int = field(
        default=1,
        metadata=option("linearisations per measurement update (1: the EKF update; more: iterated)", config="int"),
    )
    gate_probability: float | None = field(
        default=None,
        metadata=option(
            "innovation gate of every filter: 0 = off (the method), else p in (0, 1), e.g. 0.9999",
            config="float",
            off=0.0,
        ),
    )

    fused: bool = field(
        default=True,
        metadata=option(
            "use the fused (matrix-major) path of a model that has one; false: the generic path", config="bool"
        ),
    )
    compile_fused: bool = field(
        default=False,
        metadata=option(
            "compile the fused kernels ahead of time (once per machine; later processes load them)",
            config="bool",
        ),
    )

    def __post_init__(self) -> None:
        positive_int("update_iterations", self.update_iterations)
        for name in ("fused", "compile_fused"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if self.gate_probability is not None:
            chi2_threshold(self.gate_probability, 1)  # validates p

    def as_kwargs(self) -> dict[str, Any]:
        """The options as keyword arguments of a filter's constructor."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
