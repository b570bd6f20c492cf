"""The batched recursive-least-squares kernel of the retrospective cost update (seed eqs. 13-15).

For every batch member b, with regressor Psi (n x l), retrospective error z_R (l), weight R (l x l) and
forgetting factor lambda:

    S      = lambda R^-1 + Psi^T P Psi                          (l x l)
    theta <- theta - P Psi S^-1 z_R
    P     <- (P - P Psi S^-1 Psi^T P) / lambda

With lambda = 1 and P(0) = p0 I this is the exact minimizer of
sum_j |Psi_j^T theta + zeta_j|^2_R + |theta - theta_0|^2 / p0, where z_R,j = Psi_j^T theta_j + zeta_j.

Shapes: theta (B, n), P (B, n, n), psi (B, n, l), z_r (B, l), lam () or (B,), r_inv () or (l, l).
"""

from __future__ import annotations

import torch


def rls_update(theta: torch.Tensor, P: torch.Tensor, psi: torch.Tensor, z_r: torch.Tensor,
               lam: torch.Tensor | float = 1.0, r_inv: torch.Tensor | float = 1.0,
               active: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One RLS step for all members. Returns (theta, P, ok).

    Members with ``active = False`` are left exactly as they were. ``ok`` is False for an active member whose
    innovation covariance S is not positive and finite (P has lost definiteness) or whose new theta is not
    finite; such a member is also left as it was, so a caller can freeze it without losing the others.
    The P update forms ``P - a a^T / s`` (l = 1) or ``P - W W^T`` (l > 1), so P stays exactly symmetric.
    """
    B, n = theta.shape
    lam = torch.as_tensor(lam, dtype=P.dtype, device=P.device)
    lam = lam.reshape(-1, 1, 1) if lam.dim() else lam
    a = torch.bmm(P, psi)                                                  # P Psi, (B, n, l)
    l = psi.shape[-1]
    if l == 1:
        s = lam * torch.as_tensor(r_inv, dtype=P.dtype, device=P.device).reshape(()) + psi.mT @ a
        go = torch.isfinite(s) & (s > 0)                                   # (B, 1, 1)
        ok = go.reshape(B)
        if active is not None:
            go = go & active.reshape(B, 1, 1)
        step = (a / torch.where(go, s, 1.0)).squeeze(-1) * z_r              # P Psi S^-1 z_R
    else:
        eye = torch.eye(l, dtype=P.dtype, device=P.device)
        r_inv = torch.as_tensor(r_inv, dtype=P.dtype, device=P.device)
        S = lam * (r_inv * eye if r_inv.dim() == 0 else r_inv) + psi.mT @ a
        L, info = torch.linalg.cholesky_ex(S)
        ok = (info == 0) & torch.isfinite(S).flatten(1).all(1)
        go = (ok if active is None else ok & active).reshape(B, 1, 1)
        L = torch.where(go, L, eye)
        a = torch.linalg.solve_triangular(L, torch.where(go, a, 0.0).mT, upper=False).mT  # W = a L^-T
        v = torch.linalg.solve_triangular(L, torch.where(go.reshape(B, 1), z_r, 0.0).unsqueeze(-1),
                                          upper=False)                     # L^-1 z_R
        step = (a @ v).squeeze(-1)
    # A member whose update is not finite is left exactly as it was, like an inactive one.
    finite = torch.isfinite(step.sum(1))
    ok = ok & finite
    go = go & finite.reshape(B, 1, 1)
    a = torch.where(go, a, 0.0)
    if l == 1:
        P_new = P - (a @ a.mT) / torch.where(go, s, 1.0)                   # exactly symmetric
    else:
        P_new = P - a @ a.mT                                               # P - W W^T
    P_new = P_new / torch.where(go, lam, 1.0)
    theta_new = torch.where(go.reshape(B, 1), theta - step, theta)
    return theta_new, P_new, ok if active is None else ok | ~active
