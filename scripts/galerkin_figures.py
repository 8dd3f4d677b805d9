"""Figures of the Galerkin weight update on the authors' two benchmarks (docs/results/galerkin.md, docs/figures).

* ``sine-forecast.png``: the sine SDE of method.md §5 at t = 8 s without measurements —
  the exact density (Crank–Nicolson FPKE on a fine grid) and the densities of the classic
  GSF, the paper's penalised update and the Galerkin update.
* ``lorenz-weights.png``: the authors' Lorenz example — the weight of the component on the
  x₁ > 0 lobe for each filter against the mass of that lobe in a 2·10⁵-sample
  Euler–Maruyama ensemble (step 1e-3).

Usage: ``python scripts/galerkin_figures.py [OUT_DIR]`` (default ``docs/figures``).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from agsf_torch import GaussianMixture  # noqa: E402
from agsf_torch.density.grid import FokkerPlanckGrid, integrated_squared_error  # noqa: E402
from agsf_torch.experiments.studies.sine_benchmark import DT, NUM_STEPS, sine_prior  # noqa: E402
from agsf_torch.filters import AdaptiveGaussianSumFilter, GalerkinWeightUpdate, GaussianSumFilter, PenaltyWeightUpdate  # noqa: E402
from agsf_torch.models import LorenzModel, SineDriftModel  # noqa: E402

F64 = torch.float64
STYLE = {"GSF": ":", "AGSF (penalty)": "--", "AGSF (Galerkin)": "-"}


def sine_figure(path: Path) -> None:
    grid = np.linspace(-20.0, 20.0, 4001)
    solver = FokkerPlanckGrid(grid, np.sin, lambda x: 0.5 * np.ones_like(x), dt=0.002)
    xg = torch.tensor(grid, dtype=F64)[:, None]
    exact = solver.step(torch.exp(sine_prior().log_prob(xg)).numpy(), DT * NUM_STEPS)
    model = SineDriftModel()
    filters = {
        "GSF": GaussianSumFilter(model, substeps=10),
        "AGSF (penalty)": AdaptiveGaussianSumFilter(
            model, weight_update=PenaltyWeightUpdate(quadrature=40), substeps=10
        ),
        "AGSF (Galerkin)": AdaptiveGaussianSumFilter(
            model, weight_update=GalerkinWeightUpdate(quadrature=40), substeps=10
        ),
    }
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(grid, exact, "k", lw=2.5, alpha=0.35, label="exact (FPKE on a grid)")
    for name, f in filters.items():
        mix = sine_prior()
        for _ in range(NUM_STEPS):
            mix = f.predict(mix, None, DT)
        p = torch.exp(mix.log_prob(xg)).numpy()
        ise = integrated_squared_error(p, exact, grid)
        ax.plot(grid, p, linestyle=STYLE[name], label=f"{name}: ISE {ise:.4f}, w = {np.round(mix.weights.numpy(), 3)}")
    ax.set(xlim=(-7, 7), xlabel="x", ylabel="density at t = 8 s", title="ẋ = sin x + Γ: forecast without measurements")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def lorenz_figure(path: Path, samples: int = 200_000, substeps: int = 10) -> None:
    model = LorenzModel()
    prior = GaussianMixture(
        weights=torch.tensor([0.9, 0.1], dtype=F64),
        means=torch.tensor([[-0.2, -0.2, 8.0], [0.2, 0.2, 8.0]], dtype=F64),
        covs=0.5916 * torch.eye(3, dtype=F64).expand(2, 3, 3),
    )
    g = torch.Generator().manual_seed(0)
    comp = (torch.rand(samples, generator=g, dtype=F64) < 0.1).long()
    x = prior.means[comp] + math.sqrt(0.5916) * torch.randn(samples, 3, generator=g, dtype=F64)
    h = 0.01 / substeps
    sd = torch.sqrt(model.q_diag * h)
    filters = {
        "GSF": GaussianSumFilter(model),
        "AGSF (penalty)": AdaptiveGaussianSumFilter(model),
        "AGSF (Galerkin)": AdaptiveGaussianSumFilter(model, weight_update="galerkin"),
    }
    mixtures = {k: prior for k in filters}
    t, lobe, weights = [], [], {k: [] for k in filters}
    for k in range(51):
        for _ in range(substeps):
            x = x + model.drift(x) * h + sd * torch.randn(samples, 3, generator=g, dtype=F64)
        t.append(0.01 * (k + 1))
        lobe.append(float((x[:, 0] > 0).double().mean()))
        for name, f in filters.items():
            mixtures[name] = f.predict(mixtures[name], None, 0.01)
            m = mixtures[name]
            weights[name].append(float(m.weights[int(m.means[:, 0].argmax())]))
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(t, lobe, "k", lw=2.5, alpha=0.35, label=f"mass with x₁ > 0 ({samples:,} Euler–Maruyama samples)")
    for name in filters:
        ax.plot(t, weights[name], linestyle=STYLE[name], label=f"{name}: weight of the x₁ > 0 component")
    ax.set(
        xlabel="time (s)",
        ylabel="probability",
        ylim=(0, 0.6),
        title="Lorenz (σ=10, ρ=28, β=8/3, Q=diag(1,1,2)), Δt = 0.01",
    )
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "docs/figures")
    out.mkdir(parents=True, exist_ok=True)
    sine_figure(out / "sine-forecast.png")
    lorenz_figure(out / "lorenz-weights.png")
    print(f"wrote {out}/sine-forecast.png, {out}/lorenz-weights.png")
