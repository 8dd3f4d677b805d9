"""The figures of an experiment (PNG), drawn from its ``summary.json`` alone."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..files import save_figure
from ..filters.registry import FILTER_NAMES, FILTERS

__all__ = ["write_figures"]


def write_figures(out: Path, summary: dict[str, Any]) -> None:
    """Write ``rms.png``, ``axes.png``, ``weights.png`` and ``fpke.png`` into ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array(summary["time_s"])
    filters = summary["filters"]
    title = summary["config"]["name"]

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, f in filters.items():
        ax.semilogy(t, f["rms_deg"], label=name)
    ax.set(xlabel="time (s)", ylabel="RMS attitude error (deg)", title=f"{title}: RMS over {summary['config']['runs']} runs")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, out / "rms.png", dpi=110)
    plt.close(fig)

    shown = [n for n in FILTER_NAMES if n in filters and FILTERS[n].mixture] or list(filters)
    fig, axes = plt.subplots(len(shown), 3, figsize=(11, 3 * len(shown)), squeeze=False)
    for row, name in enumerate(shown):
        err = np.degrees(np.array(filters[name]["error_run0_rad"]))[:, :3] * 3600
        sig = np.degrees(np.array(filters[name]["sigma_run0_rad"]))[:, :3] * 3600
        for k in range(3):
            a = axes[row, k]
            a.plot(t, err[:, k], lw=1, label="error")
            a.plot(t, 3 * sig[:, k], "r--", lw=0.8, label="±3σ")
            a.plot(t, -3 * sig[:, k], "r--", lw=0.8)
            a.set_yscale("symlog", linthresh=1.0)
            a.set(title=f"{name} axis {k + 1} (run 0)", xlabel="time (s)", ylabel="arcsec")
            a.grid(True, alpha=0.3)
    axes[0, 0].legend()
    fig.tight_layout()
    save_figure(fig, out / "axes.png", dpi=100)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(shown), figsize=(5.5 * len(shown), 3.5), squeeze=False)
    for col, name in enumerate(shown):
        w = np.array(filters[name]["weights_run0"])
        axes[0, col].plot(t, w, lw=1)
        axes[0, col].set(title=f"{name} weights (run 0)", xlabel="time (s)", ylabel="weight", ylim=(-0.02, 1.02))
        axes[0, col].grid(True, alpha=0.3)
    fig.tight_layout()
    save_figure(fig, out / "weights.png", dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, f in filters.items():
        if "fpke_error_before_mean" in f:
            ax.semilogy(t, f["fpke_error_before_mean"], label=f"{name}: before weight update")
            ax.semilogy(t, f["fpke_error_after_mean"], "--", label=f"{name}: after weight update")
    ax.set(xlabel="time (s)", ylabel="FPKE error wᵀLw (mean over runs)", title=f"{title}: FPKE error")
    ax.grid(True, which="both", alpha=0.3)
    if ax.lines:
        ax.legend()
    fig.tight_layout()
    save_figure(fig, out / "fpke.png", dpi=110)
    plt.close(fig)


