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

    Parameters
    ----------
    M, C, K : array_like
        Mass, damping and stiffness matrices, (n, n) (a scalar for n = 1).
    force_w : array_like
        F_w, (n,) or (n, m_w): how w enters the equations of motion.
    measured : Sequence[str]
        The measured outputs (``y``).
    sees : Sequence[str]
        The outputs the unknown subsystem sees (``y0``).
    force_u : array_like, optional
        F_u, (n, m_u); the identity by default.
    actuation : bool, optional
        Add the input u of the unknown subsystem.

    Returns
    -------
    control.StateSpace
        Continuous, 2n states.

    Raises
    ------
    ConfigError
        If a signal name is unknown or its index out of range.
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
    """python-control names of a signal of ``width`` components: [name] or [name[0], name[1], ...].

    Parameters
    ----------
    name : str
        The signal's name.
    width : int
        Its number of components.

    Returns
    -------
    list of str
    """
    return [name] if width == 1 else [f"{name}[{i}]" for i in range(width)]


def sdof(m: float, c: float, k: float, measured=("velocity",), sees=("position", "velocity"),
         actuation: bool = True) -> control.StateSpace:
    """Single-degree-of-freedom structure m x'' + c x' + k x = w + u (see ``structure``).

    Parameters
    ----------
    m, c, k : float
        Mass, damping and stiffness.
    measured : Sequence[str], optional
        The measured outputs, 'position' or 'velocity'.
    sees : Sequence[str], optional
        The outputs the unknown subsystem sees.
    actuation : bool, optional
        Add the input u of the unknown subsystem.

    Returns
    -------
    control.StateSpace
        Continuous, states [q, qdot].
    """
    return structure([[m]], [[c]], [[k]], [1.0], measured, sees, actuation=actuation)


def sdof_matrices(m, c, k, measured=("velocity",), sees=("position", "velocity"), actuation: bool = True,
                  dtype=torch.float64) -> tuple[torch.Tensor, ...]:
    """Continuous (A, B, C, D) of ``sdof`` as torch tensors.

    m, c, k may be per-member tensors (B,), giving (B, rows, cols) matrices for ``LTI.continuous`` (a batch of
    structures that differ in their parameters).

    Parameters
    ----------
    m, c, k : float or torch.Tensor
        Mass, damping and stiffness, scalars or (B,) (broadcast together).
    measured : Sequence[str], optional
        The measured outputs, 'position' or 'velocity'.
    sees : Sequence[str], optional
        The outputs the unknown subsystem sees.
    actuation : bool, optional
        Add the input u of the unknown subsystem.
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).

    Returns
    -------
    tuple of torch.Tensor
        A (..., 2, 2), B (..., 2, 1 or 2), C (p, 2), D (p, 1 or 2), ``...`` the broadcast shape of m, c, k.

    Raises
    ------
    ValueError
        If a signal is neither 'position' nor 'velocity'.
    """
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


def shear_building(masses: Sequence[float], stiffnesses: Sequence[float], damping_ratio: float = 0.02,
                   force: str | int = "base", measured: Sequence[str] = ("velocity[-1]",),
                   identified: Sequence[int] = (), actuation: bool = True) -> control.StateSpace:
    """A shear building of n storeys, floors 1..n above the ground (floor 0), as a continuous structure.

    Storey j (1..n) joins floor j - 1 and floor j with stiffness ``stiffnesses[j - 1]``; floor j carries
    ``masses[j - 1]``. Damping is Rayleigh, C = a M + b K, with ``damping_ratio`` in the first two modes (the
    first alone for one storey). ``force``: ``'base'`` (w is the ground acceleration: every floor feels
    -m_j w) or a floor number 1..n (w is a force on that floor). ``measured``: 'displacement[j]' or
    'velocity[j]' of floors j = 1..n (negative j counts from the roof: -1 is the roof), relative to the ground,
    or 'acceleration[j]', the floor's absolute acceleration (what an accelerometer on it reads: relative
    acceleration plus the ground's, x_j'' + w, for base excitation), which the inputs reach at once (D != 0).

    ``identified``: the storeys whose stiffness change the unknown subsystem supplies. For each, it sees the
    storey drift d_j = x_j - x_(j-1) (output ``y0[i]``) and acts with a force pair u_j: +u_j on floor j and
    -u_j on floor j - 1 (input ``u[i]``), so that u_j = -dk_j d_j is a change dk_j of that storey's
    stiffness. State [x_1..x_n, x_1'..x_n'] (floor displacements relative to the ground and their rates).

    Parameters
    ----------
    masses : Sequence[float]
        The floors' masses, one per storey, > 0.
    stiffnesses : Sequence[float]
        The storeys' stiffnesses, > 0.
    damping_ratio : float, optional
        The Rayleigh damping ratio of the first two modes.
    force : 'base' or int, optional
        Ground acceleration, or the floor a force acts on.
    measured : Sequence[str], optional
        'displacement[j]', 'velocity[j]' or 'acceleration[j]' of floors (``y``).
    identified : Sequence[int], optional
        The storeys whose stiffness change the unknown subsystem supplies (``y0``, ``u``).
    actuation : bool, optional
        Add the inputs u of the unknown subsystem.

    Returns
    -------
    control.StateSpace
        Continuous, 2n states.

    Raises
    ------
    ConfigError
        If masses or stiffnesses are missing or not positive, ``force`` is neither 'base' nor a floor, or a
        storey or a measured signal is out of range or unknown.
    """
    import control
    m = np.asarray(masses, dtype=float).reshape(-1)
    k = np.asarray(stiffnesses, dtype=float).reshape(-1)
    n = len(m)
    if len(k) != n or n == 0 or np.any(m <= 0) or np.any(k <= 0):
        raise ConfigError(f"shear_building: needs one positive mass and one positive stiffness per storey, got "
                          f"{len(m)} masses {m.tolist()} and {len(k)} stiffnesses {k.tolist()}")
    K = np.zeros((n, n))
    for j in range(n):                       # storey j + 1 joins floors j and j + 1 (0-based: j - 1 and j)
        K[j, j] += k[j]
        if j > 0:
            K[j - 1, j - 1] += k[j]
            K[j - 1, j] -= k[j]
            K[j, j - 1] -= k[j]
    M = np.diag(m)
    w2 = np.sort(np.linalg.eigvals(np.linalg.solve(M, K)).real)
    if n == 1:
        a, b = 0.0, 2 * damping_ratio / np.sqrt(w2[0])
    else:
        w1, w2_ = np.sqrt(w2[0]), np.sqrt(w2[1])
        a, b = 2 * damping_ratio * w1 * w2_ / (w1 + w2_), 2 * damping_ratio / (w1 + w2_)
    C = a * M + b * K

    def floor(j: int, what: str) -> int:
        if not (1 <= j <= n or -n <= j <= -1):
            raise ConfigError(f"shear_building: {what} names floor {j}; floors are 1..{n} (or -1..-{n} from the "
                              "roof)")
        return j - 1 if j > 0 else n + j

    if force == "base":
        Fw = -m.reshape(n, 1)
    elif isinstance(force, (int, np.integer)) and not isinstance(force, bool):
        Fw = np.zeros((n, 1))
        Fw[floor(int(force), "force="), 0] = 1.0
    else:
        raise ConfigError(f"shear_building: force must be 'base' or a floor number 1..{n}, got {force!r}")
    storeys = [int(s) for s in identified]
    for s in storeys:
        if not 1 <= s <= n:
            raise ConfigError(f"shear_building: identified storey {s}; storeys are 1..{n}")
    Fu = np.zeros((n, len(storeys)))
    drift = np.zeros((len(storeys), 2 * n))
    for i, s in enumerate(storeys):
        Fu[s - 1, i] = 1.0
        drift[i, s - 1] = 1.0
        if s > 1:
            Fu[s - 2, i] = -1.0
            drift[i, s - 2] = -1.0
    Minv = np.linalg.inv(M)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ K, -Minv @ C]])
    B = np.vstack([np.zeros((n, 1 + (len(storeys) if actuation else 0))),
                   Minv @ (np.hstack([Fw, Fu]) if actuation else Fw)])
    rows, feed = [], []
    for sig in measured:
        kind, _, idx = str(sig).partition("[")
        try:
            j = int(idx.rstrip("]"))
        except ValueError:
            j = 0
        if kind not in ("displacement", "velocity", "acceleration") or not idx:
            raise ConfigError(f"shear_building: measured signal {sig!r}; use 'displacement[j]', 'velocity[j]' or "
                              f"'acceleration[j]' with a floor j in 1..{n} (or -1 for the roof)")
        i = floor(j, f"measured {sig!r}")
        if kind == "acceleration":            # x_j'' = row n + i of (A, B), plus the ground's for base excitation
            r, d = A[n + i].copy(), B[n + i].copy()
            if force == "base":
                d[0] += 1.0
        else:
            r, d = np.zeros(2 * n), np.zeros(B.shape[1])
            r[i + (n if kind == "velocity" else 0)] = 1.0
        rows.append(r)
        feed.append(d)
    Cm = np.vstack(rows + ([drift] if len(storeys) else []))
    Dm = np.vstack(feed + ([np.zeros((len(storeys), B.shape[1]))] if len(storeys) else []))
    names = dict(inputs=["w"] + (vector("u", len(storeys)) if actuation and storeys else []),
                 outputs=vector("y", len(rows)) + (vector("y0", len(storeys)) if storeys else []),
                 states=vector("x", n) + vector("xdot", n))
    return control.ss(A, B, Cm, Dm, **names)
