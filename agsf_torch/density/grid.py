"""Reference densities for scalar benchmarks: a fine-grid FPKE solver and a grid Bayes filter.

Both work on a uniform grid ``x_0 … x_{G−1}`` with zero density at the ends.
The FPKE ``∂p/∂t = −∂(f p)/∂x + ∂²(D p)/∂x²`` is discretised with central
differences (second order in space) and advanced with Crank–Nicolson (second
order in time, unconditionally stable) using one sparse LU factorisation.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

__all__ = ["FokkerPlanckGrid", "integrated_squared_error"]


class FokkerPlanckGrid:
    """Crank–Nicolson solver of a scalar FPKE with drift ``f(x)`` and diffusion ``D(x)``.

    Args:
        grid: uniform grid ``[G]``.
        drift: ``f`` (vectorised numpy function).
        diffusion: ``D = ½ g² q`` (vectorised numpy function).
        dt: time step of the solver (s).
    """

    def __init__(self, grid: np.ndarray, drift: Callable, diffusion: Callable, dt: float) -> None:
        self.grid = np.asarray(grid, dtype=np.float64)
        dx = float(self.grid[1] - self.grid[0])
        if not np.allclose(np.diff(self.grid), dx, rtol=1e-9, atol=0):
            raise ValueError("grid must be uniform")
        f, D = drift(self.grid), diffusion(self.grid)
        G = self.grid.size
        # (A p)_i = −(f_{i+1}p_{i+1} − f_{i−1}p_{i−1})/(2dx) + (D_{i+1}p_{i+1} − 2D_i p_i + D_{i−1}p_{i−1})/dx²
        upper = -f[1:] / (2 * dx) + D[1:] / dx**2
        lower = f[:-1] / (2 * dx) + D[:-1] / dx**2
        main = -2 * D / dx**2
        A = sp.diags([lower, main, upper], [-1, 0, 1], shape=(G, G), format="csc")
        eye = sp.identity(G, format="csc")
        self.dt = float(dt)
        self._lhs = splu((eye - 0.5 * self.dt * A).tocsc())
        self._rhs = (eye + 0.5 * self.dt * A).tocsr()
        self.dx = dx

    def step(self, p: np.ndarray, duration: float) -> np.ndarray:
        """Advance the density ``p [G]`` by ``duration`` (a multiple of ``dt``)."""
        steps = int(round(duration / self.dt))
        if not np.isclose(steps * self.dt, duration, rtol=1e-9, atol=1e-12):
            raise ValueError(f"duration {duration} is not a multiple of dt {self.dt}")
        for _ in range(steps):
            p = self._lhs.solve(self._rhs @ p)
            p[0] = p[-1] = 0.0
        return p

    def normalise(self, p: np.ndarray) -> np.ndarray:
        """Scale ``p`` to unit mass (trapezoid rule)."""
        return p / np.trapezoid(p, self.grid)


def integrated_squared_error(p: np.ndarray, q: np.ndarray, grid: np.ndarray) -> float:
    """``∫ (p − q)² dx`` on the grid (trapezoid rule)."""
    return float(np.trapezoid((np.asarray(p) - np.asarray(q)) ** 2, grid))
