"""The damaged building's data (scenario shear-building-damage, its floors' velocities measured) and the two
unscented Kalman filters that ``benchmarks/ukf_peer.py`` sets against rcotorch on it: filterpy's
``UnscentedKalmanFilter``, one member at a time, and the same filter batched over the members in torch, as a
performance-minded user writes it; and the paired comparison of two methods' errors on the same members.

Both filters estimate the augmented state [floor displacements and velocities (6), dk1, dk2, dk3] with dynamics
x(k+1) = A x + B_w w + B_u u, u_j = -dk_j k d_j(x), the parameters a random walk of variance ``Q_THETA`` per step,
y = C x with the measurement noise's variance as R, P0 = ``P0_X`` on the floors' states and ``P0_THETA`` on the
parameters, Merwe's sigma points (``ALPHA``, ``BETA``, ``KAPPA``). ``tests/test_benchmarks.py`` checks the batched
filter against filterpy's step for step, and the paired comparison.
"""

from __future__ import annotations

import time

import numpy as np
import torch

NAME = "shear-building-damage"
Q_THETA, P0_X, P0_THETA, ALPHA, BETA, KAPPA = 1e-7, 1e-8, 1e-2, 0.1, 2.0, 0.0
VELOCITY = {"sensor": "velocity", "measured": "1,2,3", "noise": 2e-4, "warmup": 500, "window": 500}


def model(sc, s):
    """The discrete building the truth is made of: A (6, 6), B_w (6, 1), B_u (6, 3), C_y (3, 6), C_d (3, 6)."""
    g = sc.build(s, 1, torch.float64, "cpu")
    known = g.blocks["known"]
    A, B, C = (getattr(known, key)[0].numpy() for key in ("A", "B", "C"))
    n_y = C.shape[0] - 3
    return A, B[:, :1], B[:, 1:], C[:n_y], C[n_y:]


def record(sc, s, batch: int, marks: list[int]):
    """w (K, B) and y (K, B, n_y) of the scenario's run to the last of ``marks`` (steps, increasing), the rcotorch
    estimates (B, 3) at each mark, its detection steps, and its cost per member-step."""
    g = sc.build(s, batch, torch.float64, "cpu")
    K = marks[-1]
    w_sig, y_sig = g.role_signal("exogenous"), g.role_signal("measured")
    w = torch.zeros(K, batch, 1, dtype=torch.float64)
    y = torch.zeros(K, batch, len(str(s["measured"]).split(",")), dtype=torch.float64)
    dk, done, seconds = [], 0, 0.0
    for mark in marks:
        t = time.perf_counter()
        g.advance(mark - done, record={w_sig: w[done:mark], y_sig: y[done:mark]})
        seconds += time.perf_counter() - t
        done = mark
        est = sc.estimates(g, s)
        dk.append(torch.stack([est[f"dk{j}"] for j in (1, 2, 3)], 1).numpy())
    return w[:, :, 0].numpy(), y.numpy(), dk, g.blocks["detector"].first_alarm().numpy(), seconds / (K * batch), \
        g.ran_engine


def filterpy_run(A, Bw, Bu, Cy, Cd, k, w, y, R):
    """One member's filterpy UKF over the data: the parameter estimates per step (K, 3) and seconds per step."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
    n = A.shape[0]

    def fx(X, dt, w_k=0.0):
        x, th = X[:n], X[n:]
        u = -th * k * (Cd @ x)
        return np.concatenate([A @ x + Bw[:, 0] * w_k + Bu @ u, th])

    def hx(X):
        return Cy @ X[:n]

    pts = MerweScaledSigmaPoints(n + 3, alpha=ALPHA, beta=BETA, kappa=KAPPA)
    ukf = UnscentedKalmanFilter(dim_x=n + 3, dim_z=Cy.shape[0], dt=1.0, hx=hx, fx=fx, points=pts)
    ukf.x = np.zeros(n + 3)
    ukf.P = np.diag([P0_X] * n + [P0_THETA] * 3)
    ukf.Q = np.diag([1e-14] * n + [Q_THETA] * 3)
    ukf.R = R
    out = np.zeros((len(w), 3))
    t = time.perf_counter()
    for i in range(len(w)):
        ukf.predict(w_k=w[i - 1] if i else 0.0)
        ukf.update(y[i])
        out[i] = ukf.x[n:]
    return out, (time.perf_counter() - t) / len(w)


def batched_ukf(A, Bw, Bu, Cy, Cd, k, w, y, R):
    """The same filter for all members at once in torch: estimates (K, B, 3) and seconds per step."""
    f64 = torch.float64
    A, Bw, Bu, Cy, Cd, R = (torch.as_tensor(a, dtype=f64) for a in (A, Bw, Bu, Cy, Cd, R))
    w, y = torch.as_tensor(w, dtype=f64), torch.as_tensor(y, dtype=f64)
    K, B = w.shape
    n = A.shape[0]
    N = n + 3
    lam = ALPHA ** 2 * (N + KAPPA) - N
    Wm = torch.full((2 * N + 1,), 1 / (2 * (N + lam)), dtype=f64)
    Wc = Wm.clone()
    Wm[0], Wc[0] = lam / (N + lam), lam / (N + lam) + 1 - ALPHA ** 2 + BETA
    X = torch.zeros(B, N, dtype=f64)
    P = torch.diag(torch.tensor([P0_X] * n + [P0_THETA] * 3, dtype=f64)).expand(B, N, N).clone()
    Q = torch.diag(torch.tensor([1e-14] * n + [Q_THETA] * 3, dtype=f64))
    out = torch.zeros(K, B, 3, dtype=f64)

    def sigma(X, P):
        L = torch.linalg.cholesky((N + lam) * P)                   # (B, N, N)
        d = L.mT                                                   # rows of L^T, as filterpy's points
        return torch.cat([X.unsqueeze(1), X.unsqueeze(1) + d, X.unsqueeze(1) - d], 1)   # (B, 2N+1, N)

    def f(S, w_k):
        x, th = S[..., :n], S[..., n:]
        u = -th * k * (x @ Cd.T)
        return torch.cat([x @ A.T + w_k.reshape(-1, 1, 1) * Bw[:, 0] + u @ Bu.T, th], -1)

    t = time.perf_counter()
    for i in range(K):
        S = f(sigma(X, P), w[i - 1] if i else torch.zeros(B, dtype=f64))      # predict: points through f
        X = torch.einsum("s,bsn->bn", Wm, S)
        Dx = S - X.unsqueeze(1)
        P = torch.einsum("s,bsi,bsj->bij", Wc, Dx, Dx) + Q
        Z = S[..., :n] @ Cy.T                                      # update: the predicted points through h
        zm = torch.einsum("s,bsz->bz", Wm, Z)
        Dz = Z - zm.unsqueeze(1)
        Pz = torch.einsum("s,bsi,bsj->bij", Wc, Dz, Dz) + R
        Pxz = torch.einsum("s,bsi,bsj->bij", Wc, Dx, Dz)
        G = torch.linalg.solve(Pz, Pxz.mT).mT                      # Pxz Pz^-1
        X = X + (G @ (y[i] - zm).unsqueeze(-1)).squeeze(-1)
        P = P - G @ Pz @ G.mT
        out[i] = X[:, n:]
    return out.numpy(), (time.perf_counter() - t) / K


def compare(err_a, err_b, resamples: int = 4000) -> dict:
    """Two methods' errors on the same members, paired: the share of members where a's is the smaller, and 95 %
    bootstrap intervals (members resampled with their pairs) of the differences of the medians and of the
    largest errors, a minus b. An interval that holds 0 says that these members cannot tell the two apart."""
    rng = np.random.default_rng(0)
    idx = rng.integers(0, len(err_a), (resamples, len(err_a)))
    a, b = err_a[idx], err_b[idx]

    def interval(d):
        return [float(np.quantile(d, 0.025)), float(np.quantile(d, 0.975))]
    return {"a_smaller_share": float((err_a < err_b).mean()),
            "median_difference": float(np.median(err_a) - np.median(err_b)),
            "median_difference_95": interval(np.median(a, 1) - np.median(b, 1)),
            "max_difference": float(err_a.max() - err_b.max()),
            "max_difference_95": interval(a.max(1) - b.max(1))}
