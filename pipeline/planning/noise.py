"""Counter-based random streams computed with tensor ops: one stream per planning problem, no
Python loop over problems, no generator state, no host synchronization.

A problem's noise is a pure function of its key (a 32-bit integer held in an int64 tensor, derived
from the episode's seed and a counter such as its replan number) and of the CEM iteration. So a
problem draws the same noise whichever other problems share the batch, on any device, in eager
mode, under `torch.compile` and inside a CUDA graph alike.

The integer hash is one of Chris Wellons' two-round multiply-xorshift hashes (hash-prospector:
shifts 16, 15, 15, multipliers 0x21f0aaad, 0x735a2d97; low bias in the avalanche test). Both
multipliers are below 2^31, so with operands below 2^32 every product stays below 2^63: int64
never overflows, whatever a backend does on signed overflow. Normal samples come from the
Box-Muller transform of 24-bit uniforms (exact in float32).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

MASK32 = 0xFFFFFFFF
_GOLDEN = 0x9E3779B9  # odd constant that separates the hashed fields


def hash32(x: torch.Tensor) -> torch.Tensor:
    """The 32-bit hash of int64 `x` in [0, 2^32), elementwise; the result is in [0, 2^32)."""
    x = x ^ (x >> 16)
    x = (x * 0x21F0AAAD) & MASK32
    x = x ^ (x >> 15)
    x = (x * 0x735A2D97) & MASK32
    return x ^ (x >> 15)


def problem_keys(seeds: Sequence[int], device: torch.device | str) -> torch.Tensor:
    """`[B]` int64 stream keys from B integer seeds (any size; folded to 32 bits by hashing)."""
    folded = [(int(s) & MASK32) ^ ((int(s) >> 32) * _GOLDEN & MASK32) for s in seeds]
    return hash32(torch.tensor(folded, dtype=torch.long, device=device))


def _hash32_int(x: int) -> int:
    """`hash32` of one Python int (no tensor: nothing to copy to a device, nothing to capture)."""
    x ^= x >> 16
    x = (x * 0x21F0AAAD) & MASK32
    x ^= x >> 15
    x = (x * 0x735A2D97) & MASK32
    return x ^ (x >> 15)


def substream(keys: torch.Tensor, counter: torch.Tensor | int) -> torch.Tensor:
    """Keys of the `counter`-th substream of each stream, `[B]` (e.g. an episode's n-th replan,
    a plan's i-th CEM iteration). `counter`: int, or int64 tensor broadcastable to `keys`."""
    if isinstance(counter, int):
        return hash32(keys ^ _hash32_int((counter + _GOLDEN) & MASK32))
    return hash32(keys ^ hash32((counter + _GOLDEN) & MASK32))


def normal(keys: torch.Tensor, shape: Sequence[int]) -> torch.Tensor:
    """`[B, *shape]` float32 standard normal samples, row b a function of `keys[b]` alone."""
    n = math.prod(shape)
    pairs = (n + 1) // 2
    counter = torch.arange(2 * pairs, dtype=torch.long, device=keys.device)
    bits = hash32(hash32(counter)[None] ^ keys[:, None])  # [B, 2P]
    uniform = ((bits >> 8).float() + 0.5) * 2.0**-24  # (0, 1), exact in float32
    u1, u2 = uniform[:, :pairs], uniform[:, pairs:]
    radius = torch.sqrt(-2.0 * torch.log(u1))
    angle = (2.0 * math.pi) * u2
    z = torch.cat([radius * torch.cos(angle), radius * torch.sin(angle)], dim=1)
    return z[:, :n].reshape(len(keys), *shape)
