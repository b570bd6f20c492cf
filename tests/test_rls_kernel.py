"""The compiled RLS kernel against the PyTorch operations of ``rls_update`` (the reference semantics)."""

import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch.engine import kernels

pytestmark = pytest.mark.skipif(not kernels.available(), reason="the compiled engine is not built here")


@pytest.mark.parametrize("l,n", [(1, 6), (2, 6), (3, 6), (1, 5), (2, 3)])
def test_native_kernel_agrees_with_pytorch_operations(l, n):
    """Per-member lambda, a full R, inactive members and one member whose S is not positive: the compiled
    kernel and the PyTorch operations agree to rounding and in ok. 37 members: whole chunks and a last one of
    5; P of 36, 25 or 9 entries: moved in 4 x 4 blocks and one by one."""
    g = torch.Generator().manual_seed(40 + l + n)
    B = 37
    theta = torch.randn(B, n, generator=g, dtype=torch.float64)
    M = torch.randn(B, n, n, generator=g, dtype=torch.float64)
    P = M @ M.mT + 0.1 * torch.eye(n, dtype=torch.float64)
    P[3] = -P[3]                                          # S not positive: frozen, not ok
    psi = torch.randn(B, n, l, generator=g, dtype=torch.float64)
    z_r = torch.randn(B, l, generator=g, dtype=torch.float64)
    lam = torch.linspace(0.9, 1.0, B, dtype=torch.float64)
    A = torch.randn(l, l, generator=g, dtype=torch.float64)
    r_inv = A @ A.T + torch.eye(l, dtype=torch.float64)
    active = torch.rand(B, generator=g) > 0.2
    active[3] = True
    out_t = rt.rls_update(theta, P, psi, z_r, lam, r_inv, active, kernel="torch")
    out_n = rt.rls_update(theta, P, psi, z_r, lam, r_inv, active, kernel="native")
    assert torch.equal(out_t[2], out_n[2]) and not bool(out_n[2][3])
    for a, b in zip(out_t[:2], out_n[:2]):
        np.testing.assert_allclose(b.numpy(), a.numpy(), rtol=1e-12, atol=1e-12)
    assert torch.equal(out_n[0][~active | ~out_n[2]], theta[~active | ~out_n[2]])


def test_native_kernel_refuses_what_it_cannot_run():
    theta, P = torch.zeros(2, 3, dtype=torch.float32), torch.eye(3, dtype=torch.float32).expand(2, 3, 3)
    with pytest.raises(rt.ConfigError, match="kernel='native'"):
        rt.rls_update(theta, P, torch.ones(2, 3, 1, dtype=torch.float32), torch.ones(2, 1), kernel="native")
