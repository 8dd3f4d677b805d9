"""A sweep's rows: the metrics each configuration contributes, and the results table."""

from __future__ import annotations

import json
from typing import Any

from ..report.statistics import WINDOW_TEXT

__all__ = ["config_metrics", "results_table"]


def config_metrics(summary: dict[str, Any]) -> dict[str, float]:
    """The row metrics of one configuration's ``summary.json``: per filter its mean RMS between star frames
    (deg), its time-averaged NEES and its NIS ratio ``nis_per_expected`` (when it had star frames), and the paired AGSF − GSF difference (deg) when there is one."""
    m: dict[str, float] = {}
    for name, f in summary["filters"].items():
        if "between_frames" in f:
            m[f"{name}/mean_rms_between_frames_deg"] = f["between_frames"]["mean_rms_deg"]
        if "time_averaged_nees" in f:  # scored against the truth (a replay of flight data is not)
            m[f"{name}/time_averaged_nees"] = f["time_averaged_nees"]
        if "nis_per_expected" in f:
            m[f"{name}/nis_per_expected"] = f["nis_per_expected"]
    d = summary.get("agsf_minus_gsf", {}).get("between_frames")
    if d:
        m["agsf_minus_gsf_deg"] = d["mean_deg"]
    return m


_RMS_SUFFIX = "/mean_rms_between_frames_deg"
_NEES_SUFFIX = "/time_averaged_nees"
_DIFFERENCE_KEY = "agsf_minus_gsf_deg"


def _table_cell(value: Any) -> str:
    """A parameter or metric as table text: strings as they are, floats in 4 significant digits,
    anything else as JSON; ``|`` escaped for Markdown."""
    if value is None:
        text = "—"
    elif isinstance(value, str):
        text = value
    elif isinstance(value, float):
        text = f"{value:.4g}"
    else:
        text = json.dumps(value)
    return text.replace("|", "\\|")


def results_table(rows: list[dict[str, Any]]) -> str:
    """A sweep's rows (``{"digest", "params", "metrics"}``, as in ``results.jsonl``) as one
    Markdown table, one line per configuration in the order of ``rows``.

    Columns: the configuration's digest (its folder ``configs/<digest>/``), every swept
    parameter, then per filter its mean RMS between star frames (deg) and its time-averaged
    NEES (dimensionless), and ``AGSF − GSF`` (deg, the paired difference of the mean RMS
    between frames) when any row has it, and ``reused (not rerun)`` when a row copied a filter's results
    from the configuration named (``row["reused"]``: filter → digest).  A metric a row lacks is shown as ``—``.  Cells are
    padded so that the table also reads as plain text; one sentence under the table says what its
    window is (:data:`~agsf_torch.experiments.report.statistics.WINDOW_TEXT`).

    Raises:
        ValueError: a row without a ``params`` or ``metrics`` mapping (named by its index).
    """
    if not rows:
        return "no finished configurations"
    for i, row in enumerate(rows):
        if (
            not isinstance(row, dict)
            or not isinstance(row.get("params"), dict)
            or not isinstance(row.get("metrics"), dict)
        ):
            raise ValueError(f"sweep row {i} must be a mapping with 'params' and 'metrics' mappings, got {row!r}")
    params = list(dict.fromkeys(k for row in rows for k in row["params"]))
    filters = list(
        dict.fromkeys(
            k.split("/", 1)[0] for row in rows for k in row["metrics"] if k.endswith((_RMS_SUFFIX, _NEES_SUFFIX))
        )
    )
    difference = any(_DIFFERENCE_KEY in row["metrics"] for row in rows)
    reused = any(row.get("reused") for row in rows)
    header = ["config", *params]
    for name in filters:
        header += [f"{name} RMS (deg)", f"{name} NEES"]
    if difference:
        header.append("AGSF − GSF (deg)")
    if reused:
        header.append("reused (not rerun)")
    body = []
    for row in rows:
        m = row["metrics"]
        cells = [_table_cell(row.get("digest")), *(_table_cell(row["params"].get(k)) for k in params)]
        for name in filters:
            cells += [_table_cell(m.get(name + _RMS_SUFFIX)), _table_cell(m.get(name + _NEES_SUFFIX))]
        if difference:
            cells.append(_table_cell(m.get(_DIFFERENCE_KEY)))
        if reused:
            by_source: dict[str, list[str]] = {}
            for name, source in (row.get("reused") or {}).items():
                by_source.setdefault(source, []).append(name)
            cells.append("; ".join(f"{', '.join(n)} ← {src}" for src, n in by_source.items()) or "—")
        body.append(cells)
    widths = [max(len(r[i]) for r in [header, *body]) for i in range(len(header))]

    def line(cells: list[str]) -> str:
        return "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"

    note = (
        f"RMS: the mean over runs of each run's RMS in the window {WINDOW_TEXT['between_frames']}; "
        "NEES: averaged over every step and run"
        + ("; AGSF − GSF: the paired per-run difference of that RMS." if difference else ".")
        + (
            " Reused: a filter that reads none of the options in which two configurations differ ran once; the "
            "later rows repeat the numbers of the configuration named (its arrays copied, not recomputed)."
            if reused
            else ""
        )
    )
    return "\n".join([line(header), line(["-" * w for w in widths]), *(line(r) for r in body), "", note])
