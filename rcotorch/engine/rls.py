"""The batched recursive-least-squares kernel of the retrospective cost update (seed eqs. 13-15).

For every batch member b, with regressor Psi (n x l), retrospective error z_R (l), weight R (l x l) and
forgetting factor lambda:

    S      = lambda R^-1 + Psi^T P Psi                          (l x l)
    theta <- theta - P Psi S^-1 z_R
    P     <- (P - P Psi S^-1 Psi^T P) / lambda

With lambda = 1 and P(0) = p0 I this is the exact minimizer of
sum_j |Psi_j^T theta + zeta_j|^2_R + |theta - theta_0|^2 / p0, where z_R,j = Psi_j^T theta_j + zeta_j.

Shapes: theta (B, n), P (B, n, n), psi (B, n, l), z_r (B, l), lam () or (B,), r_inv () or (l, l).

Cost: the covariance update is written as ``P - W W^T`` with W = P Psi L^-T (S = L L^T), for l = 1 as
``P - (a a^T) / s`` with a = P Psi (the products a_i a_j times 1 / s: no square root, and exactly symmetric),
applied in place with ``inplace=True`` (the estimator's hot path), and the division by lambda is skipped when
lambda is 1. Every operation acts on each member separately, so a member's result does not depend on the
batch it runs in.
"""

from __future__ import annotations

import functools

import torch

from ..errors import ConfigError
from . import kernels


def rls_update(theta: torch.Tensor, P: torch.Tensor, psi: torch.Tensor, z_r: torch.Tensor,
               lam: torch.Tensor | float = 1.0, r_inv: torch.Tensor | float = 1.0,
               active: torch.Tensor | None = None, *, inplace: bool = False, kernel: str = "auto"
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One RLS step for all members (module docstring: S, theta and P).

    Members with ``active = False`` are left exactly as they were. ``ok`` is False for an active member whose
    innovation covariance S is not positive and finite (P has lost definiteness) or whose new theta is not
    finite; such a member is also left as it was, so a caller can freeze it without losing the others.
    The P update forms ``P - W W^T``, so P stays exactly symmetric.

    Parameters
    ----------
    theta : torch.Tensor
        (B, n), the parameters.
    P : torch.Tensor
        (B, n, n), their covariance.
    psi : torch.Tensor
        (B, n, l), the regressor Psi.
    z_r : torch.Tensor
        (B, l), the retrospective error z_R.
    lam : torch.Tensor or float, optional
        The forgetting factor, a scalar or (B,).
    r_inv : torch.Tensor or float, optional
        R^-1, a scalar or (l, l).
    active : torch.Tensor, optional
        (B,) bool; inactive members are not updated. All are active by default.
    inplace : bool, optional
        Update theta and P (both contiguous) in place and return them; otherwise new tensors are returned and
        the inputs kept.
    kernel : {'auto', 'native', 'torch'}, optional
        ``'native'`` (the compiled kernel, CPU and float64, the same RLS code as the native engine's estimator
        step; raises where it does not apply), ``'torch'`` (PyTorch operations), or ``'auto'`` (native where it
        applies and is allowed: not inside ``Graph(engine='torch')`` steps).

    Returns
    -------
    theta : torch.Tensor
        (B, n), updated.
    P : torch.Tensor
        (B, n, n), updated.
    ok : torch.Tensor
        (B,) bool: False for an active member that could not be updated; True for inactive members.

    Raises
    ------
    ConfigError
        If ``kernel='native'`` and the compiled kernel does not apply.
    """
    B, n = theta.shape
    native = (kernels.allowed() and theta.device.type == "cpu" and theta.dtype == P.dtype == torch.float64
              and not torch.compiler.is_compiling())
    if kernel != "torch" and native:
        th, Pn = (theta, P) if inplace else (theta.clone(), P.clone())
        ok = kernels.rls_(th, Pn, psi, z_r, lam, r_inv, active)
        if ok is not None:
            return th, Pn, ok if active is None else ok | ~active.reshape(B)
    if kernel == "native":
        raise ConfigError("rls_update: kernel='native' needs the compiled engine, CPU float64 tensors and a "
                          f"contiguous theta and P ({kernels.why_unavailable() or 'they are not'})")
    l = psi.shape[-1]
    dt, dev = P.dtype, P.device
    lam_one = not isinstance(lam, torch.Tensor) and float(lam) == 1.0
    if lam_one:
        lam = 1.0                                                          # no tensor, no division
    elif not isinstance(lam, torch.Tensor):
        lam = torch.tensor(float(lam), dtype=dt, device=dev)
    if isinstance(lam, torch.Tensor) and lam.dim():
        lam = lam.reshape(-1, 1, 1)
    a = torch.bmm(P, psi)                                                  # P Psi, (B, n, l)
    if l == 1:
        r = r_inv.reshape(()) if isinstance(r_inv, torch.Tensor) else float(r_inv)
        s = (r if lam_one else lam * r) + psi.mT @ a                       # (B, 1, 1); 1.0 * r is r
        go = (s > 0) & (s < _INF)                                          # positive and finite
        ok = go.reshape(B)
        if active is not None:
            go = go & active.reshape(B, 1, 1)
        s = torch.where(go, s, 1.0)
        a.masked_fill_(~go, 0.0)             # a member that does not go contributes exact zeros below
        step = a.view(B, n) * torch.where(go.view(B, 1), z_r / s.view(B, 1), 0.0)  # P Psi S^-1 z_R, (B, n)
    else:
        eye = torch.eye(l, dtype=dt, device=dev)
        lam = torch.as_tensor(lam, dtype=dt, device=dev)
        r_inv = torch.as_tensor(r_inv, dtype=dt, device=dev)
        S = lam * (r_inv * eye if r_inv.dim() == 0 else r_inv) + psi.mT @ a
        L, info = torch.linalg.cholesky_ex(S)
        ok = (info == 0) & torch.isfinite(S).flatten(1).all(1)
        go = (ok if active is None else ok & active).reshape(B, 1, 1)
        L = torch.where(go, L, eye)
        w = torch.linalg.solve_triangular(L, torch.where(go, a, 0.0).mT, upper=False).mT  # W = a L^-T
        v = torch.linalg.solve_triangular(L, torch.where(go.reshape(B, 1), z_r, 0.0).unsqueeze(-1),
                                          upper=False)                     # L^-1 z_R
        step = (w @ v).squeeze(-1)
    # A member whose update is not finite is left exactly as it was, like an inactive one.
    finite = (step @ _ones(n, dt, dev)).abs() < _INF                        # sum of the step is finite
    ok = ok & finite
    go = go & finite.reshape(B, 1, 1)
    if l == 1:
        s_inv = torch.where(go, 1.0 / s, 0.0)                              # s^-1, zero if not go
        step.masked_fill_(~go.reshape(B, 1), 0.0)                          # (the step was not finite)
    else:
        w = torch.where(go, w, 0.0)
        step = torch.where(go.reshape(B, 1), step, 0.0)
    div = None if lam_one else torch.where(go, lam, 1.0)
    factors = (a, s_inv) if l == 1 else (w,)
    if inplace:
        _downdate_(P, *factors)                                            # P - W W^T
        if div is not None:
            P.div_(div)
        theta.sub_(step)
        theta_new, P_new = theta, P
    else:
        P_new = _downdate_(P.clone(), *factors)
        if div is not None:
            P_new = P_new / div
        theta_new = theta - step                                           # theta - 0 is theta
    return theta_new, P_new, ok if active is None else ok | ~active


_INF = float("inf")


@functools.lru_cache(maxsize=64)
def _ones(n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A ones vector: ``x @ ones`` sums the rows of x in one matrix-vector product."""
    return torch.ones(n, dtype=dtype, device=device)


def _downdate_(P: torch.Tensor, w: torch.Tensor, s_inv: torch.Tensor | None = None) -> torch.Tensor:
    """P <- P - W W^T in place for W (B, n, l): entry (i, j) subtracts sum_c w_ic w_jc; with ``s_inv`` (B, 1, 1)
    and W = a (B, n, 1), it subtracts (a_i a_j) s_inv. Either way P stays exactly symmetric, and members with
    W = 0 (or s_inv = 0) are left exactly as they were (x - 0 = x)."""
    if s_inv is not None:
        return P.sub_((w * w.mT).mul_(s_inv))                              # (a_i a_j) / s
    return P.sub_(w @ w.mT)
