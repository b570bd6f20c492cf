"""Confidence intervals of a refinement's estimates, and whether the data determined them.

The estimator's parameters eta (theta = T eta) near the end of a run follow the stochastic-approximation
recursion of the RLS update,

    eta~(k+1) = eta~(k) - P(k) Psi(k) W [Psi_true(k)^T eta~(k) + v(k)],      eta~ = eta - eta*,

where Psi(k) is the regressor the update uses (the first nu Markov parameters of u -> z applied to phi, the
open-loop filter) and Psi_true(k) = dz(k)/d eta the true sensitivity of the model error to the parameters:
the same phi filtered by the whole closed loop of the simulated system (the known model with the identified
subsystem in feedback), v(k) the part of z no parameter explains (measurement noise), W the cost's weight R.
With A = E[Psi W Psi^T]^-1 E[Psi W Psi_true^T] and the gain P(k) ~ (n_k E[Psi W Psi^T])^-1,
n_k = sum_j lam^j, the covariance X of eta~ at step N solves the Lyapunov equation

    (A - c I) X + X (A - c I)^T = sym(E[Psi W Psi^T]^-1 E[Psi W V W Psi^T] P(N)),     c = lam^N / 2,

(V = E[v v^T]). For A = I and lam = 1 this is the ordinary least-squares covariance sigma^2 P; the open-loop
filter usually makes A larger than I (the closed loop responds to a parameter error for longer than nu
steps), so sigma^2 P alone is too wide. Where A - c I has an eigenvalue with a real part <= 0 the recursion
does not settle in that direction within the run: the data did not determine it.

``parameter_covariance`` measures A, V and the right-hand side by replaying a stretch of the run (from a
snapshot of the graph's state) with theta frozen at its final value: once as it is, and once per parameter
with that parameter moved by a small step, every copy fed the same excitation and noise (the sources are
pure functions of their seeds and the step), so the differences of z are Psi_true. It works for any graph
with an estimator role, on either engine's state. ``estimate_intervals`` carries X to any function of the
graph's parameters (an estimate such as a DC gain or a physical parameter backed out of theta) by the delta
method, with its gradient from central differences.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from statistics import NormalDist

import torch

from .errors import ConfigError

LEVEL = 0.95             # the default confidence level
REL_TOL = 0.5            # determined: each interval's half-width at most this fraction of max(|estimate|, scale)
REPLAY_STEPS = 4000      # at most this many steps replayed (the convergence window's length, up to this)
SETTLE = 0.25            # the first fraction of the replay lets the perturbed copies settle


@dataclass
class ParameterCovariance:
    """The covariance of the estimator's parameters eta at the end of a run, per member.

    Attributes:
        cov: (B, n, n) float64 covariance X of eta (NaN for members that were frozen or did not settle).
        gain: (B, n, n) the matrix A of the recursion (I when the open-loop filter is exact).
        noise: (B, n_z, n_z) V, the mean z z^T of the frozen replay (the residual's covariance).
        settles: (B,) bool, whether A - c I has eigenvalues with positive real parts only.
        replayed: steps replayed; ``measured`` of them entered the statistics.
    """

    cov: torch.Tensor
    gain: torch.Tensor
    noise: torch.Tensor
    settles: torch.Tensor
    replayed: int
    measured: int

    @property
    def std(self) -> torch.Tensor:
        """(B, n) standard deviations of the parameters."""
        return self.cov.diagonal(dim1=1, dim2=2).clamp_min(0).sqrt()


def snapshot(graph) -> dict[str, torch.Tensor]:
    """A copy of the graph's state (what ``parameter_covariance`` replays from)."""
    return {k: v.detach().clone() for k, v in graph.state_dict().items()}


def _frozen_copy(graph, state: Mapping[str, torch.Tensor], eta: torch.Tensor):
    g = copy.deepcopy(graph)
    g.load_state_dict(state)
    g.engine = "torch"
    est = g.role("estimator")
    est.set_theta_free(eta)
    est.set_state(P=torch.zeros_like(est.P))          # a zero gain: theta stays where it is
    return g, est


def parameter_covariance(graph, state: Mapping[str, torch.Tensor], steps: int, settle: int | None = None,
                         rel_step: float | None = None) -> ParameterCovariance:
    """The covariance of the parameters of ``graph``'s estimator (role 'estimator') as it is now, measured by
    replaying ``steps`` steps from ``state`` (a ``snapshot`` taken earlier in the same run) with theta frozen
    at its current value; the first ``settle`` steps (default: a quarter) only let the perturbed copies settle.
    ``rel_step``: the parameters' perturbation relative to their size (default 1e-7 in float64, 1e-3 in
    float32). The graph itself is not changed."""
    steps = int(steps)
    if steps < 2:
        raise ConfigError(f"intervals: at least 2 steps to replay, got {steps}")
    settle = int(SETTLE * steps) if settle is None else int(settle)
    if not 0 <= settle < steps:
        raise ConfigError(f"intervals: settle must lie in [0, {steps}), got {settle}")
    est = graph.role("estimator")
    z_sig = graph.role_signal("error")
    eta = est.theta_free().detach()
    B, n, n_z = eta.shape[0], eta.shape[1], est.n_z
    f64 = torch.float64
    if rel_step is None:
        rel_step = 1e-7 if eta.dtype == torch.float64 else 1e-3
    size = eta.abs().amax(1, keepdim=True).expand(B, n)
    size = torch.where(size > 0, size, est.P.diagonal(dim1=1, dim2=2).abs().sqrt())
    eps = rel_step * torch.where(size > 0, size, torch.ones_like(size))            # (B, n)
    base, base_est = _frozen_copy(graph, state, eta)
    copies = []
    for j in range(n):
        e = eta.clone()
        e[:, j] += eps[:, j]
        copies.append(_frozen_copy(graph, state, e)[0])
    weight = est.r_weight.to(f64)
    grams = torch.zeros(B, n_z, n_z, n, n, dtype=f64, device=eta.device)   # sum Psi[z, i] Psi[y, j]
    cross = torch.zeros(B, n, n, dtype=f64, device=eta.device)             # sum Psi W Psi_true^T
    zz = torch.zeros(B, n_z, n_z, dtype=f64, device=eta.device)
    measured = 0
    with torch.no_grad():
        for k in range(steps):
            z = base.step()[z_sig].to(f64)
            dz = torch.stack([(c.step()[z_sig].to(f64) - z) for c in copies], dim=2)   # (B, n_z, n)
            if k < settle:
                continue
            psi = base_est.last_regressor().to(f64)                               # (B, n_z, n)
            m = base_est.row_scale(psi)
            if m is not None:                                                     # the rows as weighed
                m = m.to(f64)
                z, dz = z / m.reshape(-1, 1), dz / m.reshape(-1, 1, 1)
                psi = psi / m.reshape(-1, 1, 1)
            grams += torch.einsum("bzi,byj->bzyij", psi, psi)
            cross += torch.einsum("bzi,zy,byj->bij", psi, weight, dz / eps.to(f64).unsqueeze(1))
            zz += torch.einsum("bz,by->bzy", z, z)
            measured += 1
    V = zz / measured
    info = torch.einsum("zy,bzyij->bij", weight, grams)                           # sum Psi W Psi^T
    noise_info = torch.einsum("bzy,bzyij->bij", weight @ V @ weight, grams)       # sum Psi W V W Psi^T
    finite = torch.isfinite(info).flatten(1).all(1) & torch.isfinite(cross).flatten(1).all(1) & \
        torch.isfinite(noise_info).flatten(1).all(1)
    eye = torch.eye(n, dtype=f64, device=info.device)
    info = torch.where(finite.reshape(-1, 1, 1), info, eye)            # frozen members: NaN at the end
    cross = torch.where(finite.reshape(-1, 1, 1), cross, eye)
    noise_info = torch.where(finite.reshape(-1, 1, 1), noise_info, eye)
    info_inv = torch.linalg.pinv(info)
    A = info_inv @ cross
    P = est.P.detach().to(f64)
    rhs = info_inv @ noise_info @ P
    rhs = 0.5 * (rhs + rhs.mT)
    lam = est.lam.to(f64).reshape(-1, 1, 1).expand(B, 1, 1)
    c = 0.5 * lam ** int(est.k)
    M = A - c * torch.eye(n, dtype=f64, device=A.device)
    X, settles = _lyapunov(M, rhs)
    alive = est.alive.to(settles.device)
    settles = settles & finite.to(settles.device)
    ok = settles & alive & torch.isfinite(X).flatten(1).all(1)
    X = torch.where(ok.reshape(-1, 1, 1), X, math.nan)
    return ParameterCovariance(cov=X, gain=A, noise=V, settles=settles & alive, replayed=steps, measured=measured)


def _lyapunov(M: torch.Tensor, Q: torch.Tensor, chunk_bytes: int = 1 << 27) -> tuple[torch.Tensor, torch.Tensor]:
    """X with M X + X M^T = Q for each member (B, n, n), and whether M's eigenvalues all have positive real
    parts (only then is X the covariance of a settling recursion)."""
    B, n, _ = M.shape
    eye = torch.eye(n, dtype=M.dtype, device=M.device)
    finite = torch.isfinite(M).flatten(1).all(1) & torch.isfinite(Q).flatten(1).all(1)
    Ms = torch.where(finite.reshape(-1, 1, 1), M, eye)
    settles = finite & (torch.linalg.eigvals(Ms).real.amin(1) > 0)
    X = torch.empty_like(M)
    per = max(1, chunk_bytes // (8 * n ** 4))
    for a in range(0, B, per):
        m = Ms[a:a + per]
        # row-major vec: vec(M X) = (M kron I) vec X, vec(X M^T) = (I kron M) vec X
        K = torch.einsum("bik,jl->bijkl", m, eye) + torch.einsum("ik,bjl->bijkl", eye, m)
        K = K.reshape(-1, n * n, n * n)
        q = torch.where(finite[a:a + per].reshape(-1, 1, 1), Q[a:a + per], 0.0).reshape(-1, n * n, 1)
        sol = torch.linalg.solve_ex(K, q)
        X[a:a + per] = sol.result.reshape(-1, n, n)
    X = 0.5 * (X + X.mT)
    return X, settles


def estimate_gradients(graph, estimates: Callable[[object], Mapping[str, torch.Tensor]],
                       std: torch.Tensor) -> dict[str, torch.Tensor]:
    """d estimate / d eta for every estimate (B,) of ``estimates(graph)``, by central differences with
    steps of 1e-3 of each parameter's standard deviation ``std`` (B, n) (1e-6 of its size where that is not
    finite or zero). Returns {key: (B, n)}; theta is restored."""
    est = graph.role("estimator")
    eta = est.theta_free().detach().clone()
    theta = est.theta.clone()
    B, n = eta.shape
    h = 1e-3 * std.to(eta.dtype)
    fallback = 1e-6 * torch.maximum(eta.abs(), eta.abs().amax(1, keepdim=True)).clamp_min(1e-12)
    h = torch.where(torch.isfinite(h) & (h > 0), h, fallback)
    grads: dict[str, list] = {}
    try:
        for j in range(n):
            vals = []
            for sign in (1.0, -1.0):
                e = eta.clone()
                e[:, j] += sign * h[:, j]
                est.set_theta_free(e)
                with torch.no_grad():
                    vals.append({k: v.detach().to(torch.float64).reshape(B) for k, v in estimates(graph).items()})
            for key in vals[0]:
                grads.setdefault(key, []).append((vals[0][key] - vals[1][key]) / (2 * h[:, j].to(torch.float64)))
    finally:
        est.set_state(theta=theta)
    return {k: torch.stack(v, dim=1) for k, v in grads.items()}


def quantile(level: float) -> float:
    """The two-sided normal quantile of a confidence level (1.96 for 0.95)."""
    if not 0 < level < 1:
        raise ConfigError(f"intervals: level must lie in (0, 1), got {level}")
    return NormalDist().inv_cdf(0.5 + level / 2)


@dataclass
class Intervals:
    """Confidence intervals of named estimates, per member (each value a (B,) float64 tensor)."""

    level: float
    estimate: dict[str, torch.Tensor]
    half_width: dict[str, torch.Tensor]
    determined: torch.Tensor              # (B,) bool
    undetermined_keys: list[list[str]]    # per member, the estimates whose interval is too wide

    def lower(self, key: str) -> torch.Tensor:
        return self.estimate[key] - self.half_width[key]

    def upper(self, key: str) -> torch.Tensor:
        return self.estimate[key] + self.half_width[key]


def estimate_intervals(graph, estimates: Callable[[object], Mapping[str, torch.Tensor]], pc: ParameterCovariance,
                       level: float = LEVEL, scales: Mapping[str, float] | None = None,
                       rel_tol: float = REL_TOL) -> Intervals:
    """Intervals est +- q sd of every estimate, sd^2 = g X g^T with g its gradient in eta (delta method).

    A member's estimates are *determined* when its parameter recursion settles (``pc.settles``) and every
    interval's half-width is at most ``rel_tol`` times max(|estimate|, scale), ``scales[key]`` a size the
    user gives for an estimate that may be near zero (e.g. the nominal value a change is relative to)."""
    q = quantile(level)
    with torch.no_grad():
        values = {k: v.detach().to(torch.float64).reshape(-1).cpu() for k, v in estimates(graph).items()}
    grads = estimate_gradients(graph, estimates, pc.std)
    X = pc.cov.cpu()
    det = pc.settles.cpu().clone()
    half, bad = {}, []
    for key, v in values.items():
        g = grads[key].cpu()
        var = torch.einsum("bi,bij,bj->b", g, X, g)
        hw = q * var.clamp_min(0).sqrt()
        half[key] = torch.where(torch.isfinite(var), hw, math.nan)
        scale = float((scales or {}).get(key, 0.0))
        ok = torch.isfinite(half[key]) & (half[key] <= rel_tol * torch.clamp(v.abs(), min=scale))
        bad.append(~ok)
        det &= ok
    keys = list(values)
    undetermined = [[k for k, b in zip(keys, row) if b] for row in
                    (torch.stack(bad, 1).tolist() if bad else [[]] * det.numel())]
    return Intervals(level=level, estimate=values, half_width=half, determined=det, undetermined_keys=undetermined)
