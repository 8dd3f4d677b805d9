"""Counter-based random numbers in pure torch.

A draw is a *pure function* of ``(seed, step, stream, element)``:

    h₀ = mix(seed·G + G)
    h₁ = mix(h₀ + (step + 1)·G)
    h₂ = mix(h₁ + (stream + 1)·G)                     (the "key" of one draw)
    u(c) = (mix(h₂ + (c + 1)·G) >> 11) · 2⁻⁵³          (uniform on [0, 1), 53 bits)

where ``mix`` is the splitmix64 finaliser (Steele, Lea & Flood 2014; Stafford's
"variant 13" constants) and ``G = 0x9E3779B97F4A7C15`` (the 64-bit golden ratio).
Every stage is a bijection of a 64-bit word (multiplication by an odd constant,
addition, xor-shift), so two counters that differ in one coordinate give
independent-looking words.  Arithmetic is done on ``torch.int64`` with wrap-around
multiplication (two's complement) and *logical* right shifts emulated by masking
the arithmetic shift, so the bit pattern equals the unsigned ``uint64`` reference.

Standard normals use Box–Muller on pairs: element ``e`` uses the uniforms with
counters ``c = 2⌊e/2⌋`` and ``2⌊e/2⌋ + 1`` of the same key,

    z_e = sqrt(−2 ln(1 − u(2⌊e/2⌋))) · (cos if e even else sin)(2π u(2⌊e/2⌋ + 1)),

so that element ``e`` depends on ``e`` alone (not on how many elements are drawn).
Use distinct ``stream`` ids for uniform and normal draws: a normal draw reads the
uniforms of its own stream.

Because nothing depends on a generator's state, a batch of trajectories whose seeds
are ``seed + i`` draws, in one tensor program, exactly the numbers that B separate
single runs seeded with ``seed + i`` draw.  Seeds are Python ints reduced modulo 2⁶⁴
(:func:`as_int64`) or ``int64`` tensors (any leading shape; the ``step`` and
``stream`` arguments broadcast against it).

The stream ids of the star-tracker simulation (:data:`STREAM_INITIAL_ATTITUDE` …
:data:`STREAM_NEXT_SEED`) are defined here, in one place, so that no two noise
sources share a stream; :func:`next_episode_seeds` derives the seed of the next
episode.  (:func:`envs.camera.random_attitude_quat` uses stream 7001 by default.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "as_int64",
    "mix64",
    "hash_key",
    "random_bits",
    "counter_uniform",
    "counter_normal",
    "CounterKey",
    "STREAM_INITIAL_ATTITUDE",
    "STREAM_GYRO_RATE_NOISE",
    "STREAM_GYRO_BIAS_WALK",
    "STREAM_STAR_NOISE",
    "STREAM_NEXT_SEED",
    "SEED_MASK",
    "next_episode_seeds",
]

IntLike = int | Tensor

_U64 = 1 << 64


def as_int64(value: int) -> int:
    """Two's-complement ``int64`` value of the unsigned 64-bit word ``value mod 2⁶⁴``.

    Args:
        value: any Python int (negative values wrap as well).

    Returns:
        An int in ``[−2⁶³, 2⁶³)``.
    """
    value = int(value) % _U64
    return value - _U64 if value >= (1 << 63) else value


_GOLDEN = as_int64(0x9E3779B97F4A7C15)
_M1 = as_int64(0xBF58476D1CE4E5B9)
_M2 = as_int64(0x94D049BB133111EB)
_TWO_POW_M53 = 2.0**-53

STREAM_INITIAL_ATTITUDE = 1
"""Counter-RNG stream of the random initial attitude (step 0, 4 normals)."""
STREAM_GYRO_RATE_NOISE = 2
"""Stream of the gyro measurement noise N_v (step k, 3 normals)."""
STREAM_GYRO_BIAS_WALK = 3
"""Stream of the bias random walk N_u (step k, 3 normals)."""
STREAM_STAR_NOISE = 4
"""Stream of the star-camera noise (step k, M×3 normals)."""
STREAM_NEXT_SEED = 5
"""Stream deriving the next episode's seed on an unseeded reset."""
SEED_MASK = (1 << 62) - 1
"""Episode seeds drawn or derived by the environments lie in ``[0, SEED_MASK]`` = ``[0, 2⁶²)``."""


def _srl(x: Tensor, k: int) -> Tensor:
    """Logical right shift of int64 words (arithmetic shift, then mask the sign fill)."""
    return (x >> k) & ((1 << (64 - k)) - 1)


def mix64(x: Tensor) -> Tensor:
    """splitmix64 finaliser on int64 words (bit-exact with the uint64 reference).

    .. math:: z ← (z ⊕ (z ≫ 30))·M_1;\\; z ← (z ⊕ (z ≫ 27))·M_2;\\; z ← z ⊕ (z ≫ 31)

    with logical shifts and multiplication modulo 2⁶⁴.

    Args:
        x: ``torch.int64`` tensor of any shape.

    Returns:
        Same shape, ``torch.int64``.
    """
    x = (x ^ _srl(x, 30)) * _M1
    x = (x ^ _srl(x, 27)) * _M2
    return x ^ _srl(x, 31)


def _as_tensor(v: IntLike, device: torch.device | None) -> Tensor:
    if isinstance(v, Tensor):
        if v.dtype != torch.int64:
            raise ValueError(f"counter values must be int64 tensors, got dtype {v.dtype}")
        return v
    return torch.tensor(as_int64(v), dtype=torch.int64, device=device)


def hash_key(seed: IntLike, step: IntLike, stream: IntLike) -> Tensor:
    """Key of the draw ``(seed, step, stream)``: ``h₂`` of the module docstring.

    Args:
        seed, step, stream: Python ints or int64 tensors (broadcast together).

    Returns:
        int64 tensor of the broadcast shape.
    """
    device = next((v.device for v in (seed, step, stream) if isinstance(v, Tensor)), None)
    s = _as_tensor(seed, device)
    h = mix64(s * _GOLDEN + _GOLDEN)
    h = mix64(h + (_as_tensor(step, device) + 1) * _GOLDEN)
    return mix64(h + (_as_tensor(stream, device) + 1) * _GOLDEN)


def _counter_bits(key: Tensor, counters: Tensor) -> Tensor:
    """``mix(key + (c + 1)·G)`` for ``key [...]`` and ``counters [n]`` → ``[..., n]``."""
    return mix64(key[..., None] + (counters + 1) * _GOLDEN)


def random_bits(seed: IntLike, step: IntLike, stream: IntLike, shape: Sequence[int]) -> Tensor:
    """Raw 64-bit words (int64 bit patterns) of the counters ``0 … prod(shape) − 1``.

    Args:
        seed, step, stream: ints or int64 tensors, broadcast to a key shape ``[...]``.
        shape: per-key output shape.

    Returns:
        ``[..., *shape]`` int64.
    """
    key = hash_key(seed, step, stream)
    n = math.prod(shape)
    c = torch.arange(n, dtype=torch.int64, device=key.device)
    return _counter_bits(key, c).reshape(*key.shape, *shape)


def _bits_to_unit(bits: Tensor, dtype: torch.dtype) -> Tensor:
    """Top 53 bits → float in ``[0, 1)`` (exact multiples of 2⁻⁵³)."""
    return _srl(bits, 11).to(dtype) * _TWO_POW_M53


def counter_uniform(
    seed: IntLike,
    step: IntLike,
    stream: IntLike,
    shape: Sequence[int],
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """Uniform draws on ``[0, 1)``, a pure function of ``(seed, step, stream, element)``.

    Args:
        seed, step, stream: ints or int64 tensors, broadcast to a key shape ``[...]``.
        shape: per-key output shape; element ``e`` is the row-major flat index.
        dtype: floating dtype (53-bit resolution in float64).

    Returns:
        ``[..., *shape]``.
    """
    return _bits_to_unit(random_bits(seed, step, stream, shape), dtype)


def counter_normal(
    seed: IntLike,
    step: IntLike,
    stream: IntLike,
    shape: Sequence[int],
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """Standard normal draws by Box–Muller, a pure function of ``(seed, step, stream, element)``.

    Element ``e`` uses the uniform pair ``(u(2⌊e/2⌋), u(2⌊e/2⌋+1))`` of the key and takes
    the cosine branch for even ``e`` and the sine branch for odd ``e``:
    ``z = sqrt(−2 ln(1 − u₁)) · cos/sin(2π u₂)`` (``1 − u₁ ∈ (0, 1]``, so ``|z| ≤ 8.6``).

    Args:
        seed, step, stream: ints or int64 tensors, broadcast to a key shape ``[...]``.
        shape: per-key output shape.
        dtype: floating dtype.

    Returns:
        ``[..., *shape]`` of independent N(0, 1) draws.
    """
    key = hash_key(seed, step, stream)
    n = math.prod(shape)
    pairs = (n + 1) // 2
    c = torch.arange(pairs, dtype=torch.int64, device=key.device) * 2
    u1 = _bits_to_unit(_counter_bits(key, c), dtype)
    u2 = _bits_to_unit(_counter_bits(key, c + 1), dtype)
    radius = torch.sqrt(-2.0 * torch.log1p(-u1))
    angle = (2.0 * math.pi) * u2
    z = torch.stack((radius * torch.cos(angle), radius * torch.sin(angle)), -1)
    z = z.reshape(*key.shape, 2 * pairs)[..., :n]
    return z.reshape(*key.shape, *shape)


@dataclass(frozen=True)
class CounterKey:
    """A bundle ``(seed, step, stream)`` naming one family of counter-based draws.

    Attributes:
        seed: int or int64 tensor ``[...]`` (for example ``[B]``, one seed per trajectory).
        step: int or int64 tensor broadcastable with ``seed`` (time-step index).
        stream: int or int64 tensor (which noise source).
    """

    seed: IntLike
    step: IntLike
    stream: IntLike

    def uniform(self, shape: Sequence[int], dtype: torch.dtype = torch.float64) -> Tensor:
        """:func:`counter_uniform` of this key → ``[..., *shape]``."""
        return counter_uniform(self.seed, self.step, self.stream, shape, dtype)

    def normal(self, shape: Sequence[int], dtype: torch.dtype = torch.float64) -> Tensor:
        """:func:`counter_normal` of this key → ``[..., *shape]``."""
        return counter_normal(self.seed, self.step, self.stream, shape, dtype)


def next_episode_seeds(seeds: Tensor) -> Tensor:
    """Seeds of the next episodes, derived from the current ones.

    ``next = bits(seed, step 0, STREAM_NEXT_SEED) mod 2⁶²`` (a splitmix64 hash of the
    seed), so an unseeded reset continues deterministically.

    Args:
        seeds: int64 episode seeds ``[...]``.

    Returns:
        int64 ``[...]`` in ``[0, 2⁶²)``.
    """
    return random_bits(seeds, 0, STREAM_NEXT_SEED, ()) & SEED_MASK
