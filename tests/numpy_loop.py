"""A straightforward per-refinement NumPy implementation of ``sdof-stiffness-damping`` (seed Section V.A).

One refinement at a time, a Python loop over steps, the same equations as rcotorch's Figure-1 graph:

* known model m x'' + C x' + K x = w + u and truth m x'' + (C + dC) x' + (K + dK) x = w, both continuous
  and ZOH-discretized at Ts (``scipy.linalg.expm`` of the augmented matrix), velocity measured, the
  identified subsystem seeing y0 = [x, x'];
* white-noise force w(k): the same counter-based samples as ``rcotorch.WhiteNoise`` (stream (seed, member));
* identified subsystem u(k) = theta(k) phi(k), phi(k) = [y0(k-1), .., y0(k-nc), u(k-1), .., u(k-nc)];
* z(k) = y(k) - y_hat(k); Markov parameters beta_i = -C_y A^(i-1) B_u of u -> z, i = 1..nu;
* retrospective cost: Psi(k) = sum_i beta_i phi(k-i), z_R(k) = z(k) - sum_i beta_i u(k-i) + Psi(k)^T theta(k);
* RLS (R = 1): a = P Psi, s = lambda + Psi^T a, theta <- theta - a z_R / s, P <- (P - a a^T / s) / lambda.

It is both an independent check of the library (``tests/test_numpy_reference.py``: its final theta agrees with
rcotorch's batch-of-one run to ~1e-9) and the speed baseline of the benchmarks (``benchmarks/numpy_reference.py``
times it, ``benchmarks/throughput.py`` compares against it).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

DEFAULTS = dict(Ts=0.01, m=1.0, K=0.7, C=0.4, dK=-0.4, dC=0.5, nc=1, p0=1e6, lam=1.0, nu=15, w_std=1.0, seed=1)


def zoh(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretization: expm([[A, B], [0, 0]] dt) = [[Ad, Bd], [0, I]]."""
    n, m = A.shape[0], B.shape[1]
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, B
    E = expm(M * dt)
    return E[:n, :n], E[:n, n:]


def sdof(m: float, c: float, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Continuous (A, B) of m x'' + c x' + k x = force, state [x, x']."""
    return np.array([[0.0, 1.0], [-k / m, -c / m]]), np.array([[0.0], [1.0 / m]])


def noise(seed: int, member: int, steps: int) -> np.ndarray:
    """The excitation samples rcotorch's WhiteNoise draws for stream (seed, member), steps 0..steps-1."""
    import torch

    from rcotorch.engine import rng
    return rng.normal(seed, member, torch.arange(steps), 0, dtype=torch.float64).numpy()


def refine(steps: int, settings: dict | None = None, member: int = 0, w: np.ndarray | None = None) -> dict:
    """Run one refinement for ``steps`` steps; return theta (1, 3 nc), P, the final z and the DC-gain estimates."""
    s = dict(DEFAULTS, **(settings or {}))
    Ts, m, nc, nu, lam = s["Ts"], s["m"], int(s["nc"]), int(s["nu"]), s["lam"]
    # Known model: inputs [w, u], outputs y = x', y0 = [x, x'].
    Ak, Bk1 = sdof(m, s["C"], s["K"])
    Ad, Bd = zoh(Ak, np.hstack([Bk1, Bk1]), Ts)
    Bw, Bu = Bd[:, 0], Bd[:, 1]
    Cy = np.array([0.0, 1.0])
    # Truth: the whole structure with K + dK, C + dC, discretized at once.
    At, Bt1 = sdof(m, s["C"] + s["dC"], s["K"] + s["dK"])
    Atd, Btd = zoh(At, Bt1, Ts)
    Btd = Btd[:, 0]
    # Markov parameters of u -> z = y - y_hat: beta_i = -Cy Ad^(i-1) Bu, i = 1..nu (relative degree 1).
    beta = np.empty(nu)
    AkB = Bu.copy()
    for i in range(nu):
        beta[i] = -Cy @ AkB
        AkB = Ad @ AkB
    if w is None:
        w = s["w_std"] * noise(int(s["seed"]), member, steps)
    n_phi = 3 * nc                                  # [x(k-1), x'(k-1), .., x(k-nc), x'(k-nc), u(k-1..k-nc)]
    theta = np.zeros(n_phi)
    P = s["p0"] * np.eye(n_phi)
    x_model, x_true = np.zeros(2), np.zeros(2)
    past_y0 = np.zeros((nc, 2))                     # y0(k-1..k-nc)
    past_u = np.zeros(nc)                           # u(k-1..k-nc)
    W = nu + 1                                      # ring buffer of [phi(k-i), u(k-i)], i = 0..nu
    hist = np.zeros((W, n_phi + 1))
    lags = np.arange(1, nu + 1)
    z = 0.0
    for k in range(steps):
        # Outputs at time k.
        y_hat = Cy @ x_model
        y0 = x_model                                # [x, x'] of the simulated system
        phi = np.concatenate([past_y0.reshape(-1), past_u])
        u = theta @ phi
        y = Cy @ x_true
        z = y - y_hat
        # Retrospective cost and RLS update.
        hist[k % W, :n_phi], hist[k % W, n_phi] = phi, u
        past = hist[(k - lags) % W]                 # [phi(k-i), u(k-i)], i = 1..nu (zero before k = 0)
        filt = beta @ past
        psi = filt[:n_phi]
        z_r = z - filt[n_phi] + psi @ theta
        a = P @ psi
        sc = lam + psi @ a
        theta = theta - a * (z_r / sc)
        P = (P - np.outer(a, a) / sc) / lam
        # Advance the known model, the truth and the regressor histories.
        x_model = Ad @ x_model + Bw * w[k] + Bu * u
        x_true = Atd @ x_true + Btd * w[k]
        past_y0 = np.vstack([y0, past_y0[:-1]])
        past_u = np.concatenate([[u], past_u[:-1]])
    # DC gains of u(k) = sum_l N_l y0(k-l) + sum_l M_l u(k-l) on [x, x']: dK = -gain_x, dC = -gain_v.
    gain = np.array([theta[0:2 * nc:2].sum(), theta[1:2 * nc:2].sum()]) / (1.0 - theta[2 * nc:].sum())
    return {"theta": theta.reshape(1, n_phi), "P": P, "z": z, "dK": -gain[0], "dC": -gain[1]}
