"""Counter-based random numbers: a sample is a pure function of (seed, member, step, component).

A stream therefore needs no generator state (checkpoints hold only the step counter), is the same on CPU
and CUDA, and member b of a batched run draws exactly what a batch-of-one run with the same seed and
member index draws, so a sweep equals its separate runs member by member.
"""

from __future__ import annotations

import math

import torch

_MASK32 = 0xFFFFFFFF


def _mul32(x: torch.Tensor, c: int) -> torch.Tensor:
    """(x * c) mod 2**32 for 0 <= x < 2**32 without int64 overflow (split c into 16-bit halves)."""
    lo, hi = c & 0xFFFF, c >> 16
    return (x * lo + (((x * hi) & 0xFFFF) << 16)) & _MASK32


def _mix32(x: torch.Tensor) -> torch.Tensor:
    """A 32-bit integer finalizer with good avalanche (xor-shift-multiply, constants 0x7feb352d, 0x846ca68b)."""
    x = x ^ (x >> 16)
    x = _mul32(x, 0x7FEB352D)
    x = x ^ (x >> 15)
    x = _mul32(x, 0x846CA68B)
    return x ^ (x >> 16)


def hash32(*keys: torch.Tensor | int) -> torch.Tensor:
    """Combine integer keys into uniformly distributed 32-bit integers.

    h_1 = mix(k_1 ^ 0x9E3779B9), h_i = mix(h_(i-1) ^ mix(k_i + 0x632BE5AB)), each key taken mod 2**32.

    Parameters
    ----------
    *keys : torch.Tensor or int
        Integer keys, broadcast together (e.g. seed, member, step, component).

    Returns
    -------
    torch.Tensor
        int64, values in [0, 2**32), of the keys' broadcast shape.
    """
    h = None
    for key in keys:
        k = torch.as_tensor(key, dtype=torch.int64) if not isinstance(key, torch.Tensor) else key.long()
        k = k & _MASK32
        h = _mix32(k ^ 0x9E3779B9) if h is None else _mix32(h ^ _mix32(k + 0x632BE5AB))
    return h


def uniform(*keys: torch.Tensor | int, dtype=torch.float64) -> torch.Tensor:
    """Uniform samples in the open interval (0, 1), 53 random bits from two hashes.

    Parameters
    ----------
    *keys : torch.Tensor or int
        Integer keys, broadcast together; equal keys give equal samples.
    dtype : torch.dtype, optional
        Floating-point type of the result (float64 by default).

    Returns
    -------
    torch.Tensor
        Of the keys' broadcast shape.
    """
    a = hash32(*keys, 0x1B873593)
    b = hash32(*keys, 0x5BD1E995)
    hi = (a >> 5).to(torch.float64)  # 27 bits
    lo = (b >> 6).to(torch.float64)  # 26 bits
    u = (hi * 67108864.0 + lo + 0.5) / 9007199254740992.0
    return u.to(dtype)


def normal(seed: torch.Tensor | int, member: torch.Tensor | int, step: torch.Tensor | int,
           component: torch.Tensor | int = 0, dtype=torch.float64) -> torch.Tensor:
    """Standard normal samples of a stream, drawn in pairs of steps by the Box-Muller transform.

    The steps 2p and 2p + 1 share the uniforms u1 = uniform(seed, member, p, component, 1) and
    u2 = uniform(seed, member, p, component, 2): with r = sqrt(-2 ln u1), step 2p draws r cos(2 pi u2) and step
    2p + 1 draws r sin(2 pi u2), two independent N(0, 1) samples for one logarithm and one square root.

    Parameters
    ----------
    seed, member, step, component : torch.Tensor or int
        Integer keys, broadcast together (steps >= 0); equal keys give equal samples.
    dtype : torch.dtype, optional
        Floating-point type of the result (float64 by default).

    Returns
    -------
    torch.Tensor
        Of the keys' broadcast shape.
    """
    step = torch.as_tensor(step, dtype=torch.int64)
    pair = torch.div(step, 2, rounding_mode="floor")
    even, odd = box_muller(uniform(seed, member, pair, component, 1, dtype=torch.float64),
                           uniform(seed, member, pair, component, 2, dtype=torch.float64))
    return torch.where(step % 2 == 0, even, odd).to(dtype)


def box_muller(u1: torch.Tensor, u2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The two normals of a pair of uniforms: r cos(2 pi u2) and r sin(2 pi u2), r = sqrt(-2 ln u1).

    Parameters
    ----------
    u1, u2 : torch.Tensor
        Uniforms in (0, 1), float64, of one shape.

    Returns
    -------
    tuple of torch.Tensor
        The even step's and the odd step's samples, of that shape.
    """
    r, angle = torch.sqrt(-2.0 * torch.log(u1)), 2.0 * math.pi * u2
    return r * torch.cos(angle), r * torch.sin(angle)
