"""The attitude physics, written once (method.md §1, §3): the MRP chart, the gyro-driven kinematics and its
noise, the star camera, and the Fokker–Planck terms they give.

With ``s = pᵀp``, ``ω = ω̃ − b`` the body rate (rad/s) and ``σ_v``, ``σ_u`` the gyro's noise densities:

.. math::

    B(p) = (1 − s)I + 2[p×] + 2pp^T,\\qquad \\dot p = \\tfrac14 B(p)ω,\\qquad \\dot b = 0,

    A = \\begin{bmatrix} F & −\\tfrac14 B(p) \\\\ 0 & 0 \\end{bmatrix},\\quad
    F = \\tfrac12\\big(pω^T − ωp^T − [ω×] + (ω^Tp)I\\big),\\qquad
    g = \\begin{bmatrix} −\\tfrac14 B(p) & 0 \\\\ 0 & I \\end{bmatrix},\\quad
    gQg^T = \\operatorname{diag}\\big(\\tfrac{σ_v^2}{16}(1 + s)^2 I, σ_u^2 I\\big),

    C(p) = I + \\frac{8[p×]^2 − 4(1 − s)[p×]}{(1 + s)^2},\\qquad h_j = C(p) r_j,\\qquad
    H_j = [h_j×]\\,E,\\quad E = \\frac{4B(p)^T}{(1 + s)^2},

and the shadow set ``pˢ = −p/s`` with ``∂pˢ/∂p = (2ppᵀ − sI)/s²``.  The 3-state model (``x = p``) drops the bias
rows and columns; its known bias is removed from the gyro rate before these functions see it.

Every function is written on entries (:mod:`agsf_torch.fused.algebra`): a vector is a list of entries, a matrix a
list of rows, an entry a tensor (any shape; entries broadcast), a number known when the code runs, or ``None``
for a structural zero.  The same functions serve both paths: the generic model's tensor methods apply them to the
entries of batched tensors (:func:`~agsf_torch.fused.algebra.as_entries`, :func:`~agsf_torch.fused.algebra.as_tensor`),
and the fused kernels to lanes, where the structural zeros (the bias rows, the diagonal noise) emit no arithmetic.
"""

from __future__ import annotations

from ..fused.algebra import Entry, add, add_cross_matrix, cross, div, dot, matvec, mul, neg, sub, zeros

__all__ = [
    "mrp_norm2",
    "kinematics_matrix",
    "mrp_rate",
    "mrp_rate_jacobian",
    "body_rate",
    "drift",
    "drift_jacobian",
    "noise_gain",
    "noise_psd",
    "process_noise",
    "shadow",
    "shadow_jacobian",
    "attitude_matrix",
    "chart_map",
    "star_jacobian",
    "rate_derivatives",
    "fokker_planck_terms",
    "fokker_planck_moments",
]

Vec = list[Entry]
Mat = list[list[Entry]]


def mrp_norm2(p: Vec) -> Entry:
    """``s = pᵀp`` of an MRP ``p`` (3 entries, dimensionless)."""
    return dot((p[k], p[k]) for k in range(3))


def kinematics_matrix(p: Vec, s: Entry = None) -> Mat:
    """``B(p) = (1 − s)I + 2[p×] + 2ppᵀ`` (3×3; ``ṗ = ¼B(p)ω``, ``BBᵀ = (1 + s)²I``); ``s`` if known."""
    one_s = sub(1.0, mrp_norm2(p) if s is None else s)
    ppx = add_cross_matrix([[mul(p[i], p[j]) for j in range(3)] for i in range(3)], p)  # ppᵀ + [p×]
    return [[add(one_s if i == j else None, mul(2.0, ppx[i][j])) for j in range(3)] for i in range(3)]


def mrp_rate(p: Vec, w: Vec, s: Entry = None, transpose: bool = False) -> Vec:
    """``ṗ = ¼B(p)ω = ¼[(1 − s)ω + 2p×ω + 2(pᵀω)p]`` (rad/s → 1/s), without forming ``B``; ``transpose``:
    ``¼B(p)ᵀω`` (``B(p)ᵀ = B(−p)``)."""
    one_minus = sub(1.0, mrp_norm2(p) if s is None else s)
    pxw = cross(w, p) if transpose else cross(p, w)
    two_pw = mul(2.0, dot((p[k], w[k]) for k in range(3)))
    return [mul(0.25, add(add(mul(one_minus, w[k]), mul(2.0, pxw[k])), mul(two_pw, p[k]))) for k in range(3)]


def mrp_rate_jacobian(p: Vec, w: Vec) -> Mat:
    """``F = ∂(¼B(p)ω)/∂p = ½(pωᵀ − ωpᵀ − [ω×] + (ωᵀp)I)`` (3×3, 1/s)."""
    pw = dot((p[k], w[k]) for k in range(3))
    D = zeros(3)  # pωᵀ − ωpᵀ, antisymmetric
    for i, j in ((1, 0), (2, 0), (2, 1)):
        D[i][j] = sub(mul(p[i], w[j]), mul(w[i], p[j]))
        D[j][i] = neg(D[i][j])
    F = add_cross_matrix(D, w, -1.0)
    return [[mul(0.5, pw if i == j else F[i][j]) for j in range(3)] for i in range(3)]


def body_rate(x: Vec, u: Vec) -> Vec:
    """``ω = ω̃ − b`` (rad/s): the 6-state model's bias is ``x[3:]``; the 3-state model's ``u`` is the rate
    already."""
    return [sub(u[k], x[3 + k]) for k in range(3)] if len(x) == 6 else list(u)


def drift(x: Vec, u: Vec, s: Entry = None) -> Vec:
    """``f(x, ω̃) = [¼B(p)ω; 0]`` (``n`` = 3 or 6 entries) with ``ω`` = :func:`body_rate`; ``s = pᵀp`` if known."""
    return mrp_rate(x[:3], body_rate(x, u), s) + [None] * (len(x) - 3)


def drift_jacobian(x: Vec, u: Vec, s: Entry = None) -> Mat:
    """``A = ∂f/∂x = [[F, −¼B(p)], [0, 0]]`` (``n×n``; the 3-state model: ``F``); ``s = pᵀp`` if known."""
    F = mrp_rate_jacobian(x[:3], body_rate(x, u))
    if len(x) == 3:
        return F
    return [F[i] + [mul(-0.25, v) for v in row] for i, row in enumerate(kinematics_matrix(x[:3], s))] + zeros(3, 6)


def noise_gain(x: Vec) -> Mat:
    """``g(x) = [[−¼B(p), 0], [0, I]]`` (``n×n``; the 3-state model: ``−¼B(p)``)."""
    gp = [[mul(-0.25, v) for v in row] for row in kinematics_matrix(x[:3])]
    if len(x) == 3:
        return gp
    return [row + [None] * 3 for row in gp] + [
        [None] * 3 + [1.0 if i == j else None for j in range(3)] for i in range(3)
    ]


def noise_psd(sv2: Entry, su2: Entry, n: int) -> Mat:
    """``Q = diag(σ_v² I₃, σ_u² I₃)`` (``n×n``, rad²/s and rad²/s³); the 3-state model: ``σ_v² I₃``."""
    return [[(sv2 if i < 3 else su2) if i == j else None for j in range(n)] for i in range(n)]


def process_noise(x: Vec, sv2: Entry, su2: Entry, s: Entry = None) -> Mat:
    """``gQgᵀ = diag((σ_v²/16)(1 + s)² I₃, σ_u² I₃)`` (``n×n``; from ``BBᵀ = (1 + s)²I``); ``s = pᵀp`` if known."""
    one_s = add(1.0, mrp_norm2(x[:3]) if s is None else s)
    g_p = mul(div(sv2, 16.0), mul(one_s, one_s))
    return noise_psd(g_p, su2, len(x))


def shadow(p: Vec) -> Vec:
    """The shadow MRP ``pˢ = −p/s`` (the same attitude; ``p ≠ 0``)."""
    s = mrp_norm2(p)
    return [div(neg(v), s) for v in p]


def shadow_jacobian(p: Vec) -> Mat:
    """``J = ∂pˢ/∂p = (2ppᵀ − sI)/s²`` (3×3; the covariance maps as ``JPJᵀ``)."""
    s = mrp_norm2(p)
    s2 = mul(s, s)
    return [[div(sub(mul(mul(2.0, p[i]), p[j]), s if i == j else None), s2) for j in range(3)] for i in range(3)]


def attitude_matrix(p: Vec) -> Mat:
    """``C(p) = I + (8[p×]² − 4(1 − s)[p×])/(1 + s)²`` (inertial → body, 3×3), with ``[p×]² = ppᵀ − sI``."""
    s = mrp_norm2(p)
    one_s = add(1.0, s)
    inv = div(1.0, mul(one_s, one_s))
    a = mul(4.0, sub(1.0, s))
    pp = [[mul(8.0, sub(mul(p[i], p[j]), s if i == j else None)) for j in range(3)] for i in range(3)]
    K = add_cross_matrix(pp, [mul(a, v) for v in p], -1.0)  # 8[p×]² − 4(1 − s)[p×]
    return [[add(1.0 if i == j else None, mul(K[i][j], inv)) for j in range(3)] for i in range(3)]


def chart_map(p: Vec) -> Mat:
    """``E = 4B(p)ᵀ/(1 + s)²``: an MRP perturbation ``δp`` as the body-frame rotation ``δθ = E δp`` (rad), so
    ``δ(C r) = [(C r)×] E δp``."""
    s = mrp_norm2(p)
    one_s = add(1.0, s)
    c4 = mul(4.0, div(1.0, mul(one_s, one_s)))
    B = kinematics_matrix(p, s)
    return [[mul(c4, B[j][i]) for j in range(3)] for i in range(3)]


def star_jacobian(b: Vec, E: Mat) -> Mat:
    """``Hⱼ = ∂(C(p)rⱼ)/∂p = [bⱼ×] E`` (3×3) of a predicted body vector ``bⱼ = C(p) rⱼ`` (:func:`chart_map`)."""
    cols = [cross(b, [E[0][k], E[1][k], E[2][k]]) for k in range(3)]
    return [[cols[k][i] for k in range(3)] for i in range(3)]


def star_vector(C: Mat, r: Vec) -> Vec:
    """``h = C(p) r``: a catalogue unit vector ``r`` in the body frame."""
    return matvec(C, r)


def rate_derivatives(p: Vec, s: Entry = None) -> tuple[Mat, Vec]:
    """``(∂f_p/∂ω, ∂(div f)/∂ω) = (¼B(p), (3/2)p)`` (3×3 and 3 entries): the MRP rate and the divergence
    ``div f = (3/2)pᵀω`` are linear in the body rate, so these are all of their dependence on the bias
    (``ω = ω̃ − b``); ``s = pᵀp`` if known."""
    return [[mul(0.25, v) for v in row] for row in kinematics_matrix(p, s)], [mul(1.5, v) for v in p]


def drift_divergence(p: Vec, w: Vec) -> Entry:
    """``div f = tr ∂f/∂x = (3/2)pᵀω`` (1/s): the trace of :func:`drift_jacobian` (its ``F`` block has
    ``Fₖₖ = ½pᵀω``; the bias block is zero), ``ω`` the body rate (:func:`body_rate`)."""
    return mul(1.5, dot((p[k], w[k]) for k in range(3)))


def fokker_planck_terms(p: Vec, w: Vec, c: Entry) -> dict:
    """The Fokker–Planck terms of the MRP block at ``p`` (method.md §3), ``c = σ_v²/32``, ``s = pᵀp``:
    ``s``, ``rate`` ``f_p = ¼B(p)ω``, ``divergence`` ``div f = (3/2)pᵀω``, ``diffusion`` ``D_pp = c(1 + s)²`` (the
    diagonal), ``diffusion_divergence`` ``aₖ = 4c(1 + s)pₖ`` and ``second_divergence`` ``Σ∂²D = 4c(3 + 5s)``."""
    s = mrp_norm2(p)
    one_s = add(1.0, s)
    c4s = mul(mul(4.0, c), one_s)
    return {
        "s": s,
        "rate": mrp_rate(p, w, s),
        "divergence": drift_divergence(p, w),
        "diffusion": mul(c, mul(one_s, one_s)),
        "diffusion_divergence": [mul(c4s, p[k]) for k in range(3)],
        "second_divergence": mul(mul(4.0, c), add(3.0, mul(5.0, s))),
    }


def fokker_planck_moments(m: Vec, S: Mat, u: Vec, c: Entry) -> dict:
    """Exact expectations of the Fokker–Planck terms under ``x ~ N(m, S)`` (``n`` = 3 or 6 entries; ``u`` the
    gyro rate, the 3-state model's known bias removed; ``c = σ_v²/32``).

    With ``M`` the MRP block of ``S``, ``C = Cov(p, ω) = −S_pb`` (0 with 3 states), ``m_ω`` the mean rate:
    ``E[s] = mᵀm + tr M``, ``E[ppᵀ] = mmᵀ + M``, ``E[sp] = E[s]m + 2Mm``, ``E[s²] = E[s]² + 2tr M² + 4mᵀMm``,
    ``E[sω] = E[s]m_ω + 2Cᵀm``, ``E[p×ω] = m×m_ω + ε:C``, ``E[(pᵀω)p] = m(mᵀm_ω + tr C) + Cm + Mm_ω``.  The
    diffusion is ``D = φD₁ + D₀`` with ``φ = (1 + s)²``; ``v = f − 2a`` with ``v_p = ¼B(p)ω − 8c(1 + s)p``,
    ``∂v_p/∂p = F − 8c((1 + s)I + 2ppᵀ)`` and ``∂v_p/∂b = −¼B(p)``.

    Returns:
        ``scalar`` ``E[div f − Σ∂²D]``, ``transport`` ``E[v]``, ``transport_jacobian`` ``E[∂v/∂x]`` (bias rows
        structural zeros), ``field`` ``E[φ]``, ``gradient`` ``E[∇φ]`` and ``hessian`` ``E[∇²φ]`` (zero on the bias
        axes).
    """
    n = len(m)
    p = m[:3]
    M = [row[:3] for row in S[:3]]
    w = body_rate(m, u)
    C = [[neg(S[i][3 + j]) for j in range(3)] for i in range(3)] if n == 6 else zeros(3)
    Mm = matvec(M, p)
    Es = add(dot((p[k], p[k]) for k in range(3)), add(add(M[0][0], M[1][1]), M[2][2]))
    Epp = [[add(mul(p[i], p[j]), M[i][j]) for j in range(3)] for i in range(3)]
    Esp = [add(mul(Es, p[i]), mul(2.0, Mm[i])) for i in range(3)]
    Es2 = add(
        add(mul(Es, Es), mul(2.0, dot((M[i][j], M[i][j]) for i in range(3) for j in range(3)))),
        mul(4.0, dot((p[k], Mm[k]) for k in range(3))),
    )
    trC = add(add(C[0][0], C[1][1]), C[2][2])
    Cm = matvec(C, p)
    CTm = [dot((C[k][i], p[k]) for k in range(3)) for i in range(3)]
    eps_C = [sub(C[1][2], C[2][1]), sub(C[2][0], C[0][2]), sub(C[0][1], C[1][0])]
    E_sw = [add(mul(Es, w[i]), mul(2.0, CTm[i])) for i in range(3)]
    E_cross = [add(v, eps_C[i]) for i, v in enumerate(cross(p, w))]
    E_pw = add(dot((p[k], w[k]) for k in range(3)), trC)
    Mw = matvec(M, w)
    E_pwp = [add(add(mul(p[i], E_pw), Cm[i]), Mw[i]) for i in range(3)]
    c8 = mul(8.0, c)
    v_p = [
        sub(mul(0.25, add(sub(w[i], E_sw[i]), mul(2.0, add(E_cross[i], E_pwp[i])))), mul(c8, add(p[i], Esp[i])))
        for i in range(3)
    ]
    E_pwT = [[add(mul(p[i], w[j]), C[i][j]) for j in range(3)] for i in range(3)]
    F = add_cross_matrix([[sub(E_pwT[i][j], E_pwT[j][i]) for j in range(3)] for i in range(3)], w, -1.0)
    one_Es = add(1.0, Es)
    J_pp = [
        [
            sub(
                mul(0.5, add(F[i][j], E_pw if i == j else None)),
                mul(c8, add(one_Es if i == j else None, mul(2.0, Epp[i][j]))),
            )
            for j in range(3)
        ]
        for i in range(3)
    ]
    grad = [mul(4.0, add(p[i], Esp[i])) for i in range(3)]
    hess = [[add(mul(4.0, one_Es) if i == j else None, mul(8.0, Epp[i][j])) for j in range(3)] for i in range(3)]
    out = {
        "scalar": sub(mul(1.5, E_pw), mul(mul(4.0, c), add(3.0, mul(5.0, Es)))),
        "transport": v_p,
        "transport_jacobian": J_pp,
        "field": add(add(1.0, mul(2.0, Es)), Es2),
        "gradient": grad,
        "hessian": hess,
    }
    if n == 6:
        one_minus = sub(1.0, Es)
        px = add_cross_matrix(zeros(3), [mul(2.0, v) for v in p])  # 2[p×]
        E_B = [
            [add(add(one_minus if i == j else None, px[i][j]), mul(2.0, Epp[i][j])) for j in range(3)] for i in range(3)
        ]
        out["transport_jacobian"] = [J_pp[i] + [mul(-0.25, v) for v in E_B[i]] for i in range(3)] + zeros(3, 6)
        out["transport"] = v_p + [None] * 3
        out["gradient"] = grad + [None] * 3
        out["hessian"] = [row + [None] * 3 for row in hess] + zeros(3, 6)
    return out
