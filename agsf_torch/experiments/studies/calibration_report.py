"""The calibration study's report: Markdown tables and a figure from :func:`~agsf_torch.experiments.studies.calibration.run_study`'s results."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .calibration import MIS_SCALINGS

__all__ = ["calibration_markdown", "calibration_figure", "AXIS_GYRO_DT"]

#: The gyro interval (s) of the settings on the axes of data length and trajectories (:data:`agsf_torch.experiments.studies.calibration.STUDY`).
AXIS_GYRO_DT = 1.0


def _pct(rate: dict) -> str:
    """``rate`` as ``12.5 % (8.3–17.9)``: the share and its Clopper–Pearson 95 % interval."""
    if not rate["datasets"]:
        return "—"
    return f"{100 * rate['rate']:.1f} % ({100 * rate['low']:.1f}–{100 * rate['high']:.1f})"


def _num(x: float, digits: int = 3) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.{digits}g}"


def calibration_markdown(results: list[dict], verdicts: list[dict] | None = None) -> str:
    """The study's tables: per setting and coordinate the estimate's bias in standard errors, RMS error against
    the mean standard error, coverage and false alarm; the detection rates; the joint verdict; the baseline beside
    ours; and, if given, the diagnose verdicts' rates (:mod:`agsf_torch.experiments.studies.verdict_calibration`)."""
    lines = [
        "| setting | coordinate | identified | bias / SE | RMS error | mean SE | coverage of the 95 % interval | "
        "false alarm at the truth |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        for c in r["coordinates"]:
            alarm = c.get("false_alarm") or c.get("block_false_alarm")
            lines.append(
                f"| {r['label']} | {c['coordinate'].replace(c['name'].split('[')[0], c['name'])} | "
                f"{_pct(c['identified'])} | {_num(c['bias_over_se'], 2)} | {_num(c['rms_error'])} | "
                f"{_num(c['mean_standard_error'])} | {_pct(c['coverage'])} | "
                f"{_pct(alarm) if alarm is not None else '—'} |"
            )
    header = " | ".join(f"×{c:g}" for c in MIS_SCALINGS) + " | " + " | ".join(f"÷{c:g}" for c in MIS_SCALINGS)
    detection = [f"| setting | parameter | {header} |", "|---|---|" + "---|" * (2 * len(MIS_SCALINGS))]
    for r in results:
        for c in r["coordinates"]:
            if "detection" not in c:
                continue
            cells = [_pct(c["detection"][f"{f:.4g}"]) for f in MIS_SCALINGS]
            cells += [_pct(c["detection"][f"{1.0 / f:.4g}"]) for f in MIS_SCALINGS]
            detection.append(f"| {r['label']} | {c['name'].split('[')[0]} | " + " | ".join(cells) + " |")
    joint = [
        "| setting | parameters | converged | joint verdict's false alarm | any parameter's false alarm |",
        "|---|---|---|---|---|",
    ]
    for r in results:
        if len(r["coordinates"]) > 1:
            joint.append(
                f"| {r['label']} | {', '.join(r['learn'])} | {_pct(r['converged'])} | {_pct(r['joint_false_alarm'])} "
                f"| {_pct(r['any_parameter_false_alarm'])} |"
            )
    baseline = [
        "| setting | parameter | ML: RMS error of log σ | ALS: RMS error of log σ | ALS: mean error | ALS: positive |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        for name, b in r.get("baseline", {}).items():
            ours = next(c for c in r["coordinates"] if c["name"] == name)
            baseline.append(
                f"| {r['label']} | {name} | {_num(ours['rms_error'])} | {_num(b['rms_error'])} | "
                f"{_num(b['mean_error'])} | {_pct(b['positive'])} |"
            )
    parts = [
        "### Estimates, intervals and verdicts at the truth",
        "\n".join(lines),
        "### Detection of a mis-configured filter (the configured value × or ÷ the factor)",
        "\n".join(detection),
        "### Several parameters at once",
        "\n".join(joint),
        "### The baseline: autocovariance least squares on the same data",
        "\n".join(baseline),
    ]
    if verdicts:
        parts += ["### `agsf diagnose`'s verdicts (NEES, NIS, whiteness, and any of them)", verdicts_markdown(verdicts)]
    return "\n\n".join(parts) + "\n"


def verdicts_markdown(verdicts: list[dict]) -> str:
    """The diagnose verdicts' rates (:func:`agsf_torch.experiments.studies.calibration.verdict_study`), one table per setting: a row per check,
    the false-alarm rate at the truth, then the detection rate at each mis-scaling of each parameter."""
    out = []
    for v in verdicts:
        rows = v["rows"]
        columns = [("false alarm", None, 1.0)] + [
            (f"{r['parameter']} ×{r['scale']:g}", r["parameter"], r["scale"])
            for r in rows
            if r["check"] == "any" and r["scale"] != 1.0
        ]
        lines = [
            f"**{v['label']}** ({v['datasets']} data sets; the bands at {100 * v['level']:.3g} % each, "
            f"{100 * v['familywise_level']:.3g} % for the whole verdict)",
            "",
            "| check | " + " | ".join(c[0] for c in columns) + " |",
            "|---|" + "---|" * len(columns),
        ]
        for check in v["checks"]:
            cells = []
            for _, parameter, scale in columns:
                match = [
                    r
                    for r in rows
                    if r["check"] == check
                    and r["scale"] == scale
                    and (parameter is None or r["parameter"] == parameter)
                ]
                cells.append(_pct({"rate": match[0]["rate"], "datasets": match[0]["judged"], **match[0]}))
            lines.append(f"| {check} | " + " | ".join(cells) + " |")
        out.append("\n".join(lines))
    return "\n\n".join(out)


def calibration_figure(results: list[dict], path: Path) -> Path:
    """Two panels: (a) the RMS error of ``log σ_s`` and ``log σ_v`` against the seconds of data per data set
    (trajectories × duration), beside the mean standard error and the baseline's error; (b) the detection rate
    against the mis-scaling of the configured value, the false-alarm rate at 1.  Written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...storage.files import save_figure

    fig, (ax_err, ax_det) = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    colours = {"sigma_s": "C0", "sigma_v": "C1"}
    for name, colour in colours.items():
        pts = []
        for r in results:
            axis = set(r["learn"]) == {"sigma_s", "sigma_v"} and r["star_noise_model"] == "isotropic"
            if not axis or r["gyro_dt_s"] != AXIS_GYRO_DT:
                continue
            c = next(c for c in r["coordinates"] if c["name"] == name)
            als = r.get("baseline", {}).get(name, {}).get("rms_error", math.nan)
            pts.append((r["duration_s"] * r["trajectories"], c["rms_error"], c["mean_standard_error"], als))
        if not pts:
            continue
        x, rms, se, als = (np.array(v) for v in zip(*sorted(pts)))
        ax_err.loglog(x, rms, "o-", color=colour, label=f"{name}: ML, RMS error")
        ax_err.loglog(x, se, "x:", color=colour, label=f"{name}: ML, mean standard error")
        if np.isfinite(als).any():
            ax_err.loglog(x, als, "s--", color=colour, alpha=0.6, label=f"{name}: ALS, RMS error")
    ax_err.set_xlabel("seconds of data per data set (trajectories × duration; gyro at 1 Hz)")
    ax_err.set_ylabel("error of log σ")
    ax_err.set_title("(a) estimate error against data")
    ax_err.legend(fontsize=7)
    headline = next((r for r in results if r["learn"] == ["sigma_s", "sigma_v"]), None)
    if headline is not None:
        for c in headline["coordinates"]:
            factors = sorted([1.0 / f for f in MIS_SCALINGS] + list(MIS_SCALINGS))
            rates = [c["detection"][f"{f:.4g}"]["rate"] for f in factors]
            factors.insert(len(MIS_SCALINGS), 1.0)
            rates.insert(len(MIS_SCALINGS), c["false_alarm"]["rate"])
            ax_det.semilogx(factors, rates, "o-", color=colours.get(c["name"]), label=c["name"])
        ax_det.axhline(0.05, color="grey", lw=0.8, ls=":", label="5 %")
        ax_det.set_xticks([1 / 3, 0.5, 1, 2, 3], ["÷3", "÷2", "1", "×2", "×3"])
        ax_det.set_xticks([], minor=True)  # the log axis's own minor labels would overlap these
        ax_det.set_ylim(0, 1.02)
        ax_det.set_title(f"(b) verdict 'mis-modelled' · {headline['label']}")
        ax_det.set_xlabel("configured value / truth")
        ax_det.set_ylabel("share of data sets flagged")
        ax_det.legend(fontsize=8)
    path = Path(path)
    save_figure(fig, path)
    plt.close(fig)
    return path
