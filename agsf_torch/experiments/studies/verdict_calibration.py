"""How often ``agsf diagnose``'s verdicts are right: false alarms on a correctly configured filter and detections
of a mis-configured one, counted over many simulated data sets.

A *data set* is ``trajectories`` trajectories of the configuration's duration: what one ``agsf diagnose`` judges.
``datasets × trajectories`` trajectories are simulated once (one batched simulation, recorded,
:func:`~agsf_torch.experiments.run.recorded.record_environment`) and every filter configuration replays that same recording through the
Monte Carlo runner (:func:`~agsf_torch.experiments.run.runner.run_monte_carlo`, the one filter loop), so the verdicts of the configurations
are paired data set by data set.  A configuration is the base one with the filters assuming ``s × σ`` for one
``parameter`` (``σ_s``: ``filter_sigma_s_scale = s``; ``σ_v``: ``filter_sigma_v_scale = s``) while the simulation
stays at the truth; ``s = 1`` is the correctly configured filter, run once and shared by every parameter.  Each data
set is judged by :func:`~agsf_torch.consistency.consistency_check_arrays`, the checks ``agsf diagnose`` prints
(:func:`~agsf_torch.consistency.consistency_checks`), for all data sets at once.

The rate of a check is ``failures / judged`` over the data sets (``judged``: those for which ``agsf diagnose`` makes
the check), with its Clopper–Pearson (exact binomial) 95 % interval: at ``s = 1`` the false-alarm rate, elsewhere
the detection rate (the power).  ``"any"`` is ``agsf diagnose``'s overall verdict: a data set fails if any check
fails (or none can be made).

What a consistent filter's rates should be, from the bands of :mod:`agsf_torch.consistency`.  The bands are
simultaneous (Bonferroni): with the truth the 3 checks are each two-sided at level ``α_c = α/3``
(:attr:`VerdictRates.level`; ``α = 1 − confidence = 5 %``, so ``α_c ≈ 1.67 %``):

* **NEES**: the run- and time-averaged NEES against the band of the average of ``B`` independent χ²(n) values.
  That band is exact for a single time step; averaging over the steps of a run shrinks the spread (errors
  decorrelate over time), so the level is *at most about* ``α_c`` — ``α_c`` only if the errors were perfectly
  correlated over the run — and the check is conservative (also less powerful) the longer the run.
* **NIS**: the pooled ``Σ NIS / Σ E[NIS]`` against the band of a χ²(Σk)/Σk: exact (level ``α_c``) for white
  Gaussian innovations with the expected number of degrees of freedom, the linear-Gaussian case.
* **whiteness**: the runs' lag-1 autocorrelations ``r_b = Σ z_k z_{k−1} / Σ z_k²`` of the standardised NIS
  ``z`` about its known mean 0, averaged with weights ``p_b`` (the run's pairs), against ``±Φ⁻¹(1 − α_c/2)/√P``
  (``2.39/√P``), ``P = Σ p_b``.  For white innovations the numerator has mean 0 and variance ``p_b``
  (``E[z²] = 1``), so ``r_b`` has mean 0 and a variance that tends to ``1/p_b`` as the run's frames ``n_b`` grow;
  the level tends to ``α_c`` with them.  For runs of a few tens of frames it is lower, and more runs per data set
  do not raise it: each ``r_b`` is divided by its own run's ``Σ z_k²`` (``|r_b| ≤ 1``, lighter tails than the
  normal) and its variance is below ``1/p_b`` (about ``p_b/n_b²`` to first order), so the check is conservative —
  for white ``χ²(10)`` NIS about 0.8 % at ``α_c = 1.67 %`` with runs of 20 or 30 frames, one run or 48 per data
  set, and under 0.1 % for one run of 10.  :attr:`VerdictRates.whiteness_level` is the level for the run's own
  update pattern (white ``χ²(⅔d)`` NIS drawn and judged by the same band).  (About each run's own mean instead,
  ``r_b`` would have mean ``−1/n_b`` (Moran 1948): a bias that does not shrink with more runs while the band
  does.)

The overall verdict (``"any"``) controls the family-wise false-alarm rate: a consistent filter fails some check
with probability at most ``Σ α_c = α = 5 %`` (:attr:`VerdictRates.familywise_level`), however the checks depend on
each other; for independent checks at level ``α_c`` it would be ``1 − (1 − α/3)³ ≈ 4.92 %``.  The NEES and NIS
statistics of a data set are positively correlated, and the NEES check (and the whiteness check for few frames) is
conservative, so the measured rate is lower.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...consistency import check_level, consistency_check_arrays
from ..config.factories import filter_model, loop_options, make_env, make_filters
from ..config.loader import ExperimentConfig
from ..report.statistics import clopper_pearson
from ..run.recorded import RecordingEnv, record_environment
from ..run.resources import check_memory
from ..run.runner import run_monte_carlo

__all__ = ["PARAMETERS", "CHECKS", "LEVEL_SAMPLES", "VerdictRates", "diagnose_verdict_rates"]

#: The parameters that can be mis-scaled → the configuration key that scales what the filters assume.
PARAMETERS = {"sigma_s": "filter_sigma_s_scale", "sigma_v": "filter_sigma_v_scale"}
#: The checks ``agsf diagnose`` makes on a simulation (with the truth), then its overall verdict.
CHECKS = ("nees", "nis", "whiteness", "any")


@dataclass(frozen=True)
class VerdictRates:
    """The verdicts of ``agsf diagnose`` over ``D`` data sets (numpy arrays; axes filter ``F``, parameter ``P``,
    scale ``S``, check ``C`` = :data:`CHECKS`, data set ``D``).

    Attributes:
        filters: ``F`` filter names; parameters: ``P`` names of :data:`PARAMETERS`; checks: :data:`CHECKS`.
        scales: ``[S]`` the mis-scalings ``s`` (the filters assume ``s × σ``), 1 included (first if it was not
            asked for); at ``s = 1`` every parameter's entries are the one correctly configured run.
        datasets: ``D``; trajectories: trajectories per data set; seed: the simulation's seed.
        failed: ``[F, P, S, C, D]`` bool, data set ``d`` fails check ``c`` (``"any"``: the overall verdict fails).
        judged: ``[F, P, S, C, D]`` bool, the check is made for data set ``d`` (``"any"``: always).
        values: ``[F, P, S, C, D]`` the check's statistic (NEES, NIS / expected, lag-1 autocorrelation; NaN where
            not made and for ``"any"``).
        failures, count: ``[F, P, S, C]`` data sets failing / judged.
        rate: ``[F, P, S, C]`` ``failures / count`` (NaN if ``count`` is 0): the false-alarm rate at ``s = 1``,
            the detection rate elsewhere.
        interval: ``[F, P, S, C, 2]`` its Clopper–Pearson 95 % interval.
        level: ``α_c = α/3``, each check's nominal false-alarm rate (``1 −`` each band's confidence,
            :attr:`~agsf_torch.consistency.CheckArrays.level`): the family's ``α`` split over the 3 checks.
        familywise_level: ``α = 3·α_c``, the bound (Bonferroni) on the overall verdict's false-alarm rate.
        whiteness_level: ``[F]`` the whiteness check's false-alarm rate for white innovations with the correctly
            configured run's update pattern (the module docstring): the fraction of :data:`LEVEL_SAMPLES`
            synthetic data sets of white ``χ²(⅔d)`` NIS that fail it.
    """

    filters: tuple[str, ...]
    parameters: tuple[str, ...]
    scales: np.ndarray
    checks: tuple[str, ...]
    datasets: int
    trajectories: int
    seed: int
    failed: np.ndarray
    judged: np.ndarray
    values: np.ndarray
    failures: np.ndarray
    count: np.ndarray
    rate: np.ndarray
    interval: np.ndarray
    level: float
    familywise_level: float
    whiteness_level: np.ndarray

    @property
    def false_alarm(self) -> np.ndarray:
        """``[F, C]`` the false-alarm rate of each check (the rate at ``s = 1``)."""
        return self.rate[:, 0, self._truth]

    @property
    def false_alarm_interval(self) -> np.ndarray:
        """``[F, C, 2]`` its Clopper–Pearson 95 % interval."""
        return self.interval[:, 0, self._truth]

    @property
    def _truth(self) -> int:
        return int(np.flatnonzero(self.scales == 1.0)[0])

    def rows(self) -> list[dict[str, Any]]:
        """One flat record per filter, parameter, scale and check, for a results table: ``filter``,
        ``parameter``, ``scale``, ``check``, ``kind`` (``"false alarm"`` at ``s = 1``, else ``"detection"``),
        ``failures``, ``judged``, ``rate``, ``low``, ``high``."""
        out = []
        for f, p, s, c in np.ndindex(self.rate.shape):
            out.append(
                {
                    "filter": self.filters[f],
                    "parameter": self.parameters[p],
                    "scale": float(self.scales[s]),
                    "check": self.checks[c],
                    "kind": "false alarm" if self.scales[s] == 1.0 else "detection",
                    "failures": int(self.failures[f, p, s, c]),
                    "judged": int(self.count[f, p, s, c]),
                    "rate": float(self.rate[f, p, s, c]),
                    "low": float(self.interval[f, p, s, c, 0]),
                    "high": float(self.interval[f, p, s, c, 1]),
                }
            )
        return out


def diagnose_verdict_rates(
    cfg: ExperimentConfig,
    *,
    datasets: int = 200,
    trajectories: int | None = None,
    scales: tuple[float, ...] = (1.0, 1.25, 1.5, 2.0, 3.0),
    parameters: tuple[str, ...] = ("sigma_s", "sigma_v"),
    seed: int | None = None,
    progress: bool = False,
    force: bool = False,
) -> VerdictRates:
    """The false-alarm and detection rates of ``agsf diagnose``'s checks on ``cfg`` (the module docstring).

    Simulates ``datasets × trajectories`` trajectories of ``cfg`` once, then runs ``cfg``'s filters on them
    correctly configured and, for each parameter and scale ``s ≠ 1``, assuming ``s ×`` its true value; judges each
    data set as ``agsf diagnose`` does.  One run of the filters per configuration (``1 + P·(S − 1)`` runs, each of
    the whole batch).

    Args:
        cfg: the base configuration (its ``runs`` is replaced by ``datasets × trajectories``); it must be correctly
            configured: ``filter_sigma_s_scale = filter_sigma_v_scale = 1``.
        datasets: ``D ≥ 1`` data sets.
        trajectories: trajectories per data set (default ``cfg.runs``: one ``agsf diagnose`` of ``cfg``).
        scales: the mis-scalings, finite and > 0, distinct; 1 (the truth) is always run.
        parameters: which of :data:`PARAMETERS` to mis-scale, one at a time.
        seed: the simulation's seed (default ``cfg.seed``): trajectory ``i`` is seeded ``seed + i``.
        progress: show progress bars.
        force: run even if the memory estimate (:func:`~agsf_torch.experiments.run.resources.check_memory`) exceeds what is available.

    Returns:
        :class:`VerdictRates`.

    Raises:
        ValueError: empty or invalid ``scales`` or ``parameters``, ``datasets`` or ``trajectories`` not an integer
            ≥ 1, a mis-configured ``cfg``, or a batch the configuration refuses (e.g. ``seed + D·T − 1`` too large)
            — before anything runs.
    """
    scales_ = _check_scales(scales)
    parameters = _check_parameters(parameters)
    datasets = _check_count("datasets", datasets)
    trajectories = _check_count("trajectories", cfg.runs if trajectories is None else trajectories)
    for key in PARAMETERS.values():
        if getattr(cfg, key) != 1.0:
            raise ValueError(
                f"the base configuration must be correctly configured ({key} = 1, the truth), got {getattr(cfg, key)!r}"
            )
    if 1.0 not in scales_:
        scales_ = (1.0, *scales_)
    truth = cfg.replace(runs=datasets * trajectories, seed=cfg.seed if seed is None else seed)
    configs = {(p, s): truth.replace(**{PARAMETERS[p]: s}) for p in parameters for s in scales_ if s != 1.0}
    check_memory(truth, force=force)

    recording = record_environment(make_env(truth), truth.num_steps, seed=truth.seed, progress=progress)
    judged_truth = _judge(truth, recording, datasets, progress, "s = 1")
    F, P, S, C = len(cfg.filters), len(parameters), len(scales_), len(CHECKS)
    failed = np.zeros((F, P, S, C, datasets), bool)
    judged = np.zeros((F, P, S, C, datasets), bool)
    values = np.full((F, P, S, C, datasets), np.nan)
    for i, p in enumerate(parameters):
        for j, s in enumerate(scales_):
            arrays = judged_truth if s == 1.0 else _judge(configs[p, s], recording, datasets, progress, f"{p} × {s:g}")
            failed[:, i, j], judged[:, i, j], values[:, i, j] = arrays[:3]
    failures, count = failed.sum(-1), judged.sum(-1)
    with np.errstate(invalid="ignore"):
        rate = failures / count
    level = check_level(_CONFIDENCE, C - 1)  # the checks with the truth: C − 1 (all but "any")
    return VerdictRates(
        filters=tuple(cfg.filters),
        parameters=parameters,
        scales=np.array(scales_),
        checks=CHECKS,
        datasets=datasets,
        trajectories=trajectories,
        seed=truth.seed,
        failed=failed,
        judged=judged,
        values=values,
        failures=failures,
        count=count,
        rate=rate,
        interval=clopper_pearson(failures, count),
        level=level,
        familywise_level=(C - 1) * level,
        whiteness_level=np.array([_whiteness_level(nis_dof, truth.seed, level) for nis_dof in judged_truth[3]]),
    )


#: The family's confidence of the consistency checks (``consistency_checks``' default, what ``agsf diagnose``
#: uses: a consistent filter passes every check with at least this probability) and that of the rates' intervals.
_CONFIDENCE = 0.95


def _judge(cfg: ExperimentConfig, recording, datasets: int, progress: bool, label: str) -> tuple[np.ndarray, ...]:
    """Run ``cfg``'s filters on ``recording`` as ``agsf run`` / ``agsf diagnose`` do and judge each data set.

    Returns:
        ``(failed [F, C, D], judged [F, C, D], values [F, C, D], nis_dof [F, D, T, B])``, the last the valid NIS
        entries of each update.
    """
    res = run_monte_carlo(
        RecordingEnv(recording), make_filters(cfg), progress=progress, label=label, **loop_options(cfg)
    )
    n = filter_model(cfg).state_dim

    def by_dataset(a: np.ndarray) -> np.ndarray:  # [D·B, T] → [D, T, B], data set d = trajectories dB … dB + B − 1
        return a.reshape(datasets, -1, a.shape[-1]).swapaxes(-1, -2)

    out = []
    for name in cfg.filters:
        tr = res.traces[name]
        nis_dof = by_dataset(tr.nis_dof)
        checks = consistency_check_arrays(
            nees=by_dataset(tr.nees), state_dim=n, nis=by_dataset(tr.nis), nis_dof=nis_dof, confidence=_CONFIDENCE
        )
        made = np.stack([c.made for c in checks.values()])  # [3, D]
        passed = np.stack([c.passed for c in checks.values()])
        fail_any = ~(passed.all(0, where=made) & made.any(0))  # agsf diagnose: nothing judged is not a pass
        failed = np.concatenate((made & ~passed, fail_any[None]))
        judged = np.concatenate((made, np.ones((1, datasets), bool)))
        values = np.concatenate(
            (np.stack([np.where(c.made, c.value, np.nan) for c in checks.values()]), np.full((1, datasets), np.nan))
        )
        out.append((failed, judged, values, nis_dof))
    return tuple(np.stack(a) for a in zip(*out, strict=True))


def _whiteness_level(nis_dof: np.ndarray, seed: int, level: float) -> float:
    """The whiteness check's false-alarm rate for white innovations with the update pattern ``nis_dof [D, T, B]``:
    the fraction of :data:`LEVEL_SAMPLES` synthetic data sets (the pattern's ``D`` repeated) whose NIS, drawn
    independently from ``χ²(⅔·d)``, fail the check with its band at nominal level ``level`` (the one the check
    has in the family of the 3 checks with the truth); NaN if no data set has a pair of updates in a run."""
    rows = (nis_dof > 0).any((0, 2))  # the star frames: the check ignores the other steps
    dof = nis_dof[:, rows]
    D = dof.shape[0]
    gen = np.random.default_rng(seed)
    per_chunk = max(1, min(LEVEL_SAMPLES, _LEVEL_CHUNK // max(dof[0].size, 1)) // D)  # repeats of the D data sets
    failed, made = 0, 0
    for _ in range(-(-LEVEL_SAMPLES // (per_chunk * D))):
        d = np.broadcast_to(dof, (per_chunk, *dof.shape))
        nis = np.where(d > 0, gen.chisquare(np.where(d > 0, 2.0 / 3.0 * d, 1.0)), np.nan)
        check = consistency_check_arrays(
            nees=None, state_dim=1, nis=nis, nis_dof=d, confidence=1.0 - level, familywise=False
        )
        white = check["whiteness"]
        failed += int((white.made & ~white.passed).sum())
        made += int(white.made.sum())
    return failed / made if made else math.nan


#: Synthetic data sets behind :attr:`VerdictRates.whiteness_level` (its standard error is at most ``0.5/√`` this).
LEVEL_SAMPLES = 20000
#: NIS entries drawn at once for it (bounds its memory).
_LEVEL_CHUNK = 2_000_000


def _check_scales(scales) -> tuple[float, ...]:
    if isinstance(scales, (str, bytes)) or not hasattr(scales, "__iter__"):
        raise ValueError(f"scales must be a sequence of numbers, got {scales!r}")
    values = tuple(scales)
    if not values:
        raise ValueError("scales is empty: give the mis-scalings to measure, e.g. (1.0, 2.0, 3.0)")
    for s in values:
        if isinstance(s, bool) or not isinstance(s, (int, float, np.integer, np.floating)):
            raise ValueError(f"scales must be numbers, got {s!r} in {values!r}")
        if not (math.isfinite(s) and s > 0):
            raise ValueError(f"scales must be finite and > 0 (the filters assume s × the true σ), got {s!r}")
    values = tuple(float(s) for s in values)
    if len(set(values)) != len(values):
        raise ValueError(f"scales must be distinct, got {values!r}")
    return values


def _check_parameters(parameters) -> tuple[str, ...]:
    values = (parameters,) if isinstance(parameters, str) else tuple(parameters)
    if not values:
        raise ValueError(f"parameters is empty: name one or more of {sorted(PARAMETERS)}")
    unknown = [p for p in values if p not in PARAMETERS]
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {unknown!r}: the parameters that can be mis-scaled are {sorted(PARAMETERS)}"
        )
    if len(set(values)) != len(values):
        raise ValueError(f"parameters must be distinct, got {values!r}")
    return values


def _check_count(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an integer ≥ 1, got {value!r}")
    return int(value)
