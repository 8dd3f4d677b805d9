"""The weight-update matrices: the paper's ``L_ij = ∫LᵢLⱼ dx`` and the Galerkin ``K_ij = ∫pᵢLⱼ dx``.

``pᵢ pⱼ = z_ij N(x; m_ij, S_ij)`` (:mod:`.pairs`), so ``L_ij = z_ij E_{N(m_ij, S_ij)}[ℓᵢℓⱼ]``
and ``K_ij = z_ij E[ℓⱼ]``, each evaluated over the ``N(N+1)/2`` unordered pairs.
"""

from __future__ import annotations

import copy
import functools
import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from ..chunks import check_chunk_size
from ..compiled_kernels import compiled_function
from ..models.base import ContinuousModel
from ..quadrature import ProductRule
from ..shapes import broadcast_shapes
from .moments import residual_mean
from .pairs import ProductGaussians, product_gaussians
from .residual import ComponentRates, residual_factor

__all__ = [
    "FPKEMatrix",
    "fpke_matrix",
    "fused_fpke_matrix",
    "GalerkinMatrices",
    "galerkin_matrices",
    "fused_galerkin_matrices",
]


def _product_chunk(
    model: ContinuousModel, m: Tensor, LS: Tensor, xi: Tensor, u: Tensor | None, ri: ComponentRates, rj: ComponentRates
) -> tuple[Tensor, Tensor]:
    """``(ℓᵢ, ℓⱼ)`` at the nodes ``x_k = m + LS ξ_k`` of the pairs, ``[..., Pc, K]`` each."""
    x = m.unsqueeze(-2) + xi @ LS.transpose(-1, -2)  # [..., Pc, K, n]
    terms = model.fokker_planck_terms(x, u)
    return residual_factor(terms, x, ri), residual_factor(terms, x, rj)


def _pair_chunk(
    model: ContinuousModel,
    m: Tensor,
    LS: Tensor,
    xi: Tensor,
    wq: Tensor,
    u: Tensor | None,
    ri: ComponentRates,
    rj: ComponentRates,
) -> Tensor:
    """``Σ_k w_k ℓᵢ(x_k) ℓⱼ(x_k)`` over one chunk of nodes, ``[..., Pc]``."""
    vi, vj = _product_chunk(model, m, LS, xi, u, ri, rj)
    return (vi * vj * wq).sum(-1)


def _galerkin_chunk(
    model: ContinuousModel,
    m: Tensor,
    LS: Tensor,
    xi: Tensor,
    wq: Tensor,
    u: Tensor | None,
    ri: ComponentRates,
    rj: ComponentRates,
) -> Tensor:
    """``(Σ_k w_k ℓᵢ(x_k), Σ_k w_k ℓⱼ(x_k))`` over one chunk of nodes, stacked ``[2, ..., Pc]``."""
    vi, vj = _product_chunk(model, m, LS, xi, u, ri, rj)
    return torch.stack(((vi * wq).sum(-1), (vj * wq).sum(-1)))


_CHUNKS = {"pair": _pair_chunk, "galerkin": _galerkin_chunk, "product": _product_chunk}
#: Chunk kernels of a model whose export or compilation failed (kernel name, model class): run eagerly.
_FAILED: set[tuple[str, type]] = set()


def _kernel(name: str, compile: bool):
    """The chunk kernel ``name`` (called as ``kernel(model, *args)``), eager or compiled ahead of time for each
    model and shape (:func:`_compiled_chunk`)."""
    fn = _CHUNKS[name]
    return functools.partial(_compiled_chunk, name) if compile else fn


def _model_tensors(model: ContinuousModel) -> dict[str, Tensor]:
    """A model's own tensors (its buffers and parameters, or plain tensor attributes): inputs of its compiled kernels,
    not constants baked into them."""
    if isinstance(model, torch.nn.Module):
        found = {**dict(model.named_buffers(recurse=False)), **dict(model.named_parameters(recurse=False))}
    else:
        found = {key: value for key, value in vars(model).items() if torch.is_tensor(value)}
    return {key: found[key] for key in sorted(found) if found[key] is not None}


def _with_tensors(model: ContinuousModel, tensors: dict[str, Tensor]) -> ContinuousModel:
    """A shallow copy of ``model`` whose own tensors (:func:`_model_tensors`) are ``tensors``."""
    traced = copy.copy(model)
    if isinstance(model, torch.nn.Module):
        traced._buffers, traced._parameters = dict(model._buffers), dict(model._parameters)
        for key, value in tensors.items():
            (traced._parameters if key in model._parameters else traced._buffers)[key] = value
    else:
        for key, value in tensors.items():
            object.__setattr__(traced, key, value)
    return traced


def _fingerprint(model: ContinuousModel) -> tuple:
    """What a model's compiled chunk kernels depend on besides their inputs: its class and its attributes other
    than tensors (its tensors, inputs of the kernels, by dtype and shape)."""
    own = _model_tensors(model)
    parts = [(key, (value.dtype, tuple(value.shape))) for key, value in own.items()]
    for key, value in sorted(vars(model).items()):
        if key not in ("_buffers", "_parameters") and not torch.is_tensor(value):
            parts.append((key, repr(value)))
    return (type(model), tuple(parts))


def _compiled_chunk(name: str, model: ContinuousModel, *args):
    """``_CHUNKS[name](model, *args)`` compiled ahead of time (:func:`agsf_torch.compiled_kernels.compiled_function`:
    keyed by the exported graph, exported once per process, model and shape).  A model whose kernel cannot be
    exported or compiled (data-dependent control flow, say) runs it eagerly after one warning; so does a call that
    needs gradients (a compiled kernel has no backward)."""
    fn = _CHUNKS[name]
    flat: list[Tensor] = []
    layout: list = []  # per argument: None, "tensor" or the ComponentRates' field count
    for arg in args:
        if arg is None:
            layout.append(None)
        elif isinstance(arg, ComponentRates):
            fields = (arg.means, arg.chol, arg.mean_rates, arg.cov_rates, arg.precision, arg.covs)
            flat.extend(t.contiguous() for t in fields)
            layout.append(len(fields))
        else:
            flat.append(arg.contiguous())
            layout.append("tensor")
    own = _model_tensors(model)
    names = list(own)
    flat.extend(own.values())
    if (name, type(model)) in _FAILED or (torch.is_grad_enabled() and any(t.requires_grad for t in flat)):
        return fn(model, *args)

    def kernel(*tensors: Tensor) -> tuple[Tensor, ...]:
        it = iter(tensors)
        traced = _with_tensors(model, dict(zip(names, tensors[len(tensors) - len(names) :])))
        rebuilt = []
        for kind in layout:
            if kind is None:
                rebuilt.append(None)
            elif kind == "tensor":
                rebuilt.append(next(it))
            else:
                means, chol, mean_rates, cov_rates, precision, covs = (next(it) for _ in range(kind))
                rebuilt.append(ComponentRates(means, chol, mean_rates, cov_rates, precision, covs))
        out = fn(traced, *rebuilt)
        return out if isinstance(out, tuple) else (out,)

    try:
        compiled = compiled_function(f"fpke_{name}", kernel, flat, (_fingerprint(model), tuple(layout)))
        out = compiled(*flat)
    except Exception as exc:  # noqa: BLE001 - any exporter, compiler or runtime failure: the eager kernel
        _FAILED.add((name, type(model)))
        why = " ".join(str(exc).split())
        warnings.warn(
            f"the FPKE kernel {name!r} of {type(model).__name__} could not be compiled ({type(exc).__name__}: "
            f"{why[:300]}); running it eagerly",
            RuntimeWarning,
            stacklevel=3,
        )
        return fn(model, *args)
    return out if name == "product" else out[0]


def _padded_nodes(xi: Tensor, wq: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """A chunk of nodes ``xi [k, n]`` and weights ``wq [k]`` padded to ``size`` nodes of weight zero (at the
    origin, where every integrand is finite), so that a compiled kernel sees one shape."""
    k = xi.shape[0]
    if k == size:
        return xi, wq
    return torch.cat((xi, xi.new_zeros(size - k, xi.shape[1]))), torch.cat((wq, wq.new_zeros(size - k)))


def _pairs(rates: ComponentRates) -> tuple[ProductGaussians, Tensor]:
    """The prologue of every matrix: the product Gaussians and ``log max z_ij`` ``[...]``."""
    prod = product_gaussians(rates)
    return prod, prod.log_z.amax(-1)


def _integrate_pairs(
    kernel,
    model: ContinuousModel,
    u: Tensor | None,
    rates: ComponentRates,
    nodes: Tensor,
    node_weights: Tensor,
    chunk_size: int | None,
    max_chunk_elements: int,
    out_shape: tuple[int, ...],
) -> tuple[ProductGaussians, Tensor, Tensor]:
    """The pairs' product Gaussians, ``log max z_ij`` ``[...]`` and ``kernel`` accumulated over the
    rule's nodes in chunks that bound memory."""
    prod, log_scale = _pairs(rates)
    m = prod.mean
    n = m.shape[-1]
    if u is not None:
        u = u[..., None, None, :]
    if chunk_size is None:
        per_node = max(1, int(m[..., 0].numel()) * n * n)
        chunk_size = max(1, max_chunk_elements // per_node)
    acc = torch.zeros(*out_shape, *m.shape[:-1], dtype=m.dtype, device=m.device)
    compiled = isinstance(kernel, functools.partial)
    for start in range(0, nodes.shape[0], chunk_size):
        xi = nodes[start : start + chunk_size].to(m)
        wq = node_weights[start : start + chunk_size].to(m)
        if compiled:  # one shape for every chunk: the last padded with nodes of weight zero
            xi, wq = _padded_nodes(xi, wq, min(chunk_size, nodes.shape[0]))
        acc = acc + kernel(model, m, prod.chol, xi, wq, u, prod.first, prod.second)
    return prod, log_scale, acc


def _product_rule_pairs(
    kernel,
    model: ContinuousModel,
    u: Tensor | None,
    prod: ProductGaussians,
    rule: ProductRule,
    chunk_size: int | None,
    max_chunk_elements: int,
) -> Tensor:
    """``E[ℓᵢℓⱼ] = ĉᵢ·ĉⱼ`` for every pair ``[..., P]`` with a :class:`ProductRule`, in chunks of
    pairs (``chunk_size`` pairs, or as many as keep ``[pairs, K, n, n]`` under ``max_chunk_elements``)."""
    lead = prod.mean.shape[:-1]
    n = prod.mean.shape[-1]

    def flat(t: Tensor, event: int) -> Tensor:
        tail = t.shape[t.dim() - event :]
        return t.expand(*lead, *tail).reshape(-1, *tail)

    m, LS = flat(prod.mean, 1), flat(prod.chol, 2)
    ri, rj = (r.map(lambda t, dim: flat(t, -dim - 1)) for r in (prod.first, prod.second))
    uf = None if u is None else flat(u.unsqueeze(-2), 1).unsqueeze(-2)  # [Q, 1, m]
    xi = rule.nodes.to(m)
    K = xi.shape[0]
    if chunk_size is None:
        chunk_size = max(1, max_chunk_elements // (K * n * n))
    out = []
    P = m.shape[0]
    # compiled: one shape for every chunk, the last padded with copies of its first pair (their values dropped)
    rows = (
        (lambda a: _padded_rows(a, min(chunk_size, P), P, m.device)) if isinstance(kernel, functools.partial) else None
    )
    for a in range(0, P, chunk_size):
        sl = slice(a, a + chunk_size) if rows is None else rows(a)
        vi, vj = kernel(
            model,
            m[sl],
            LS[sl],
            xi,
            None if uf is None else uf[sl],
            ri.map(lambda t, dim: t[sl]),
            rj.map(lambda t, dim: t[sl]),
        )
        vi, vj = vi[: min(chunk_size, P - a)], vj[: min(chunk_size, P - a)]
        c = rule.coefficients(torch.stack((vi, vj)))
        out.append((c[0] * c[1]).sum(-1))
    if not out:  # no pairs: an empty batch
        return m.new_zeros(lead)
    return torch.cat(out).reshape(lead)


def _padded_rows(a: int, size: int, total: int, device: torch.device) -> Tensor:
    """The rows ``a, a+1, …`` of a chunk of ``size`` rows out of ``total``: past the end, row ``a`` again."""
    index = torch.arange(a, a + size, device=device)
    return torch.where(index < total, index, a)


@dataclass(frozen=True)
class FPKEMatrix:
    """``L = exp(log_scale) · L̃``, with ``L̃ = z̃_ij E[ℓᵢℓⱼ]`` kept in a safe range.

    Attributes:
        scaled: ``L̃`` ``[..., N, N]`` symmetric PSD.
        log_scale: ``[...]``, the largest ``log z_ij`` of each mixture.
    """

    scaled: Tensor
    log_scale: Tensor

    def full(self) -> Tensor:
        """The unscaled ``L`` (may overflow to inf for extremely narrow components)."""
        return self.scaled * torch.exp(self.log_scale)[..., None, None]

    def error(self, weights: Tensor) -> Tensor:
        """Unscaled FPKE error ``wᵀ L w`` ``[...]``."""
        q = (weights.unsqueeze(-2) @ self.scaled @ weights.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        return q * torch.exp(self.log_scale)


def _symmetric_from_pairs(vals: Tensor, index: Tensor, N: int) -> Tensor:
    out = torch.zeros(*vals.shape[:-1], N, N, dtype=vals.dtype, device=vals.device)
    out[..., index[0], index[1]] = vals
    out[..., index[1], index[0]] = vals
    return out


def fpke_matrix(
    model: ContinuousModel,
    u: Tensor | None,
    rates: ComponentRates,
    nodes: Tensor,
    node_weights: Tensor,
    chunk_size: int | None = None,
    max_chunk_elements: int = 2**24,
    compile: bool = False,
    pair_products: bool = True,
) -> FPKEMatrix:
    """``L_ij = ∫ Lᵢ Lⱼ dx`` for every pair of components (method.md §3).

    Only the ``N(N+1)/2`` pairs ``i ≤ j`` are evaluated (:func:`product_gaussians`).
    Quadrature points ``x = m_ij + chol(S_ij) ξ`` are processed in chunks
    (``chunk_size`` nodes, or as many as keep a ``[..., pairs, chunk, n, n]``
    tensor under ``max_chunk_elements``) to bound memory.

    Args:
        model: the continuous-time model.
        u: input ``[..., m]`` (broadcast against the trajectory dims) or ``None``.
        rates: components ``[..., N, ...]`` with their moment rates.
        nodes, node_weights: a rule for ``N(0, I_n)`` (:mod:`agsf_torch.quadrature`); or
            ``nodes`` a :class:`~agsf_torch.quadrature.ProductRule` for the space of ``ℓ``
            (``node_weights`` unused): ``E[ℓᵢℓⱼ] = ĉᵢ·ĉⱼ`` from one value of each factor per
            node — exact with far fewer nodes than a rule of twice the degree.
        chunk_size: nodes per chunk (quadrature) or pairs per chunk (product rule), a
            positive integer, or ``None`` (automatic).
        compile: evaluate the per-chunk products with the kernel compiled ahead of time
            (:mod:`agsf_torch.compiled_kernels`, keyed by its exported graph: once per machine, model and shape);
            the model's own route is asked for its compiled form (the attitude models: the lanes kernel of
            :mod:`agsf_torch.fused.pair_products`).
        pair_products: with a :class:`ProductRule`, take the model's own exact route to ``E[ℓᵢℓⱼ]`` when it
            has one (:meth:`~agsf_torch.models.base.ContinuousModel.fpke_pair_products`: the 6-state attitude
            model integrates the bias block in closed form); ``False`` interpolates on the product rule.

    Returns:
        :class:`FPKEMatrix` (``[..., N, N]``).
    """
    chunk_size = check_chunk_size(chunk_size)
    N = rates.means.shape[-2]
    rates = rates.with_precision()  # ℓᵢ at the nodes reads Πᵢ: formed per component, not per pair
    if isinstance(nodes, ProductRule):
        prod, log_scale = _pairs(rates)
        acc = model.fpke_pair_products(u, prod, compile=compile) if pair_products else None
        if acc is None:
            acc = _product_rule_pairs(
                _kernel("product", compile), model, u, prod, nodes, chunk_size, max_chunk_elements
            )
    else:
        prod, log_scale, acc = _integrate_pairs(
            _kernel("pair", compile), model, u, rates, nodes, node_weights, chunk_size, max_chunk_elements, ()
        )
    return _fpke_from_pairs(prod.log_z, log_scale, acc, prod.index, N)


@dataclass(frozen=True)
class GalerkinMatrices:
    """The Galerkin weight update's matrices (method.md §3b), scaled by ``exp(−log_scale)``.

    Attributes:
        mass: ``M̃_ij = z_ij / max z`` ``[..., N, N]`` (symmetric PSD, closed form).
        drift: ``K̃_ij = z_ij E_{N(m_ij, S_ij)}[ℓⱼ] / max z`` ``[..., N, N]`` (``K_ij = ∫ pᵢ Lⱼ dx``).
        log_scale: ``log max_ij z_ij`` ``[...]``.
    """

    mass: Tensor
    drift: Tensor
    log_scale: Tensor


def galerkin_matrices(
    model: ContinuousModel,
    u: Tensor | None,
    rates: ComponentRates,
    nodes: Tensor | None = None,
    node_weights: Tensor | None = None,
    chunk_size: int | None = None,
    max_chunk_elements: int = 2**24,
    compile: bool = False,
    fused: bool = True,
) -> GalerkinMatrices:
    """``M_ij = ∫ pᵢpⱼ dx`` and ``K_ij = ∫ pᵢ Lⱼ dx`` for every pair of components (method.md §3b).

    ``M_ij = z_ij`` in closed form; ``K_ij = z_ij E_{N(m_ij, S_ij)}[ℓⱼ]``, evaluated once
    per unordered pair ``i ≤ j`` (the product Gaussian is symmetric in ``i, j``: the
    same integral machinery gives ``E[ℓⱼ]`` for ``K_ij`` and ``E[ℓᵢ]`` for ``K_ji``):

    * ``nodes = None``: in closed form from the model's Gaussian moments
      (:meth:`~agsf_torch.models.base.ContinuousModel.fokker_planck_moments`,
      :func:`agsf_torch.fpke.moments.residual_mean`) — exact, ``O(n³)`` per pair;
    * a rule ``(nodes, node_weights)``: by quadrature, as :func:`fpke_matrix`.

    With ``nodes = None`` and ``fused`` (default), a model with a fused kernel for the pairs
    (:meth:`~agsf_torch.models.base.ContinuousModel.fused_galerkin_pairs`: the attitude models) computes
    ``log z_ij`` and both ``E[ℓ]`` in one pass over memory (:func:`fused_galerkin_matrices`; it forms the
    components' moment rates itself, from ``rates.means`` and ``rates.covs``: the model's own rates),
    compiled ahead of time if ``compile``; the numbers are those of the generic route to rounding.

    Returns:
        :class:`GalerkinMatrices` (``[..., N, N]``).

    Raises:
        ValueError: ``nodes = None`` for a model without Gaussian moments.
    """
    chunk_size = check_chunk_size(chunk_size)
    N = rates.means.shape[-2]
    if nodes is None and fused:
        G = fused_galerkin_matrices(model, u, rates.means, rates.covs, compile)
        if G is not None:
            return G
    if nodes is None:
        prod, log_scale = _pairs(rates)
        moments = model.fokker_planck_moments(prod.mean, prod.cov, None if u is None else u.unsqueeze(-2))
        if moments is None:
            raise ValueError(
                f"{type(model).__name__} gives no Gaussian moments (fokker_planck_moments); pass a quadrature rule"
            )
        acc = residual_mean(moments, prod.cov, prod.sides, *prod.side_moments())  # [2, ..., P]: E[ℓᵢ], E[ℓⱼ]
    else:
        rates = rates.with_precision()
        prod, log_scale, acc = _integrate_pairs(
            _kernel("galerkin", compile), model, u, rates, nodes, node_weights, chunk_size, max_chunk_elements, (2,)
        )
    return _galerkin_from_pairs(prod.index, prod.log_z, log_scale, acc, N)


def _galerkin_from_pairs(index: Tensor, log_z: Tensor, log_scale: Tensor, acc: Tensor, N: int) -> GalerkinMatrices:
    """``M̃`` and ``K̃`` from the pairs' ``log z_ij`` ``[..., P]`` and ``E[ℓᵢ], E[ℓⱼ]`` ``[2, ..., P]``."""
    z = torch.exp(log_z - log_scale[..., None])
    mass = _symmetric_from_pairs(z, index, N)
    drift = torch.zeros_like(mass)
    i, j = index
    drift[..., j, i] = z * acc[0]  # K_ji = z_ij E[ℓᵢ]
    drift[..., i, j] = z * acc[1]  # K_ij = z_ij E[ℓⱼ] (on the diagonal both are E[ℓᵢ])
    return GalerkinMatrices(mass, drift, log_scale)


def _fused_pairs(hook, u: Tensor | None, means: Tensor, covs: Tensor, compile: bool) -> tuple[Tensor, ...] | None:
    """A model's fused pair kernel (``hook``: ``fused_penalty_pairs`` or ``fused_galerkin_pairs``) on the
    components ``means [..., N, n]``, ``covs [..., N, n, n]`` and ``u [..., m]`` broadcast to their trajectory
    dims: its outputs ``[..., P]`` (``P = N(N+1)/2``), or ``None`` where the model declines."""
    N, n = means.shape[-2:]
    lead = broadcast_shapes(means.shape[:-2], covs.shape[:-3], () if u is None else u.shape[:-1])
    T = math.prod(lead)
    uf = None if u is None else u.expand(*lead, u.shape[-1]).reshape(T, u.shape[-1])
    out = hook(
        means.expand(*lead, N, n).reshape(T, N, n), covs.expand(*lead, N, n, n).reshape(T, N, n, n), uf, compile=compile
    )
    return None if out is None else tuple(t.reshape(*lead, N * (N + 1) // 2) for t in out)


def _fpke_from_pairs(log_z: Tensor, log_scale: Tensor, acc: Tensor, index: Tensor, N: int) -> FPKEMatrix:
    """``L̃`` from the pairs' ``log z_ij`` and ``E[ℓᵢℓⱼ]`` ``[..., P]``, scaled by ``exp(−log_scale)``."""
    vals = torch.exp(log_z - log_scale[..., None]) * acc
    return FPKEMatrix(_symmetric_from_pairs(vals, index, N), log_scale)


def fused_fpke_matrix(
    model: ContinuousModel, u: Tensor | None, means: Tensor, covs: Tensor, compile: bool = False
) -> FPKEMatrix | None:
    """:func:`fpke_matrix` on the model's exact rule for the components ``means [..., N, n]``,
    ``covs [..., N, n, n]`` with their moment rates (at ``u [..., m]``) by the model's fused kernel
    (:meth:`~agsf_torch.models.base.ContinuousModel.fused_penalty_pairs`: product Gaussians, rates and
    ``E[ℓᵢℓⱼ]`` on lanes), compiled ahead of time if ``compile``; ``None`` if the model has no such kernel or
    declines this batch (then :func:`fpke_matrix` applies)."""
    out = _fused_pairs(model.fused_penalty_pairs, u, means, covs, compile)
    if out is None:
        return None
    log_z, acc = out
    N = means.shape[-2]
    return _fpke_from_pairs(log_z, log_z.amax(-1), acc, torch.triu_indices(N, N, device=means.device), N)


def fused_galerkin_matrices(
    model: ContinuousModel, u: Tensor | None, means: Tensor, covs: Tensor, compile: bool = False
) -> GalerkinMatrices | None:
    """:func:`galerkin_matrices` of the components ``means [..., N, n]``, ``covs [..., N, n, n]`` with their
    moment rates (:func:`~agsf_torch.propagation.moment_derivatives` at ``u [..., m]``) by the model's fused
    kernel (:meth:`~agsf_torch.models.base.ContinuousModel.fused_galerkin_pairs`: rates, product Gaussians and
    ``E[ℓ]`` in one pass), compiled ahead of time if ``compile``; ``None`` if the model has no such kernel or
    declines this many pairs (then the generic route applies)."""
    out = _fused_pairs(model.fused_galerkin_pairs, u, means, covs, compile)
    if out is None:
        return None
    log_z, e_i, e_j = out
    N = means.shape[-2]
    index = torch.triu_indices(N, N, device=means.device)
    return _galerkin_from_pairs(index, log_z, log_z.amax(-1), torch.stack((e_i, e_j)), N)
