"""The Gaussian mixture belief ``p̂(x) = Σᵢ wᵢ N(x; μᵢ, Pᵢ)``.

Shapes (any leading batch dims ``...``, usually one trajectory dim ``B``):
log-weights ``[..., N]``, means ``[..., N, n]``, covariances ``[..., N, n, n]``.
Weights are stored in the log domain and normalised with log-sum-exp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .finite import all_finite
from .shapes import broadcast_shapes

__all__ = ["GaussianMixture", "split_gaussian", "check_covariance", "check_symmetric", "as_real_tensor"]


def _describe(value: object) -> str:
    if torch.is_tensor(value):
        return f"a {value.dtype} tensor of shape {tuple(value.shape)}"
    return f"{type(value).__name__} {value!r}"[:120]


def as_real_tensor(
    name: str, value: object, dtype: torch.dtype | None = None, device: torch.device | None = None
) -> Tensor:
    """``value`` as a real floating-point tensor, or ``ValueError`` naming ``name``.

    A floating-point tensor keeps its dtype unless ``dtype`` is given; integer and bool
    tensors and any array-like (lists, numbers, numpy arrays) become float64 (or
    ``dtype``); complex values and anything that is not numeric (strings, ``None``,
    dicts…) are refused.
    """
    try:
        t = (
            torch.as_tensor(value, device=device)
            if torch.is_tensor(value)
            else torch.as_tensor(value, dtype=dtype or torch.float64, device=device)
        )
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{name} must be a real tensor, got {_describe(value)} ({exc})") from None
    if t.is_complex():
        raise ValueError(f"{name} must be real, got a {t.dtype} tensor")
    if dtype is not None:
        return t.to(dtype)
    return t if t.is_floating_point() else t.to(torch.float64)


def check_covariance(name: str, P: Tensor, rtol: float = 1e-9) -> None:
    """Raise ``ValueError`` unless every ``P[..., :, :]`` is finite, symmetric and positive definite.

    The message names the first offending batch index.
    """
    check_symmetric(name, P, rtol)
    info = torch.linalg.cholesky_ex(P).info
    if bool((info != 0).any()):
        idx = (info != 0).nonzero()[0].tolist()
        raise ValueError(f"{name} is not positive definite at batch index {tuple(idx)}")


def check_symmetric(name: str, P: Tensor, rtol: float = 1e-9) -> None:
    """Raise ``ValueError`` unless ``P [..., n, n]`` is a floating-point tensor, finite and symmetric to ``rtol`` of
    its largest diagonal entry, naming ``name`` and the first offending batch index."""
    if not torch.is_tensor(P) or not P.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got {_describe(P)}")
    if P.dim() < 2 or P.shape[-1] != P.shape[-2]:
        raise ValueError(f"{name} must have shape [..., n, n], got {tuple(P.shape)}")
    if not all_finite(P):
        idx = (~torch.isfinite(P)).flatten(-2).any(-1).nonzero()[0].tolist()
        raise ValueError(f"{name} has non-finite entries at batch index {tuple(idx)}")
    scale = P.diagonal(dim1=-2, dim2=-1).abs().amax(-1, keepdim=True)[..., None]
    asym = (P - P.transpose(-1, -2)).abs() > rtol * scale
    if bool(asym.any()):
        idx = asym.flatten(-2).any(-1).nonzero()[0].tolist()
        raise ValueError(f"{name} is not symmetric at batch index {tuple(idx)}")


@dataclass(frozen=True)
class GaussianMixture:
    """A batch of Gaussian mixtures.

    Construct with keyword arguments, giving either ``weights`` or
    ``log_weights`` (unnormalised is fine: they are normalised here)::

        GaussianMixture(weights=w, means=mu, covs=P)      # w [..., N]
        GaussianMixture(log_weights=lw, means=mu, covs=P)

    Inputs are validated (shapes, finiteness, symmetric positive definite
    covariances, non-negative weights with a positive sum) unless
    ``validate=False`` (used internally by the filters on their own outputs).
    Integer or bool tensors and array-likes are converted to float64 (a floating
    tensor keeps its dtype; ``covs`` and the weights take the dtype of ``means``);
    a non-numeric or complex field is a ``ValueError`` naming it.
    """

    log_weights: Tensor
    means: Tensor
    covs: Tensor

    def __init__(
        self,
        *,
        means: Tensor,
        covs: Tensor,
        weights: Tensor | None = None,
        log_weights: Tensor | None = None,
        validate: bool = True,
    ) -> None:
        means = as_real_tensor("means", means)
        covs = as_real_tensor("covs", covs, means.dtype, means.device)
        if (weights is None) == (log_weights is None):
            raise ValueError("give exactly one of weights= or log_weights=")
        if weights is not None:
            weights = as_real_tensor("weights", weights, means.dtype, means.device)
            if validate:
                if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
                    raise ValueError("weights must be finite and non-negative")
                if bool((weights.sum(-1) <= 0).any()):
                    raise ValueError("weights must have a positive sum in every mixture")
            log_weights = torch.log(weights)
        else:
            log_weights = as_real_tensor("log_weights", log_weights, means.dtype, means.device)
            if validate and (bool(torch.isnan(log_weights).any()) or bool(torch.isposinf(log_weights).any())):
                raise ValueError("log_weights must not be NaN or +inf")
        if validate:
            if means.dim() < 2:
                raise ValueError(f"means must have shape [..., N, n], got {tuple(means.shape)}")
            n = means.shape[-1]
            if covs.shape[-2:] != (n, n) or covs.shape[:-2] != means.shape[:-1]:
                raise ValueError(f"covs must have shape {tuple(means.shape) + (n,)}, got {tuple(covs.shape)}")
            if log_weights.shape != means.shape[:-1]:
                raise ValueError(f"weights must have shape {tuple(means.shape[:-1])}, got {tuple(log_weights.shape)}")
            if not all_finite(means):
                idx = (~torch.isfinite(means)).any(-1).nonzero()[0].tolist()
                raise ValueError(f"means must be finite; non-finite entry at batch index {tuple(idx)}")
            check_covariance("covs", covs)
            if bool(torch.isneginf(log_weights).all(-1).any()):
                raise ValueError("weights must have a positive sum in every mixture")
        log_weights = log_weights - torch.logsumexp(log_weights, -1, keepdim=True)
        object.__setattr__(self, "log_weights", log_weights)
        # own memory per entry (an expanded, stride-0 tensor is copied: torch.func refuses to differentiate through
        # one and in-place updates would write one value to every alias); a no-op for the filters' own tensors
        object.__setattr__(self, "means", means.contiguous())
        object.__setattr__(self, "covs", covs.contiguous())

    # ------------------------------------------------------------ properties
    @property
    def weights(self) -> Tensor:
        """Normalised weights ``[..., N]``."""
        return self.log_weights.exp()

    @property
    def num_components(self) -> int:
        return self.means.shape[-2]

    @property
    def state_dim(self) -> int:
        return self.means.shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        return self.means.shape[:-2]

    def replace(self, *, validate: bool = True, **kwargs: Tensor) -> GaussianMixture:
        """A copy with some of ``log_weights``, ``means``, ``covs`` replaced.

        The result is validated as by the constructor (shapes, finite means, symmetric
        positive definite covariances, log-weights without NaN or +inf and not all −inf);
        ``validate=False`` skips that for the filters' own outputs, whose covariances they
        have already checked (a Cholesky factorisation per component saved per step), and then
        keeps the weights as they are when they are not replaced (normalised already).

        Raises:
            ValueError: an unknown field, or (with ``validate``) a malformed one, named.
        """
        unknown = sorted(set(kwargs) - {"log_weights", "means", "covs"})
        if unknown:
            raise ValueError(f"replace() takes log_weights, means and covs, got {', '.join(unknown)}")
        fields = {"log_weights": self.log_weights, "means": self.means, "covs": self.covs}
        fields.update(kwargs)
        if not validate and "log_weights" not in kwargs:  # the weights are normalised already: kept as they are
            out = object.__new__(GaussianMixture)
            means = as_real_tensor("means", fields["means"])
            object.__setattr__(out, "means", means)
            for name in ("covs", "log_weights"):
                object.__setattr__(out, name, as_real_tensor(name, fields[name], means.dtype, means.device))
            return out
        return GaussianMixture(validate=validate, **fields)

    # ------------------------------------------------------------ statistics
    def moments(self) -> tuple[Tensor, Tensor]:
        """Mean and covariance of the mixture.

        .. math:: μ = Σ_i w_i μ_i,\\qquad P = Σ_i w_i \\left(P_i + (μ_i - μ)(μ_i - μ)^T\\right)

        Returns:
            ``(mean [..., n], cov [..., n, n])``.
        """
        w = self.weights
        mean = (w[..., None] * self.means).sum(-2)
        d = self.means - mean[..., None, :]
        spread = d[..., :, None] * d[..., None, :]
        cov = (w[..., None, None] * (self.covs + spread)).sum(-3)
        return mean, 0.5 * (cov + cov.transpose(-1, -2))

    def component_log_prob(self, x: Tensor) -> Tensor:
        """``log N(x_k; μ_i, P_i)`` for every point and component.

        Args:
            x: ``[..., K, n]``.

        Returns:
            ``[..., N, K]``.
        """
        L = torch.linalg.cholesky(self.covs)  # [..., N, n, n]
        d = x.unsqueeze(-3) - self.means.unsqueeze(-2)  # [..., N, K, n]
        z = torch.linalg.solve_triangular(L, d.transpose(-1, -2), upper=False)  # [..., N, n, K]
        maha = (z * z).sum(-2)
        logdet = 2.0 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1, keepdim=True)
        return -0.5 * (maha + logdet + self.state_dim * math.log(2.0 * math.pi))

    def log_prob(self, x: Tensor) -> Tensor:
        """Log-density of the mixture, ``log Σ_i w_i N(x_k; μ_i, P_i)``.

        Args:
            x: ``[..., K, n]``.

        Returns:
            ``[..., K]``.
        """
        return torch.logsumexp(self.log_weights[..., None] + self.component_log_prob(x), -2)

    def entropy_of_weights(self) -> Tensor:
        """Shannon entropy of the weights, ``−Σ wᵢ log wᵢ`` (nats), ``[...]``."""
        return torch.special.entr(self.log_weights.exp()).sum(-1)  # entr(w) = −w log w, 0 at w = 0

    # ---------------------------------------------------------- construction
    @classmethod
    def from_gaussian(cls, mean: Tensor, cov: Tensor, num_components: int = 1, spread: float = 0.5) -> GaussianMixture:
        """Moment-preserving split of ``N(mean, cov)`` into ``num_components``.

        See :func:`split_gaussian` for the scheme: along the principal axis of ``cov`` (for an isotropic
        ``cov`` every axis is principal, and the eigensolver's choice among them is used).

        Args:
            mean: ``[..., n]``; cov: ``[..., n, n]`` symmetric positive definite; their leading dims broadcast (a
                covariance ``[n, n]`` shared by every trajectory's mean, say).
            num_components: ``N ≥ 1`` (1: the Gaussian itself).
            spread: in ``(0, 1)``, the share of the principal variance carried by the spacing of the means
                (each component keeps ``1 − spread`` of it; :func:`split_gaussian`).
        """
        mean = as_real_tensor("mean", mean)
        cov = as_real_tensor("cov", cov, mean.dtype, mean.device)
        if mean.dim() < 1 or cov.dim() < 2 or cov.shape[-2:] != (mean.shape[-1],) * 2:
            raise ValueError(f"mean [..., n] and cov [..., n, n] do not match: {tuple(mean.shape)}, {tuple(cov.shape)}")
        try:
            lead = broadcast_shapes(mean.shape[:-1], cov.shape[:-2])
        except RuntimeError:
            raise ValueError(
                f"mean {tuple(mean.shape)} and cov {tuple(cov.shape)} have leading (trajectory) dims that do not "
                "broadcast: give one of each per trajectory, or one shared by every trajectory"
            ) from None
        n = mean.shape[-1]
        mean, cov = mean.expand(*lead, n), cov.expand(*lead, n, n)
        if not bool(torch.isfinite(mean).all()):
            raise ValueError("mean must be finite")
        check_covariance("cov", cov)
        w, mu, P = split_gaussian(mean, cov, num_components, spread)
        return cls(weights=w, means=mu, covs=P, validate=False)


def split_gaussian(
    mean: Tensor, cov: Tensor, num_components: int, spread: float = 0.5
) -> tuple[Tensor, Tensor, Tensor]:
    """Split a Gaussian into ``N`` components along its principal axis, preserving mean and covariance.

    With ``λ, v`` the largest eigenpair of ``P`` and ``u_i`` equally spaced in
    ``[−2, 2]``: weights ``w_i ∝ exp(−u_i²/2)``, offsets ``m_i = c u_i`` with ``c``
    chosen so that ``Σ w_i m_i² = spread``; then

    .. math:: μ_i = μ + m_i \\sqrt{λ}\\, v,\\qquad P_i = P - \\mathrm{spread}\\; λ\\, v v^T

    so ``Σ w_i μ_i = μ`` and ``Σ w_i (P_i + (μ_i − μ)(μ_i − μ)ᵀ) = P`` exactly
    (to rounding).  The split is differentiable in ``mean`` and ``cov`` with the
    principal direction ``v`` held fixed (``λ = vᵀPv``).  ``spread ∈ (0, 1)`` is the share of the principal variance
    carried by the spacing of the means; each component keeps ``1 − spread``.

    Args:
        mean: ``[..., n]``; cov: ``[..., n, n]``; num_components ≥ 1.

    Returns:
        ``(weights [..., N], means [..., N, n], covs [..., N, n, n])``.
    """
    if int(num_components) != num_components or num_components < 1:
        raise ValueError(f"num_components must be a positive integer, got {num_components}")
    if not 0.0 < spread < 1.0:
        raise ValueError(f"spread must lie in (0, 1), got {spread}")
    N = int(num_components)
    batch = mean.shape[:-1]
    if N == 1:
        w = torch.ones(*batch, 1, dtype=mean.dtype, device=mean.device)
        return w, mean.unsqueeze(-2).clone(), cov.unsqueeze(-3).clone()
    u = torch.linspace(-2.0, 2.0, N, dtype=mean.dtype, device=mean.device)
    w = torch.exp(-0.5 * u * u)
    w = w / w.sum()
    u = u - (w * u).sum()  # exactly zero-mean offsets
    m = u * math.sqrt(spread) / torch.sqrt((w * u * u).sum())
    # principal direction from the detached covariance (eigenvectors of repeated eigenvalues have
    # no derivative); λ = vᵀPv carries the gradient with respect to P
    v = torch.linalg.eigh(cov.detach())[1][..., :, -1]  # [..., n]
    lam = (v.unsqueeze(-2) @ cov @ v.unsqueeze(-1)).squeeze(-1).squeeze(-1)  # [...]
    offsets = m[:, None] * (torch.sqrt(lam)[..., None] * v).unsqueeze(-2)  # [..., N, n]
    means = mean.unsqueeze(-2) + offsets
    P = cov - spread * lam[..., None, None] * v[..., :, None] * v[..., None, :]
    P = 0.5 * (P + P.transpose(-1, -2))
    covs = P.unsqueeze(-3).expand(*batch, N, *cov.shape[-2:]).clone()
    return w.expand(*batch, N).clone(), means, covs
