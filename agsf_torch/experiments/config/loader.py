"""Experiment configurations: a validated dataclass, TOML presets and ``key=value`` overrides.

Every value decoded or guessed from the paper (method.md §4) is a named field
here with that value as its default; the presets in ``presets/*.toml`` set the
rest.  The filters' options are not written here: they are the fields the filters
and weight updates declare (:data:`agsf_torch.filters.registry.CONFIG_OPTIONS`), added
to :class:`ExperimentConfig` under the same names and validated by those classes.  Files are read with :mod:`tomllib` (data only, no code execution).
Unknown keys, wrong types and out-of-range values raise ``ValueError`` naming
the key, before any work starts.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
import warnings
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import tomllib

from ...constants import DEFAULT_SIGMA_U, DEFAULT_SIGMA_V, DEG_PER_HOUR
from ...filters.registry import ADAPTIVE_FILTERS, CONFIG_OPTIONS, FILTER_NAMES, filter_spec

__all__ = [
    "REPLAY_IGNORED",
    "ExperimentConfig",
    "load_config",
    "load_preset",
    "preset_names",
    "parse_override",
    "FILTER_NAMES",
    "DEFAULT_FILTERS",
    "MAX_SEED",
    "config_key_help",
]

#: The filters of a configuration that names none (the paper's three).
DEFAULT_FILTERS = ("EKF", "GSF", "AGSF")
#: Largest run seed: trajectory ``i`` is seeded ``seed + i``, and the simulator's seeds lie in ``[0, 2⁶²)``.
MAX_SEED = 2**62 - 1


#: The configuration's fields a replay of a recording does not read: the simulation's own (the file holds the
#: star frames, the stars and their directions, the rates and the faults).  ``gyro_bias_deg_per_hr`` is not one
#: of them: ``agsf learn`` starts its bias there.
REPLAY_IGNORED = ("star_period", "max_stars", "fov_deg", "focal_length", "omega0", "rate_axes", "faults")


@dataclass(frozen=True)
class _ExperimentFields:
    """One Monte Carlo experiment (units: s, rad, rad/s unless the name says otherwise).

    Attributes:
        name: label of the experiment.
        runs: Monte Carlo trajectories (one batch).
        duration: simulated time (s).
        dt: gyro period (s) — paper: 10 Hz (guess).
        star_period: time between star frames (s) — paper cases: 1, 2, 5.
        sigma_s: star noise per axis (rad) — paper: 10 µrad (guess).
        max_stars: stars per frame — paper: 5.
        fov_deg: field of view (deg, square) — paper: 8.
        focal_length: m — paper: 65 mm.
        sigma_v: angle random walk (rad/s^½) — guess √10·1e-7.
        sigma_u: rate random walk (rad/s^{3/2}) — guess √10·1e-10.
        gyro_bias_deg_per_hr: initial gyro bias per axis — guess 0.1.
        omega0: truth rate magnitude per axis (rad/s) — guess 2π/100.
        rate_axes: truth rate ``ω = ω₀ · rate_axes`` — guess [1, 1, 0].
        estimate_bias: ``False``: 3-state, bias known (paper); ``True``: 6-state.
        prior_var: prior MRP variance per axis — paper: 1e-3 (an error of θ per axis: ``tan²(θ/4)``).
        prior_attitude: where the filters' prior mean lies: ``"gaussian"`` (drawn from ``N(truth, P₀)``, consistent
            with the prior covariance) or ``"uniform"`` (a uniformly random attitude, independent of the truth: a
            lost-in-space start; ``P₀`` then only says how wide the filters take their prior to be).
        prior_bias_sigma_deg_per_hr: prior bias σ (6-state).
        components: N of the Gaussian sums.
        spread: share of the principal prior variance carried by the component means.
        filters: which of ``FILTER_NAMES`` to run (EKF, GSF, AGSF, AGSF-galerkin, MEKF, MEKF-fix, USQUE, PF).
        seed: seeds truth, noise and prior draws (trajectory ``i``: ``seed + i``), an integer with
            ``0 ≤ seed`` and ``seed + runs − 1 ≤ MAX_SEED``.
        filter_sigma_s_scale: the filters assume ``σ_s × scale`` (1: the simulated value;
            other values make a deliberately mis-modelled filter, e.g. for ``agsf diagnose``).
        filter_sigma_v_scale: likewise for σ_v.
        star_noise_model: the filters' star-vector noise model, ``"isotropic"`` (σ_s²I₃,
            the method) or ``"tangent"`` (noise across the star direction only).
        faults: sensor faults injected by the environment (:mod:`envs.faults`), a list
            of tables such as ``{kind = "star_outage", start = 60.0, end = 180.0}``.
    """

    name: str = "experiment"
    runs: int = 100
    duration: float = 30.0
    dt: float = 0.1
    star_period: float = 1.0
    sigma_s: float = 10e-6
    max_stars: int = 5
    fov_deg: float = 8.0
    focal_length: float = 0.065
    sigma_v: float = DEFAULT_SIGMA_V
    sigma_u: float = DEFAULT_SIGMA_U
    gyro_bias_deg_per_hr: float = 0.1
    omega0: float = 2.0 * math.pi / 100.0
    rate_axes: list = field(default_factory=lambda: [1.0, 1.0, 0.0])
    estimate_bias: bool = False
    prior_var: float = 1e-3
    prior_attitude: str = "gaussian"
    prior_bias_sigma_deg_per_hr: float = 0.2
    components: int = 5
    spread: float = 0.5
    filters: list = field(default_factory=lambda: list(DEFAULT_FILTERS))
    seed: int = 0
    filter_sigma_s_scale: float = 1.0
    filter_sigma_v_scale: float = 1.0
    star_noise_model: str = "isotropic"
    faults: list = field(default_factory=list)

    def __post_init__(self) -> None:
        types = {f.name: f.type for f in dataclasses.fields(self)}
        for key, kind in types.items():
            value = getattr(self, key)
            if kind == "float":
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise ValueError(f"config key '{key}' must be a number, got {value!r}")
                object.__setattr__(self, key, float(value))
            elif kind == "int":
                if isinstance(value, bool) or not isinstance(value, int):
                    raise ValueError(f"config key '{key}' must be an integer, got {value!r}")
            elif kind == "bool":
                off = CONFIG_OPTIONS[key].off if key in CONFIG_OPTIONS else None
                if not isinstance(value, bool) and not (off is not None and value == off):
                    raise ValueError(
                        f"config key '{key}' must be true or false"
                        + (f" (or {off!r})" if off is not None else "")
                        + f", got {value!r}"
                    )
            elif kind == "str":
                if not isinstance(value, str):
                    raise ValueError(f"config key '{key}' must be a string, got {value!r}")
            elif kind == "list":
                if not isinstance(value, list):
                    example = json.dumps([value] if isinstance(value, (str, int, float)) else [])
                    raise ValueError(
                        f"config key '{key}' must be a list (a TOML array), e.g. --set {key}='{example}', got {value!r}"
                    )
        positive = (
            "duration",
            "dt",
            "star_period",
            "sigma_s",
            "fov_deg",
            "focal_length",
            "prior_var",
            "prior_bias_sigma_deg_per_hr",
            "filter_sigma_s_scale",
            "filter_sigma_v_scale",
        )
        for key in positive:
            v = getattr(self, key)
            if not math.isfinite(v) or v <= 0:
                raise ValueError(f"config key '{key}' must be finite and > 0, got {v!r}")
        for key in ("sigma_v", "sigma_u", "omega0"):
            v = getattr(self, key)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"config key '{key}' must be finite and ≥ 0, got {v!r}")
        if not math.isfinite(self.gyro_bias_deg_per_hr):
            raise ValueError(f"config key 'gyro_bias_deg_per_hr' must be finite, got {self.gyro_bias_deg_per_hr!r}")
        for key in ("runs", "max_stars", "components"):
            if getattr(self, key) < 1:
                raise ValueError(f"config key '{key}' must be ≥ 1, got {getattr(self, key)!r}")
        if not 0.0 < self.spread < 1.0:
            raise ValueError(f"config key 'spread' must lie in (0, 1), got {self.spread!r}")
        if self.fov_deg >= 180.0:
            raise ValueError(f"config key 'fov_deg' must be < 180, got {self.fov_deg!r}")
        if self.prior_attitude not in ("gaussian", "uniform"):
            raise ValueError(
                f"config key 'prior_attitude' must be 'gaussian' or 'uniform', got {self.prior_attitude!r}"
            )
        if self.star_noise_model not in ("isotropic", "tangent"):
            raise ValueError(
                f"config key 'star_noise_model' must be 'isotropic' or 'tangent', got {self.star_noise_model!r}"
            )
        from envs.faults import parse_faults

        try:
            parse_faults(self.faults)
        except ValueError as exc:
            raise ValueError(f"config key 'faults': {exc}") from None
        if len(self.rate_axes) != 3 or not all(
            isinstance(v, (int, float)) and math.isfinite(v) for v in self.rate_axes
        ):
            raise ValueError(f"config key 'rate_axes' must be 3 finite numbers, got {self.rate_axes!r}")
        for key, opt in CONFIG_OPTIONS.items():  # each declaring class validates its own option
            for owner in opt.owners:
                try:
                    owner(**{key: opt.to_api(getattr(self, key))})
                except ValueError as exc:
                    off = "" if opt.off is None else f" (or {opt.off!r}: off)"
                    raise ValueError(f"config key '{key}': {exc}{off}") from None
        if (
            not self.filters
            or any(f not in FILTER_NAMES for f in self.filters)
            or len(set(self.filters)) != len(self.filters)
        ):
            raise ValueError(
                f"config key 'filters' must be a non-empty list of distinct names from {FILTER_NAMES}, got {self.filters!r}"
            )
        from ...qp import MAX_COMPONENTS

        if self.components > MAX_COMPONENTS and any(f in ADAPTIVE_FILTERS for f in self.filters):
            raise ValueError(
                f"config key 'components' must be ≤ {MAX_COMPONENTS} with an adaptive filter (the weight QP's limit), "
                f"got {self.components}"
            )
        managed = [f for f in self.filters if filter_spec(f).managed]
        capacity = getattr(self, "capacity", CONFIG_OPTIONS["capacity"].default)
        adaptive_managed = [f for f in managed if f in ADAPTIVE_FILTERS]
        if adaptive_managed and isinstance(capacity, int) and capacity > MAX_COMPONENTS:
            raise ValueError(
                f"config key 'capacity' must be ≤ {MAX_COMPONENTS} for the adaptive managed filter(s) "
                f"{', '.join(adaptive_managed)} (the weight QP's limit; GSF-managed has none), got {capacity}"
            )
        if managed and isinstance(capacity, int) and capacity < self.components:
            raise ValueError(
                f"config key 'capacity' ({capacity}) must be ≥ 'components' ({self.components}) for the managed "
                f"filter(s) {', '.join(managed)}: the mixture's slots hold its components"
            )
        if not 0 <= self.seed <= MAX_SEED - (self.runs - 1):
            raise ValueError(f"config key 'seed' must lie in [0, {MAX_SEED} − (runs − 1)], got {self.seed!r}")
        ratio = self.star_period / self.dt
        if abs(ratio - round(ratio)) > 1e-9 * ratio:
            raise ValueError(f"config key 'star_period' must be a multiple of dt={self.dt}, got {self.star_period!r}")
        if abs(self.duration / self.dt - round(self.duration / self.dt)) > 1e-9 * self.duration / self.dt:
            raise ValueError(f"config key 'duration' must be a multiple of dt={self.dt}, got {self.duration!r}")
        from envs import StarTrackerConfig

        try:  # the simulator's own checks (physical ranges, faults against max_stars), at configuration time
            StarTrackerConfig(**self.env_settings())
        except ValueError as exc:
            raise ValueError(f"config: {exc}") from None

    # ------------------------------------------------------------------
    @property
    def num_steps(self) -> int:
        return int(round(self.duration / self.dt))

    def filter_options(self) -> dict[str, Any]:
        """The filters' options (:data:`~agsf_torch.filters.registry.CONFIG_OPTIONS`) as the filters take
        them (``gate_probability = 0`` → ``None``), for :func:`~agsf_torch.filters.registry.make_filter`."""
        return {key: opt.to_api(getattr(self, key)) for key, opt in CONFIG_OPTIONS.items()}

    def env_settings(self) -> dict[str, Any]:
        """The simulator's settings (:class:`envs.StarTrackerConfig` fields) of this configuration."""
        return {
            "max_steps": self.num_steps,
            "dt": self.dt,
            "star_period": self.star_period,
            "sigma_v": self.sigma_v,
            "sigma_u": self.sigma_u,
            "initial_bias": self.gyro_bias_deg_per_hr * DEG_PER_HOUR,
            "sigma_s": self.sigma_s,
            "fov_deg": self.fov_deg,
            "focal_length": self.focal_length,
            "max_stars": self.max_stars,
            "rate": [self.omega0 * a for a in self.rate_axes],
            "faults": self.faults,
        }

    def warn_unreached_faults(self) -> None:
        """Warn, naming them, of the faults that start at or after the end of the run (``duration``): legal (a
        longer run meets them) but injected into nothing.  Called where the configuration is simulated
        (:func:`~agsf_torch.experiments.config.factories.make_env`), not where it is read: a replay of a recording reads no fault."""
        from envs.faults import parse_faults

        late = [i for i, fault in enumerate(parse_faults(self.faults)) if fault.start >= self.duration]
        if late:
            warnings.warn(
                f"config: fault(s) {late} start at or after the end of the run (duration = {self.duration:g} s): "
                "they never happen",
                stacklevel=3,
            )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def digest(self, *, replay: bool = False) -> str:
        """Short hash of the configuration (identifies an experiment in an output folder).  With ``replay``,
        of the fields a replay of a recording reads: every field but :data:`REPLAY_IGNORED`, so that a key the
        replay does not read cannot make the same replay a different experiment."""
        fields = {k: v for k, v in self.to_dict().items() if not (replay and k in REPLAY_IGNORED)}
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]

    def filter_digest(self, name: str) -> str:
        """Short hash of what filter ``name``'s results depend on in this configuration: every field except
        the label, the list of filters, the options of the other filters and, for a one-component filter,
        ``components`` and ``spread``.  Two configurations with the same filter digest give that filter the
        same simulated data, prior and options, hence the same numbers (a sweep runs it once)."""
        from ...filters.registry import filter_spec

        spec = filter_spec(name)
        skip = {"name", "filters"} | (set(CONFIG_OPTIONS) - spec.option_names)
        if not spec.mixture:
            skip |= {"components", "spread"}
        fields = {k: v for k, v in self.to_dict().items() if k not in skip}
        return hashlib.sha256(json.dumps({"filter": name, **fields}, sort_keys=True).encode()).hexdigest()[:16]

    def replace(self, **changes: Any) -> ExperimentConfig:
        return config_from_mapping({**self.to_dict(), **changes})


def _option_lines() -> str:
    return "\n".join(
        f"        {opt.name}: {opt.help} (default {opt.default!r}; declared by "
        f"{', '.join(c.__name__ for c in opt.owners)})."
        for opt in CONFIG_OPTIONS.values()
    )


#: One Monte Carlo experiment: the fields of the experiment and of the filters' options.
ExperimentConfig = dataclasses.make_dataclass(
    "ExperimentConfig",
    [(o.name, o.kind, field(default=o.default)) for o in CONFIG_OPTIONS.values()],
    bases=(_ExperimentFields,),
    frozen=True,
)
ExperimentConfig.__module__ = __name__  # pickled by reference (Ray workers, multiprocessing)
ExperimentConfig.__doc__ = (
    _ExperimentFields.__doc__.rstrip()
    + "\n\n    The filters' options (declared by the filters and weight updates, one name everywhere):\n\n"
    + _option_lines()
    + "\n"
)


def config_key_help() -> dict[str, str]:
    """Every configuration key with its help line, in field order (from :class:`ExperimentConfig`'s
    docstring, whose filter options come from the classes that declare them): the list the
    command line shows under ``--set``."""
    doc = ExperimentConfig.__doc__ or ""
    entries: dict[str, str] = {}
    key = None
    for line in doc.splitlines():
        match = re.match(r"^        (\w+): (.*)$", line)
        if match:
            key = match.group(1)
            entries[key] = match.group(2).strip()
        elif key is not None and line.startswith("            "):
            entries[key] += " " + line.strip()
        else:
            key = None
    return {f.name: entries.get(f.name, "") for f in dataclasses.fields(ExperimentConfig)}


def config_from_mapping(data: dict[str, Any]) -> ExperimentConfig:
    known = {f.name for f in dataclasses.fields(ExperimentConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"unknown config key(s): {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    return ExperimentConfig(**data)


def preset_names() -> list[str]:
    """Names of the presets shipped as package data."""
    folder = resources.files("agsf_torch.experiments.config") / "presets"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def _resolve(data: dict[str, Any], seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """Merge a TOML table onto the preset it names with ``preset = "..."`` (if any)."""
    data = dict(data)
    base = data.pop("preset", None)
    if base is None:
        return data
    if not isinstance(base, str) or base in seen:
        raise ValueError(f"config key 'preset' must name a preset (no cycles), got {base!r}")
    merged = _resolve(_preset_table(base), seen + (base,))
    merged.update(data)
    return merged


def _preset_table(name: str) -> dict[str, Any]:
    path = resources.files("agsf_torch.experiments.config") / "presets" / f"{name}.toml"
    if not path.is_file():
        raise ValueError(f"unknown preset {name!r}; available: {', '.join(preset_names())}")
    return tomllib.loads(path.read_text())


def load_preset(name: str) -> ExperimentConfig:
    """A preset shipped with the package (``case1``, ``case2``, ``case3``, ``wide_prior``, …)."""
    return config_from_mapping(_resolve(_preset_table(name), (name,)))


def load_config(path: str | Path, overrides: list[str] | None = None) -> ExperimentConfig:
    """Read a TOML configuration (a file, or a preset name) and apply ``key=value`` overrides.

    A file may start from a preset with ``preset = "case1"``.
    """
    p = Path(path)
    if p.suffix == ".toml" or p.exists():
        if not p.exists():
            raise ValueError(f"config file {p} does not exist")
        if not p.is_file():
            raise ValueError(f"config file {p} is not a file")
        try:
            data = tomllib.loads(p.read_text(encoding="utf-8"))
        except UnicodeDecodeError as exc:
            raise ValueError(f"config file {p} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"config file {p} is not valid TOML: {exc}") from None
        cfg = _resolve(data)
    else:
        cfg = load_preset(str(path)).to_dict()
    for item in overrides or []:
        key, value = parse_override(item)
        cfg[key] = value
    return config_from_mapping(cfg)


def parse_override(item: str) -> tuple[str, Any]:
    """``"key=value"`` with the value read as a TOML value (bare words as strings).

    Raises:
        ValueError: no ``=``, a key that is not a configuration field (the message lists the known keys), or a
            value that begins as an array, a table or a quoted string and is not valid TOML.
    """
    if "=" not in item:
        raise ValueError(f"override {item!r} must look like key=value")
    key, text = item.split("=", 1)
    key = key.strip()
    known = {f.name for f in dataclasses.fields(ExperimentConfig)}
    if key not in known:
        raise ValueError(f"unknown config key '{key}' in override {item!r} (known: {', '.join(sorted(known))})")
    text = text.strip()
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError as exc:
        if text[:1] in ("[", "{", '"', "'"):  # meant as an array, a table or a quoted string: not a bare word
            raise ValueError(
                f"the value of '{key}' in override {item!r} is not valid TOML ({exc}); strings inside an array or a "
                "table are quoted, and the shell strips one level of quotes (e.g. --set 'filters=[\"GSF\"]')"
            ) from None
        value = text
    return key, value
