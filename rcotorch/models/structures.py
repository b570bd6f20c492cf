"""Physical models used as known subsystems: mass-spring-damper structures with named signals."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..errors import ConfigError

if TYPE_CHECKING:
    import control

SIGNALS = ("position", "velocity")


def structure(M, C, K, force_w, measured: Sequence[str], sees: Sequence[str], force_u=None,
              actuation: bool = True) -> control.StateSpace:
    """Continuous structure M q'' + C q' + K q = F_w w + F_u u, state [q, q'].

    Outputs are ``measured`` then ``sees`` (the signals the unknown subsystem acts on), each an entry
    'position[i]' / 'velocity[i]' (or 'position' / 'velocity' for one degree of freedom). Inputs are w and,
    if ``actuation``, u (the unknown subsystem's forces, F_u = I by default).

    The system's signals are named as rcotorch's known model expects them: inputs ``w`` and ``u``, outputs
    ``y`` (the measured ones) and ``y0`` (the seen ones), with ``[i]`` appended where there are several;
    states ``q[i]`` and ``qdot[i]`` (``q``, ``qdot`` for one degree of freedom).
    """
    import control
    M, C, K = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (M, C, K))
    n = M.shape[0]
    Minv = np.linalg.inv(M)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ K, -Minv @ C]])
    Fw = np.asarray(force_w, dtype=float).reshape(n, -1)
    cols = [Fw]
    if actuation:
        cols.append(np.eye(n) if force_u is None else np.asarray(force_u, dtype=float).reshape(n, -1))
    Bm = np.vstack([np.zeros((n, sum(c.shape[1] for c in cols))), Minv @ np.hstack(cols)])

    def row(sig: str) -> np.ndarray:
        kind, _, idx = sig.partition("[")
        try:
            i = int(idx.rstrip("]")) if idx else 0
        except ValueError:
            i = -1
        if kind not in SIGNALS or not 0 <= i < n:
            names = list(SIGNALS) if n == 1 else [f"{k}[i]" for k in SIGNALS]
            raise ConfigError(f"structure: unknown signal {sig!r} in measured= or sees=; the accepted names are "
                              f"{', '.join(map(repr, names))}" + (f" with 0 <= i < {n}" if n > 1 else "")
                              + (" (or 'position[0]', 'velocity[0]')" if n == 1 else ""))
        r = np.zeros(2 * n)
        r[i if kind == "position" else n + i] = 1.0
        return r

    Cm = np.array([row(s) for s in list(measured) + list(sees)])
    names = dict(inputs=vector("w", Fw.shape[1]) + (vector("u", cols[1].shape[1]) if actuation else []),
                 outputs=vector("y", len(measured)) + vector("y0", len(sees)),
                 states=vector("q", n) + vector("qdot", n))
    return control.ss(A, Bm, Cm, np.zeros((Cm.shape[0], Bm.shape[1])), **names)


def vector(name: str, width: int) -> list[str]:
    """python-control names of a signal of ``width`` components: [name] or [name[0], name[1], ...]."""
    return [name] if width == 1 else [f"{name}[{i}]" for i in range(width)]


def sdof(m: float, c: float, k: float, measured=("velocity",), sees=("position", "velocity"),
         actuation: bool = True) -> control.StateSpace:
    """Single-degree-of-freedom m x'' + c x' + k x = w + u."""
    return structure([[m]], [[c]], [[k]], [1.0], measured, sees, actuation=actuation)


def sdof_matrices(m, c, k, measured=("velocity",), sees=("position", "velocity"), actuation: bool = True,
                  dtype=torch.float64) -> tuple[torch.Tensor, ...]:
    """Continuous (A, B, C, D) of ``sdof`` as torch tensors; m, c, k may be per-member tensors (B,), giving
    (B, rows, cols) matrices for ``LTI.continuous`` (a batch of structures that differ in their parameters)."""
    m, c, k = torch.broadcast_tensors(*(torch.as_tensor(x, dtype=dtype) for x in (m, c, k)))
    zero, one = torch.zeros_like(m), torch.ones_like(m)
    A = torch.stack([torch.stack([zero, one], -1), torch.stack([-k / m, -c / m], -1)], -2)
    col = torch.stack([zero, 1 / m], -1).unsqueeze(-1)
    B = torch.cat([col, col], -1) if actuation else col
    rows = {"position": [1.0, 0.0], "velocity": [0.0, 1.0]}
    for sig in list(measured) + list(sees):
        if sig not in rows:
            raise ValueError(f"unknown sdof signal {sig!r}: use 'position' or 'velocity'")
    C = torch.tensor([rows[sig] for sig in list(measured) + list(sees)], dtype=dtype)
    D = torch.zeros(C.shape[0], B.shape[-1], dtype=dtype)
    return A, B, C, D
