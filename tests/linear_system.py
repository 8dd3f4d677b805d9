"""Shared exact-answer fixture: a 3-state linear SDE observed linearly, and its
exact discretisation (Van Loan) for filterpy's KalmanFilter."""

from __future__ import annotations

import numpy as np
import scipy.linalg
import torch

from agsf_torch.models import FunctionMeasurement, LinearModel

DT = 0.1
A = np.array([[0.0, 1.0, 0.0], [-1.0, -0.2, 0.5], [0.0, 0.0, -0.05]])
G = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
Q = np.diag([0.3, 0.01])
Bu = np.array([[0.0], [1.0], [0.0]])
H = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
R = np.array([[0.04, 0.01], [0.01, 0.09]])


def discretise(dt: float = DT) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(F, Q_d, B_d)`` of the exact zero-order-hold discretisation (Van Loan's method)."""
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A
    M[:n, n:] = G @ Q @ G.T
    M[n:, n:] = A.T
    E = scipy.linalg.expm(M * dt)
    F = E[n:, n:].T
    Qd = F @ E[:n, n:]
    Z = np.zeros((n + 1, n + 1))
    Z[:n, :n] = A
    Z[:n, n:] = Bu
    Bd = scipy.linalg.expm(Z * dt)[:n, n:]
    return F, 0.5 * (Qd + Qd.T), Bd


def model() -> LinearModel:
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    return LinearModel(t(A), t(G), t(Q), B=t(Bu))


def measurement() -> FunctionMeasurement:
    Ht = torch.tensor(H, dtype=torch.float64)
    return FunctionMeasurement(lambda x: x @ Ht.T, torch.tensor(R, dtype=torch.float64))


def simulate(num_steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Inputs ``[T, 1]`` and measurements ``[T, 2]`` of one trajectory of the discretised system."""
    rng = np.random.default_rng(seed)
    F, Qd, Bd = discretise()
    x = rng.normal(size=3)
    us, ys = [], []
    for _ in range(num_steps):
        u = np.array([np.sin(0.3 * len(us))])
        x = F @ x + Bd @ u + rng.multivariate_normal(np.zeros(3), Qd)
        us.append(u)
        ys.append(H @ x + rng.multivariate_normal(np.zeros(2), R))
    return np.array(us), np.array(ys)
