"""A numba peer: ``sdof-stiffness-damping`` as a jitted loop, written the way a performance-minded user would.

The same equations as the NumPy loop (``numpy_loop.py``, and rcotorch's Figure-1 graph): ZOH-discretized known
model and truth (scipy ``expm``, in Python, outside the loop), Markov parameters beta_i = -C_y A^(i-1) B_u, the
retrospective cost over a ring buffer of [phi, u], the scalar RLS update, and the excitation drawn inside the
loop from the same counter-based stream as ``rcotorch.engine.rng`` (seed, member, pair of steps, component; the
hash written out in uint32 arithmetic, Box-Muller with ``math.log``, ``math.cos`` and ``math.sin``).

Three variants, each compiled once (``numba.njit``, not cached):

* ``refine_one``: one member, a plain loop over steps;
* ``refine_prange``: B members, ``prange`` over members, each member its own loop (threads share nothing);
* ``refine_lanes``: B members in chunks of 16 lanes (state as (…, 16) arrays, every operation a loop over the
  lanes, which LLVM vectorizes), ``prange`` over chunks.

The stream pairs its steps: steps 2p and 2p + 1 take r cos(2 pi u2) and r sin(2 pi u2) of the uniforms of pair
p. Each variant draws it either one normal a step (``pairs=False``: a log, a square root and a cosine or a sine
each step) or two at a time (``pairs=True``: one log and one square root, a cosine and a sine for two steps, the
sine kept for the next step), as a user writing for speed would; both give the same numbers.

``tests/test_numba_peer.py`` checks every variant, either way, against the NumPy loop to 1e-9 and the stream's
normals against N(0, 1) (skipped without numba); ``benchmarks/peer.py`` times it against the native engine.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange
from numpy_loop import DEFAULTS, sdof, zoh

LANES = 16
U32 = np.uint32


@numba.njit(inline="always")
def _mix(x):
    """rng._mix32 in uint32 arithmetic."""
    x = x ^ (x >> U32(16))
    x = U32(x * U32(0x7FEB352D))
    x = x ^ (x >> U32(15))
    x = U32(x * U32(0x846CA68B))
    return x ^ (x >> U32(16))


@numba.njit(inline="always")
def _mix_key(key):
    """rng._mix32(key + 0x632BE5AB) for a 32-bit key: the carry of the 33-bit sum enters the first shift."""
    lo = U32(key + U32(0x632BE5AB))
    hi = U32(1) if lo < key else U32(0)
    y = lo ^ ((lo >> U32(16)) | (hi << U32(16)))
    y = U32(y * U32(0x7FEB352D))
    y = y ^ (y >> U32(15))
    y = U32(y * U32(0x846CA68B))
    return y ^ (y >> U32(16))


@numba.njit(inline="always")
def _uniform(h, c1, c2):
    a = np.int64(_mix(h ^ c1) >> U32(5))
    b = np.int64(_mix(h ^ c2) >> U32(6))
    return (a * 67108864.0 + b + 0.5) / 9007199254740992.0


@numba.njit(inline="always")
def _stream(seed, member):
    """The hash of (seed, member), the common prefix of every sample of a stream."""
    h = _mix(U32(seed & 0xFFFFFFFF) ^ U32(0x9E3779B9))
    return _mix(h ^ _mix_key(U32(member & 0xFFFFFFFF)))


@numba.njit(inline="always")
def _uniforms(h0, p):
    """The two uniforms of the pair p of the stream with prefix h0 (component 0)."""
    h = _mix(_mix(h0 ^ _mix_key(U32(p & 0xFFFFFFFF))) ^ _mix_key(U32(0)))
    c1, c2 = _mix_key(U32(0x1B873593)), _mix_key(U32(0x5BD1E995))
    return _uniform(_mix(h ^ _mix_key(U32(1))), c1, c2), _uniform(_mix(h ^ _mix_key(U32(2))), c1, c2)


@numba.njit(inline="always")
def _normal(h0, k):
    """rng.normal(seed, member, k, 0) from the stream prefix h0, alone."""
    u1, u2 = _uniforms(h0, k // 2)
    r = math.sqrt(-2.0 * math.log(u1))
    return r * math.cos(2.0 * math.pi * u2) if k % 2 == 0 else r * math.sin(2.0 * math.pi * u2)


@numba.njit(inline="always")
def _normal_pair(h0, p):
    """rng.normal(seed, member, k, 0) at the steps k = 2p and 2p + 1 from the stream prefix h0, together."""
    u1, u2 = _uniforms(h0, p)
    r = math.sqrt(-2.0 * math.log(u1))
    return r * math.cos(2.0 * math.pi * u2), r * math.sin(2.0 * math.pi * u2)


@numba.njit(inline="always")
def _member(steps, h0, w_std, Ad, Bw, Bu, Atd, Btd, beta, p0, lam, theta_out, P_out, pairs=False):
    """One refinement (nc = 1: phi = [x(k-1), x'(k-1), u(k-1)]), the NumPy loop's equations. With ``pairs`` the
    excitation draws its normals two at a time (``_normal_pair``), as a user writing for speed would: the same
    numbers."""
    nu = beta.shape[0]
    W = nu + 1
    theta = np.zeros(3)
    P = np.zeros((3, 3))
    for i in range(3):
        P[i, i] = p0
    hist = np.zeros((W, 4))
    xm0 = xm1 = xt0 = xt1 = 0.0
    py0 = py1 = pu = 0.0
    a = np.zeros(3)
    psi = np.zeros(3)
    inv_lam = 1.0 / lam
    r = 0                                                # k mod W
    spare = 0.0
    for k in range(steps):
        if not pairs:
            w = w_std * _normal(h0, k)
        elif k % 2 == 0:
            first, spare = _normal_pair(h0, k // 2)
            w = w_std * first
        else:
            w = w_std * spare
        y_hat = xm1
        u = theta[0] * py0 + theta[1] * py1 + theta[2] * pu
        z = xt1 - y_hat
        hist[r, 0], hist[r, 1], hist[r, 2], hist[r, 3] = py0, py1, pu, u
        f0 = f1 = f2 = f3 = 0.0
        row = r
        for i in range(nu):
            row = row - 1 if row > 0 else W - 1          # time k-1-i, no modulo in the loop
            f0 += beta[i] * hist[row, 0]
            f1 += beta[i] * hist[row, 1]
            f2 += beta[i] * hist[row, 2]
            f3 += beta[i] * hist[row, 3]
        psi[0], psi[1], psi[2] = f0, f1, f2
        z_r = z - f3 + f0 * theta[0] + f1 * theta[1] + f2 * theta[2]
        s = lam
        for i in range(3):
            a[i] = P[i, 0] * psi[0] + P[i, 1] * psi[1] + P[i, 2] * psi[2]
            s += psi[i] * a[i]
        inv_s = 1.0 / s
        g = z_r * inv_s
        for i in range(3):
            theta[i] -= a[i] * g
            ai = a[i] * inv_s
            for j in range(3):
                P[i, j] = (P[i, j] - ai * a[j]) * inv_lam
        y0a, y0b = xm0, xm1
        n0 = Ad[0, 0] * xm0 + Ad[0, 1] * xm1 + Bw[0] * w + Bu[0] * u
        n1 = Ad[1, 0] * xm0 + Ad[1, 1] * xm1 + Bw[1] * w + Bu[1] * u
        xm0, xm1 = n0, n1
        t0 = Atd[0, 0] * xt0 + Atd[0, 1] * xt1 + Btd[0] * w
        t1 = Atd[1, 0] * xt0 + Atd[1, 1] * xt1 + Btd[1] * w
        xt0, xt1 = t0, t1
        py0, py1, pu = y0a, y0b, u
        r = r + 1 if r < W - 1 else 0
    theta_out[:] = theta
    P_out[:, :] = P


@numba.njit
def refine_one(steps, seed, member, w_std, Ad, Bw, Bu, Atd, Btd, beta, p0, lam, theta_out, P_out, pairs=False):
    _member(steps, _stream(seed, member), w_std, Ad, Bw, Bu, Atd, Btd, beta, p0, lam, theta_out, P_out, pairs)


@numba.njit(parallel=True)
def refine_prange(steps, seeds, members, w_std, Ad, Bw, Bu, Atd, Btd, beta, p0, lam, theta_out, P_out,
                  pairs=False):
    for b in prange(seeds.shape[0]):
        _member(steps, _stream(seeds[b], members[b]), w_std, Ad, Bw, Bu, Atd, Btd, beta, p0, lam, theta_out[b],
                P_out[b], pairs)


@numba.njit(inline="always")
def _chunk(steps, h0, w_std, Ad, Bw, Bu, Atd, Btd, beta, p0, lam, theta_out, P_out, pairs=False):
    """LANES members at once: every quantity a (LANES,) vector, every operation a loop over the lanes."""
    L = LANES
    nu = beta.shape[0]
    W = nu + 1
    theta = np.zeros((3, L))
    P = np.zeros((3, 3, L))
    for i in range(3):
        P[i, i, :] = p0
    hist = np.zeros((W, 4, L))
    xm0, xm1, xt0, xt1 = np.zeros(L), np.zeros(L), np.zeros(L), np.zeros(L)
    py0, py1, pu = np.zeros(L), np.zeros(L), np.zeros(L)
    a, psi, f3, w, u, z_r, s = (np.zeros((3, L)), np.zeros((3, L)), np.zeros(L), np.zeros(L), np.zeros(L),
                                np.zeros(L), np.zeros(L))
    inv_lam = 1.0 / lam
    r = 0
    spare = np.zeros(L)
    for k in range(steps):
        if pairs and k % 2 == 0:
            for l in range(L):
                first, spare[l] = _normal_pair(h0[l], k // 2)
                w[l] = w_std * first
        elif pairs:
            for l in range(L):
                w[l] = w_std * spare[l]
        else:
            for l in range(L):
                w[l] = w_std * _normal(h0[l], k)
        for l in range(L):
            u[l] = theta[0, l] * py0[l] + theta[1, l] * py1[l] + theta[2, l] * pu[l]
            hist[r, 0, l], hist[r, 1, l], hist[r, 2, l], hist[r, 3, l] = py0[l], py1[l], pu[l], u[l]
            psi[0, l] = psi[1, l] = psi[2, l] = f3[l] = 0.0
        row = r
        for i in range(nu):
            row = row - 1 if row > 0 else W - 1
            bi = beta[i]
            for l in range(L):
                psi[0, l] += bi * hist[row, 0, l]
                psi[1, l] += bi * hist[row, 1, l]
                psi[2, l] += bi * hist[row, 2, l]
                f3[l] += bi * hist[row, 3, l]
        for l in range(L):
            z_r[l] = (xt1[l] - xm1[l]) - f3[l] + psi[0, l] * theta[0, l] + psi[1, l] * theta[1, l] + \
                psi[2, l] * theta[2, l]
            s[l] = lam
        for i in range(3):
            for l in range(L):
                a[i, l] = P[i, 0, l] * psi[0, l] + P[i, 1, l] * psi[1, l] + P[i, 2, l] * psi[2, l]
                s[l] += psi[i, l] * a[i, l]
        for l in range(L):
            s[l] = 1.0 / s[l]                                # s now holds 1 / s
        for i in range(3):
            for l in range(L):
                theta[i, l] -= a[i, l] * (z_r[l] * s[l])
            for j in range(3):
                for l in range(L):
                    P[i, j, l] = (P[i, j, l] - a[i, l] * s[l] * a[j, l]) * inv_lam
        for l in range(L):
            y0a, y0b = xm0[l], xm1[l]
            n0 = Ad[0, 0] * xm0[l] + Ad[0, 1] * xm1[l] + Bw[0] * w[l] + Bu[0] * u[l]
            n1 = Ad[1, 0] * xm0[l] + Ad[1, 1] * xm1[l] + Bw[1] * w[l] + Bu[1] * u[l]
            xm0[l], xm1[l] = n0, n1
            t0 = Atd[0, 0] * xt0[l] + Atd[0, 1] * xt1[l] + Btd[0] * w[l]
            t1 = Atd[1, 0] * xt0[l] + Atd[1, 1] * xt1[l] + Btd[1] * w[l]
            xt0[l], xt1[l] = t0, t1
            py0[l], py1[l], pu[l] = y0a, y0b, u[l]
        r = r + 1 if r < W - 1 else 0
    for l in range(L):
        for i in range(3):
            theta_out[l, i] = theta[i, l]
            for j in range(3):
                P_out[l, i, j] = P[i, j, l]


@numba.njit(parallel=True)
def refine_lanes(steps, seeds, members, w_std, Ad, Bw, Bu, Atd, Btd, beta, p0, lam, theta_out, P_out, pairs=False):
    B = seeds.shape[0]
    nchunks = (B + LANES - 1) // LANES
    for c in prange(nchunks):
        h0 = np.empty(LANES, dtype=np.uint32)
        for l in range(LANES):
            b = min(c * LANES + l, B - 1)          # spare lanes repeat the last member
            h0[l] = _stream(seeds[b], members[b])
        th = np.empty((LANES, 3))
        Pc = np.empty((LANES, 3, 3))
        _chunk(steps, h0, w_std, Ad, Bw, Bu, Atd, Btd, beta, p0, lam, th, Pc, pairs)
        for l in range(min(LANES, B - c * LANES)):
            theta_out[c * LANES + l] = th[l]
            P_out[c * LANES + l] = Pc[l]


def model(settings: dict | None = None) -> dict:
    """The discretized matrices and Markov parameters of the NumPy loop (nc = 1)."""
    s = dict(DEFAULTS, **(settings or {}))
    if int(s["nc"]) != 1:
        raise ValueError("the numba peer is written for nc = 1")
    Ad, Bd = zoh(*_known(s), s["Ts"])
    At, Bt = sdof(s["m"], s["C"] + s["dC"], s["K"] + s["dK"])
    Atd, Btd = zoh(At, Bt, s["Ts"])
    Cy = np.array([0.0, 1.0])
    beta = np.empty(int(s["nu"]))
    AkB = Bd[:, 1].copy()
    for i in range(len(beta)):
        beta[i] = -Cy @ AkB
        AkB = Ad @ AkB
    return dict(w_std=float(s["w_std"]), Ad=Ad, Bw=Bd[:, 0].copy(), Bu=Bd[:, 1].copy(), Atd=Atd,
                Btd=Btd[:, 0].copy(), beta=beta, p0=float(s["p0"]), lam=float(s["lam"]), seed=int(s["seed"]))


def _known(s):
    A, B1 = sdof(s["m"], s["C"], s["K"])
    return A, np.hstack([B1, B1])


def streams(B: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(seed, member) of each member as rcotorch.WhiteNoise draws them: (seed, 0) alone, (seed, b) in a batch."""
    return np.full(B, seed, dtype=np.int64), (np.arange(B, dtype=np.int64) if B > 1 else np.zeros(1, np.int64))


def run(variant: str, steps: int, B: int = 1, settings: dict | None = None,
        pairs: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Final theta (B, 3) and P (B, 3, 3) of ``variant`` ('one', 'prange', 'lanes') for B members; ``pairs``:
    normals drawn two at a time (the same numbers)."""
    m = model(settings)
    seed = m.pop("seed")
    args = [m[k] for k in ("w_std", "Ad", "Bw", "Bu", "Atd", "Btd", "beta", "p0", "lam")]
    theta, P = np.empty((B, 3)), np.empty((B, 3, 3))
    seeds, members = streams(B, seed)
    if variant == "one":
        for b in range(B):
            refine_one(steps, seeds[b], members[b], *args, theta[b], P[b], pairs)
    else:
        fn = {"prange": refine_prange, "lanes": refine_lanes}[variant]
        fn(steps, seeds, members, *args, theta, P, pairs)
    return theta, P
