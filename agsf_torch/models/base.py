"""The model protocol: continuous-time dynamics and measurement models.

A user model subclasses :class:`ContinuousModel` (an Itô SDE
``dx = f(x, u) dt + g(x) dβ``, ``E[dβ dβᵀ] = Q dt``) and/or
:class:`MeasurementModel` (``y = h(x) + v``, ``v ~ N(0, R)``).  Everything a
filter needs beyond ``f, g, Q, h, R`` — Jacobians, the diffusion matrix and the
derivative terms of the Fokker–Planck operator — has a default computed with
``torch.func``; a subclass may override any of them with a closed form.  A closed form or fused kernel
is marked with the physics it was derived from (:mod:`~agsf_torch.models.derived`): a subclass of a model
that changes that physics gets these defaults instead of its parent's derivations.

Shape contract: every method is *elementwise over leading batch dims*: an input
``x`` of shape ``[..., n]`` gives outputs whose leading dims are the broadcast of
``x``'s leading dims with those of the model's own tensors (for example the star
directions of a measurement).  Filters rely on this to evaluate all trajectories
and all mixture components in one call.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from ..finite import check_finite
from .contract import check_measurement_batch, check_model_contract, check_noise_cov
from .derived import record_derivations

__all__ = [
    "check_measurement_batch",
    "FokkerPlanckTerms",
    "FokkerPlanckMoments",
    "batched_jacobian",
    "ContinuousModel",
    "MeasurementModel",
    "check_finite",
    "sum_last",
    "check_nonnegative",
]


def sum_last(x: Tensor, keepdim: bool = False) -> Tensor:
    """``x.sum(-1)`` as a product with a vector of ones: the same sum, several times faster on CPU for
    a short last dimension (torch's reduction kernel is slow over 3–6 contiguous entries)."""
    out = x @ x.new_ones(x.shape[-1])
    return out.unsqueeze(-1) if keepdim else out


def check_nonnegative(name: str, value) -> Tensor:
    """Return ``value`` as a float64 tensor, or raise if negative or non-finite."""
    t = torch.as_tensor(value, dtype=torch.float64) if not isinstance(value, Tensor) else value
    check_finite(name, t)
    if bool((t < 0).any()):
        raise ValueError(f"{name} must be non-negative, got {t.tolist()}")
    return t


def batched_jacobian(fn: Callable[[Tensor], Tensor], x: Tensor) -> Tensor:
    """Jacobian of an elementwise-batched function by forward-mode AD.

    One Jacobian–vector product per state direction (``n`` in all), each
    evaluated for the whole batch at once, so the cost is ``n`` batched calls of
    ``fn`` whatever the batch size.

    Args:
        fn: maps ``[..., n]`` to ``[..., d]``, elementwise over leading dims.
        x: ``[..., n]``.

    Returns:
        ``∂fn/∂x`` of shape ``[..., d, n]``.
    """
    n = x.shape[-1]
    eye = torch.eye(n, dtype=x.dtype, device=x.device)
    basis = eye.reshape(n, *([1] * (x.dim() - 1)), n).expand(n, *x.shape)

    def column(t: Tensor) -> Tensor:
        return torch.func.jvp(fn, (x,), (t,))[1]

    return torch.func.vmap(column)(basis).movedim(0, -1)


@dataclass(frozen=True)
class FokkerPlanckTerms:
    """The model's pieces of the Fokker–Planck operator at points ``x`` (method.md §3).

    ``L_FP(p) = −Σⱼ ∂(fⱼ p)/∂xⱼ + Σⱼₖ ∂²(Dⱼₖ p)/∂xⱼ∂xₖ`` needs, at each point:

    Attributes:
        drift: ``f(x, u)`` ``[..., n]``.
        drift_divergence: ``div f = Σⱼ ∂fⱼ/∂xⱼ`` ``[...]``.
        diffusion: ``D(x) = ½ g Q gᵀ`` ``[..., n, n]``, or its diagonal ``[..., n]``
            when ``D`` is diagonal (a cheaper path in the FPKE residual).
        diffusion_divergence: ``aₖ = Σⱼ ∂Dⱼₖ/∂xⱼ`` ``[..., n]``.
        diffusion_second_divergence: ``Σⱼₖ ∂²Dⱼₖ/∂xⱼ∂xₖ`` ``[...]``.
    """

    drift: Tensor
    drift_divergence: Tensor
    diffusion: Tensor
    diffusion_divergence: Tensor
    diffusion_second_divergence: Tensor


@dataclass(frozen=True)
class FokkerPlanckMoments:
    """Gaussian expectations of the model's Fokker–Planck terms, for the closed-form ``E[ℓᵢ]`` (method.md §3b).

    Under ``x ~ N(m, S)``, for a model whose diffusion is a scalar field times a fixed
    matrix plus a constant, ``D(x) = φ(x) D₁ + D₀`` (``D₁``, ``D₀`` given by their
    diagonals when diagonal), and with ``v = f − 2a`` (``aₖ = Σⱼ ∂Dⱼₖ/∂xⱼ``):

    Attributes:
        scalar: ``E[div f − Σⱼₖ ∂²Dⱼₖ/∂xⱼ∂xₖ]`` ``[...]``.
        transport: ``E[v]`` ``[..., n]``; transport_jacobian: ``E[∂v/∂x]`` ``[..., n, n]``.
        field: ``E[φ]`` ``[...]``; field_gradient: ``E[∇φ]`` ``[..., n]``; field_hessian: ``E[∇²φ]`` ``[..., n, n]``.
        pattern: ``D₁`` ``[n]`` (diagonal) or ``[n, n]``; constant: ``D₀`` ``[n]`` or ``[n, n]``.
    """

    scalar: Tensor
    transport: Tensor
    transport_jacobian: Tensor
    field: Tensor
    field_gradient: Tensor
    field_hessian: Tensor
    pattern: Tensor
    constant: Tensor


class ContinuousModel(nn.Module):
    """Continuous-time stochastic model ``dx = f(x, u) dt + g(x) dβ``, ``E[dβdβᵀ] = Q dt``.

    Subclasses set :attr:`state_dim` and implement :meth:`drift`,
    :meth:`noise_gain` and :meth:`noise_psd`.  Tensors that parametrise the
    model should be registered as buffers so ``.to(device)`` moves them.  A model
    driven by an input declares its size in :attr:`input_dim`; then
    :meth:`check_input` (called by the filters and by the model itself) refuses a
    missing input or one whose last dimension differs, instead of broadcasting it.
    """

    state_dim: int

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        record_derivations(cls)  # closed forms and kernels hold only for the physics they were derived from

    #: Size ``m`` of the input ``u [..., m]``; ``None``: not declared (no input, or one the model checks itself).
    input_dim: int | None = None
    #: What the input is, for error messages (e.g. ``"the gyro reading ω̃, rad/s"``), or ``None``.
    input_description: str | None = None

    def check_input(self, u: Tensor | None) -> None:
        """Raise ``ValueError`` unless ``u`` fits :attr:`input_dim`: ``u [..., m]`` with ``m = input_dim``.

        A shape check only (no data is read): cheap enough for every evaluation of the drift.
        Nothing is checked when :attr:`input_dim` is ``None``.
        """
        m = self.input_dim
        if m is None:
            return
        what = f"{type(self).__name__}'s input" + (f": {self.input_description}" if self.input_description else "")
        if u is None:
            desc = f" ({self.input_description})" if self.input_description else ""
            raise ValueError(f"{type(self).__name__} needs an input u [..., {m}]{desc}, got None")
        if u.dim() < 1 or u.shape[-1] != m:
            raise ValueError(
                f"u must have shape [..., {m}] ({what}), got {tuple(u.shape)}; "
                "it is not broadcast over the input's entries"
            )

    def drift(self, x: Tensor, u: Tensor | None) -> Tensor:
        """Drift ``f(x, u)``: ``x [..., n]``, ``u [..., m]`` (or None) → ``[..., n]``."""
        raise NotImplementedError(f"{type(self).__name__} must implement drift(x, u): [..., n] → [..., n]")

    def noise_gain(self, x: Tensor) -> Tensor:
        """Noise gain ``g(x)``: ``[..., n]`` → ``[..., n, q]``."""
        raise NotImplementedError(f"{type(self).__name__} must implement noise_gain(x): [..., n] → [..., n, q]")

    def noise_psd(self) -> Tensor:
        """Spectral density ``Q`` of the driving white noise, ``[q, q]``."""
        raise NotImplementedError(f"{type(self).__name__} must implement noise_psd(): the [q, q] spectral density Q")

    def check_contract(self, x: Tensor, u: Tensor | None) -> None:
        """Refuse (``ValueError`` naming the method, the shape expected and the one returned) a model whose
        :meth:`drift`, :meth:`noise_gain` or :meth:`noise_psd` breaks the shape contract at ``x [..., n]`` (also at
        :func:`~.contract.elementwise_probe` states), or whose ``Q`` is not a finite symmetric positive semidefinite
        matrix (a negative density was accepted and integrated): :func:`~.contract.check_model_contract`.  The
        filters call it once, at their first ``predict`` with this model, before anything changes; a subclass may
        extend it."""
        check_model_contract(self, x, u)

    # ----------------------------------------------------------- derived terms
    def drift_jacobian(self, x: Tensor, u: Tensor | None) -> Tensor:
        """``A = ∂f/∂x`` at ``x``, ``[..., n, n]`` (default: ``torch.func``)."""
        return batched_jacobian(lambda z: self.drift(z, u), x)

    def drift_divergence(self, x: Tensor, u: Tensor | None) -> Tensor:
        """``∇·f = tr ∂f/∂x`` at ``x``, ``[...]`` (1/s; default: the trace of :meth:`drift_jacobian`)."""
        return self.drift_jacobian(x, u).diagonal(dim1=-2, dim2=-1).sum(-1)

    def process_noise(self, x: Tensor) -> Tensor:
        """``g(x) Q g(x)ᵀ``, the Riccati equation's source term, ``[..., n, n]``."""
        g = self.noise_gain(x)
        return g @ self.noise_psd().to(g) @ g.transpose(-1, -2)

    def diffusion(self, x: Tensor) -> Tensor:
        """Diffusion matrix of the Fokker–Planck operator, ``D(x) = ½ g Q gᵀ``, ``[..., n, n]``."""
        return 0.5 * self.process_noise(x)

    def fokker_planck_terms(self, x: Tensor, u: Tensor | None) -> FokkerPlanckTerms:
        """Drift, diffusion and their derivatives at ``x`` (default: ``torch.func``).

        ``div f`` is :meth:`drift_divergence`; ``aₖ = Σⱼ ∂Dⱼₖ/∂xⱼ`` and
        ``Σⱼₖ ∂²Dⱼₖ/∂xⱼ∂xₖ = div a`` by nested forward-mode differentiation of
        :meth:`diffusion`.  Subclasses with closed forms override this.
        """
        n = x.shape[-1]

        def divergence_of_diffusion(z: Tensor) -> Tensor:
            J = batched_jacobian(lambda v: self.diffusion(v).flatten(-2), z)  # [..., n*n, n]
            J = J.unflatten(-2, (n, n))  # [..., j, k, l] = ∂D_jk/∂x_l
            return J.diagonal(dim1=-3, dim2=-1).sum(-1)  # Σ_j ∂D_jk/∂x_j

        a = divergence_of_diffusion(x)
        c = batched_jacobian(divergence_of_diffusion, x).diagonal(dim1=-2, dim2=-1).sum(-1)
        return FokkerPlanckTerms(
            drift=self.drift(x, u),
            drift_divergence=self.drift_divergence(x, u),
            diffusion=self.diffusion(x),
            diffusion_divergence=a,
            diffusion_second_divergence=c,
        )

    def fpke_quadrature_points(self, factors: int = 2) -> tuple[int, ...] | None:
        """Gauss–Hermite points per axis that integrate a product of ``factors`` residual
        factors exactly, if known: ``ℓⱼ`` (``factors = 1``, the Galerkin weight update,
        method.md §3b) or ``ℓᵢℓⱼ`` (``factors = 2``, the paper's matrix ``L``, §3).

        A polynomial ``ℓ`` of degree ``d`` in a coordinate needs ``⌈(factors·d + 1)/2⌉``
        points on that axis (``m`` points integrate degree ``2m − 1`` exactly).
        ``None`` (default) lets the adaptive filter choose a generic rule.
        """
        return None

    def fpke_polynomial_space(self) -> tuple[tuple[tuple[int, ...], int], ...] | None:
        """The polynomial space of ``ℓᵢ(m + Lξ)`` in ``ξ`` (``L`` lower-triangular), if ``ℓ`` is polynomial:
        ``((axes, total degree), ...)``, one group per block of coordinates, ``ℓ`` lying in the
        tensor product of the groups' total-degree spaces.  The paper's matrix ``E[ℓᵢℓⱼ]`` is
        then computed exactly by interpolation at a unisolvent node set
        (:func:`agsf_torch.quadrature.product_rule`).  ``None`` (default): a quadrature rule.
        """
        return None

    def fpke_pair_products(self, u: Tensor | None, pairs: Any, *, compile: bool = False) -> Tensor | None:
        """``E_{N(m_ij, S_ij)}[ℓᵢℓⱼ]`` ``[..., P]`` for every pair of components by a route of the model's own
        (``pairs``: :class:`~agsf_torch.fpke.ProductGaussians`, precisions formed), exact like the interpolatory
        rule of :meth:`fpke_polynomial_space` and cheaper; ``None`` (default): that rule is used.  The paper's
        matrix ``L`` is computed from it (:func:`~agsf_torch.fpke.fpke_matrix`); ``compile`` asks for a
        route compiled ahead of time where the model has one."""
        return None

    def fused_penalty_pairs(
        self, means: Tensor, covs: Tensor, u: Tensor | None, *, compile: bool = False
    ) -> tuple[Tensor, Tensor] | None:
        """The pair products of :meth:`fpke_pair_products` from the components alone, by a fused kernel
        (:mod:`agsf_torch.fused`) that also forms their product Gaussians and moment rates, if the model has
        one: ``(log z_ij, E_{N(m_ij, S_ij)}[ℓᵢℓⱼ])``, each ``[T, P]`` for the ``P = N(N+1)/2`` pairs ``i ≤ j``
        (``torch.triu_indices`` order) of ``T`` mixtures given as ``means [T, N, n]``, ``covs [T, N, n, n]`` and
        ``u [T, m]``; ``None`` (default, or a batch the model declines): the route of :func:`~agsf_torch.fpke.fpke_matrix`."""
        return None

    def fokker_planck_moments(self, mean: Tensor, cov: Tensor, u: Tensor | None) -> FokkerPlanckMoments | None:
        """Closed-form Gaussian expectations of the Fokker–Planck terms under ``N(mean, cov)``
        (``mean [..., n]``, ``cov [..., n, n]``, ``u [..., m]``), or ``None`` (default): then
        the Galerkin weight update integrates ``ℓⱼ`` by quadrature.  A model with
        polynomial ``f`` and ``D`` of the form of :class:`FokkerPlanckMoments` can give
        them exactly, which makes the Galerkin update cost ``O(n³)`` per pair of components.
        """
        return None

    def check_step(self, mean: Tensor, u: Tensor | None, step: float) -> None:
        """Refuse (``ValueError`` naming the cause) a propagation interval of ``step`` seconds that the moment
        equations cannot follow at ``mean [..., N, n]`` and ``u [..., m]``; by default every interval is
        accepted.  Called by the filters before anything changes."""

    def fused_propagation(
        self, mean: Tensor, cov: Tensor, u: Tensor | None, dt: float, substeps: int = 1, *, compile: bool = False
    ) -> tuple[Tensor, Tensor, Tensor] | None:
        """The moment propagation of :func:`agsf_torch.propagation.propagate_moments` by a fused kernel
        (:mod:`agsf_torch.fused`), if the model has one: ``(mean [..., n], cov [..., n, n],
        positive_definite [...] bool)`` (the kernel's own Cholesky pivots); ``None`` (default): the
        filters take the generic path.  Arguments as :func:`~agsf_torch.propagation.propagate_moments`;
        ``compile`` runs the kernel compiled ahead of time (:mod:`agsf_torch.fused.lanes`)."""
        return None

    def fused_galerkin_pairs(
        self, means: Tensor, covs: Tensor, u: Tensor | None, *, compile: bool = False
    ) -> tuple[Tensor, Tensor, Tensor] | None:
        """The Galerkin pair integrals of :func:`agsf_torch.fpke.galerkin_matrices` (closed-form route, the
        components' moment rates included) by a fused kernel (:mod:`agsf_torch.fused`), if the model has one:
        ``(log z_ij, E[ℓᵢ], E[ℓⱼ])``, each ``[T, P]`` for the ``P = N(N+1)/2`` pairs ``i ≤ j``
        (``torch.triu_indices`` order) of ``T`` mixtures given as ``means [T, N, n]``, ``covs [T, N, n, n]``
        and ``u [T, m]``; ``None`` (default): the generic path."""
        return None

    # --------------------------------------------------------- state manifold
    def canonicalize(self, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
        """Re-express Gaussian components in a canonical chart (identity by default).

        Args:
            mean: ``[..., n]``; cov: ``[..., n, n]``.
        """
        return mean, cov

    def align(self, mean: Tensor, cov: Tensor, reference: Tensor) -> tuple[Tensor, Tensor]:
        """Re-express components in the chart of ``reference`` before they are combined
        (identity by default).

        Args:
            mean: ``[..., N, n]``; cov: ``[..., N, n, n]``; reference: broadcastable to ``mean``.
        """
        return mean, cov

    def state_error(self, x_est: Tensor, x_true: Tensor) -> Tensor:
        """Estimation error ``x_est − x_true`` expressed in the estimate's chart, ``[..., n]``."""
        return x_est - x_true


class MeasurementModel(nn.Module):
    """Measurement ``y = h(x) + v``, ``v ~ N(0, R)``.

    Subclasses implement :meth:`predict` and :meth:`noise_cov`; :meth:`jacobian`
    defaults to ``torch.func``.  :meth:`mask` marks which of the ``d``
    measurement entries are valid (``None``: all); invalid entries contribute
    nothing to an update.  :attr:`block_size` is the number of entries of one
    independent measurement (e.g. 3 for a star vector): innovation gating
    (:mod:`agsf_torch.gating`) accepts or rejects whole blocks; ``None`` (default)
    gates the vector as one block.
    """

    block_size: int | None = None

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        record_derivations(cls)  # closed forms and kernels hold only for the physics they were derived from

    def state_entries(self) -> tuple[int, ...] | None:
        """The state entries ``h`` reads, or ``None`` (default): all of them.  The second-order update then takes
        the measurement's second differences over the marginal of these entries only
        (:func:`agsf_torch.update.measurement_second_differences`), which is exact: ``h`` does not vary along the
        others.  A model that declares them derives it from its ``predict`` (``derived_from``), so a subclass that
        reads more gets ``None``."""
        return None

    def predict(self, x: Tensor) -> Tensor:
        """Predicted measurement ``h(x)``: ``[..., n]`` → ``[..., d]``."""
        raise NotImplementedError(f"{type(self).__name__} must implement predict(x): [..., n] → [..., d]")

    def noise_cov(self) -> Tensor:
        """Measurement noise covariance ``R``, ``[d, d]`` or ``[..., d, d]``."""
        raise NotImplementedError(f"{type(self).__name__} must implement noise_cov(): R, [d, d] or [..., d, d]")

    def jacobian(self, x: Tensor) -> Tensor:
        """``H = ∂h/∂x`` at ``x``, ``[..., d, n]`` (default: ``torch.func``)."""
        return batched_jacobian(self.predict, x)

    def mask(self) -> Tensor | None:
        """Validity of each measurement entry, ``[..., d]`` bool, or ``None`` (all valid)."""
        return None

    def fused_update(
        self,
        log_weights: Tensor,
        means: Tensor,
        covs: Tensor,
        y: Tensor,
        iterations: int = 1,
        *,
        mask: Tensor | None = None,
        mixture_nis: bool = True,
        compile: bool = False,
    ):
        """The update of :func:`agsf_torch.update.kalman_update` (same arguments and result) by a fused
        kernel (:mod:`agsf_torch.fused`), if the measurement has one for this state; ``None`` (default):
        the filters take the generic path.  ``compile`` runs the kernel compiled ahead of time (:mod:`agsf_torch.fused.lanes`)."""
        return None

    def data_log_likelihood(
        self, log_weights: Tensor, nu: Tensor, HL: Tensor, y: Tensor, valid: Tensor
    ) -> Tensor | None:
        """``log Σᵢ wᵢ p(y | component i)`` over the degrees of freedom the data has, where they are fewer than the
        ``d`` entries the update's noise model spreads its noise over (a unit vector: 2 of its 3); ``None``
        (default): the update's own ``log Σᵢ wᵢβᵢ`` is the data's.

        Args:
            log_weights: ``[..., N]``; nu: the innovations at the last linearisation ``[..., N, d]``; HL: ``H L``
                there (``L`` a factor of the prior covariance, ``P = LLᵀ``) ``[..., N, d, k]``; y: ``[..., d]``;
                valid: entry validity ``[..., N, d]`` (1 or 0).

        Returns:
            ``[...]``, or ``None``.
        """
        return None

    def check_measurement(self, y: Tensor) -> Tensor:
        """Validate a measurement vector ``y [..., d]`` against the model before an update; return
        the ``y`` to use.

        Called by the filters before anything changes.  The default checks that :meth:`mask`,
        if any, has ``d`` entries, that the mask and the noise are one per trajectory of ``y`` or one for all
        (:func:`~.contract.check_measurement_batch`), and that :meth:`noise_cov` is a finite symmetric ``[d, d]`` or
        ``[..., d, d]`` positive semidefinite matrix (:func:`~.contract.check_noise_cov`; a negative variance was reported as a
        component covariance losing definiteness, a wrong size as a raw solver error); subclasses add their
        own checks (the size ``d``, unit vectors…) and may return a corrected ``y`` (e.g. normalised).

        Raises:
            ValueError: naming ``y``, the mask or ``noise_cov``, and the shapes or values.
        """
        mask = self.mask()
        if mask is not None and (mask.dim() < 1 or mask.shape[-1] != y.shape[-1]):
            raise ValueError(
                f"the measurement mask has shape {tuple(mask.shape)}, y has {tuple(y.shape)}: their last dims differ"
            )
        name, d, R = type(self).__name__, y.shape[-1] if y.dim() else 0, self.noise_cov()
        if not isinstance(R, Tensor) or R.dim() < 2 or R.shape[-2:] != (d, d):
            got = tuple(R.shape) if isinstance(R, Tensor) else type(R).__name__
            raise ValueError(f"{name}.noise_cov must be [d, d] or [..., d, d] with d = {d} (y's entries), got {got}")
        if mask is not None:
            check_measurement_batch("mask", mask.shape[:-1], y)
        check_measurement_batch(f"{name}.noise_cov", R.shape[:-2], y)
        check_noise_cov(f"{name}.noise_cov", R)
        return y
