"""One wide Gaussian that must become several: mixture management on the sine SDE, against the exact density.

The scalar SDE of method.md §5, ``dx = sin x dt + dβ`` (``q = 1``), started from **one** Gaussian component: by
default the benchmark prior ``0.1 N(−0.2, 1) + 0.9 N(0.2, 1)`` (:func:`.sine_benchmark.sine_prior`) collapsed to
the single Gaussian of the same mean and variance, ``N(0.16, 1.0144)``.  The mean sits just right of the unstable
equilibrium 0, so the exact density folds towards the stable points ``±π`` and becomes bimodal; a single Gaussian
(the unmanaged one-component GSF, i.e. the EKF) follows its mean to ``+π`` and loses the left mode.  A managed
filter (:class:`~agsf_torch.filters.management.MixtureManagement`) splits the component where its entropy test
fires, before each propagation.

Reference: the Crank–Nicolson FPKE solution on the benchmark's grid (4001 points on [−20, 20], solver step
0.002 s), started from the same prior.  Filters, all advanced by one ``predict`` per step of ``DT = 0.1`` s
(one call advances all components; the only Python loop is over time):

* ``gsf``: :class:`GaussianSumFilter`, one component, unmanaged (the EKF's density);
* ``gsf_managed``, ``agsf_managed`` (the paper's weight update, ``"penalty"``), ``agsf_galerkin_managed``
  (``"galerkin"``): the same one-component prior, with management (default: capacity 16, the other options
  the defaults);
* with ``benchmark_prior=True``, as a reference point, the unmanaged ``gsf_benchmark``, ``agsf_benchmark`` and
  ``agsf_galerkin_benchmark`` from the benchmark's two-component prior, scored against the grid density started
  from that prior (same mean and variance as the one-component prior, not the same density).

Run it as ``python -m agsf_torch.experiments.studies.split_density [densities.png [history.png]]`` (prints the
tables; :func:`split_density_figure`, :func:`split_density_history_figure`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...density.grid import FokkerPlanckGrid, integrated_squared_error
from ...filters.adaptive import AdaptiveGaussianSumFilter
from ...filters.gaussian_sum import GaussianSumFilter
from ...filters.management import MixtureManagement, entropy_nonlinearity, pad_mixture
from ...filters.weight_updates import GalerkinWeightUpdate, PenaltyWeightUpdate
from ...mixture import GaussianMixture
from ...models.base import ContinuousModel
from ...models.benchmarks import SineDriftModel
from .sine_benchmark import DT, GRID, sine_prior

__all__ = [
    "one_component_prior",
    "predict_management_pass",
    "run_split_density",
    "split_density_tables",
    "split_density_figure",
    "split_density_history_figure",
    "FILTER_LABELS",
]

#: Display names of the filters of :func:`run_split_density`.
FILTER_LABELS = {
    "gsf": "GSF, 1 component (EKF)",
    "gsf_managed": "GSF-managed",
    "agsf_managed": "AGSF-managed",
    "agsf_galerkin_managed": "AGSF-galerkin-managed",
    "gsf_benchmark": "GSF, benchmark prior (2)",
    "agsf_benchmark": "AGSF, benchmark prior (2)",
    "agsf_galerkin_benchmark": "AGSF-galerkin, benchmark prior (2)",
}


def one_component_prior(mean: float | None = None, variance: float | None = None) -> GaussianMixture:
    """``N(mean, variance)`` as a one-component mixture (scalar state); by default the mean and variance of
    :func:`.sine_benchmark.sine_prior` (``0.16`` and ``1.0144``)."""
    m, P = sine_prior().moments()
    mean = float(m[0]) if mean is None else float(mean)
    variance = float(P[0, 0]) if variance is None else float(variance)
    if not (math.isfinite(mean) and math.isfinite(variance) and variance > 0):
        raise ValueError(f"the prior needs a finite mean and a finite variance > 0, got {mean!r}, {variance!r}")
    f64 = torch.float64
    return GaussianMixture(
        weights=torch.ones(1, dtype=f64),
        means=torch.tensor([[mean]], dtype=f64),
        covs=torch.tensor([[[variance]]], dtype=f64),
    )


def predict_management_pass(
    model: ContinuousModel, management: MixtureManagement, mixture: GaussianMixture, u: torch.Tensor | None = None
) -> GaussianMixture:
    """The management pass a managed Gaussian-sum filter runs before a propagation, from the public functions:
    ``mixture`` padded to ``capacity`` slots, pruned, merged and split where the entropy test
    (:func:`~agsf_torch.filters.management.entropy_nonlinearity`) exceeds ``split_entropy_rate``.

    Returns:
        The managed mixture (``capacity`` slots), before any propagation.
    """
    padded = pad_mixture(mixture, management.capacity)
    score = axis = None
    if management.split_entropy_rate > 0:
        score, axis = entropy_nonlinearity(model, padded.means, padded.covs, u)
    return management.apply(padded, model, score, axis, management.split_entropy_rate).mixture


def _build_filters(
    management: MixtureManagement, substeps: int, quadrature: int, benchmark_prior: bool
) -> dict[str, tuple[GaussianSumFilter, str]]:
    def penalty() -> PenaltyWeightUpdate:
        return PenaltyWeightUpdate(quadrature=quadrature)

    def galerkin() -> GalerkinWeightUpdate:
        return GalerkinWeightUpdate(quadrature=quadrature)

    m = SineDriftModel
    filters: dict[str, tuple[GaussianSumFilter, str]] = {
        "gsf": (GaussianSumFilter(m(), substeps=substeps), "one_component"),
        "gsf_managed": (GaussianSumFilter(m(), substeps=substeps, management=management), "one_component"),
        "agsf_managed": (
            AdaptiveGaussianSumFilter(m(), substeps=substeps, management=management, weight_update=penalty()),
            "one_component",
        ),
        "agsf_galerkin_managed": (
            AdaptiveGaussianSumFilter(m(), substeps=substeps, management=management, weight_update=galerkin()),
            "one_component",
        ),
    }
    if benchmark_prior:
        filters["gsf_benchmark"] = (GaussianSumFilter(m(), substeps=substeps), "benchmark")
        filters["agsf_benchmark"] = (
            AdaptiveGaussianSumFilter(m(), substeps=substeps, weight_update=penalty()),
            "benchmark",
        )
        filters["agsf_galerkin_benchmark"] = (
            AdaptiveGaussianSumFilter(m(), substeps=substeps, weight_update=galerkin()),
            "benchmark",
        )
    return filters


def _p_log_p(p: np.ndarray) -> np.ndarray:
    """``p log p`` on the grid (``0 log 0 = 0``; the grid solution's negative rounding counted as 0)."""
    p = np.clip(p, 0.0, None)
    return np.where(p > 0, p * np.log(np.where(p > 0, p, 1.0)), 0.0)


def run_split_density(
    *,
    horizon: float = 8.0,
    report_times: Sequence[float] = (0.5, 1.0, 2.0, 4.0, 8.0),
    mean: float | None = None,
    variance: float | None = None,
    management: MixtureManagement | None = None,
    substeps: int = 10,
    quadrature: int = 40,
    benchmark_prior: bool = True,
) -> dict[str, Any]:
    """Propagate one wide Gaussian on the sine SDE with and without mixture management; score every step
    against the grid FPKE density.

    Steps of ``DT = 0.1`` s up to ``horizon`` (a multiple of ``DT``); no measurements.  At every step ``k``
    (time ``t_k = (k + 1)·DT``), for every filter with density ``q`` and the grid density ``p`` of its prior:

    * ``ise``: ``∫ (q − p)² dx`` (1/length; trapezoid on the grid);
    * ``log_score``: ``∫ p log q dx`` (nats): the expected log-density, under the filter's mixture, of a draw
      from the exact density, computed on the grid (no sampling); higher is better;
    * ``kl``: ``∫ p log p dx − ∫ p log q dx`` (nats, ``≥ 0`` up to the grid's quadrature): the Kullback–Leibler
      divergence of the filter's density from the exact one;
    * ``kl_tail``: the part of ``kl`` from ``|x| > 2π`` (beyond the wells at ``±π``: the exact density leaks
      towards the next wells ``±3π``);
    * ``mass_left``: ``∫_{x<0} q dx``, ``mass_tail``: ``∫_{|x|>2π} q dx`` (the exact ones:
      ``reference[...]["mass_left"]``, ``["mass_tail"]``);
    * ``active``: components with nonzero weight after the step; ``splits``, ``merges``, ``prunes``: the
      management pass before the step's propagation (zeros for unmanaged filters).

    Args:
        horizon: final time (s), a positive multiple of ``DT``.
        report_times: times (s, multiples of ``DT`` in ``(0, horizon]``) at which the densities on the grid
            are kept.
        mean, variance: of the one-component prior (default: :func:`one_component_prior`'s).
        management: of the managed filters (default ``MixtureManagement(capacity=16)``).
        substeps: RK4 steps per ``DT`` of every filter.
        quadrature: Gauss–Hermite points of the weight updates (``PenaltyWeightUpdate(quadrature=...)`` and
            ``GalerkinWeightUpdate(quadrature=...)``), as the benchmark's tests.
        benchmark_prior: also run the unmanaged filters from :func:`.sine_benchmark.sine_prior`.

    Returns:
        A dict:

        * ``"time"``: ``[S]`` step end times (s); ``"grid"``: ``[G]`` (``G = 4001``); ``"report_times"``: ``[R]``;
          ``"report_index"``: ``[R]`` step indices of ``report_times``;
        * ``"prior"``: ``{"mean", "variance"}`` of the one-component prior; ``"management"``: its options;
        * ``"reference"``: prior name (``"one_component"``, ``"benchmark"``) → ``{"density": [R, G]``,
          ``"neg_entropy": [S]`` (``∫ p log p``, nats), ``"mass_left": [S]``, ``"mass_tail": [S]}``;
        * ``"filters"``: name (keys of :data:`FILTER_LABELS`) → ``{"prior"`` (reference name), ``"ise"``,
          ``"log_score"``, ``"kl"``, ``"kl_tail"``, ``"mass_left"``, ``"mass_tail"`` (each ``[S]`` float64),
          ``"active"``, ``"splits"``, ``"merges"``, ``"prunes"`` (each ``[S]`` int64), ``"density": [R, G]}``;
        * ``"first_split"``: for ``gsf_managed``, the first step whose management pass split:
          ``{"step"`` (int), ``"before"`` (the mixture entering that step), ``"after"``
          (:func:`predict_management_pass` of it: the split mixture before propagation), ``"propagated"`` (the
          filter's output of that step)``}``, or ``None`` if it never split.
    """
    steps = int(round(horizon / DT))
    if steps < 1 or not math.isclose(steps * DT, horizon, rel_tol=1e-9):
        raise ValueError(f"horizon must be a positive multiple of {DT} s, got {horizon!r}")
    report_index = []
    for t in report_times:
        k = int(round(t / DT)) - 1
        if not (0 <= k < steps and math.isclose((k + 1) * DT, t, rel_tol=1e-9)):
            raise ValueError(f"report time {t!r} is not a multiple of {DT} s in (0, {horizon}]")
        report_index.append(k)
    management = MixtureManagement(capacity=16) if management is None else management
    grid = GRID
    xg = torch.tensor(grid, dtype=torch.float64)[:, None]
    priors = {"one_component": one_component_prior(mean, variance)}
    if benchmark_prior:
        priors["benchmark"] = sine_prior()
    solver = FokkerPlanckGrid(grid, np.sin, lambda x: 0.5 * np.ones_like(x), dt=0.002)
    left, tail = grid < 0, np.abs(grid) > 2 * math.pi

    ref_p = {name: torch.exp(prior.log_prob(xg)).numpy() for name, prior in priors.items()}
    reference = {
        name: {"density": [], **{key: np.empty(steps) for key in ("neg_entropy", "mass_left", "mass_tail")}}
        for name in priors
    }
    filters = _build_filters(management, substeps, quadrature, benchmark_prior)
    records = {
        name: {
            "prior": prior_name,
            **{key: np.empty(steps) for key in ("ise", "log_score", "kl", "kl_tail", "mass_left", "mass_tail")},
            **{key: np.zeros(steps, dtype=np.int64) for key in ("active", "splits", "merges", "prunes")},
            "density": [],
        }
        for name, (_, prior_name) in filters.items()
    }
    beliefs = {name: priors[prior_name] for name, (_, prior_name) in filters.items()}
    for filt, _ in filters.values():
        filt.reset()
    first_split = None
    ref_plogp = {}
    for k in range(steps):
        for name, p in ref_p.items():
            p = solver.step(p, DT)
            ref_p[name], ref_plogp[name] = p, _p_log_p(p)
            reference[name]["neg_entropy"][k] = float(np.trapezoid(ref_plogp[name], grid))
            reference[name]["mass_left"][k] = float(np.trapezoid(np.where(left, p, 0.0), grid))
            reference[name]["mass_tail"][k] = float(np.trapezoid(np.where(tail, p, 0.0), grid))
            if k in report_index:
                reference[name]["density"].append(p.copy())
        for name, (filt, prior_name) in filters.items():
            before = beliefs[name]
            mix = filt.predict(before, None, DT)
            beliefs[name] = mix
            rec, p = records[name], ref_p[prior_name]
            log_q = mix.log_prob(xg).numpy()
            q = np.exp(log_q)
            rec["ise"][k] = integrated_squared_error(q, p, grid)
            p_log_q = np.clip(p, 0.0, None) * log_q
            rec["log_score"][k] = float(np.trapezoid(p_log_q, grid))
            rec["kl"][k] = reference[prior_name]["neg_entropy"][k] - rec["log_score"][k]
            rec["kl_tail"][k] = float(np.trapezoid(np.where(tail, ref_plogp[prior_name] - p_log_q, 0.0), grid))
            rec["mass_left"][k] = float(np.trapezoid(np.where(left, q, 0.0), grid))
            rec["mass_tail"][k] = float(np.trapezoid(np.where(tail, q, 0.0), grid))
            rec["active"][k] = int(torch.isfinite(mix.log_weights).sum())
            for key in ("splits", "merges", "prunes"):
                if key in filt.diagnostics:
                    rec[key][k] = int(filt.diagnostics[key])
            if k in report_index:
                rec["density"].append(q)
            if name == "gsf_managed" and first_split is None and rec["splits"][k] > 0:
                after = predict_management_pass(filt.model, management, before)
                first_split = {"step": k, "before": before, "after": after, "propagated": mix}
    for rec in (*records.values(), *reference.values()):
        rec["density"] = np.stack(rec["density"])
    m0, P0 = priors["one_component"].moments()
    return {
        "time": DT * np.arange(1, steps + 1),
        "grid": grid,
        "report_times": np.asarray(report_times, dtype=np.float64),
        "report_index": np.asarray(report_index, dtype=np.int64),
        "prior": {"mean": float(m0[0]), "variance": float(P0[0, 0])},
        "management": management.as_dict(),
        "reference": reference,
        "filters": records,
        "first_split": first_split,
    }


def split_density_tables(result: dict[str, Any]) -> str:
    """Markdown tables of :func:`run_split_density`'s result at its report times: ISE, log score (with the exact
    density's ``∫ p log p`` as the best attainable), KL, mass left of 0, and active components (at the report
    times, and the range over the run)."""
    idx = result["report_index"]
    head = " | ".join(f"t = {t:g} s" for t in result["report_times"])
    sep = " | ".join("---:" for _ in idx)
    out = []

    def table(title: str, key: str, fmt: str, extra_rows: Sequence[tuple[str, np.ndarray]] = ()) -> None:
        out.append(f"**{title}**\n\n| filter | {head} |\n| --- | {sep} |")
        for label, values in extra_rows:
            out.append(f"| {label} | " + " | ".join(format(values[i], fmt) for i in idx) + " |")
        for name, rec in result["filters"].items():
            out.append(f"| {FILTER_LABELS[name]} | " + " | ".join(format(rec[key][i], fmt) for i in idx) + " |")
        out.append("")

    ref = result["reference"]
    table("Integrated squared error ∫(q − p)² dx", "ise", ".2e")
    rows = [("exact, ∫ p log p (one-component prior)", ref["one_component"]["neg_entropy"])]
    if "benchmark" in ref:
        rows.append(("exact, ∫ p log p (benchmark prior)", ref["benchmark"]["neg_entropy"]))
    table("Log score ∫ p log q dx (nats; higher is better)", "log_score", ".4f", rows)
    table("KL divergence ∫ p log(p/q) dx (nats)", "kl", ".2e")
    table("Part of the KL divergence from |x| > 2π (nats)", "kl_tail", ".2e")
    rows = [("exact (one-component prior)", ref["one_component"]["mass_left"])]
    if "benchmark" in ref:
        rows.append(("exact (benchmark prior)", ref["benchmark"]["mass_left"]))
    table("Mass left of 0", "mass_left", ".4f", rows)
    rows = [("exact (one-component prior)", ref["one_component"]["mass_tail"])]
    if "benchmark" in ref:
        rows.append(("exact (benchmark prior)", ref["benchmark"]["mass_tail"]))
    table("Mass beyond |x| > 2π", "mass_tail", ".2e", rows)
    out.append(f"**Active components**\n\n| filter | {head} | min–max over the run |\n| --- | {sep} | ---: |")
    for name, rec in result["filters"].items():
        cells = " | ".join(str(int(rec["active"][i])) for i in idx)
        out.append(f"| {FILTER_LABELS[name]} | {cells} | {rec['active'].min()}–{rec['active'].max()} |")
    return "\n".join(out) + "\n"


_STYLES = {
    "gsf": dict(color="tab:red", ls=":"),
    "gsf_managed": dict(color="tab:blue", ls="--"),
    "agsf_managed": dict(color="tab:orange", ls="-."),
    "agsf_galerkin_managed": dict(color="tab:green", ls=(0, (5, 1, 1, 1))),
    "gsf_benchmark": dict(color="tab:red", ls="-", alpha=0.45),
    "agsf_benchmark": dict(color="tab:orange", ls="-", alpha=0.45),
    "agsf_galerkin_benchmark": dict(color="tab:green", ls="-", alpha=0.45),
}


def split_density_figure(
    result: dict[str, Any],
    path: str | Path,
    times: Sequence[float] = (1.0, 2.0, 8.0),
    names: Sequence[str] = ("gsf", "gsf_managed", "agsf_managed", "agsf_galerkin_managed"),
    xlim: tuple[float, float] = (-7.0, 7.0),
    log_xlim: tuple[float, float] = (-12.0, 12.0),
) -> Path:
    """One column per time in ``times`` (a subset of the result's report times): the grid density of the
    one-component prior and the densities of ``names``, on a linear scale over ``xlim`` (top) and a log scale
    over ``log_xlim`` (bottom, the tails); saved as PNG at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...storage.files import save_figure

    rt = [float(t) for t in result["report_times"]]
    cols = []
    for t in times:
        hits = [i for i, r in enumerate(rt) if math.isclose(r, t, rel_tol=1e-9)]
        if not hits:
            raise ValueError(f"time {t} is not one of the report times {rt}")
        cols.append(hits[0])
    grid = result["grid"]
    fig, axes = plt.subplots(2, len(cols), figsize=(4.6 * len(cols), 7.0), squeeze=False)
    for j, (c, t) in enumerate(zip(cols, times, strict=True)):
        k = int(result["report_index"][c])
        for row, ax in enumerate(axes[:, j]):
            exact = result["reference"]["one_component"]["density"][c]
            ax.plot(grid, exact, color="k", lw=2.2, label="exact (grid FPKE)")
            for name in names:
                rec = result["filters"][name]
                label = f"{FILTER_LABELS[name]} ({int(rec['active'][k])})"
                ax.plot(grid, rec["density"][c], lw=1.4, **_STYLES.get(name, {}), label=label)
            if row == 0:
                ax.set(xlim=xlim, title=f"t = {t:g} s")
            else:
                ax.set_yscale("log")
                ax.set(xlim=log_xlim, ylim=(1e-8, 2.0), xlabel="x (rad)")
                for edge in (-2 * math.pi, 2 * math.pi):
                    ax.axvline(edge, color="0.6", lw=0.8, ls="--", zorder=0)
            ax.grid(True, alpha=0.3)
    axes[0, 0].set_ylabel("density")
    axes[1, 0].set_ylabel("density (log scale; dashed: |x| = 2π)")
    axes[0, -1].legend(fontsize=7.5, title="filter (active components)", title_fontsize=7.5)
    fig.suptitle(
        f"sine SDE from one component N({result['prior']['mean']:.2f}, {result['prior']['variance']:.4f})",
        fontsize=10,
    )
    fig.tight_layout()
    out = save_figure(fig, path, dpi=110)
    plt.close(fig)
    return Path(out)


def split_density_history_figure(result: dict[str, Any], path: str | Path) -> Path:
    """Every filter's ISE and KL divergence (log scales) and active component count against time; saved as PNG
    at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...storage.files import save_figure

    t = result["time"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for name, rec in result["filters"].items():
        style = {"lw": 1.4, **_STYLES.get(name, {})}
        axes[0].semilogy(t, rec["ise"], label=FILTER_LABELS[name], **style)
        axes[1].semilogy(t, rec["kl"], **style)
        axes[2].step(t, rec["active"], where="post", **style)
    axes[0].set(xlabel="time (s)", ylabel="∫ (q − p)² dx", title="integrated squared error")
    axes[1].set(xlabel="time (s)", ylabel="∫ p log(p/q) dx (nats)", title="KL divergence from the exact density")
    axes[2].set(xlabel="time (s)", ylabel="components with nonzero weight", title="active components")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7.5)
    fig.tight_layout()
    out = save_figure(fig, path, dpi=100)
    plt.close(fig)
    return Path(out)


def _main(argv: Sequence[str]) -> None:
    result = run_split_density()
    print(f"prior N({result['prior']['mean']:.6g}, {result['prior']['variance']:.6g}); {result['management']}")
    fs = result["first_split"]
    if fs is not None:
        m0, P0 = fs["before"].moments()
        m1, P1 = fs["after"].moments()
        print(
            f"first split at step {fs['step']}: mean {float(m0[0])!r} -> {float(m1[0])!r}, "
            f"variance {float(P0[0, 0])!r} -> {float(P1[0, 0])!r}"
        )
    print(split_density_tables(result))
    if argv:
        print(split_density_figure(result, argv[0]))
    if len(argv) > 1:
        print(split_density_history_figure(result, argv[1]))


if __name__ == "__main__":
    import sys

    _main(sys.argv[1:])
