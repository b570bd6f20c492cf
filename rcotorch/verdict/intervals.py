"""Confidence intervals of a refinement's estimates, and whether the data determined them.

The estimator's parameters eta (theta = T eta) near the end of a run follow the stochastic-approximation
recursion of the RLS update,

    eta~(k+1) = eta~(k) - P(k) Psi(k) W [Psi_true(k)^T eta~(k) + v(k)],      eta~ = eta - eta*,

where Psi(k) is the regressor the update uses (the first nu Markov parameters of u -> z applied to phi, the
open-loop filter) and Psi_true(k) = dz(k)/d eta the true sensitivity of the model error to the parameters:
the same phi filtered by the whole closed loop of the simulated system (the known model with the identified
subsystem in feedback), v(k) the part of z no parameter explains (measurement noise), W the cost's weight R.
With A = E[Psi W Psi^T]^-1 E[Psi W Psi_true^T] and the gain P(k) ~ (n_k E[Psi W Psi^T])^-1,
n_k = sum_j lam^j, the covariance X of eta~ at step N is the variance the recursion gathers over its time
T = sum_{k<=N} 1 / n_k (ln N + 0.58 for lam = 1):

    X = X_inf - exp(-M T) X_inf exp(-M T)^T,   M X_inf + X_inf M^T = Q,   M = A - c I,   c = lam^N / 2,
    Q = sym(E[Psi W Psi^T]^-1 Omega P(N)),

Omega the long-run covariance of the scores Psi W z (E[Psi W V W Psi^T], V = E[v v^T], for white residuals).
For A = I and lam = 1 this is the ordinary least-squares covariance sigma^2 P; the open-loop filter usually
makes A larger than I (the closed loop responds to a parameter error for longer than nu steps), so sigma^2 P
alone is too wide. A direction with an eigenvalue of A near 0 was not excited by the data (``EXCITED``): the
data did not determine it.

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
from typing import Any

import numpy as np
import torch

from ..engine import kernels
from ..errors import ConfigError
from . import sampling

LEVEL = 0.95             # the default confidence level
REL_TOL = 0.5            # determined: each interval's half-width at most this fraction of max(|estimate|, scale)
REPLAY_STEPS = 4000      # at most this many steps replayed (the convergence window's length, up to this)
SETTLE = 0.25            # the first fraction of the replay lets the perturbed copies settle
SETTLE_TAUS = 5.0        # ... or, where longer, this many time constants of the frozen loop's slowest mode
SETTLE_MAX = 4 * REPLAY_STEPS    # at most this many steps to settle (rcotorch.run.runner.loop_settle)
LAGS = 25                # lags of the residual checks (z's autocorrelation, its cross-correlation with w)
KEEP_MEMBERS = 8         # members whose replayed outputs are kept for figures
SCORE_LAGS = 25          # lags of the scores' long-run covariance (correlated residuals widen the intervals)
CHUNK_BYTES = 1 << 26    # the replay's regressors are summed in chunks of steps of at most this many bytes
WHITE_P = 0.01           # residuals whose whiteness test gives a smaller p-value are treated as correlated
EXCITED = 0.05           # a direction of theta whose eigenvalue of A is smaller was not excited by the data
OFFSET_FACTOR = 2.0      # an estimate the output error's step moves by more half-widths than this is biased
OFFSET_FACTOR_CORRELATED = 1.0  # the same where the residuals are not white (WHITE_P)
BIAS_TOL = 0.05          # an estimate that step moves by more than this fraction of its size is biased
NEGLIGIBLE = 1e-3        # a bias or drift below this fraction of an estimate's size is corrected, never flagged
UNEXPLAINED_MIN = 0.01   # residuals_matter: the least share of z's energy no parameter explains
WIDENING_MATTERS = 1.25  # ... and the least widening of a standard deviation by the residuals' correlation
OFFSET_Z = 1.96          # a move beyond this many of the step's own standard deviations widens the interval too
DRIFT_FAR = 2.0          # ... and one beyond this many half-widths is a member still drifting (not converged)
DRIFT_Z = 1.96           # a remaining transient beyond this many of its standard deviations is the estimate's drift


@dataclass
class ParameterCovariance:
    """The covariance of the estimator's parameters eta at the end of a run, per member.

    Attributes:
        cov: (B, n, n) float64 covariance X of eta (NaN for members that were frozen or did not settle).
        gain: (B, n, n) the matrix A of the recursion (I when the open-loop filter is exact).
        noise: (B, n_z, n_z) V, the mean z z^T of the frozen replay (the residual's covariance).
        settles: (B,) bool, whether every eigenvalue of A has a real part above ``EXCITED`` (every direction of
            the parameters was excited by the data).
        replayed: steps replayed; ``measured`` of them entered the statistics.
        offset: (B, n) the Gauss-Newton step of the window's output error from eta,
            -(sum J^T W J)^-1 sum J^T W z with J = dz/d eta of the frozen loop (``OFFSET_FACTOR``).
        correlated: (B,) bool, whether the whiteness test rejected white residuals (p-value below ``WHITE_P``).
        offset_cov: (B, n, n) the covariance of ``offset``'s random error (white residuals; with forgetting the
            parameters' own covariance added).
        widening: (B,) how many times wider the correlation of the residuals makes the parameters' standard
            deviations (the largest ratio over the parameters; 1 where the residuals are white).
        unexplained: (B,) the share of z's weighted energy over the window that the output error's Gauss-Newton
            step leaves: near 0 where z is a parameter error the model can take back (a noise-free run still
            converging), near 1 where it is noise or dynamics no parameter represents.
        sampling: (B, n) the refined model's estimate minus the physics' (``bias_source``: 'physics', the
            physics at the estimates that ``replay`` was given, or 'sampling', the continuous feedback a sampled
            one stands for, ``rcotorch.verdict.sampling``), or None where neither applies (``sampling_note``
            says why).
    """

    cov: torch.Tensor
    gain: torch.Tensor
    noise: torch.Tensor
    settles: torch.Tensor
    replayed: int
    measured: int
    offset: torch.Tensor | None = None
    correlated: torch.Tensor | None = None
    widening: torch.Tensor | None = None
    unexplained: torch.Tensor | None = None
    offset_cov: torch.Tensor | None = None
    sampling: torch.Tensor | None = None
    sampling_note: str | None = None
    bias_source: str | None = None

    @property
    def std(self) -> torch.Tensor:
        """(B, n) standard deviations of the parameters."""
        return self.cov.diagonal(dim1=1, dim2=2).clamp_min(0).sqrt()


def snapshot(graph) -> dict[str, torch.Tensor]:
    """A copy of the graph's state (what ``parameter_covariance`` replays from)."""
    return {k: v.detach().clone() for k, v in graph.state_dict().items()}


def _frozen_copy(graph, state: Mapping[str, torch.Tensor], eta: torch.Tensor, engine: str = "torch"):
    g = copy.deepcopy(graph)
    g.load_state_dict(state)
    g.engine = engine
    est = g.role("estimator")
    est.set_theta_free(eta)
    est.set_state(P=torch.zeros_like(est.P))          # a zero gain: theta stays where it is
    return g, est


@dataclass
class Residuals:
    """Checks of the refined model on the replayed window (theta frozen at its final value), per member.

    Attributes:
        steps: samples the statistics hold (N).
        autocorr: (B, L + 1, n_z) normalized autocorrelation of each channel of z at lags 0..L (1 at lag 0).
        xcorr: (B, L + 1, n_z, n_w) normalized cross-correlation of z(k) with w(k - lag), lags 0..L, or None
            when the graph declares no exogenous signal (role 'exogenous').
        bound: the 95% band of a correlation of white, independent signals, 1.96 / sqrt(N).
        whiteness_p: (B,) the Ljung-Box test's p-value that z is white (the smallest over z's channels).
        fit, fit_initial: (B,) the fit in percent, 100 (1 - |y - y_hat| / |y - mean y|), of the refined model
            and of the initial one (theta as the run started) on the same data.
        series: the first members' measured, refined and initial outputs {name: (N, M, n_y)} for figures.
    """

    steps: int
    autocorr: torch.Tensor
    xcorr: torch.Tensor | None
    bound: float
    whiteness_p: torch.Tensor
    fit: torch.Tensor
    fit_initial: torch.Tensor
    series: dict[str, torch.Tensor]


@dataclass
class Replay:
    """What ``replay`` measures: the parameters' covariance and the residual checks."""

    covariance: ParameterCovariance
    residuals: Residuals


def parameter_covariance(graph, state: Mapping[str, torch.Tensor], steps: int,
                         settle: int | torch.Tensor | None = None, rel_step: float | None = None
                         ) -> ParameterCovariance:
    """The covariance of the parameters of ``graph``'s estimator (``replay(...).covariance``)."""
    return replay(graph, state, steps, settle, rel_step).covariance


def replay(graph, state: Mapping[str, torch.Tensor], steps: int, settle: int | torch.Tensor | None = None,
           rel_step: float | None = None, lags: int = LAGS, keep: int = KEEP_MEMBERS,
           score_lags: int = SCORE_LAGS, physics=None) -> Replay:
    """Replay ``steps`` steps of ``graph`` from ``state`` (a ``snapshot`` taken earlier in the same run) with the
    estimator's theta frozen at its current value, to measure the parameters' covariance (module docstring)
    and to check the refined model's residuals: copies with each parameter moved by a small step, and one with
    the initial theta. The first ``settle`` steps (default: a quarter) only let the copies settle; ``settle``
    may be one per member, (B,) (then each member measures the ``steps - max(settle)`` steps after its own, so
    that what a member finds does not depend on the others).
    ``rel_step``: the parameters' perturbation relative to their size (default 1e-7 in float64, 1e-3 in
    float32). ``lags``: correlation lags of the residual checks; ``keep``: members whose outputs are kept for
    figures; ``score_lags``: lags of the scores' long-run covariance (``_ScoreSums``). ``physics``: a graph like
    ``graph`` whose physical blocks (``physical_blocks``) hold the physics at the estimates; one more copy runs
    with those blocks in place of ``graph``'s, and the Gauss-Newton step of its output against the refined
    model's prediction is the estimates' bias against the physics (``ParameterCovariance.sampling``; without it,
    where the graph declares a continuous feedback, ``rcotorch.verdict.sampling`` measures that bias). The graph
    itself is not changed."""
    steps = int(steps)
    if steps < 2:
        raise ConfigError(f"intervals: at least 2 steps to replay, got {steps}")
    est = graph.role("estimator")
    B_all = est.theta.shape[0]
    own = torch.as_tensor(int(SETTLE * steps) if settle is None else settle, dtype=torch.int64).reshape(-1)
    own = own.expand(B_all).to(est.theta.device) if own.numel() == 1 else own.to(est.theta.device)
    if own.shape != (B_all,) or int(own.min()) < 0 or int(own.max()) >= steps:
        raise ConfigError(f"intervals: settle must be one number or one per member in [0, {steps}), got {settle}")
    settle, last = int(own.min()), int(own.max())           # the steps before every member's and any member's
    measured = steps - last                                 # the steps each member measures, after its own settle
    z_sig = graph.role_signal("error")
    y_sig = graph.role_signal("measured") if "measured" in graph.roles else z_sig
    w_sig = graph.role_signal("exogenous") if "exogenous" in graph.roles else None
    eta = est.theta_free().detach()
    B, n, n_z = eta.shape[0], eta.shape[1], est.n_z
    f64, dev = torch.float64, eta.device
    if rel_step is None:
        rel_step = 1e-7 if eta.dtype == torch.float64 else 1e-3
    size = eta.abs().amax(1, keepdim=True).expand(B, n)
    size = torch.where(size > 0, size, est.P.diagonal(dim1=1, dim2=2).abs().sqrt())
    eps = rel_step * torch.where(size > 0, size, torch.ones_like(size))            # (B, n)
    # Every copy runs on the graph's engine (native where it can): it advances to where the steps that count
    # begin (less the Markov parameters' reach), then records its outputs: the base copy (theta frozen at its
    # value) also the estimator's inputs and u, from which its regressors are rebuilt (``regressors_over``);
    # the copies with each parameter moved and with the initial theta, z.
    theta0 = est.theta0.expand(B, -1, -1).reshape(B, -1)
    runs = [eta] + [eta + eps[:, j:j + 1] * torch.eye(n, dtype=eta.dtype, device=dev)[j] for j in range(n)]
    runs.append(theta0.index_select(1, est.free_idx.to(theta0.device)))
    ports = [p for p in est.inputs if p not in ("z", "valid") and (est.name, p) in graph.sources]
    regressor_inputs = {p: graph.sources[(est.name, p)] for p in ports}
    pre = max(0, settle - est.window - est.nc)              # steps advanced before recording
    # Where the graph declares a continuous feedback, the base copy records from the replay's first step on,
    # so that the refined model simulated with that feedback (``sampling``) settles as long as the copies.
    swap = physical_blocks(graph) if physics is not None else None
    how = sampling.plan(graph) if not swap else "the physics at the estimates are simulated instead"
    b0 = 0 if isinstance(how, dict) or swap else pre
    shift = pre - b0                                        # the base copy's steps recorded before the others'
    recorded, sampled_minus_continuous = [], None
    for e in runs:
        g, e_est = _frozen_copy(graph, state, e, engine=graph.engine)
        start = b0 if not recorded else pre
        if start:
            g.advance(start)
        signals = [z_sig]
        if not recorded:
            signals += [y_sig] + ([w_sig] if w_sig is not None else []) + list(regressor_inputs.values()) + \
                [(est.name, "u")]
            if isinstance(how, dict):
                signals += how["record"] + [graph.role_signal("prediction")]
                x_start = g.blocks[how["known"]].x.clone()
            elif swap:
                signals += [graph.role_signal("prediction")]
            base_est, history = e_est, e_est.regressor_history()
        names = {f"{blk}.{port}": (blk, port) for blk, port in dict.fromkeys(signals)}
        rec = g.run(steps - start, record={name: name for name in names})
        recorded.append({names[name]: v for name, v in rec.items()})
        if len(recorded) == 1 and isinstance(how, dict):
            with torch.no_grad():
                y_c = recorded[0][graph.role_signal("prediction")].to(f64)
                y_f = sampling.continuous_prediction(g, how, x_start, recorded[0], steps - start)
            sampled_minus_continuous = (y_f - y_c)[shift:]     # z_c - z_f, over the other copies' steps
        if len(recorded) == 1 and swap:
            y_c = recorded[0][graph.role_signal("prediction")].to(f64)
            y_p = _physics_output(graph, state, eta, physics, swap, steps - b0, b0)
            sampled_minus_continuous = (y_p - y_c)[shift:]
        del g
    # From here on, steps are counted from the first recorded one of the copies.
    settle, last, own = settle - pre, last - pre, own - pre
    first = recorded[0]
    base_inputs = {p: first[sig] for p, sig in regressor_inputs.items()}
    base_u = first[(est.name, "u")]
    recorded[0] = first = {sig: v[shift:] for sig, v in first.items()}
    first = {sig: v.to(f64) for sig, v in first.items()}
    recorded = [first] + [{sig: v.to(f64) for sig, v in r.items()} for r in recorded[1:]]
    zs = torch.stack([r[z_sig] for r in recorded[1:n + 1]], dim=3)                      # (steps, B, n_z, n)
    weight = est.r_weight.to(f64)
    eps64 = eps.to(f64)
    # The residual checks need only the recorded outputs: all at once, each member's own measured steps.
    ahead = own.reshape(1, B) + torch.arange(measured, device=dev).reshape(-1, 1)          # (T, B) step of each

    def measured_part(x: torch.Tensor) -> torch.Tensor:
        if settle == last:                                  # every member measures the same steps
            return x[settle:settle + measured]
        return x.gather(0, ahead.reshape(measured, B, *([1] * (x.dim() - 2))).expand(measured, B, *x.shape[2:]))

    res = _ResidualSums(B, lags, keep, dev)
    res.add(measured_part(first[z_sig]), None if w_sig is None else measured_part(first[w_sig]),
            measured_part(first[y_sig]), measured_part(recorded[-1][z_sig]))
    z_all = first[z_sig][settle:]                                                       # (T', B, n_z), T' >= T
    # where a member's measured steps begin after the first member's, the steps outside its own count zero
    at = torch.arange(settle, steps - pre, device=dev).reshape(-1, 1) - own.reshape(1, B)   # each member's own step
    within = None if settle == last else ((at >= 0) & (at < measured)).to(f64)
    jwj = torch.zeros(B, n, n, dtype=f64, device=dev)               # sum J^T W J, J = Psi_true^T = dz / d eta
    jwz = torch.zeros(B, n, dtype=f64, device=dev)                  # sum J^T W z
    jwd = torch.zeros(B, n, dtype=f64, device=dev)                  # sum J^T W (z_f - z_c)
    zwz = torch.zeros(B, dtype=f64, device=dev)                     # sum z^T W z
    jgram = torch.zeros(B, n_z, n_z, n, n, dtype=f64, device=dev)   # sum J[z, i] J[y, j]
    grams = torch.zeros(B, n_z, n_z, n, n, dtype=f64, device=dev)   # sum Psi[z, i] Psi[y, j]
    cross = torch.zeros(B, n, n, dtype=f64, device=dev)             # sum Psi W Psi_true^T
    zz = torch.zeros(B, n_z, n_z, dtype=f64, device=dev)
    scores = _ScoreSums(B, n, score_lags, dev)
    # The base copy's regressors, summed in chunks of steps (each sum over a chunk is one batched product):
    # chunk x B x n_z x n values at most CHUNK_BYTES.
    chunk = max(1, min(steps - pre - settle, CHUNK_BYTES // max(1, 8 * B * n_z * n * 2)))

    def flush(t0: int, upto: int) -> None:
        """Add the regressors of the measured steps t0 .. upto - 1 (relative to settle)."""
        nonlocal jwj, jwz, jwd, zwz, jgram, grams, cross, zz
        C = upto - t0
        psi = base_est.regressors_over(history, base_inputs, base_u, shift + settle + t0, shift + settle + upto)
        psi = psi.transpose(0, 1)                                                  # (B, C, n_z, n)
        z = z_all[t0:upto].transpose(0, 1)                                         # (B, C, n_z)
        jac = (zs[settle + t0:settle + upto].transpose(0, 1) - z.unsqueeze(3)) / eps64.reshape(B, 1, 1, n)
        if within is not None:
            inside = within[t0:upto].transpose(0, 1)                               # (B, C)
            z, jac = z * inside.unsqueeze(-1), jac * inside.reshape(B, C, 1, 1)
            psi = psi * inside.reshape(B, C, 1, 1)
        jac_w = weight @ jac                                                       # W J (W symmetric)
        jwj += _tsum(jac, jac_w)
        jwz += _tsum(jac_w, z.unsqueeze(-1)).squeeze(-1)
        zwz += ((z @ weight) * z).sum((1, 2))
        flat_j = jac.reshape(B, C, n_z * n)
        jgram += (flat_j.mT @ flat_j).reshape(B, n_z, n, n_z, n).permute(0, 1, 3, 2, 4)
        if sampled_minus_continuous is not None:
            d = sampled_minus_continuous[settle + t0:settle + upto].transpose(0, 1)      # (B, C, n_z)
            if within is not None:
                d = d * inside.unsqueeze(-1)
            jwd += _tsum(jac_w, d.unsqueeze(-1)).squeeze(-1)
        m = base_est.row_scale(psi.reshape(-1, n_z, n))
        if m is not None:                                                     # the rows as weighed
            m = m.to(f64).reshape(B, C)
            z = z / m.unsqueeze(-1)
            jac_w = jac_w / m.reshape(B, C, 1, 1)
            psi = psi / m.reshape(B, C, 1, 1)
        flat = psi.reshape(B, C, n_z * n)
        grams += (flat.mT @ flat).reshape(B, n_z, n, n_z, n).permute(0, 1, 3, 2, 4)
        cross += _tsum(psi, jac_w)
        zz += z.mT @ z
        scores.add(_tsum_rows(psi, z @ weight))

    with torch.no_grad():
        for t0 in range(0, steps - pre - settle, chunk):
            flush(t0, min(steps - pre - settle, t0 + chunk))
    V = zz / measured
    finite = torch.isfinite(grams).flatten(1).all(1) & torch.isfinite(cross).flatten(1).all(1) & \
        torch.isfinite(V).flatten(1).all(1)
    eye = torch.eye(n, dtype=f64, device=dev)
    info = torch.einsum("zy,bzyij->bij", weight, grams)                           # sum Psi W Psi^T
    residuals = res.result()
    correlated = (residuals.whiteness_p < WHITE_P).to(dev)
    noise_info = scores.long_run(correlated)          # sum Psi W z z^T W Psi^T, lagged terms where z is not white
    white_info = scores.long_run(torch.zeros_like(correlated))
    finite = finite & torch.isfinite(noise_info).flatten(1).all(1)
    info = torch.where(finite.reshape(-1, 1, 1), info, eye)            # frozen members: NaN at the end
    cross = torch.where(finite.reshape(-1, 1, 1), cross, eye)
    noise_info = torch.where(finite.reshape(-1, 1, 1), noise_info, eye)
    white_info = torch.where(finite.reshape(-1, 1, 1), white_info, eye)
    info_inv = torch.linalg.pinv(info)
    A = info_inv @ cross
    P = est.P.detach().to(f64)
    lam = est.lam.to(f64).reshape(-1, 1, 1).expand(B, 1, 1)
    N = int(est.k)
    c = 0.5 * lam ** N
    M = A - c * torch.eye(n, dtype=f64, device=A.device)
    # The recursion has run for the time sum_k 1/n_k in the units of its gain (ln N + 0.58 for lam = 1): a
    # direction that relaxes slowly (an eigenvalue of A - cI near or below 0) has gathered its variance over
    # that time only, X_T = X - exp(-M T) X exp(-M T)^T (the integral of the variance's equation from 0 to T).
    E = torch.linalg.matrix_exp(-M * _gain_time(est.lam.to(f64).cpu().reshape(-1).expand(B), N
                                                 ).to(M.device).reshape(-1, 1, 1))

    def covariance(omega: torch.Tensor) -> torch.Tensor:
        rhs = info_inv @ omega @ P
        X = _lyapunov(M, 0.5 * (rhs + rhs.mT))
        X = X - E @ X @ E.mT
        return 0.5 * (X + X.mT)
    X = covariance(noise_info)
    # how much wider the correlation of the residuals makes the intervals (1 where they are white)
    X_white = covariance(white_info) if bool(correlated.any()) else X
    widening = (X.diagonal(dim1=1, dim2=2) / X_white.diagonal(dim1=1, dim2=2).clamp_min(1e-300)).clamp_min(0).sqrt()
    widening = torch.where(correlated.to(dev), widening.amax(1), 1.0)
    settles = torch.linalg.eigvals(torch.where(finite.reshape(-1, 1, 1), A, eye)).real.amin(1) > EXCITED
    alive = est.alive.to(settles.device)
    settles = settles & finite.to(settles.device)
    ok = settles & alive & torch.isfinite(X).flatten(1).all(1)
    X = torch.where(ok.reshape(-1, 1, 1), X, math.nan)
    # The output error's Gauss-Newton step over the window: where the frozen loop's error is smaller.
    step_ok = ok & torch.isfinite(jwj).flatten(1).all(1) & torch.isfinite(jwz).all(1)
    offset = -(torch.linalg.pinv(torch.where(step_ok.reshape(-1, 1, 1), jwj, eye)) @
               torch.where(step_ok.reshape(-1, 1), jwz, 0.0).unsqueeze(-1)).squeeze(-1)
    offset = torch.where(step_ok.reshape(-1, 1), offset, math.nan)
    # the step's random error, (sum J^T W J)^-1 (sum J^T W V W J) (sum J^T W J)^-1 for white residuals (the window's
    # output-error estimate's), with the parameters' own X added under forgetting (the two are then not nested)
    jwj_inv = torch.linalg.pinv(torch.where(step_ok.reshape(-1, 1, 1), jwj, eye))
    offset_cov = jwj_inv @ torch.einsum("bzy,bzyij->bij", weight @ V @ weight, jgram) @ jwj_inv
    forgets = (est.lam.to(f64).reshape(-1).expand(B) < 1).to(dev).reshape(-1, 1, 1)
    offset_cov = torch.where(step_ok.reshape(-1, 1, 1), offset_cov + torch.where(forgets, X, 0.0), math.nan)
    bias = None
    if sampled_minus_continuous is not None:   # the sampled estimate minus the continuous physics' (``sampling``)
        bias = -(torch.linalg.pinv(torch.where(step_ok.reshape(-1, 1, 1), jwj, eye)) @
                 torch.where(step_ok.reshape(-1, 1), jwd, 0.0).unsqueeze(-1)).squeeze(-1)
        bias = torch.where(step_ok.reshape(-1, 1), bias, math.nan)
    # the share of z's weighted energy that no parameter explains (what the Gauss-Newton step leaves)
    explained = (jwz.unsqueeze(1) @ torch.linalg.pinv(torch.where(step_ok.reshape(-1, 1, 1), jwj, eye)) @
                 jwz.unsqueeze(-1)).reshape(B)
    unexplained = torch.where(zwz > 0, (1 - explained / zwz.clamp_min(1e-300)).clamp(0, 1), 0.0)
    pc = ParameterCovariance(cov=X, gain=A, noise=V, settles=settles & alive, replayed=steps, measured=measured,
                             offset=offset, offset_cov=offset_cov, correlated=correlated, widening=widening,
                             unexplained=unexplained,
                             sampling=bias, sampling_note=None if isinstance(how, dict) or swap else how,
                             bias_source="physics" if swap else "sampling" if isinstance(how, dict) else None)
    return Replay(covariance=pc, residuals=residuals)


def physical_blocks(graph) -> dict[str, str] | None:
    """The blocks of ``graph`` that make its measured output: {block name: the signal it yields the measured
    output on} for the physical system (role 'physical'), and the blocks that feed its inputs other than the
    exogenous source (the truth in feedback of a ``truth=`` refinement), or None where the graph has no physical
    system (recorded data, no roles)."""
    if "physical" not in graph.roles or "error" not in graph.roles:
        return None
    name = graph.roles["physical"]
    if name not in graph.blocks or graph.roles.get("excitation") is None:
        return None
    out = {name: None}
    w_blk = graph.role_signal("exogenous")[0] if "exogenous" in graph.roles else None
    model = {graph.roles.get("known"), graph.roles.get("estimator")}
    for (blk, _), (src, _) in graph.sources.items():
        if blk == name and src not in (w_blk, *model):
            out[src] = None
    return out


def _physics_output(graph, state, eta, physics, swap: Mapping[str, Any], steps: int, start: int) -> torch.Tensor:
    """The noise-free measured output of ``graph`` with ``swap``'s blocks taken from ``physics`` (their state
    from ``state`` where a buffer of the same name and shape exists), over ``steps`` steps after ``start``,
    (steps, B, n_y) float64."""
    g, _ = _frozen_copy(graph, state, eta, engine=graph.engine)
    for name in swap:
        if name not in physics.blocks:
            raise ConfigError(f"intervals: the physics graph has no block '{name}' (the graph's physical system)")
        blk = copy.deepcopy(physics.blocks[name]).to(device=eta.device)
        blk.reset(eta.shape[0])
        for key, value in g.blocks[name]._buffers.items():
            mine = blk._buffers.get(key)
            if value is not None and mine is not None and mine.shape == value.shape and key in ("x", "k"):
                blk._buffers[key] = value.clone()
        g.blocks[name] = blk
    if start:
        g.advance(start)
    y_sig = graph.role_signal("measured")
    if y_sig[0] == "measurement":                          # the physical output before the measurement noise
        y_sig = graph.sources[("measurement", "clean")]
    rec = g.run(steps, record={"y": f"{y_sig[0]}.{y_sig[1]}"})
    return rec["y"].to(torch.float64)


class _ScoreSums:
    """The long-run covariance of the scores s(k) = Psi(k) W z(k): sum_k s(k) s(k)^T plus, for lags 1..L,
    (1 - lag / (L + 1)) (G_lag + G_lag^T) with G_lag = sum_k s(k) s(k - lag)^T (Bartlett weights, as the
    Newey-West estimator). For white z this is sum Psi W V W Psi^T; where z is correlated (dynamics the refined
    model does not explain; its whiteness test's p-value below WHITE_P) the lagged terms widen the intervals."""

    def __init__(self, B: int, n: int, lags: int, device):
        self.L, self.n = lags, 0
        self.ring = torch.zeros(B, lags, n, dtype=torch.float64, device=device)      # the last L scores
        self.gram = torch.zeros(lags + 1, B, n, n, dtype=torch.float64, device=device)

    def add(self, s: torch.Tensor) -> None:
        """Add the scores of consecutive steps, (C, B, n): G_lag += sum_t s(t) s(t - lag)^T, the last L scores
        of the previous chunk (zeros before the first) supplying s(t - lag) at the chunk's start."""
        L, C = self.L, s.shape[0]
        x = torch.cat([self.ring, s.transpose(0, 1)], dim=1)                   # (B, L + C, n), batch first
        now = torch.cat([torch.zeros_like(self.ring), x[:, L:]], dim=1)        # the chunk's own steps only
        self.gram += _lag_sums(now.transpose(0, 1), x.transpose(0, 1), L, outer=True)
        self.ring = x[:, x.shape[1] - L:].contiguous()
        self.n += C

    def long_run(self, members: torch.Tensor) -> torch.Tensor:
        """sum s s^T for every member, with the lagged terms for ``members`` ((B,) bool) only: where z is
        white they have expectation zero and would only add their sampling noise."""
        g = self.gram
        lagged = torch.zeros_like(g[0])
        for lag in range(1, self.L + 1):
            lagged += (1 - lag / (self.L + 1)) * (g[lag] + g[lag].mT)
        return g[0] + torch.where(members.reshape(-1, 1, 1), lagged, 0.0)


def _tsum(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """sum over steps t and rows z of a[:, t, z, i] b[:, t, z, j]: a (B, C, n_z, n), b (B, C, n_z, m) -> (B, n, m),
    one batched product."""
    B = a.shape[0]
    return a.reshape(B, -1, a.shape[-1]).mT @ b.reshape(B, -1, b.shape[-1])


def _tsum_rows(psi: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The scores of each step, s(t) = Psi(t) v(t): psi (B, C, n_z, n), v (B, C, n_z) -> (C, B, n)."""
    return (psi * v.unsqueeze(-1)).sum(2).transpose(0, 1)


def _lag_sums(a: torch.Tensor, b: torch.Tensor, lags: int, outer: bool) -> torch.Tensor:
    """sum over t = lag .. T-1 of a(t) * b(t - lag) (``outer``: the outer product a(t) b(t - lag)^T) for
    lag = 0 .. ``lags``, stacked: a (T, B, n), b (T, B, m) -> (lags + 1, B, n) or (lags + 1, B, n, m).

    On the CPU the native kernel (``kernels.lag_sums``) takes them in one pass over time; elsewhere every lag at
    once by FFT over time (the cross-correlation, zero-padded to at least T + lags so that no lag wraps around),
    members taken in blocks whose spectra hold about CHUNK_BYTES."""
    native = kernels.lag_sums(a, b, lags, outer)
    if native is not None:
        return native
    T, B, n, m = a.shape[0], a.shape[1], a.shape[2], b.shape[2]
    nfft = 1 << max(1, (T + lags - 1).bit_length())
    width = n + m + (n * m if outer else n)
    block = max(1, CHUNK_BYTES // (16 * (nfft // 2 + 1) * width))
    out = torch.empty((lags + 1, B, n, m) if outer else (lags + 1, B, n), dtype=a.dtype, device=a.device)
    for b0 in range(0, B, block):
        b1 = min(B, b0 + block)
        fa = torch.fft.rfft(a[:, b0:b1], n=nfft, dim=0)
        fb = torch.fft.rfft(b[:, b0:b1], n=nfft, dim=0).conj()
        # irfft(F[a] conj(F[b]))[lag] = sum_t a(t) b(t - lag)
        spec = fa.unsqueeze(-1) * fb.unsqueeze(-2) if outer else fa * fb
        out[:, b0:b1] = torch.fft.irfft(spec, n=nfft, dim=0)[:lags + 1]
    return out


class _ResidualSums:
    """The sums of the residual checks over the replay: lagged products of z and w, the fit's sums, and the first
    members' outputs."""

    def __init__(self, B: int, lags: int, keep: int, device):
        self.B, self.L, self.keep, self.dev = B, lags, keep, device
        self.n = 0

    def add(self, z: torch.Tensor, w: torch.Tensor | None, y: torch.Tensor, z_init: torch.Tensor) -> None:
        """The sums of the replay's measured steps, from its recorded outputs: z and z_init (T, B, n_z), w
        (T, B, n_w) or None, y (T, B, n_y)."""
        f64, L, kept = torch.float64, self.L, slice(0, self.keep)
        z, y, z_init = z.to(f64), y.to(f64), z_init.to(f64)
        self.n = z.shape[0]
        self.zz = _lag_sums(z, z, L, outer=False)                              # z(k) z(k - lag)
        self.z_sum = z.sum(0)
        self.w_on = w is not None
        if self.w_on:
            w = w.to(f64)
            self.zw = _lag_sums(z, w, L, outer=True)                           # z(k) w(k - lag)
            self.w_sq = (w * w).sum(0)
            self.w_sum = w.sum(0)
        self.fit = {"zz": (z * z).sum((0, 2)), "zi": (z_init * z_init).sum((0, 2)), "y": y.sum(0),
                    "yy": (y * y).sum((0, 2))}
        self.series = {"measured": y[:, kept].cpu(), "refined": (y[:, kept] - z[:, kept]).cpu(),
                       "initial": (y[:, kept] - z_init[:, kept]).cpu()}

    def result(self) -> Residuals:
        N, L = self.n, self.L
        counts = (N - torch.arange(L + 1, dtype=torch.float64, device=self.dev)).clamp_min(1).reshape(-1, 1, 1)
        mean_z = self.z_sum / N
        cov_z = self.zz / counts - mean_z.unsqueeze(0) ** 2                     # (L + 1, B, n_z)
        auto = (cov_z / cov_z[:1]).permute(1, 0, 2)                              # (B, L + 1, n_z)
        xcorr = None
        if self.w_on:
            mean_w = self.w_sum / N
            cov_zw = self.zw / counts.unsqueeze(-1) - (mean_z.unsqueeze(-1) * mean_w.unsqueeze(1)).unsqueeze(0)
            var_w = self.w_sq / N - mean_w ** 2
            scale = torch.sqrt(cov_z[0].unsqueeze(-1) * var_w.unsqueeze(1))         # (B, n_z, n_w)
            xcorr = (cov_zw / scale.unsqueeze(0)).permute(1, 0, 2, 3)
        r = auto[:, 1:]                                                          # lags 1..L
        lag = torch.arange(1, L + 1, dtype=torch.float64, device=self.dev).reshape(1, -1, 1)
        q = N * (N + 2) * (r * r / (N - lag).clamp_min(1)).sum(1)                 # Ljung-Box, (B, n_z)
        from scipy.special import chdtrc  # the chi-squared survival function
        p = torch.as_tensor(chdtrc(L, torch.nan_to_num(q, nan=math.inf).cpu().numpy()), dtype=torch.float64)
        f = self.fit
        spread = torch.sqrt(f["yy"] - (f["y"] ** 2).sum(1) / N).clamp_min(1e-300)   # |y - mean y|
        return Residuals(steps=N, autocorr=auto.cpu(), xcorr=None if xcorr is None else xcorr.cpu(),
                         bound=1.959964 / math.sqrt(N), whiteness_p=p.amin(1),
                         fit=(100 * (1 - torch.sqrt(f["zz"]) / spread)).cpu(),
                         fit_initial=(100 * (1 - torch.sqrt(f["zi"]) / spread)).cpu(),
                         series=dict(self.series))


def _gain_time(lam: torch.Tensor, N: int) -> torch.Tensor:
    """sum_{k=1..N} 1 / n_k with n_k = sum_{j<k} lam^j (the RLS gain's time), per member."""
    k = torch.arange(1, N + 1, dtype=torch.float64)
    out = torch.empty_like(lam)
    for value in torch.unique(lam):
        n_k = k if value == 1 else (1 - value ** k) / (1 - value)
        out[lam == value] = (1.0 / n_k).sum()
    return out


def _lyapunov(M: torch.Tensor, Q: torch.Tensor, chunk_bytes: int = 1 << 27) -> torch.Tensor:
    """X with M X + X M^T = Q for each member (B, n, n) (NaN-free members only; the others get a solution
    for M = I, Q = 0)."""
    B, n, _ = M.shape
    eye = torch.eye(n, dtype=M.dtype, device=M.device)
    finite = torch.isfinite(M).flatten(1).all(1) & torch.isfinite(Q).flatten(1).all(1)
    Ms = torch.where(finite.reshape(-1, 1, 1), M, eye)
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
    return 0.5 * (X + X.mT)


def estimate_gradients(graph, estimates: Callable[[object], Mapping[str, torch.Tensor]],
                       std: torch.Tensor) -> dict[str, torch.Tensor]:
    """d estimate / d eta for every estimate (B,) of ``estimates(graph)``, by central differences with
    steps of 1e-3 of each parameter's standard deviation ``std`` (B, n) (1e-6 of its size where that is not
    finite or zero). Returns {key: (B, n)}; theta is restored, in the tensor the graph held (the same tensor, the
    same values), so that the graph can go on stepping."""
    est = graph.role("estimator")
    eta = est.theta_free().detach().clone()
    held = est._buffers["theta"]
    theta = held.clone()
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
        held.copy_(theta)
        est.set_state(theta=held)
    return {k: torch.stack(v, dim=1) for k, v in grads.items()}


def rls_half_widths(graph, estimates: Callable[[object], Mapping[str, torch.Tensor]], covariances: torch.Tensor,
                    members: list[int], level: float = LEVEL) -> dict[str, torch.Tensor]:
    """Half-widths of the estimates' intervals from RLS covariances: each of ``covariances`` (T, M, n, n) (the
    estimator's P at T steps for the M ``members``, or any covariance of eta) carried to each estimate by the
    delta method with the gradient at the graph's current parameters. It is not calibrated (the open-loop
    filter and forgetting make sigma^2 P too wide or too narrow; ``Run.band_over_time`` scales it to the final
    interval). Returns {key: (T, M) float64 on the CPU}; the graph's state is left as it was (the same
    tensors, the same values).

    Parameters
    ----------
    graph : rcotorch.graph.Graph
        A graph with an estimator role.
    estimates : callable
        ``estimates(graph)`` -> {key: (B,) tensor}.
    covariances : torch.Tensor
        (T, M, n, n).
    members : list of int
        The members the covariances belong to.
    level : float, optional
        Confidence level.

    Returns
    -------
    dict[str, torch.Tensor]
        {key: (T, M)}.
    """
    est = graph.role("estimator")
    cov = covariances.to(torch.float64).cpu()
    std = torch.diagonal(est.P.detach().to(torch.float64), dim1=1, dim2=2).clamp_min(0).sqrt()
    grads = estimate_gradients(graph, estimates, std)
    out = {}
    for key, g in grads.items():
        g = g.to(torch.float64).cpu()[members]                                      # (M, n)
        var = torch.einsum("mi,tmij,mj->tm", g, cov, g)
        out[key] = quantile(level) * var.clamp_min(0).sqrt()
    return out


def change_explained(est, theta_start: torch.Tensor, k_start: int, pc: ParameterCovariance,
                     p: float = 0.999) -> torch.Tensor:
    """(B,) True where the parameters' change over the convergence window, eta(N) - eta(k0), is what their
    own random error explains: d^T V^-1 d within the chi-square quantile ``p``, V = X (1 + n_N / n_k0) the
    variance of the difference when the errors at k0 and N are taken as independent (X at k0 is X n_N / n_k0,
    n_k = sum_{j<k} lam^j the RLS memory), so larger than the covariance it ignores. With forgetting the
    estimate keeps moving by about its interval; the window's change then says nothing about convergence."""
    from scipy.special import chdtri  # the chi-squared quantile of an upper tail

    B, n = pc.cov.shape[0], pc.cov.shape[1]
    eta = est.theta_free().detach().to(torch.float64).cpu()
    start = theta_start.reshape(B, -1).to(torch.float64).cpu().index_select(1, est.free_idx.cpu())
    d = (eta - start).unsqueeze(-1)
    lam = est.lam.to(torch.float64).cpu().reshape(-1).expand(B)
    N = int(est.k)

    def memory(k: int) -> torch.Tensor:
        return torch.where(lam < 1, (1 - lam ** k) / (1 - lam).clamp_min(1e-300), torch.full_like(lam, float(k)))
    ratio = memory(N) / memory(max(k_start, 1)).clamp_min(1e-300)
    V = pc.cov.cpu() * (1 + ratio).reshape(-1, 1, 1)
    ok = torch.isfinite(V).flatten(1).all(1)
    Vs = torch.where(ok.reshape(-1, 1, 1), V, torch.eye(n, dtype=V.dtype))
    stat = (d.mT @ torch.linalg.pinv(Vs) @ d).reshape(B)
    return ok & (stat <= float(chdtri(n, 1 - p)))


def residuals_matter(pc: ParameterCovariance, found: Intervals) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,) bool, where the residuals' lack of whiteness matters for the estimates, and (B,) the factor by which
    their correlation widened the parameters' standard deviations. It matters where z fails the whiteness test
    (``WHITE_P``), what the test saw is not a parameter error the model can take back (at least
    ``UNEXPLAINED_MIN`` of z's energy is left by the output error's Gauss-Newton step: a noise-free run still
    converging leaves almost none), and it changes the intervals: their correlation widens a standard deviation
    by ``WIDENING_MATTERS`` or more, or an estimate is biased beyond its interval."""
    B = pc.cov.shape[0]
    correlated = pc.correlated.cpu() if pc.correlated is not None else torch.zeros(B, dtype=torch.bool)
    widening = pc.widening.cpu() if pc.widening is not None else torch.ones(B, dtype=torch.float64)
    unexplained = pc.unexplained.cpu() if pc.unexplained is not None else torch.ones(B, dtype=torch.float64)
    biased = found.biased.cpu() if found.biased is not None else torch.zeros(B, dtype=torch.bool)
    matter = correlated & (unexplained >= UNEXPLAINED_MIN) & ((widening >= WIDENING_MATTERS) | biased)
    return matter, widening


def remaining_transient(est, theta_start: torch.Tensor, k_start: int, pc: ParameterCovariance
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """The part of the parameters' error that the recursion has not yet forgotten, from their drift over the
    convergence window: with the error's deterministic part relaxing as d eta~ / dT = -A eta~ in the gain's time
    T (``_gain_time``; ln k for lam = 1), eta~(N) = exp(-A D) eta~(k0) over the window's D = T(N) - T(k0), so

        tau = eta~(N) = (I - exp(A D))^-1 (eta(N) - eta(k0)).

    Its random part: the change's covariance X_N + X_k0 - E X_k0 - X_k0 E^T with E = exp(-A D) and
    X_k0 = X_N n_N / n_k0 (n_k the RLS memory), carried through the same matrix. With lam = 1 and a gain A
    near I the window's last fifth leaves about a quarter of the start's error, so tau is four times the
    drift; with forgetting D is large and tau near 0. Returns tau (B, n) and its covariance (B, n, n), NaN for
    members without a finite covariance."""
    B, n = pc.cov.shape[0], pc.cov.shape[1]
    f64 = torch.float64
    eta = est.theta_free().detach().to(f64).cpu()
    start = theta_start.reshape(B, -1).to(f64).cpu().index_select(1, est.free_idx.cpu())
    lam = est.lam.to(f64).cpu().reshape(-1).expand(B)
    N = int(est.k)
    k0 = max(1, min(int(k_start), N))
    D = (_gain_time(lam, N) - _gain_time(lam, k0)).reshape(-1, 1, 1)

    def memory(k: int) -> torch.Tensor:
        return torch.where(lam < 1, (1 - lam ** k) / (1 - lam).clamp_min(1e-300), torch.full_like(lam, float(k)))
    X = pc.cov.cpu().to(f64)
    A = pc.gain.cpu().to(f64)
    ok = torch.isfinite(X).flatten(1).all(1) & torch.isfinite(A).flatten(1).all(1)
    eye = torch.eye(n, dtype=f64)
    A = torch.where(ok.reshape(-1, 1, 1), A, eye)
    X = torch.where(ok.reshape(-1, 1, 1), X, 0.0)
    E = torch.linalg.matrix_exp(-A * D)
    ok = ok & torch.isfinite(E).flatten(1).all(1) & (E.flatten(1).abs().amax(1) < 1e6)
    E = torch.where(ok.reshape(-1, 1, 1), E, 0.0)
    M = -E @ torch.linalg.pinv(eye - E)              # (I - exp(A D))^-1, written to stay finite as exp(-A D) -> 0
    X0 = X * (memory(N) / memory(k0)).reshape(-1, 1, 1)
    Xd = X + X0 - E @ X0 - X0 @ E.mT
    tau = (M @ (eta - start).unsqueeze(-1)).squeeze(-1)
    cov = M @ (0.5 * (Xd + Xd.mT)) @ M.mT
    tau = torch.where(ok.reshape(-1, 1), tau, math.nan)
    cov = torch.where(ok.reshape(-1, 1, 1), cov, math.nan)
    return tau, cov


def band(graph, fn: Callable[[object], torch.Tensor], pc: ParameterCovariance, level: float = LEVEL
         ) -> tuple[torch.Tensor, torch.Tensor]:
    """The value of ``fn(graph)`` ((B, F) float, e.g. a frequency response's magnitude on a grid) and the
    half-width of its confidence band (delta method, as ``estimate_intervals``), each (B, F)."""
    value = fn(graph).detach().to(torch.float64).cpu()
    F = value.shape[1]
    grads = estimate_gradients(graph, lambda g: {str(i): c for i, c in enumerate(fn(g).unbind(1))}, pc.std)
    g = torch.stack([grads[str(i)] for i in range(F)], dim=1).cpu()                    # (B, F, n)
    var = torch.einsum("bfi,bij,bfj->bf", g, pc.cov.cpu(), g)
    return value, quantile(level) * var.clamp_min(0).sqrt()


def member_band(graph, fn: Callable[[object], object], pc: ParameterCovariance, member: int = 0,
                level: float = LEVEL) -> tuple[np.ndarray, np.ndarray] | None:
    """``fn(graph)`` for one member ((F,) values computed from that member's parameters, e.g. a magnitude
    response on a grid; any code) and the half-width of its confidence band (delta method, central differences
    in that member's parameters), or None where its covariance is not finite."""
    X = pc.cov[member].to(torch.float64).cpu()
    if not bool(torch.isfinite(X).all()):
        return None
    est = graph.role("estimator")
    eta, held = est.theta_free().detach().clone(), est._buffers["theta"]
    theta = held.clone()
    sd = pc.std[member].cpu()
    h = torch.where(sd > 0, 1e-3 * sd, 1e-6 * eta[member].abs().clamp_min(1e-12).cpu())
    value = np.asarray(fn(graph), dtype=float)
    grads = []
    try:
        for j in range(eta.shape[1]):
            sides = []
            for sign in (1.0, -1.0):
                e = eta.clone()
                e[member, j] += sign * float(h[j])
                est.set_theta_free(e)
                sides.append(np.asarray(fn(graph), dtype=float))
            grads.append((sides[0] - sides[1]) / (2 * float(h[j])))
    finally:
        held.copy_(theta)
        est.set_state(theta=held)
    G = np.stack(grads, axis=-1)                                                    # (F, n)
    var = np.einsum("fi,ij,fj->f", G, X.numpy(), G)
    return value, quantile(level) * np.sqrt(np.clip(var, 0, None))


def quantile(level: float) -> float:
    """The two-sided normal quantile of a confidence level (1.96 for 0.95)."""
    if not 0 < level < 1:
        raise ConfigError(f"intervals: level must lie in (0, 1), got {level}")
    return NormalDist().inv_cdf(0.5 + level / 2)


@dataclass
class Intervals:
    """Confidence intervals of named estimates, per member (each value a (B,) float64 tensor).

    ``bias[key]``: the estimate's bias where one beyond its interval was found (NaN elsewhere): the sampled
    estimate minus the continuous physics' (``rcotorch.verdict.sampling``), or the estimate minus the
    output error's optimum; ``biased_keys`` and ``bias_reason`` say which and why, per member."""

    level: float
    estimate: dict[str, torch.Tensor]
    half_width: dict[str, torch.Tensor]
    determined: torch.Tensor              # (B,) bool
    undetermined_keys: list[list[str]]    # per member, the estimates whose interval is too wide
    offset: dict[str, torch.Tensor] | None = None   # the estimates' move by the output error's step (B,)
    widened: torch.Tensor | None = None   # (B,) bool: an interval includes that move (``OFFSET_FACTOR``)
    biased: torch.Tensor | None = None    # (B,) bool: an estimate carries a bias beyond its interval
    bias: dict[str, torch.Tensor] | None = None
    biased_keys: list[list[str]] | None = None
    bias_reason: list[str | None] | None = None
    drifting: torch.Tensor | None = None   # (B,) bool: an estimate still drifts by more than its interval
    drift: dict[str, torch.Tensor] | None = None   # the estimates' part of the remaining transient (0 if none)

    def lower(self, key: str) -> torch.Tensor:
        return self.estimate[key] - self.half_width[key]

    def upper(self, key: str) -> torch.Tensor:
        return self.estimate[key] + self.half_width[key]


SAMPLING_REASON = "sampling: the sampled feedback's estimate differs from the continuous physics' by more than " \
    "its interval"
PHYSICS_REASON = "model: the refined model's estimate differs from the physics' at that estimate by more than " \
    "its interval"
OUTPUT_ERROR_REASON = "output error: the refinement settled away from the point the data favour, by more than " \
    "the interval"


def estimate_intervals(graph, estimates: Callable[[object], Mapping[str, torch.Tensor]], pc: ParameterCovariance,
                       level: float = LEVEL, scales: Mapping[str, float] | None = None,
                       rel_tol: float = REL_TOL,
                       transient: tuple[torch.Tensor, torch.Tensor] | None = None) -> Intervals:
    """Intervals est +- q sd of every estimate, sd^2 = g X g^T with g its gradient in eta (delta method).

    Two biases are measured against the half-width:

    * **the output error's optimum** (``pc.offset``): where the window's output error is smaller away from the
      estimate by more than its random error (the estimate's move d = g offset exceeds ``OFFSET_FACTOR``
      half-widths, or ``OFFSET_FACTOR_CORRELATED`` where the residuals are not white: the model leaves
      dynamics unexplained, and a step beyond the interval is then the bias they cause), the half-width
      becomes q sd + |d|, so that the interval reaches the point the data favour; where |d| is also more than
      ``BIAS_TOL`` times max(|estimate|, scale), the estimate is *biased* (the refinement settled well away
      from what the data determine);
    * **sampling a continuous feedback** (``pc.sampling``, where the graph declares one): the estimate's
      bias against the continuous physics, beta = g b - d (d as above where it widens the interval, else 0).
      Where |beta| is more than the half-width q sd and than ``NEGLIGIBLE`` of the estimate's size, the
      estimate is *biased* by beta (its cause the model where |g b| >= |d|, else the output error); otherwise
      the half-width is q sd + |beta|, so that the interval holds the physics' parameter.

    And the error the recursion has not yet forgotten (``transient``, ``remaining_transient``'s tau and its
    covariance): where the estimate's part t = g tau exceeds ``DRIFT_Z`` of its own standard deviations (the
    estimate still drifts beyond what its noise explains), the half-width grows by |t| where |t| is at most
    the half-width (or below ``NEGLIGIBLE`` of the estimate's size), and the member is *drifting* (not
    converged) where it is more.

    A member's estimates are *determined* when its parameter recursion settles (``pc.settles``) and every
    interval's half-width is at most ``rel_tol`` times max(|estimate|, scale), ``scales[key]`` a size the
    user gives for an estimate that may be near zero (e.g. the nominal value a change is relative to)."""
    q = quantile(level)
    with torch.no_grad():
        values = {k: v.detach().to(torch.float64).reshape(-1).cpu() for k, v in estimates(graph).items()}
    grads = estimate_gradients(graph, estimates, pc.std)
    X = pc.cov.cpu()
    det = pc.settles.cpu().clone()
    half, bad, moved, biases, flagged = {}, [], {}, {}, []
    widened = torch.zeros_like(det)
    any_off, any_sampled, drifting = torch.zeros_like(det), torch.zeros_like(det), torch.zeros_like(det)
    drifts = {}
    factor = torch.full(det.shape, OFFSET_FACTOR, dtype=torch.float64)
    if pc.correlated is not None:
        factor = torch.where(pc.correlated.cpu(), OFFSET_FACTOR_CORRELATED, factor)
    for key, v in values.items():
        g = grads[key].cpu()
        var = torch.einsum("bi,bij,bj->b", g, X, g)
        hw = q * var.clamp_min(0).sqrt()
        scale = float((scales or {}).get(key, 0.0))
        size = torch.clamp(v.abs(), min=scale)
        bias = torch.full_like(v, math.nan)
        off = torch.zeros_like(det)
        d, extra = torch.zeros_like(v), torch.zeros_like(v)      # the output error's move, the widening
        d_seen = torch.zeros_like(v)                              # ... where only its own noise says it counts
        if pc.offset is not None:
            d = torch.einsum("bi,bi->b", g, pc.offset.cpu())
            moved[key] = d
            beyond = torch.isfinite(d) & torch.isfinite(hw) & (d.abs() > factor * hw)
            widen = beyond if pc.correlated is None else beyond | (pc.correlated.cpu() & torch.isfinite(d))
            off = beyond & (d.abs() > BIAS_TOL * size)          # the data favour a point well away
            bias = torch.where(off, -d, bias)
            significant = torch.zeros_like(widen)   # beyond the step's own random error: widens, never flags
            if pc.offset_cov is not None:
                sd_d = torch.einsum("bi,bij,bj->b", g, pc.offset_cov.cpu(), g).clamp_min(0).sqrt()
                significant = torch.isfinite(d) & torch.isfinite(hw) & (d.abs() > OFFSET_Z * sd_d) & ~widen
            d_seen = torch.where(significant, d, 0.0)
            d = torch.where(widen, d, 0.0)
            extra = d.abs() + d_seen.abs()
            widened |= widen | significant
        sampled = torch.zeros_like(det)
        if pc.sampling is not None:
            # the estimate minus the physics' parameter: the model's bias, less the part of it that the output
            # error's move already takes back
            model = torch.einsum("bi,bi->b", g, pc.sampling.cpu())
            total = model - d
            known = torch.isfinite(total) & torch.isfinite(hw)
            flag = known & (total.abs() > hw) & (total.abs() > NEGLIGIBLE * size)
            bias = torch.where(flag, total, bias)
            extra = torch.where(known & ~flag, (total - d_seen).abs(), extra)
            sampled = flag & (model.abs() >= d.abs())      # the model's part dominates, else the output error's
            off = off | (flag & ~sampled)
        hw = hw + extra
        if transient is not None:
            t = torch.einsum("bi,bi->b", g, transient[0])
            sd_t = torch.einsum("bi,bij,bj->b", g, transient[1], g).clamp_min(0).sqrt()
            moving = torch.isfinite(t) & torch.isfinite(hw) & (t.abs() > DRIFT_Z * sd_t)
            drifts[key] = torch.where(moving, t, 0.0)
            far = moving & (t.abs() > DRIFT_FAR * hw) & (t.abs() > NEGLIGIBLE * size)
            drifting |= far
            hw = torch.where(moving & ~far, hw + t.abs(), hw)
        half[key] = torch.where(torch.isfinite(var), hw, math.nan)
        biases[key] = bias
        ok = torch.isfinite(half[key]) & (half[key] <= rel_tol * size)
        bad.append(~ok)
        flagged.append(off | sampled)
        any_off |= off
        any_sampled |= sampled
        det &= ok
    keys = list(values)

    def per_member(rows: list[torch.Tensor]) -> list[list[str]]:
        return [[k for k, b in zip(keys, row) if b] for row in
                (torch.stack(rows, 1).tolist() if rows else [[]] * det.numel())]
    model_reason = PHYSICS_REASON if pc.bias_source == "physics" else SAMPLING_REASON
    reason = [model_reason if a else OUTPUT_ERROR_REASON if b else None
              for a, b in zip(any_sampled.tolist(), any_off.tolist())]
    return Intervals(level=level, estimate=values, half_width=half, determined=det,
                     undetermined_keys=per_member(bad), offset=moved or None, widened=widened,
                     biased=any_off | any_sampled, bias=biases, biased_keys=per_member(flagged),
                     bias_reason=reason, drifting=drifting if transient is not None else None, drift=drifts or None)
