"""Linear time-invariant SDE ``dx = (A x + B u) dt + G dβ`` — the exact-answer reference model."""

from __future__ import annotations

import torch
from torch import Tensor

from .base import ContinuousModel, check_finite

__all__ = ["LinearModel"]


class LinearModel(ContinuousModel):
    """``f(x, u) = A x + B u``, ``g = G``, noise spectral density ``Q``.

    For this model the EKF is the exact Kalman–Bucy filter, and a Gaussian
    propagated by its moment equations solves the Fokker–Planck equation
    exactly, which makes it the reference for tests of every filter.

    Args:
        A: ``[n, n]``; G: ``[n, q]``; Q: ``[q, q]`` symmetric PSD;
        B: optional input matrix ``[n, m]``.  With it the model declares :attr:`input_dim` ``= m``, so the filters
            require ``u [..., m]`` (a zero input is given as zeros); without it an input is refused, not ignored.
    """

    def __init__(self, A: Tensor, G: Tensor, Q: Tensor, B: Tensor | None = None) -> None:
        super().__init__()
        A, G, Q = (torch.as_tensor(t, dtype=torch.float64) for t in (A, G, Q))
        n = A.shape[-1]
        if A.shape != (n, n):
            raise ValueError(f"A must be square [n, n], got {tuple(A.shape)}")
        if G.dim() != 2 or G.shape[0] != n:
            raise ValueError(f"G must be [n, q] with n = {n}, got {tuple(G.shape)}")
        if Q.shape != (G.shape[1], G.shape[1]):
            raise ValueError(f"Q must be [q, q] with q = {G.shape[1]}, got {tuple(Q.shape)}")
        for name, t in (("A", A), ("G", G), ("Q", Q)):
            check_finite(name, t)
        if B is not None:
            B = torch.as_tensor(B, dtype=torch.float64)
            if B.dim() != 2 or B.shape[0] != n:
                raise ValueError(f"B must be [n, m] with n = {n}, got {tuple(B.shape)}")
            check_finite("B", B)
        self.state_dim = n
        self.input_dim = None if B is None else B.shape[1]
        self.register_buffer("A", A)
        self.register_buffer("G", G)
        self.register_buffer("Q", Q)
        self.register_buffer("B", B)

    def check_input(self, u: Tensor | None) -> None:
        """:meth:`ContinuousModel.check_input` with ``input_dim = m`` of ``B``; without ``B``, ``u`` must be ``None``."""
        if self.B is None and u is not None:
            raise ValueError(
                f"LinearModel has no input matrix B, got an input u of shape {tuple(torch.as_tensor(u).shape)} "
                "(it would be ignored): give B=[n, m] or pass u=None"
            )
        super().check_input(u)

    def drift(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        """``A x + B u`` → ``[..., n]``."""
        out = x @ self.A.to(x).T
        if self.B is not None and u is not None:
            out = out + u @ self.B.to(x).T
        return out

    def drift_jacobian(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        """``A`` broadcast to ``[..., n, n]``."""
        return self.A.to(x).expand(*x.shape[:-1], self.state_dim, self.state_dim)

    def noise_gain(self, x: Tensor) -> Tensor:
        """``G`` broadcast to ``[..., n, q]``."""
        return self.G.to(x).expand(*x.shape[:-1], *self.G.shape)

    def noise_psd(self) -> Tensor:
        return self.Q
