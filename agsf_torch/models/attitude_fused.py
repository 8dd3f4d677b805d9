"""The attitude model's fused paths (:mod:`agsf_torch.fused`): its propagation, its Galerkin pairs and its penalty
pairs on lanes, the hooks of :class:`~agsf_torch.models.base.ContinuousModel` that the filters take where a model
has them.  :class:`FusedAttitudePaths` is a mixin of :class:`~agsf_torch.models.attitude.AttitudeModel`: its
kernels and that class's methods are built from the same functions (:mod:`agsf_torch.attitude.physics`), so each hook is marked as derived from them
(:func:`~agsf_torch.models.derived.derived_from`): on a subclass that changes the dynamics or the noise
without overriding the hook, the hook gives way to the generic path.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..shapes import broadcast_shapes
from .base import ContinuousModel
from .derived import derived_from

__all__ = ["ATTITUDE_DYNAMICS", "FusedAttitudePaths"]

#: The methods of :class:`~agsf_torch.models.attitude.AttitudeModel` that state its dynamics: its closed forms
#: and kernels are derived from these.
ATTITUDE_DYNAMICS = ("drift", "noise_gain", "noise_psd", "_gyro_rate")
#: What the kernels evaluate besides the dynamics: the closed forms they were checked against.
_KERNEL_PHYSICS = (
    *ATTITUDE_DYNAMICS,
    "drift_jacobian",
    "process_noise",
    "fokker_planck_terms",
    "fokker_planck_moments",
)


def _compiled(compile: bool, *tensors: Tensor) -> bool:
    """``compile``, unless one of ``tensors`` asks for gradients: a compiled kernel records none, the eager one does."""
    return compile and not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors))


class FusedAttitudePaths:
    """The fused hooks of the attitude model (module docstring); they read its ``estimate_bias``, ``bias``,
    ``sigma_v``, ``sigma_u``, ``state_dim`` and ``check_input``."""

    #: Pairs from which the eager lanes route (:mod:`agsf_torch.fused.pair_products`) beats the batched one, by
    #: state dimension (the crossover ``agsf bench`` measures).
    EAGER_MIN_PAIRS = {3: 100, 6: 400}

    @derived_from(*_KERNEL_PHYSICS, generic=ContinuousModel.fpke_pair_products)
    def fpke_pair_products(self, u: Tensor | None, pairs, *, compile: bool = False) -> Tensor | None:
        """``E[ℓᵢℓⱼ]`` of every pair at 84 MRP nodes, the bias block (6 states) integrated in closed form (``ℓ`` is
        quadratic in it), a tenth of the 840 nodes of :meth:`fpke_polynomial_space`: on lanes
        (:mod:`agsf_torch.fused.pair_products`, compiled ahead of time if ``compile``) from
        :attr:`EAGER_MIN_PAIRS` pairs on or when compiled; below, batched (:mod:`.attitude_bias_block`),
        or ``None`` for the 3-state model (its 84-node interpolatory rule is then the generic route)."""
        from ..fused.pair_products import attitude_pair_products as on_lanes

        self._refuse_per_trajectory("the FPKE pair products")
        if u is not None:
            self.check_input(u)
            count = math.prod(pairs.mean.shape[:-1])
            if compile or count >= self.EAGER_MIN_PAIRS[self.state_dim]:
                inputs = (u, pairs.mean, pairs.chol, pairs.first.means, pairs.first.cov_rates)
                return on_lanes(
                    pairs, self._gyro_rate(u), self.sigma_v, self.sigma_u, compile=_compiled(compile, *inputs)
                )
        if not self.estimate_bias:
            return None
        from .attitude_bias_block import attitude_pair_products

        return attitude_pair_products(self, u, pairs)

    @derived_from(*_KERNEL_PHYSICS, generic=ContinuousModel.fused_penalty_pairs)
    def fused_penalty_pairs(
        self, means: Tensor, covs: Tensor, u: Tensor | None, *, compile: bool = False
    ) -> tuple[Tensor, Tensor] | None:
        """``(log z_ij, E[ℓᵢℓⱼ])`` ``[T, P]`` with the pairs' product Gaussians and the components' moment rates
        formed on lanes too (:func:`~agsf_torch.fused.pair_products.attitude_penalty_pairs`), when compiled and
        nothing asks for gradients (eagerly its kernel of product Gaussians is slower than the batched LAPACK
        route below ~1,500 pairs: :meth:`fpke_pair_products` then applies); ``None`` otherwise, or without a gyro
        rate.  Like :meth:`fpke_pair_products`, it evaluates this class's own equations: a subclass that changes
        the dynamics or the noise must override both."""
        from ..fused.pair_products import attitude_penalty_pairs

        if u is None or not compile:
            return None
        self.check_input(u)
        self._refuse_per_trajectory("the FPKE penalty pairs")
        if not _compiled(compile, u, means, covs, self.sigma_v, self.sigma_u, self.bias):
            return None  # the compiled kernel records no gradients: the eager routes do
        T = means.shape[0]
        rate = self._gyro_rate(u)
        return attitude_penalty_pairs(means, covs, rate.expand(T, 3), self.sigma_v, self.sigma_u, compile=True)

    @derived_from(*_KERNEL_PHYSICS, generic=ContinuousModel.fused_propagation)
    def fused_propagation(
        self, mean: Tensor, cov: Tensor, u: Tensor, dt: float, substeps: int = 1, *, compile: bool = False
    ) -> tuple[Tensor, Tensor, Tensor]:
        """RK4 of ``(μ, Φ, S)`` and the congruence on lanes, unrolled with the model's structural zeros
        (:mod:`agsf_torch.fused.propagation`): the arithmetic of :func:`~agsf_torch.propagation.propagate_moments`
        in one pass over memory.  Returns ``(mean, cov, positive_definite [...] bool)``, or ``None`` (the
        generic path) for an eager call on fewer lanes than it pays for (:func:`~agsf_torch.fused.lanes.worth_fusing`)
        and for noise per trajectory (the kernel takes one ``σ_v``, ``σ_u`` and bias for all lanes)."""
        from ..fused.lanes import run_in_chunks, worth_fusing
        from ..fused.propagation import propagation_kernel

        self.check_input(u)
        n = self.state_dim
        lead = broadcast_shapes(mean.shape[:-1], cov.shape[:-2], u.shape[:-1])
        count = math.prod(lead)
        if self.per_trajectory_noise or not worth_fusing(count, compile):
            return None
        rate = self._gyro_rate(u)
        inputs = (
            mean.expand(*lead, n).reshape(count, n),
            cov.expand(*lead, n, n).reshape(count, n, n),
            rate.expand(*lead, 3).reshape(count, 3),
        )
        like = inputs[0]
        shared = (
            torch.as_tensor(dt, dtype=like.dtype, device=like.device),
            (self.sigma_v**2).to(like),
            (self.sigma_u**2).to(like),
        )
        m, P, ok = run_in_chunks(
            propagation_kernel(substeps),
            inputs,
            shared=shared,
            compile=_compiled(compile, *inputs, *shared),
            key=("attitude", n, substeps),
        )
        return m.reshape(*lead, n), P.reshape(*lead, n, n), ok.reshape(lead)

    @derived_from(*_KERNEL_PHYSICS, generic=ContinuousModel.fused_galerkin_pairs)
    def fused_galerkin_pairs(
        self, means: Tensor, covs: Tensor, u: Tensor, *, compile: bool = False
    ) -> tuple[Tensor, Tensor, Tensor] | None:
        """``(log z_ij, E[ℓᵢ], E[ℓⱼ])`` ``[T, P]`` of the Galerkin update's pairs on lanes
        (:mod:`agsf_torch.fused.galerkin`): the arithmetic of :func:`~agsf_torch.propagation.moment_derivatives`
        and of the closed-form :func:`~agsf_torch.fpke.galerkin_matrices` route (product Gaussians,
        :meth:`fokker_planck_moments`, ``E[ℓ]`` of both sides) in one pass over memory; ``None`` (the generic
        path) for an eager call on fewer pairs than it pays for (:func:`~agsf_torch.fused.lanes.worth_fusing`)."""
        from ..fused.galerkin import attitude_pair_kernel
        from ..fused.lanes import DEFAULT_CHUNK, run_in_chunks, worth_fusing

        self.check_input(u)
        self._refuse_per_trajectory("the Galerkin pairs")
        T, N = means.shape[:2]
        pairs = N * (N + 1) // 2
        if not worth_fusing(T * pairs, compile):
            return None
        rate = self._gyro_rate(u).expand(T, 3)
        like = means
        shared = ((self.sigma_v**2 / 32.0).to(like), (self.sigma_v**2).to(like), (self.sigma_u**2).to(like))
        tensors = (means, covs, rate)
        return run_in_chunks(
            attitude_pair_kernel,
            tensors,
            shared=shared,
            compile=_compiled(compile, *tensors, *shared),
            chunk=max(1, DEFAULT_CHUNK // pairs),
            key=("attitude-galerkin", self.state_dim),
        )
