"""Small-matrix algebra on entries, unrolled at trace time with structural zeros and ones removed.

A matrix is a list of rows; an entry is a lane tensor ``[C]`` (one value per component), a
Python number known when the kernel is traced, or ``None`` for a structural zero.  The
operations here fold what is known: ``None`` terms are skipped, ``1.0`` factors are not
multiplied, so a product with the attitude model's zero bias rows, Φ's identity bias block or
a block-diagonal noise matrix emits no arithmetic for those entries (as Matriplex's generated
code does).  Every function is plain Python over entries: it runs eagerly, or is traced
by :func:`torch.export.export` and compiled into one loop (:mod:`agsf_torch.fused.lanes`).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "Entry",
    "add",
    "sub",
    "neg",
    "mul",
    "dot",
    "matmul",
    "matmul_t",
    "identity",
    "zeros",
    "symmetric_part",
    "cholesky",
    "cholesky_solve",
    "forward_substitution",
    "div",
    "matvec",
    "cross",
    "cross_matrix",
    "add_cross_matrix",
    "as_entries",
    "as_tensor",
    "count",
]

Entry = Tensor | float | None

#: Arithmetic operations emitted since the last :func:`count` reset (for FLOP counts of a traced kernel).
_OPS = [0]


def _tick() -> None:
    if not torch.compiler.is_compiling():  # counted when run eagerly; a traced kernel has no side effects
        _OPS[0] += 1


def count(reset: bool = False) -> int:
    """Floating-point operations emitted by this module's functions (lane operations, each ``C`` FLOPs);
    ``reset`` starts a new count."""
    value = _OPS[0]
    if reset:
        _OPS[0] = 0
    return value


def add(a: Entry, b: Entry) -> Entry:
    """``a + b`` (``None`` is zero)."""
    if a is None:
        return b
    if b is None:
        return a
    if isinstance(a, float) and isinstance(b, float):
        return a + b
    _tick()
    return a + b


def sub(a: Entry, b: Entry) -> Entry:
    """``a − b`` (``None`` is zero)."""
    if b is None:
        return a
    if a is None:
        return neg(b)
    if isinstance(a, float) and isinstance(b, float):
        return a - b
    _tick()
    return a - b


def neg(a: Entry) -> Entry:
    """``−a``."""
    if a is None:
        return None
    if isinstance(a, float):
        return -a
    _tick()
    return -a


def mul(a: Entry, b: Entry) -> Entry:
    """``a · b`` (``None`` is zero; a known 1 emits nothing)."""
    if a is None or b is None:
        return None
    if isinstance(a, float):
        if a == 0.0:
            return None
        if a == 1.0:
            return b
        if isinstance(b, float):
            return a * b
    if isinstance(b, float):
        if b == 0.0:
            return None
        if b == 1.0:
            return a
    _tick()
    return a * b


def div(a: Entry, b: Entry) -> Entry:
    """``a / b`` (``None`` is zero; ``b`` must not be)."""
    if a is None:
        return None
    if isinstance(a, float) and isinstance(b, float):
        return a / b
    if isinstance(b, float) and b == 1.0:
        return a
    _tick()
    return a / b


def dot(terms) -> Entry:
    """``Σ aₖ bₖ`` over pairs ``(aₖ, bₖ)``, skipping structural zeros."""
    out: Entry = None
    for a, b in terms:
        out = add(out, mul(a, b))
    return out


def matmul(A: list[list[Entry]], B: list[list[Entry]]) -> list[list[Entry]]:
    """``A B``."""
    k = len(B)
    return [[dot((A[i][t], B[t][j]) for t in range(k)) for j in range(len(B[0]))] for i in range(len(A))]


def matmul_t(A: list[list[Entry]], B: list[list[Entry]]) -> list[list[Entry]]:
    """``A Bᵀ``."""
    k = len(A[0])
    return [[dot((A[i][t], B[j][t]) for t in range(k)) for j in range(len(B))] for i in range(len(A))]


def matvec(A: list[list[Entry]], x: list[Entry]) -> list[Entry]:
    """``A x``."""
    return [dot((row[k], x[k]) for k in range(len(x))) for row in A]


def cross(a: list[Entry], b: list[Entry]) -> list[Entry]:
    """``a × b`` of two 3-vectors."""
    return [
        sub(mul(a[1], b[2]), mul(a[2], b[1])),
        sub(mul(a[2], b[0]), mul(a[0], b[2])),
        sub(mul(a[0], b[1]), mul(a[1], b[0])),
    ]


#: ``[v×]``'s off-diagonal entries: ``(i, j) → (k, ±1)`` with ``[v×]ᵢⱼ = ±vₖ``.
_SKEW = {(0, 1): (2, -1.0), (0, 2): (1, 1.0), (1, 0): (2, 1.0), (1, 2): (0, -1.0), (2, 0): (1, -1.0), (2, 1): (0, 1.0)}


def cross_matrix(v: list[Entry]) -> list[list[Entry]]:
    """``[v×]`` (``[v×] u = v × u``), its diagonal structural zeros."""
    return add_cross_matrix(zeros(3), v)


def add_cross_matrix(A: list[list[Entry]], v: list[Entry], sign: float = 1.0) -> list[list[Entry]]:
    """``A ± [v×]`` (3×3, ``sign`` = ±1) with one addition or subtraction per off-diagonal entry (no negations)."""
    out = [list(row) for row in A]
    for (i, j), (k, s) in _SKEW.items():
        out[i][j] = add(A[i][j], v[k]) if s * sign > 0 else sub(A[i][j], v[k])
    return out


def identity(n: int) -> list[list[Entry]]:
    """``I_n`` with known ones and structural zeros."""
    return [[1.0 if i == j else None for j in range(n)] for i in range(n)]


def zeros(n: int, m: int | None = None) -> list[list[Entry]]:
    """A structural zero ``n×m`` matrix."""
    return [[None] * (n if m is None else m) for _ in range(n)]


def symmetric_part(A: list[list[Entry]]) -> list[list[Entry]]:
    """``½(A + Aᵀ)`` (the diagonal as it is)."""
    n = len(A)
    return [[A[i][j] if i == j else mul(0.5, add(A[i][j], A[j][i])) for j in range(n)] for i in range(n)]


def cholesky(P: list[list[Entry]]) -> tuple[list[list[Entry]], list[Entry], Tensor]:
    """The lower Cholesky factor ``L`` of ``P = LLᵀ`` (lower triangle read), the reciprocals of its
    diagonal and whether every pivot is positive and finite (``[C]`` bool).

    A non-positive pivot is clamped to ``1e-300`` so the arithmetic stays finite; the flag says where.
    Every diagonal entry of ``P`` must be a lane (a positive definite matrix has no structural zero there).
    """
    n = len(P)
    L: list[list[Entry]] = zeros(n)
    inv: list[Entry] = [None] * n
    ok = None
    for j in range(n):
        d = P[j][j]
        for k in range(j):
            d = sub(d, mul(L[j][k], L[j][k]))
        good = d > 0.0
        ok = good if ok is None else ok & good
        L[j][j] = d.clamp_min(1e-300).sqrt()
        inv[j] = 1.0 / L[j][j]
        for i in range(j + 1, n):
            v = P[i][j]
            for k in range(j):
                v = sub(v, mul(L[i][k], L[j][k]))
            L[i][j] = mul(v, inv[j])
    return L, inv, ok


def forward_substitution(L: list[list[Entry]], inv: list[Entry], b: list[Entry]) -> list[Entry]:
    """``z = L⁻¹ b`` for a lower-triangular ``L`` with the reciprocals ``inv`` of its diagonal (known zeros of
    ``b`` emit no arithmetic until they fill in)."""
    n = len(L)
    z: list[Entry] = [None] * n
    for k in range(n):
        v = b[k]
        for t in range(k):
            v = sub(v, mul(L[k][t], z[t]))
        z[k] = mul(v, inv[k])
    return z


def cholesky_solve(L: list[list[Entry]], inv: list[Entry], b: list[Entry]) -> list[Entry]:
    """``x = (LLᵀ)⁻¹ b`` for one right-hand side ``b``: :func:`forward_substitution`, then back substitution."""
    n = len(L)
    z = forward_substitution(L, inv, b)
    x: list[Entry] = [None] * n
    for k in reversed(range(n)):
        v = z[k]
        for t in range(k + 1, n):
            v = sub(v, mul(L[t][k], x[t]))
        x[k] = mul(v, inv[k])
    return x


def as_entries(t: Tensor, shape: tuple[int, ...]):
    """The entries of ``t [..., *shape]`` as nested lists (``shape`` deep) of views ``[...]``: how a batched tensor
    method applies a function written on entries (any leading dims; the views broadcast as their tensors do)."""
    if not shape:
        return t
    return [as_entries(row, shape[1:]) for row in t.unbind(-len(shape))]


def as_tensor(nested, like: Tensor | None = None) -> Tensor:
    """Nested lists of entries (tensors broadcasting to one shape ``[...]``, numbers, ``None`` for zero) back to
    one tensor ``[..., *shape]``; ``like`` gives the dtype and device where no entry is a tensor."""

    def flatten(x) -> list:
        return [v for item in x for v in flatten(item)] if isinstance(x, list) else [x]

    def dims(x) -> list[int]:
        return [len(x), *dims(x[0])] if isinstance(x, list) else []

    flat = flatten(nested)
    tensors = [v for v in flat if isinstance(v, Tensor)]
    ref = tensors[0] if tensors else like
    values = sorted({0.0 if v is None else float(v) for v in flat if not isinstance(v, Tensor)})
    constants = [torch.full((), value, dtype=ref.dtype, device=ref.device) for value in values]
    # one call broadcasts every entry (each distinct constant, the structural zeros say, once)
    views = iter(torch.broadcast_tensors(*tensors, *constants))
    columns = [next(views) for _ in tensors]
    constant_views = {value: next(views) for value in values}
    tensor_columns = iter(columns)
    stacked = [
        next(tensor_columns) if isinstance(v, Tensor) else constant_views[0.0 if v is None else float(v)] for v in flat
    ]
    return torch.stack(stacked, -1).reshape(*stacked[0].shape, *dims(nested))
