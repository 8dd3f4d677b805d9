"""Charts of the state space, and the log-density of a Gaussian mixture in a chart.

**MRP chart** (``chart="mrp"``, method.md §1).  MRPs ``p`` and ``pˢ = −p/|p|²`` name
the same attitude, so a Gaussian on MRP coordinates is a density on the rotation group
only after folding onto one chart.  Samples are kept in the canonical chart
``|p| ≤ 1`` and a mixture is scored as

.. math:: \\hat p(x) = Σ_i w_i \\left[N(x; μ_i, P_i) + N(s(x); μ_i, P_i)\\,|\\det ∂s/∂x|\\right],
          \\quad |\\det ∂s/∂x| = |p|^{-6},

so components on either MRP set count consistently (bias coordinates unchanged).
The particles switch to the shadow set when ``|p| > 1`` as the filters do.  The
model's Itô SDE is not exactly chart-invariant: mapping it through the shadow map
adds the drift ``(σ_v²/16)(1 + s)² p/s²`` (``σ_v²/4 · p`` at ``|p| = 1``, ~2.5e-14 per
second for the default gyro), the only difference between simulating in one chart or
switching.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..mixture import GaussianMixture
from ..models.attitude import AttitudeModel
from ..models.base import ContinuousModel
from ..rotations import mrp_canonical, mrp_shadow, mrp_shadow_jacobian

__all__ = ["CHARTS", "check_chart", "chart_for", "switch_flow", "canonical_points", "mixture_log_density"]

#: Supported charts: ``"euclidean"`` (plain log-density) and ``"mrp"`` (first three
#: state entries are MRPs, folded onto ``|p| ≤ 1``).
CHARTS = ("euclidean", "mrp")


def check_chart(chart: str, n: int) -> str:
    """``chart`` if it is one of :data:`CHARTS` and fits a state of dimension ``n`` (``"mrp"`` needs ``n ≥ 3``),
    else ``ValueError`` naming what is wrong."""
    if chart not in CHARTS:
        raise ValueError(f"chart must be one of {CHARTS}, got {chart!r}")
    if chart == "mrp" and n < 3:
        raise ValueError(f"chart='mrp' needs a state whose first 3 entries are MRPs, got state dimension {n}")
    return chart


def chart_for(model: ContinuousModel) -> str:
    """The chart in which samples of ``model`` are kept and mixtures scored.

    ``"mrp"`` for :class:`~agsf_torch.models.AttitudeModel`, ``"euclidean"`` otherwise.
    """
    return "mrp" if isinstance(model, AttitudeModel) else "euclidean"


def canonical_points(x: Tensor, chart: str = "euclidean") -> Tensor:
    """Points in the canonical chart: MRPs with ``|p| > 1`` replaced by ``pˢ = −p/|p|²``.

    Args:
        x: ``[..., n]``; chart: ``"euclidean"`` (identity) or ``"mrp"``.

    Returns:
        ``[..., n]``.
    """
    check_chart(chart, x.shape[-1])
    if chart == "euclidean":
        return x
    return torch.cat((mrp_canonical(x[..., :3]), x[..., 3:]), -1)


def switch_flow(x: Tensor, S: Tensor | None = None, Sig: Tensor | None = None):
    """Shadow switch of points (and of tangent matrices) where ``|p| > 1``.

    ``p ← −p/s``; ``S ← T S`` and ``Σ ← T Σ Tᵀ`` with ``T = blockdiag(∂pˢ/∂p, I)``.
    """
    p = x[..., :3]
    s = (p * p).sum(-1)
    switch = s > 1.0
    if not bool(switch.any()):
        return x, S, Sig
    safe = torch.where(switch[..., None], p, torch.ones_like(p))
    new_p = torch.where(switch[..., None], mrp_shadow(safe), p)
    x = torch.cat((new_p, x[..., 3:]), -1)
    if S is None:
        return x, S, Sig
    n = x.shape[-1]
    T = torch.eye(n, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], n, n).clone()
    T[..., :3, :3] = torch.where(switch[..., None, None], mrp_shadow_jacobian(safe), T[..., :3, :3])
    S = T @ S
    Sig = T @ Sig @ T.transpose(-1, -2)
    return x, S, 0.5 * (Sig + Sig.transpose(-1, -2))


def mixture_log_density(mixture: GaussianMixture, x: Tensor, *, chart: str = "euclidean") -> Tensor:
    """Log-density of a Gaussian mixture at points, in the chart's canonical coordinates.

    ``"euclidean"``: ``log Σᵢ wᵢ N(x; μᵢ, Pᵢ)``.  ``"mrp"``: the points are first put in
    the canonical chart ``|p| ≤ 1``, and each component is folded onto it,

    .. math:: \\log Σ_i w_i \\left[N(x; μ_i, P_i) + N(s(x); μ_i, P_i)\\,|p|^{-6}\\right],
              \\quad s(x) = [−p/|p|^2;\\ b],

    the density on the rotation group (times the bias space) of the law of the
    canonicalised Gaussian sum.

    Args:
        mixture: batch shape ``[]`` or ``[B]``, ``N`` components, state dimension ``n``.
        x: ``[B, K, n]`` (or ``[K, n]`` with an unbatched mixture).

    Returns:
        ``[B, K]`` (nats).
    """
    chart = check_chart(chart, x.shape[-1])
    if chart == "euclidean":
        return mixture.log_prob(x)
    x = canonical_points(x, chart)
    p = x[..., :3]
    s = (p * p).sum(-1)  # [..., K]
    tiny = s <= torch.finfo(x.dtype).tiny ** 0.5
    s_safe = torch.where(tiny, torch.ones_like(s), s)
    xs = torch.cat((mrp_shadow(torch.where(tiny[..., None], torch.ones_like(p), p)), x[..., 3:]), -1)
    direct = mixture.component_log_prob(x)  # [..., N, K]
    shadow = mixture.component_log_prob(xs) - 3.0 * torch.log(s_safe).unsqueeze(-2)
    shadow = torch.where(tiny.unsqueeze(-2), torch.full_like(shadow, -math.inf), shadow)
    both = torch.stack((direct, shadow), -1)  # [..., N, K, 2]
    lw = mixture.log_weights[..., None, None]
    return torch.logsumexp(lw + both, dim=(-3, -1))
