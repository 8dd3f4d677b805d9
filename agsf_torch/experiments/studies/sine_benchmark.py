"""The scalar benchmark of method.md §5: ``ẋ = sin x + Γ``, optional ``y = x² + v``.

Prior ``0.1 N(−0.2, 1) + 0.9 N(0.2, 1)``, propagation step 0.1 s to t = 8 s.
References: without measurements, a Crank–Nicolson solution of the FPKE on a
fine grid; with measurements, the grid Bayes filter (the same solver between
measurements, Bayes' rule on the grid at measurement times).  The truth is
simulated by Euler–Maruyama at step 0.1/1000.  **[choice]** measurements every
``measure_every`` propagation steps (default 10: one per second).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from ...density.grid import FokkerPlanckGrid, integrated_squared_error
from ...filter_loop import StepInput, filter_steps
from ...filters.gaussian_sum import GaussianSumFilter
from ...mixture import GaussianMixture
from ...models.function_measurement import FunctionMeasurement

__all__ = ["sine_prior", "run_sine_benchmark", "DT", "NUM_STEPS", "GRID"]

DT = 0.1
NUM_STEPS = 80
#: The reference's grid (rad): the FPKE solver's nodes.
GRID = np.linspace(-20.0, 20.0, 4001)


def sine_prior() -> GaussianMixture:
    """``0.1 N(−0.2, 1) + 0.9 N(0.2, 1)``."""
    f64 = torch.float64
    return GaussianMixture(
        weights=torch.tensor([0.1, 0.9], dtype=f64),
        means=torch.tensor([[-0.2], [0.2]], dtype=f64),
        covs=torch.ones(2, 1, 1, dtype=f64),
    )


def _simulate_truth(seed: int, q: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.normal(0.2, 1.0) if rng.random() < 0.9 else rng.normal(-0.2, 1.0)
    h = DT / 1000
    xs = np.empty(NUM_STEPS)
    for k in range(NUM_STEPS):
        noise = rng.normal(size=1000) * np.sqrt(q * h)
        for e in noise:
            x = x + np.sin(x) * h + e
        xs[k] = x
    ys = xs**2 + rng.normal(size=NUM_STEPS)
    return xs, ys


def run_sine_benchmark(
    filters: Mapping[str, GaussianSumFilter], *, measure_every: int | None = None, seed: int = 0
) -> dict[str, np.ndarray]:
    """Integrated squared error of each filter's density against the reference at every step.

    Args:
        filters: name → filter (built on ``SineDriftModel``).
        measure_every: propagation steps between measurements ``y = x² + v``
            (``None``: no measurements, reference = the FPKE solution).
        seed: truth and measurement noise.

    Returns:
        name → ISE ``[NUM_STEPS]``, plus ``"time"``.
    """
    grid = GRID
    solver = FokkerPlanckGrid(grid, np.sin, lambda x: 0.5 * np.ones_like(x), dt=0.002)
    xg = torch.tensor(grid, dtype=torch.float64)[:, None]
    _, ys = _simulate_truth(seed)
    meas = FunctionMeasurement(lambda x: x**2, torch.eye(1, dtype=torch.float64))
    p = torch.exp(sine_prior().log_prob(xg)).numpy()
    refs = []
    for k in range(NUM_STEPS):
        p = solver.step(p, DT)
        if measure_every and (k + 1) % measure_every == 0:
            p = solver.normalise(p * np.exp(-0.5 * (ys[k] - grid**2) ** 2))
        refs.append(p.copy())
    out: dict[str, np.ndarray] = {"time": DT * np.arange(1, NUM_STEPS + 1)}
    y = torch.tensor(ys, dtype=torch.float64)[:, None]
    inputs = [
        StepInput(DT, None, (y[k], meas) if measure_every and (k + 1) % measure_every == 0 else None)
        for k in range(NUM_STEPS)
    ]
    for filt in filters.values():
        filt.reset()
    ise = {name: np.empty(NUM_STEPS) for name in filters}
    mixtures = {name: sine_prior() for name in filters}
    for step in filter_steps(filters, mixtures, inputs):
        for name, fs in step.filters.items():
            ise[name][step.index] = integrated_squared_error(
                torch.exp(fs.mixture.log_prob(xg)).numpy(), refs[step.index], grid
            )
    out.update(ise)
    return out
