"""A plain NumPy loop of a Figure-1 refinement with a static-gain identified subsystem, for any such graph.

The per-step cost baseline of ``benchmarks/engine_cost.py`` for graphs other than ``sdof-stiffness-damping``
(which has its own loop, ``tests/numpy_loop.py``): ``silverbox-cubic-stiffness``, ``twodof-stiffness`` and a
graph with basis features. One refinement at a time, a Python loop over steps, the equations written out:

* known model x(k+1) = A x + B [w; u], outputs [y; y0] = C x + D [w; u] (matrices read from the built graph);
* physical system: recorded w, y played back, or a white-noise w (``rcotorch.engine.rng``, the same samples) into an
  LTI plant;
* identified subsystem u = Theta phi, phi = the basis features of y0(k) (a NumPy function given by the
  caller), Theta with pinned entries (the estimator's mask);
* retrospective cost with Markov parameters beta_d .. beta_(d+nu-1) over a ring buffer of [phi, u], and the
  scalar-z RLS update (lambda, R = 1).

The graph's blocks only supply the numbers (matrices, Markov parameters, settings); ``engine_cost.py`` checks
that the loop's final theta equals rcotorch's to 1e-9.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from rcotorch.engine import rng


@dataclass
class Loop:
    """The numbers of one refinement (member 0 of a built graph)."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    x0: np.ndarray
    n_w: int
    beta: np.ndarray              # (nu, n_u): u -> z, z scalar
    first_delay: int
    free: np.ndarray              # indices of the free entries of Theta (n_u x n_phi, row-major)
    n_phi: int
    p0: float
    lam: float
    features: Callable[[np.ndarray], np.ndarray]
    w: np.ndarray                 # (steps, n_w) excitation or recorded input
    y: np.ndarray | None = None   # (steps,) recorded output, or None with a plant
    plant: tuple | None = None    # (A, B, C, D, x0) of the physical system (input w, output y)


def _np(t: torch.Tensor) -> np.ndarray:
    return t[0].detach().to(torch.float64).cpu().numpy().copy()


def from_graph(g, steps: int, features: Callable[[np.ndarray], np.ndarray]) -> Loop:
    """Read member 0's numbers from a refinement graph (roles 'known', 'estimator', 'physical')."""
    known, est, phys = g.role("known"), g.role("estimator"), g.role("physical")
    if est.n_z != 1 or not est.proper or est.nc != 0:
        raise ValueError("the NumPy loop is written for a scalar z and a static gain (nc = 0, proper)")
    if not torch.all(est.r_inv == 1):
        raise ValueError("the NumPy loop is written for R = 1")
    n_w = known.inputs["w"]
    common = dict(A=_np(known.A), B=_np(known.B), C=_np(known.C), D=_np(known.D), x0=_np(known.x0), n_w=n_w,
                  beta=_np(est.beta)[:, 0, :], first_delay=est.first_delay, free=est.free_idx.cpu().numpy().astype(int),
                  n_phi=est.n_phi, p0=float(est.p0[0]), lam=float(est.lam[0]), features=features)
    if hasattr(phys, "values"):                                         # rcotorch.Recorded: played back
        v = _np(phys.values)[:steps]
        cols = list(phys.outputs)
        return Loop(**common, w=v[:, [cols.index("w")]], y=v[:, cols.index("y")])
    exc = g.role("excitation")
    seed, member = int(exc.stream[0, 0]), int(exc.stream[0, 1])
    k = torch.arange(steps).reshape(-1, 1)
    c = torch.arange(exc.width).reshape(1, -1)
    w = (float(exc.std[0, 0]) * rng.normal(seed, member, k, c, dtype=torch.float64) + float(exc.mean[0, 0]))
    plant = (_np(phys.A), _np(phys.B), _np(phys.C), _np(phys.D), _np(phys.x0))
    return Loop(**common, w=w.numpy(), plant=plant)


def refine(L: Loop, steps: int) -> np.ndarray:
    """Run the refinement for ``steps`` steps; return Theta (n_u, n_phi)."""
    n_u, n_phi, nu, d = L.beta.shape[1], L.n_phi, L.beta.shape[0], L.first_delay
    Cy, Dy = L.C[0], L.D[0]
    Cs, Ds = L.C[1:], L.D[1:]
    theta = np.zeros(n_u * n_phi)
    free = L.free
    P = L.p0 * np.eye(len(free))
    x = L.x0.copy()
    if L.plant is not None:
        Ap, Bp, Cp, Dp, xp = L.plant
        xp = xp.copy()
    W = nu + d
    hist = np.zeros((W, n_phi + n_u))                 # [phi(t), u(t)] at row t mod W
    lags = np.arange(d, d + nu)
    for k in range(steps):
        w = L.w[k]
        y0 = Cs @ x + Ds[:, :L.n_w] @ w               # the regressor port (no feedthrough from u)
        phi = L.features(y0)
        u = theta.reshape(n_u, n_phi) @ phi
        inp = np.concatenate([w, u])
        y_hat = Cy @ x + Dy @ inp
        if L.plant is None:
            y = L.y[k]
        else:
            y = Cp[0] @ xp + Dp[0] @ w
            xp = Ap @ xp + Bp @ w
        z = y - y_hat
        hist[k % W, :n_phi], hist[k % W, n_phi:] = phi, u
        past = hist[(k - lags) % W]                   # [phi, u](k - d - i), i = 0..nu-1 (zero before k = 0)
        psi_full = (L.beta.T @ past[:, :n_phi]).reshape(-1)   # Psi[a * n_phi + j] = sum_i beta_i[a] phi_j
        zeta = z - np.sum(L.beta * past[:, n_phi:])
        psi = psi_full[free]
        z_r = zeta + psi @ theta[free]
        a = P @ psi
        s = L.lam + psi @ a
        theta[free] = theta[free] - a * (z_r / s)
        P = (P - np.outer(a, a) / s) / L.lam
        x = L.A @ x + L.B @ inp
    return theta.reshape(n_u, n_phi)
