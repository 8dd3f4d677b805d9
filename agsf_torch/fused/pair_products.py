"""The attitude model's ``E[ℓᵢℓⱼ]`` (the penalty update's ``L``, method.md §3) on lanes.

The same mathematics as :mod:`agsf_torch.models.attitude_bias_block` (6 states: the bias block in closed form,
ten Hermite coefficients in ``ξ_b`` per MRP node) and as the 84-node interpolatory rule of the
3-state model (one value per node), written on entries (:mod:`agsf_torch.fused.algebra`) with one
lane per pair and node: a pair's ``N(m, S = LLᵀ)`` gives the nodes ``p = m_p + L_pp ξ`` and
``β = m_b + L_bp ξ`` for the ``K = 84`` MRP nodes ``ξ`` of
:func:`~agsf_torch.quadrature.product_rule` (total degree 6 in three dimensions).  Everything
affine in ``ξ`` is formed once per pair and side and evaluated at the nodes with three multiply–adds:

.. math:: z_0 = Π(x_0 − μ) = Π(m − μ) + ΠL_{:,p}\\,ξ,\\qquad \\dot P z_0 = \\dot PΠ(m − μ) + \\dot PΠL_{:,p}\\,ξ,

and so are the per-pair matrices of the bias block (``Z = Π_{:,b}L_bb``, ``ZᵀṖZ``); a node pays only for
what varies with it (``s = pᵀp``, the drift, ``D``, ``¼B(p)L_bb`` once for both sides, the coefficients).  Per node the kernel is ~700 floating-point operations for both sides of a 6-state
pair.  ``E[ℓᵢℓⱼ]`` is then ``Σ_c vᵢ,cᵀ W vⱼ,c`` over the channels ``c`` with ``W = TᵀT`` (``T`` the
rule's map from values at the nodes to orthonormal Hermite coefficients): exactly the dot product of
the two sides' coefficients.

Two entry points: :func:`attitude_pair_products` takes the pairs' product Gaussians from
:func:`~agsf_torch.fpke.pairs.product_gaussians` (the model's ``fpke_pair_products`` hook);
:func:`attitude_penalty_pairs` starts from the components and forms the product Gaussians and the moment
rates on lanes too (:func:`attitude_pair_moments_kernel`, a kernel of its own: inside the node kernel the
compiler would recompute these per-pair values at every node), which the penalty update takes
(``fused_penalty_pairs``); there the pairs ``(i, i)`` take :func:`attitude_diagonal_pair_values_kernel`, the
same kernel given their one component, evaluated once.  Compiled, the node kernels run in chunks of
:data:`COMPILED_PAIRS` pairs (by the number of states).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..attitude import physics
from .algebra import Entry, add, cholesky, dot, matmul, matvec, mul, sub, zeros
from .lanes import entries, stack_entries
from .propagation import attitude_rates

__all__ = [
    "COMPILED_PAIRS",
    "attitude_pair_values_kernel",
    "attitude_pair_moments_kernel",
    "attitude_diagonal_pair_values_kernel",
    "attitude_penalty_pairs",
    "pair_product_weights",
    "attitude_pair_products",
]

Mat = list[list[Entry]]

#: Row and column of the six entries of a symmetric 3×3 matrix: the diagonal, then (0, 1), (0, 2), (1, 2).
_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def pair_product_weights(T: Tensor) -> Tensor:
    """``W = TᵀT`` ``[K, K]``: ``E[fg] = f(ξ)ᵀ W g(ξ)`` for two functions of the rule's space given by their
    values at its nodes (``T`` maps values to orthonormal Hermite coefficients)."""
    return T.transpose(0, 1) @ T


def _lower(L: Mat) -> Mat:
    """A lower-triangular factor with its upper triangle as structural zeros."""
    return [[v if j <= i else None for j, v in enumerate(row)] for i, row in enumerate(L)]


def _affine_at_nodes(a: list[Entry], A: Mat, xi: list[Tensor]) -> list[Entry]:
    """``a + Aξ`` at every node: ``a [r]`` and ``A [r][3]`` per pair (``[c, 1]`` lanes), ``ξ`` three ``[K]``."""
    return [add(a[r], dot((A[r][k], xi[k]) for k in range(3))) for r in range(len(a))]


def _node_terms(p: list[Entry], w: list[Entry], c: Tensor, L_bb: Mat | None) -> dict:
    """What both sides share at the nodes (:mod:`agsf_torch.attitude.physics`): ``h = −f_p + 2a_p``
    (``f_p = ¼B(p)ω``, ``a_p = 4c(1+s)p``), ``d_p = c(1+s)²`` and ``scalar`` ``div f − Σ∂²D``; with a bias block
    (``L_bb`` given), ``rate_matrix`` ``∂f_p/∂ω = ¼B(p)``, ``divergence_gradient`` ``∂(div f)/∂ω = (3/2)p`` and
    ``BL`` ``¼B(p)L_bb``."""
    t = physics.fokker_planck_terms(p, w, c)
    h = [sub(mul(2.0, a), f) for a, f in zip(t["diffusion_divergence"], t["rate"])]
    scalar = sub(t["divergence"], t["second_divergence"])
    out = {"h": h, "d_p": t["diffusion"], "scalar": scalar}
    if L_bb is not None:
        out["rate_matrix"], out["divergence_gradient"] = physics.rate_derivatives(p, t["s"])
        out["BL"] = matmul(out["rate_matrix"], L_bb)
    return out


def _side_values(
    n: int,
    mE: list[Entry],
    LE: Mat,
    xi: list[Tensor],
    terms: dict,
    mu: list[Entry],
    Pi: Mat,
    rate: list[Entry],
    Pdot: Mat,
    d_b: Tensor,
) -> list[Entry]:
    """The channels of ``ℓ`` of one side at every node: ``[ℓ]`` (3 states) or the ten Hermite coefficients in
    ``ξ_b`` (6 states; :mod:`agsf_torch.models.attitude_bias_block`)."""
    delta = [sub(mE[r], mu[r]) for r in range(n)]
    a = matvec(Pi, delta)  # Π(m − μ) per pair
    A = matmul(Pi, [row[:3] for row in LE])  # Π L_{:,p} per pair
    z0 = _affine_at_nodes(a, A, xi)
    Pz = _affine_at_nodes(matvec(Pdot, a), matmul(Pdot, A), xi)
    d = [terms["d_p"]] * 3 + [d_b] * (n - 3)
    v0 = [add(rate[r], terms["h"][r]) for r in range(3)] + [rate[r] for r in range(3, n)]
    # ℓ(x₀) = Σ zᵣ(v₀ᵣ + ½(Ṗz)ᵣ − dᵣzᵣ) + tr(DΠ) + div f − Σ∂²D − ½tr(ΠṖ)
    tr_Pi_p = add(add(Pi[0][0], Pi[1][1]), Pi[2][2])
    per_pair = mul(-0.5, dot((Pi[r][t], Pdot[r][t]) for r in range(n) for t in range(n)))
    if n == 6:
        per_pair = add(per_pair, mul(d_b, add(add(Pi[3][3], Pi[4][4]), Pi[5][5])))
    c0 = add(
        add(dot((z0[r], sub(add(v0[r], mul(0.5, Pz[r])), mul(d[r], z0[r]))) for r in range(n)), per_pair),
        add(mul(terms["d_p"], tr_Pi_p), terms["scalar"]),
    )
    if n == 3:
        return [c0]
    L_bb = [row[3:] for row in LE[3:]]
    Z = matmul([row[3:] for row in Pi], L_bb)  # Π_{:,b} L_bb [6][3] per pair
    # g = Zᵀ(v₀ + Ṗz₀ − 2Dz₀) + L_bbᵀ(¼B(p)ᵀz₀,p − (3/2)p)
    wv = [sub(add(v0[r], Pz[r]), mul(mul(2.0, d[r]), z0[r])) for r in range(n)]
    Bq, dq = terms["rate_matrix"], terms["divergence_gradient"]
    q = [sub(dot((Bq[t][k], z0[t]) for t in range(3)), dq[k]) for k in range(3)]
    g = [add(dot((Z[r][k], wv[r]) for r in range(n)), dot((q[t], L_bb[t][k]) for t in range(3))) for k in range(3)]
    # G = ½ZᵀṖZ − Σₐ dₐ ZₐZₐᵀ + sym(Z_pᵀ ¼B(p)L_bb)
    PZ = matmul(Pdot, Z)
    M = matmul([list(col) for col in zip(*Z[:3])], terms["BL"])  # Z_pᵀ ¼B(p)L_bb
    G = []
    for r, col in _SYM:
        ZPZ = mul(0.5, dot((Z[t][r], PZ[t][col]) for t in range(n)))  # per pair
        Op = dot((Z[t][r], Z[t][col]) for t in range(3))
        Ob = dot((Z[t][r], Z[t][col]) for t in range(3, n))
        per = sub(ZPZ, mul(d_b, Ob))
        symM = M[r][col] if r == col else mul(0.5, add(M[r][col], M[col][r]))
        G.append(add(sub(per, mul(terms["d_p"], Op)), symM))
    root2 = math.sqrt(2.0)
    return (
        [add(c0, add(add(G[0], G[1]), G[2]))]
        + g
        + [mul(root2, G[k]) for k in range(3)]
        + [mul(2.0, G[k]) for k in range(3, 6)]
    )


def attitude_pair_values_kernel(m: Tensor, L: Tensor, u: Tensor, *sides_and_shared: Tensor) -> tuple[Tensor]:
    """``E[ℓᵢℓⱼ]`` ``[Q]`` of ``Q`` pairs (module docstring); given one side, ``E[ℓᵢ²]`` of pairs ``(i, i)``, that
    side evaluated once (``vᵢᵀWvᵢ`` per channel).

    Args:
        m, L: the pair's product Gaussian ``N(m, LLᵀ)``: ``[Q, n]``, ``[Q, n, n]`` (lower-triangular).
        u: the gyro rate ``[Q, 3]`` (rad/s; the 3-state model's known bias removed).
        sides_and_shared: each side's ``μ``, ``Π = P⁻¹``, ``μ̇`` and ``Ṗ`` (``[Q, n]``, ``[Q, n, n]``; two sides or
            one), then the MRP nodes ``ξ`` ``[K, 3]``, ``W = TᵀT`` ``[K, K]`` (:func:`pair_product_weights`),
            ``c = σ_v²/32`` and ``d_b = σ_u²/2`` (0-d tensors; ``d_b`` unused with 3 states).
    """
    *sides, nodes, W, c, d_b = sides_and_shared
    Q, n = m.shape
    mE, LE, uE = _column(entries(m, (n,))), _lower(_column(entries(L, (n, n)))), _column(entries(u, (3,)))
    xi = list(nodes.unbind(-1))
    p = _affine_at_nodes(mE[:3], LE[:3], xi)
    if n == 6:
        beta = _affine_at_nodes(mE[3:], [row[:3] for row in LE[3:]], xi)
        w = [sub(uE[k], beta[k]) for k in range(3)]
        terms = _node_terms(p, w, c, [row[3:] for row in LE[3:]])
    else:
        terms = _node_terms(p, uE, c, None)
    shapes = ((n,), (n, n), (n,), (n, n))
    values = []
    for a in range(0, len(sides), 4):  # each side's μ, Π, μ̇, Ṗ as [Q, 1] columns
        side = (_column(entries(t, shape)) for t, shape in zip(sides[a : a + 4], shapes))
        vals = _side_values(n, mE, LE, xi, terms, *side, d_b)
        values.append(torch.stack([v.expand(Q, nodes.shape[0]) for v in vals], 1))  # [Q, channels, K]
    vi, vj = values if len(values) == 2 else values * 2
    return (((vi @ W) * vj).sum((-2, -1)),)


def attitude_diagonal_pair_values_kernel(*args: Tensor) -> tuple[Tensor]:
    """:func:`attitude_pair_values_kernel` of the pairs ``(i, i)`` (one side): a kernel of its own, compiled for
    its own arguments."""
    return attitude_pair_values_kernel(*args)


def _column(x):
    """Entries of pairs ``[Q]`` (nested lists) as ``[Q, 1]`` columns, to broadcast against the nodes ``[K]``;
    numbers, structural zeros and 0-d parameters pass through."""
    if isinstance(x, list):
        return [_column(v) for v in x]
    return x.unsqueeze(-1) if isinstance(x, Tensor) and x.dim() > 0 else x


def attitude_pair_moments_kernel(
    mu_i: Tensor, P_i: Tensor, mu_j: Tensor, P_j: Tensor, u: Tensor, sv2: Tensor, su2: Tensor
) -> tuple[Tensor, ...]:
    """What :func:`attitude_pair_values_kernel` reads of ``Q`` pairs, from their components alone: the product
    Gaussian (:func:`~agsf_torch.fused.galerkin.product_gaussian`) as ``m`` ``[Q, n]``, the lower Cholesky factor
    ``L`` ``[Q, n, n]`` of its ``S`` and ``log z`` ``[Q]`` (NaN on a lane where a factorisation met a non-positive
    pivot), and each side's moment rates ``μ̇`` ``[Q, n]``, ``Ṗ`` ``[Q, n, n]``
    (:func:`~agsf_torch.fused.propagation.attitude_rates`).

    Args:
        mu_*, P_*: each side's ``μ`` ``[Q, n]`` and ``P`` ``[Q, n, n]``; u: the gyro rate ``[Q, 3]`` (rad/s; the
            3-state model's known bias removed); sv2, su2: ``σ_v²``, ``σ_u²`` (0-d tensors).
    """
    from .galerkin import product_gaussian

    Q, n = mu_i.shape
    uE = entries(u, (3,))
    comps, rates = [], []
    for mu, P in ((mu_i, P_i), (mu_j, P_j)):
        mE, PE = entries(mu, (n,)), entries(P, (n, n))
        rate, _, Pdot = attitude_rates(mE, zeros(n), PE, uE, sv2, su2)
        comps.append((mE, PE))
        rates += [rate, Pdot]
    g = product_gaussian(*comps[0], *comps[1])
    L, _, good = cholesky(g["cov"])
    log_z = torch.where(g["ok"] & good, g["log_z"], torch.nan)

    return (stack_entries(g["mean"], Q), stack_entries(L, Q), *(stack_entries(r, Q) for r in rates), log_z)


#: Pairs per call of the compiled kernel (its threaded variant; fewer pairs take the serial one), by the number of
#: states.  Each pair carries a row of ``K = 84`` nodes, so the kernel's temporaries are ``[pairs, 84]``: at 128
#: pairs ~86 KB each, which stay in the core's cache, where chunks of the default 1,024 lanes (688 KB each) went to
#: memory.  With 3 states a node carries one channel instead of ten, far fewer temporaries, and the number of calls
#: dominates: larger chunks (the timings: ``agsf bench``, docs/results/performance.md).
COMPILED_PAIRS = {3: 512, 6: 128}

_WEIGHTS: dict[tuple, tuple[Tensor, Tensor]] = {}


def _mrp_nodes_and_weights(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """The 84 MRP nodes of total degree 6 and their ``W = TᵀT``."""
    key = (dtype, device)
    if key not in _WEIGHTS:
        from ..quadrature import product_rule

        rule = product_rule((((0, 1, 2), 6),), 3, dtype=dtype, device=device)
        _WEIGHTS[key] = (rule.nodes, pair_product_weights(rule.groups[0][1].to(dtype=dtype, device=device)))
    return _WEIGHTS[key]


def attitude_pair_products(
    prod, rate: Tensor, sigma_v: Tensor, sigma_u: Tensor, *, compile: bool = False, chunk: int | None = None
) -> Tensor:
    """``E_{N(m_ij, S_ij)}[ℓᵢℓⱼ]`` ``[..., P]`` of every pair of an attitude mixture on lanes (module docstring).

    Args:
        prod: the pairs' :class:`~agsf_torch.fpke.pairs.ProductGaussians` (sides with precisions formed).
        rate: the gyro rate ``[..., 3]`` (rad/s; the 3-state model's known bias removed), broadcast against the
            trajectory dims.
        sigma_v, sigma_u: the gyro's rate and bias noise densities.
        compile: run the kernel compiled ahead of time (:func:`~.lanes.run_in_chunks`).
        chunk: pairs per eager call (default: as many as keep ``DEFAULT_CHUNK`` node lanes).
    """
    lead, flat = prod.mean.shape[:-1], prod.flat
    sides = []
    for r in (prod.first, prod.second):
        sides += [flat(r.means, 1), flat(r.precision, 2), flat(r.mean_rates, 1), flat(r.cov_rates, 2)]
    m = flat(prod.mean, 1)
    if m.shape[0] == 0:
        return m.new_zeros(lead)
    inputs = (m, flat(prod.chol, 2), flat(rate.unsqueeze(-2), 1), *sides)
    return _pair_values(inputs, sigma_v, sigma_u, compile, chunk).reshape(lead)


def _pair_values(
    inputs: tuple, sigma_v: Tensor, sigma_u: Tensor, compile: bool, chunk: int | None = None, kernel=None
) -> Tensor:
    """``kernel`` (:func:`attitude_pair_values_kernel`, or its diagonal variant) over its batch-first ``inputs`` in
    chunks (eagerly ``chunk`` pairs, by default as many as keep ``DEFAULT_CHUNK`` node lanes; compiled
    :data:`COMPILED_PAIRS`): ``[Q]``."""
    from .lanes import DEFAULT_CHUNK, run_in_chunks

    m = inputs[0]
    nodes, W = _mrp_nodes_and_weights(m.dtype, m.device)
    (acc,) = run_in_chunks(
        kernel or attitude_pair_values_kernel,
        inputs,
        shared=(nodes, W, (sigma_v**2 / 32.0).to(m), (0.5 * sigma_u**2).to(m)),
        compile=compile,
        chunk=chunk or max(1, DEFAULT_CHUNK // nodes.shape[0]),
        key=("attitude pair products", m.shape[-1]),
        compiled_chunk=COMPILED_PAIRS.get(m.shape[-1], 128),
    )
    return acc


def attitude_penalty_pairs(
    means: Tensor, covs: Tensor, rate: Tensor, sigma_v: Tensor, sigma_u: Tensor, *, compile: bool = False
) -> tuple[Tensor, Tensor]:
    """``(log z_ij, E_{N(m_ij, S_ij)}[ℓᵢℓⱼ])`` ``[T, P]`` of the pairs ``i ≤ j`` (``torch.triu_indices`` order) of ``T``
    attitude mixtures from the components alone, on lanes: the pairs' product Gaussians and the components'
    moment rates (:func:`attitude_pair_moments_kernel`), then ``E[ℓᵢℓⱼ]`` (:func:`attitude_pair_values_kernel`,
    in chunks of :data:`COMPILED_PAIRS` pairs when compiled); compiled ahead of time if ``compile``.  The
    precisions ``Πᵢ`` are formed once per component, as :class:`~agsf_torch.fpke.residual.ComponentRates` does.

    Args:
        means: ``μ`` ``[T, N, n]``; covs: ``P`` ``[T, N, n, n]``; rate: the gyro rate ``[T, 3]`` (rad/s; the
            3-state model's known bias removed).
        sigma_v, sigma_u: the gyro's rate and bias noise densities.
    """
    from .lanes import run_in_chunks

    T, N, n = means.shape
    first, second = torch.triu_indices(N, N, device=means.device)
    P = first.shape[0]
    if T * P == 0:
        return means.new_zeros(T, P), means.new_zeros(T, P)
    prec = torch.cholesky_inverse(torch.linalg.cholesky(covs))
    prec = 0.5 * (prec + prec.transpose(-1, -2))
    # lanes pair-major, the pairs i < j first: those take both sides, the pairs (i, i) (the same component on
    # both sides) one, each set a contiguous slice of the lanes (no copies)
    order = torch.cat(((first != second).nonzero()[:, 0], (first == second).nonzero()[:, 0]))
    first, second = first[order], second[order]
    split = T * (P - N)

    def side(t: Tensor, index: Tensor) -> Tensor:  # [T, N, …] → the pairs' side, pair-major [P·T, …] (one gather)
        return t.transpose(0, 1)[index].reshape(P * T, *t.shape[2:])

    u = rate.unsqueeze(0).expand(P, T, 3).reshape(P * T, 3)
    sv2, su2 = (sigma_v**2).to(means), (sigma_u**2).to(means)
    mu_i, mu_j = side(means, first), side(means, second)
    m, L, rate_i, Pdot_i, rate_j, Pdot_j, log_z = run_in_chunks(
        attitude_pair_moments_kernel,
        (mu_i, side(covs, first), mu_j, side(covs, second), u),
        shared=(sv2, su2),
        compile=compile,
        key=("attitude pair moments", n),
    )
    Pi_i, Pi_j = side(prec, first), side(prec, second)
    both = (m, L, u, mu_i, Pi_i, rate_i, Pdot_i, mu_j, Pi_j, rate_j, Pdot_j)
    acc_off = _pair_values(tuple(t[:split] for t in both), sigma_v, sigma_u, compile)
    one = (m, L, u, mu_i, Pi_i, rate_i, Pdot_i)
    diagonal = attitude_diagonal_pair_values_kernel
    acc_diag = _pair_values(tuple(t[split:] for t in one), sigma_v, sigma_u, compile, kernel=diagonal)
    back = torch.empty_like(order)
    back[order] = torch.arange(P, device=order.device)  # lane order → triu order

    def triu(t: Tensor) -> Tensor:
        return t.reshape(P, T).t()[:, back]

    return triu(log_z), triu(torch.cat((acc_off, acc_diag)))
