"""The batched RLS kernel against the closed-form (regularized, exponentially weighted) least-squares solution.

Every test runs twice: with the PyTorch operations (what CUDA and float32 run, and ``Graph(engine='torch')``)
and with the compiled kernel (the same RLS code as the native engine's estimator step)."""

import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch.engine import kernels


@pytest.fixture(autouse=True, params=["torch", "native"])
def kernel(request):
    """Run the test on one RLS implementation: ``rls_update``'s default picks the compiled kernel unless it is
    disabled."""
    if request.param == "native" and not kernels.available():
        pytest.skip(f"no native engine: {kernels.why_unavailable()}")
    if request.param == "torch":
        with kernels.disabled():
            yield request.param
    else:
        yield request.param


def _sequence(rng, n, l, N):
    return rng.standard_normal((N, n, l)), rng.standard_normal((N, l))


def _run_rls(theta0, p0, psis, zetas, lam=1.0, r_inv=1.0):
    """Feed z_r,j = psi_j^T theta_j + zeta_j (z_r recomputed from the current theta) to rls_update, B = 1."""
    n = theta0.size
    theta = torch.tensor(theta0, dtype=torch.float64).reshape(1, n)
    P = p0 * torch.eye(n, dtype=torch.float64).reshape(1, n, n)
    for psi_j, zeta_j in zip(psis, zetas):
        psi = torch.tensor(psi_j).unsqueeze(0)
        z_r = (psi.mT @ theta.unsqueeze(-1)).squeeze(-1) + torch.tensor(zeta_j).unsqueeze(0)
        theta, P, ok = rt.rls_update(theta, P, psi, z_r, lam, r_inv)
        assert bool(ok.all())
    return theta[0].numpy(), P[0].numpy()


def _closed_form(theta0, p0, psis, zetas, R, lam=1.0):
    """argmin sum_j lam^(N-1-j) |psi_j^T th + zeta_j|^2_R + lam^N (th - th0)^T P0^-1 (th - th0)."""
    n, N = theta0.size, len(psis)
    info = lam ** N * np.eye(n) / p0
    rhs = info @ theta0
    for j, (psi, zeta) in enumerate(zip(psis, zetas)):
        w = lam ** (N - 1 - j)
        info = info + w * psi @ R @ psi.T
        rhs = rhs - w * psi @ R @ zeta
    return np.linalg.solve(info, rhs), np.linalg.inv(info)


@pytest.mark.parametrize("l", [1, 2])
def test_lambda_one_matches_regularized_least_squares(l):
    rng = np.random.default_rng(10 + l)
    n, N, p0 = 4, 25, 3.0
    psis, zetas = _sequence(rng, n, l, N)
    theta0 = rng.standard_normal(n)
    if l == 1:
        R = np.array([[2.5]])
    else:
        Lr = rng.standard_normal((l, l))
        R = Lr @ Lr.T + 0.5 * np.eye(l)           # symmetric positive definite, not identity
    r_inv = torch.tensor(np.linalg.inv(R)) if l > 1 else float(1.0 / R[0, 0])
    theta, P = _run_rls(theta0, p0, psis, zetas, 1.0, r_inv)
    theta_ref, P_ref = _closed_form(theta0, p0, psis, zetas, R)
    np.testing.assert_allclose(theta, theta_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(P, P_ref, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("l", [1, 2])
def test_forgetting_factor_matches_exponentially_weighted_least_squares(l):
    rng = np.random.default_rng(20 + l)
    n, N, p0, lam = 3, 40, 10.0, 0.93
    psis, zetas = _sequence(rng, n, l, N)
    theta0 = rng.standard_normal(n)
    theta, P = _run_rls(theta0, p0, psis, zetas, lam, 1.0)
    theta_ref, P_ref = _closed_form(theta0, p0, psis, zetas, np.eye(l), lam)
    np.testing.assert_allclose(theta, theta_ref, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(P, P_ref, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("l", [1, 2])
def test_batch_equals_separate_calls_bitwise(l):
    g = torch.Generator().manual_seed(5)
    B, n = 8, 5
    theta = torch.randn(B, n, generator=g, dtype=torch.float64)
    M = torch.randn(B, n, n, generator=g, dtype=torch.float64)
    P = M @ M.mT + torch.eye(n, dtype=torch.float64)
    psi = torch.randn(B, n, l, generator=g, dtype=torch.float64)
    z_r = torch.randn(B, l, generator=g, dtype=torch.float64)
    lam = torch.linspace(0.9, 1.0, B, dtype=torch.float64)
    r_inv = 0.7 if l == 1 else torch.tensor([[1.2, 0.1], [0.1, 0.8]], dtype=torch.float64)
    th_b, P_b, ok_b = rt.rls_update(theta, P, psi, z_r, lam, r_inv)
    assert bool(ok_b.all())
    for b in range(B):
        th1, P1, ok1 = rt.rls_update(theta[b:b + 1], P[b:b + 1], psi[b:b + 1], z_r[b:b + 1], lam[b:b + 1], r_inv)
        assert torch.equal(th_b[b:b + 1], th1)
        assert torch.equal(P_b[b:b + 1], P1)
        assert bool(ok1.all())


@pytest.mark.parametrize("l", [1, 2])
def test_inactive_members_unchanged_exactly(l):
    g = torch.Generator().manual_seed(6)
    B, n = 6, 3
    theta = torch.randn(B, n, generator=g, dtype=torch.float64)
    P = torch.eye(n, dtype=torch.float64).expand(B, n, n) * 4.0
    psi = torch.randn(B, n, l, generator=g, dtype=torch.float64)
    z_r = torch.randn(B, l, generator=g, dtype=torch.float64)
    active = torch.tensor([True, False, True, False, False, True])
    th, P_new, ok = rt.rls_update(theta, P, psi, z_r, 0.95, 1.0, active)
    assert bool(ok.all())
    assert torch.equal(th[~active], theta[~active])
    assert torch.equal(P_new[~active], P[~active])
    assert not torch.equal(th[active], theta[active])
    assert bool((P_new[active] != P[active]).any())
    # The active members are as if the others were not there.
    th_a, P_a, _ = rt.rls_update(theta[active], P[active], psi[active], z_r[active], 0.95, 1.0)
    assert torch.equal(th[active], th_a)
    assert torch.equal(P_new[active], P_a)


def test_p_stays_exactly_symmetric_l1():
    g = torch.Generator().manual_seed(7)
    B, n = 4, 6
    theta = torch.zeros(B, n, dtype=torch.float64)
    P = 1e8 * torch.eye(n, dtype=torch.float64).expand(B, n, n).clone()
    for _ in range(200):
        psi = torch.randn(B, n, 1, generator=g, dtype=torch.float64)
        z_r = torch.randn(B, 1, generator=g, dtype=torch.float64)
        theta, P, ok = rt.rls_update(theta, P, psi, z_r, 0.99, 1.0)
        assert bool(ok.all())
        assert torch.equal(P, P.mT)


def test_non_positive_innovation_freezes_member_and_reports_not_ok():
    B, n = 3, 2
    theta = torch.ones(B, n, dtype=torch.float64)
    P = torch.eye(n, dtype=torch.float64).repeat(B, 1, 1)
    P[1] = -10.0 * torch.eye(n, dtype=torch.float64)          # lost definiteness: S < 0
    psi = torch.ones(B, n, 1, dtype=torch.float64)
    z_r = torch.ones(B, 1, dtype=torch.float64)
    th, P_new, ok = rt.rls_update(theta, P, psi, z_r)
    assert ok.tolist() == [True, False, True]
    assert torch.equal(th[1], theta[1]) and torch.equal(P_new[1], P[1])
    assert torch.isfinite(th).all() and torch.isfinite(P_new).all()


@pytest.mark.parametrize("l", [1, 2])
def test_non_finite_update_leaves_member_unchanged(l):
    B, n = 3, 2
    theta = torch.zeros(B, n, dtype=torch.float64)
    P = torch.eye(n, dtype=torch.float64).repeat(B, 1, 1)
    psi = torch.ones(B, n, l, dtype=torch.float64)
    z_r = torch.ones(B, l, dtype=torch.float64)
    z_r[1, 0] = float("inf")                                   # S is fine, the new theta is not finite
    th, P_new, ok = rt.rls_update(theta, P, psi, z_r, 0.9)
    assert ok.tolist() == [True, False, True]
    assert torch.equal(th[1], theta[1])
    assert torch.equal(P_new[1], P[1])
