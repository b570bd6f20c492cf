"""MIMO-correct RCO estimator: a hand-built NumPy reference of the update (Kronecker Psi, RLS), masks.

The reference follows docs/method.md literally and independently of the library's layout: theta is
vectorized *column-major* (vec), so that vec(beta theta phi) = (phi^T (x) beta) vec(theta) and

    Psi(k) = sum_{i=d..d+nu-1} phi(k-i) (x) beta_i^T                      (n_u n_phi x n_z)
    z_R(k) = z(k) + sum_i beta_i [theta(k) - theta(k-i)] phi(k-i)          (from the stored past thetas)

then the RLS equations of docs/method.md. P(0) = p0 I, so the ordering of the free entries inside P does not
matter. phi(k) is built from the documented order (signal by signal, lag by lag, then past u).
"""

import control
import numpy as np
import pytest
import torch

import rcotorch as rt


def _phi(signals, hist, u_hist, k, lags, nc, feed_u, n_u):
    """phi(k) from the input history hist[name][k] and the estimator's own outputs u_hist[k]."""
    parts = []
    for name in signals:
        for lag in lags:
            parts.append(hist[name][k - lag] if k - lag >= 0 else np.zeros_like(hist[name][0]))
    if feed_u:
        for lag in range(1, nc + 1):
            parts.append(u_hist[k - lag] if k - lag >= 0 else np.zeros(n_u))
    return np.concatenate(parts)


def reference(signals, z_seq, beta, d, *, nc, proper, feed_u, n_u, mask, p0, lam, R):
    """One member: returns theta (n_u, n_phi) after len(z_seq) steps and the outputs u(k)."""
    T = len(z_seq)
    lags = list(range(0 if proper else 1, nc + 1))
    n_z = z_seq.shape[1]
    nu = beta.shape[0]
    u_hist, phis, thetas = [], [], []
    n_phi = len(_phi(signals, signals, [], 0, lags, nc, feed_u, n_u))
    theta = np.zeros((n_u, n_phi))
    free = mask.flatten(order="F")                        # vec (column-major) of the mask
    P = p0 * np.eye(int(free.sum()))
    Rinv = np.linalg.inv(R)
    for k in range(T):
        phi = _phi(signals, signals, u_hist, k, lags, nc, feed_u, n_u)
        u = theta @ phi
        u_hist.append(u)
        phis.append(phi)
        thetas.append(theta.copy())
        Psi = np.zeros((n_u * n_phi, n_z))
        z_r = z_seq[k].copy()
        for i in range(d, d + nu):
            if k - i < 0:
                continue
            b = beta[i - d]                               # (n_z, n_u)
            Psi += np.kron(phis[k - i][:, None], b.T)     # phi (x) beta^T
            z_r += b @ (theta - thetas[k - i]) @ phis[k - i]
        Psi = Psi[free]
        S = lam * Rinv + Psi.T @ P @ Psi
        gain = P @ Psi @ np.linalg.inv(S)
        vec = theta.flatten(order="F")
        vec[free] = vec[free] - gain @ z_r
        theta = vec.reshape(n_phi, n_u).T
        P = (P - gain @ Psi.T @ P) / lam
    return theta, np.array(u_hist)


CASES = {
    # name: (signal widths, n_u, n_z, nc, proper, feed_u, nu, d, mask builder)
    "lu2_lz1_dynamic": ({"y0": 1, "w": 1}, 2, 1, 2, False, True, 3, 1, None),
    "lu2_lz2_dynamic": ({"y0": 2}, 2, 2, 2, False, True, 4, 2, None),
    "lu2_lz2_proper": ({"y0": 2}, 2, 2, 1, True, False, 3, 1, None),
    "lu2_lz1_static_masked": ({"y0": 2}, 2, 1, 0, True, False, 5, 1, "diag"),
    "lu2_lz2_dynamic_masked": ({"y0": 2}, 2, 2, 1, False, True, 3, 1, "no_cross"),
}


def _mask(kind, n_u, n_phi):
    if kind is None:
        return np.ones((n_u, n_phi), dtype=bool)
    if kind == "diag":                                    # force on mass i sees q_i only
        return np.eye(n_u, n_phi, dtype=bool)
    if kind == "no_cross":                                # u_i sees s_i(k-1) and its own u_i(k-1) only
        m = np.zeros((n_u, n_phi), dtype=bool)
        for i in range(n_u):
            m[i, i] = m[i, 2 + i] = True
        return m
    raise ValueError(kind)


@pytest.mark.parametrize("case", list(CASES))
def test_update_matches_kronecker_reference(case):
    widths, n_u, n_z, nc, proper, feed_u, nu, d, mkind = CASES[case]
    rng = np.random.default_rng(7)
    B, T = 2, 12
    lags = list(range(0 if proper else 1, nc + 1))
    n_phi = len(lags) * sum(widths.values()) + (nc * n_u if feed_u else 0)
    mask = _mask(mkind, n_u, n_phi)
    beta = rng.normal(size=(nu, n_z, n_u))
    R = np.array([[2.0, 0.3], [0.3, 1.0]])[:n_z, :n_z]
    p0, lam = np.array([10.0, 3.0]), np.array([1.0, 0.97])
    sig = {s: rng.normal(size=(B, T, w)) for s, w in widths.items()}
    z = rng.normal(size=(B, T, n_z))

    est = rt.RCOEstimator(widths, n_u=n_u, n_z=n_z, nc=nc, proper=proper, feed_u=feed_u,
                          mask=torch.as_tensor(mask), p0=p0, lam=lam, R=R, markov=beta, first_delay=d)
    est.reset(B)
    us = []
    for k in range(T):
        out = est.step(**{s: torch.as_tensor(v[:, k]) for s, v in sig.items()}, z=torch.as_tensor(z[:, k]))
        us.append(out["u"].numpy())
    us = np.stack(us, 1)
    for b in range(B):
        theta_ref, u_ref = reference({s: v[b] for s, v in sig.items()}, z[b], beta, d, nc=nc, proper=proper,
                                     feed_u=feed_u, n_u=n_u, mask=mask, p0=p0[b], lam=lam[b], R=R)
        np.testing.assert_allclose(est.theta[b].numpy(), theta_ref, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(us[b], u_ref, rtol=1e-9, atol=1e-11)
    # pinned entries are exactly zero, free ones moved
    theta = est.theta.numpy()
    assert np.all(theta[:, ~mask] == 0.0)
    assert np.all(np.abs(theta[:, mask]) > 0)


def test_masked_static_gain_stays_pinned_over_a_long_closed_loop_run():
    """2-DOF structure, masked static gain: off-diagonal (cross) entries remain exactly 0.0 in a graph."""
    ts = 0.05
    Kc = np.array([[1.2, -0.5], [-0.5, 1.1]])
    G = rt.models.structure(np.eye(2), 0.8 * np.array([[2, -1], [-1, 2]]), Kc, [1, 1],
                            measured=["velocity[1]"], sees=["position[0]", "position[1]"])
    known = rt.LTI.from_control(G, inputs={"w": 1, "u": 2}, outputs={"y": 1, "y0": 2}, dt=ts, name="known")
    est = rt.RCOEstimator.static_gain({"y0": 2}, n_u=2, mask=[[True, False], [False, True]], p0=1e3)
    assert est.theta_names == ["0:y0[0](k)", "1:y0[1](k)"]
    g = rt.refinement(known, est, truth=rt.Gain(-np.diag([0.4, 0.5])), excitation=rt.WhiteNoise(1, seed=3),
                      nu=10, batch_size=3)
    g.run(500)
    th = est.theta.numpy()
    assert np.all(th[:, 0, 1] == 0.0) and np.all(th[:, 1, 0] == 0.0)
    assert np.all(th[:, 0, 0] != 0.0) and np.all(th[:, 1, 1] != 0.0)
    assert est.P.shape == (3, 2, 2)


def test_markov_parameters_are_lz_by_lu_matrices():
    """derive_markov for 2 measured outputs and 2 forces equals -C A^(i-1) B of python-control's ZOH."""
    ts = 0.1
    K = np.array([[1.2, -0.5], [-0.5, 1.1]])
    Cd = np.array([[1.6, -0.8], [-0.8, 1.6]])
    G = rt.models.structure(np.eye(2), Cd, K, [1, 1], measured=["velocity[1]", "position[0]"],
                            sees=["position[0]", "position[1]"])
    known = rt.LTI.from_control(G, inputs={"w": 1, "u": 2}, outputs={"y": 2, "y0": 2}, dt=ts, name="known")
    beta, d = rt.derive_markov(known, "u", "y", 6)
    Gd = control.sample_system(G, ts, method="zoh")
    A, Bu, Cy = Gd.A, Gd.B[:, 1:3], Gd.C[:2]
    ref = np.stack([-Cy @ np.linalg.matrix_power(A, i - 1) @ Bu for i in range(1, 7)])
    assert d == 1
    assert beta.shape == (1, 6, 2, 2)
    np.testing.assert_allclose(beta[0].numpy(), ref, rtol=1e-10, atol=1e-14)
