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
import functools
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
from .joined import held_block, hooks_leave, join, own_blocks

LEVEL = 0.95             # the default confidence level
REL_TOL = 0.5            # determined: each interval's half-width at most this fraction of max(|estimate|, scale)
REPLAY_STEPS = 4000      # at most this many steps replayed (the convergence window's length, up to this)
SETTLE = 0.25            # the first fraction of the replay lets the perturbed copies settle
SETTLE_TAUS = 5.0        # ... or, where longer, this many time constants of the frozen loop's slowest mode
SETTLE_MAX = 4 * REPLAY_STEPS    # at most this many steps to settle (rcotorch.run.end_checks.loop_settle)
LAGS = 25                # lags of the residual checks (z's autocorrelation, its cross-correlation with w)
SAMPLES_PER_LAG = 5      # ... and of the scores' covariance: at most one lag per this many measured steps
KEEP_MEMBERS = 8         # members whose replayed outputs are kept for figures
SCORE_LAGS = 25          # lags of the scores' long-run covariance (correlated residuals widen the intervals)
CHUNK_BYTES = 1 << 26    # the FFT of the lagged sums (off the CPU) takes members in blocks of about this many bytes
STRETCH_BYTES = 1 << 23  # the replay steps in stretches whose J (C x B x n_z x n float64) takes about this many bytes
WHITE_P = 0.01           # residuals whose whiteness test gives a smaller p-value are treated as correlated
EXCITED = 0.05           # a direction of theta whose eigenvalue of A is smaller was not excited by the data
OFFSET_FACTOR = 2.0      # an estimate the output error's step moves by more half-widths than this is biased
OFFSET_FACTOR_CORRELATED = 1.0  # the same where the residuals are not white (WHITE_P)
BIAS_TOL = 0.05          # an estimate that step moves by more than this fraction of its size is biased
NEGLIGIBLE = 1e-3        # a bias or drift below this fraction of an estimate's size is corrected, never flagged
UNEXPLAINED_MIN = 0.01   # residuals_matter: the least share of z's energy no parameter explains
WIDENING_MATTERS = 1.25  # ... and the least widening of a standard deviation by the residuals' correlation
OFFSET_HOLD_Z = 1.0      # a move beyond this many of the step's own standard deviations: the interval holds its end
DRIFT_FAR = 2.0          # a drift beyond this many half-widths is a member still drifting (not converged) ...
DRIFT_Z = 1.96           # ... where it is also beyond this many of its own standard deviations
DRIFT_HOLD_Z = 0.5       # a drift beyond this many of its standard deviations: the interval holds its end ...
DRIFT_NOISE = 1.0        # ... and this many of its standard deviations past it
OPTIMUM_P = 0.2          # the joint test's p-value below which the window's output-error optimum replaces the estimate
OPTIMUM_DRIFT_Z = 1.0    # a drift beyond this many of its sd: the widened interval is held beside the estimate's ...
OPTIMUM_AGREE = 0.5      # ... and beside the optimum's where est - drift lies beyond this many of its half-widths
JOIN_COPIES = True       # step the replay's copies inside one graph, sharing what they compute alike (``joined``)


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
        optimum_cov: (B, n, n) the covariance of the output error's optimum itself, eta + offset, over the window
            (the sandwich (sum J^T W J)^-1 (sum J^T W V W J) (sum J^T W J)^-1, white residuals).
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
    optimum_cov: torch.Tensor | None = None
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
    est.hold(eta)
    return g, est


def _held_copy(frozen, eta: torch.Tensor):
    """A copy of ``frozen`` (a ``_frozen_copy`` not yet stepped) holding theta at ``eta`` instead."""
    g = copy.deepcopy(frozen)
    g.role("estimator").hold(eta)
    return g


@dataclass
class Residuals:
    """Checks of the refined model on the replayed window (theta frozen at its final value), per member.

    Attributes:
        steps: samples the statistics hold (N).
        autocorr: (B, L + 1, n_z) normalized autocorrelation of each channel of z at lags 0..L (1 at lag 0).
        xcorr: (B, L + 1, n_z, n_w) normalized cross-correlation of z(k) with w(k - lag), lags 0..L, or None
            when the graph declares no exogenous signal (role 'exogenous').
        bound: the 95% band of a correlation of white, independent signals, 1.96 / sqrt(N).
        whiteness_p: (B,) the Ljung-Box test's p-value that z is white (the smallest over z's channels); NaN
            where the window is too short for a lag (``SAMPLES_PER_LAG``): whiteness was not tested.
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
           score_lags: int = SCORE_LAGS, physics=None, progress: Callable[[int, int], None] | None = None
           ) -> Replay:
    """Replay ``steps`` steps of ``graph`` from ``state`` (a ``snapshot`` taken earlier in the same run) with the
    estimator's theta frozen at its current value, to measure the parameters' covariance (module docstring)
    and to check the refined model's residuals: copies with each parameter moved by a small step, and one with
    the initial theta. The first ``settle`` steps (default: a quarter) only let the copies settle; ``settle``
    may be one per member, (B,) (then each member measures the ``steps - max(settle)`` steps after its own, so
    that what a member finds does not depend on the others).
    ``rel_step``: the parameters' perturbation relative to their size (default 1e-7 in float64, 1e-3 in
    float32). ``lags``: correlation lags of the residual checks (at most one per ``SAMPLES_PER_LAG`` measured
    steps, as ``score_lags``); ``keep``: members whose outputs are kept for
    figures; ``score_lags``: lags of the scores' long-run covariance (``_ScoreSums``). ``physics``: a graph like
    ``graph`` whose physical blocks (``physical_blocks``) hold the physics at the estimates; one more copy runs
    with those blocks in place of ``graph``'s, and the Gauss-Newton step of its output against the refined
    model's prediction is the estimates' bias against the physics (``ParameterCovariance.sampling``; without it,
    where the graph declares a continuous feedback, ``rcotorch.verdict.sampling`` measures that bias). The graph
    itself is not changed. ``progress``: called with the steps replayed and ``steps`` after each stretch.

    The copies step side by side through the measured steps in stretches short enough for their records to stay
    in cache, and every sum is taken stretch by stretch: nothing of the length of the window is kept."""
    steps = int(steps)
    if steps < 2:
        raise ConfigError(f"intervals: at least 2 steps to replay, got {steps}")
    est = graph.role("estimator")
    B = est.theta.shape[0]
    settle_of = torch.as_tensor(int(SETTLE * steps) if settle is None else settle, dtype=torch.int64).reshape(-1)
    settle_of = (settle_of.expand(B) if settle_of.numel() == 1 else settle_of).to(est.theta.device)
    if settle_of.shape != (B,) or int(settle_of.min()) < 0 or int(settle_of.max()) >= steps:
        raise ConfigError(f"intervals: settle must be one number or one per member in [0, {steps}), got {settle}")
    copies = _Copies(graph, state, rel_step, physics)
    n = copies.eps.shape[1]
    first = int(settle_of.min())                          # the first step any member measures
    measured = steps - int(settle_of.max())               # the steps each member measures, after its own settle
    # a lag needs several times its length of data (a short window tests fewer lags, one under 5 steps none)
    lags, score_lags = min(lags, measured // SAMPLES_PER_LAG), min(score_lags, measured // SAMPLES_PER_LAG)
    sums = _WindowSums(B, n, est.n_z, score_lags, est.r_weight, copies.eps, settle_of, measured, est.theta.device)
    res = _ResidualSums(B, lags, keep, measured, settle_of, copies.w_sig is not None, est.theta.device)
    copies.settle(first)
    # steps per stretch: J's records of a stretch (C x B x n_z x n float64) about STRETCH_BYTES
    stretch = max(1, min(steps - first, STRETCH_BYTES // max(1, 8 * B * est.n_z * n)))
    with torch.no_grad():
        for t0 in range(first, steps, stretch):
            C = min(stretch, steps - t0)
            rec = copies.record(C)
            # 1 at each member's own measured steps, None where every member measures the same ones
            own = torch.arange(t0, t0 + C, device=settle_of.device).reshape(-1, 1) - settle_of.reshape(1, B)
            inside = None if measured == steps - first else ((own >= 0) & (own < measured)).to(torch.float64)
            res.add(t0, rec, inside)
            psi = copies.regressors(rec, C)
            sums.add(psi, rec, t0, inside, copies.base_est)
            if progress is not None:
                progress(t0 + C, steps)
    residuals = res.result()
    return Replay(covariance=sums.covariance(est, residuals, steps, measured, copies), residuals=residuals)


class _Copies:
    """The frozen copies of a replay, stepped side by side from the same state: the base copy (theta = eta, the
    estimate), one per parameter with that parameter moved by eps (their differences of z from the base copy's are
    J = Psi_true^T), one with the initial theta (the initial model's fit), and where a physics at the estimates is
    given (``physics``) a copy with its physical blocks in place of the graph's (``_physics_copy``). Each
    stretch's records land in buffers kept from stretch to stretch.

    Where the graph has no step hooks, the other copies run inside the base copy's graph (``joined.join``): of each,
    only the blocks that differ from the base copy's and that its recorded signal depends on (for a moved
    parameter: the estimator and the model it feeds back through), reading every other signal (the excitation,
    the measured system, recorded data) from the base copy's blocks. The signals are the same numbers as
    separate copies give; what the copies share is computed once."""

    def __init__(self, graph, state, rel_step: float | None, physics):
        est = graph.role("estimator")
        self.graph = graph
        self.z_sig = graph.role_signal("error")
        self.y_sig = graph.role_signal("measured") if "measured" in graph.roles else self.z_sig
        self.w_sig = graph.role_signal("exogenous") if "exogenous" in graph.roles else None
        eta = est.theta_free().detach()
        B, n = eta.shape
        if rel_step is None:
            rel_step = 1e-7 if eta.dtype == torch.float64 else 1e-3
        size = eta.abs().amax(1, keepdim=True).expand(B, n)
        size = torch.where(size > 0, size, est.P.diagonal(dim1=1, dim2=2).abs().sqrt())
        self.eps = rel_step * torch.where(size > 0, size, torch.ones_like(size))           # (B, n)
        eye = torch.eye(n, dtype=eta.dtype, device=eta.device)
        theta0 = est.theta0.expand(B, -1, -1).reshape(B, -1).index_select(1, est.free_idx.to(eta.device))
        self.base, self.base_est = _frozen_copy(graph, state, eta, engine=graph.engine)
        holds = {f"moved{j}": eta + self.eps[:, j:j + 1] * eye[j] for j in range(n)}
        holds["initial"] = theta0
        ports = [p for p in est.inputs if p not in ("z", "valid") and (est.name, p) in graph.sources]
        self.regressor_inputs = {p: graph.sources[(est.name, p)] for p in ports}
        self.u_sig = (est.name, "u")
        # Where the graph declares a continuous feedback, the refined model is also simulated with that feedback
        # (``sampling``) from the replay's first step on, so that it settles as long as the copies.
        swap = physical_blocks(graph) if physics is not None else None
        self.how = sampling.plan(graph) if not swap else "the physics at the estimates are simulated instead"
        self.continuous = None
        if isinstance(self.how, dict):
            self.continuous = sampling.ContinuousPrediction(self.base, self.how,
                                                            self.base.blocks[self.how["known"]].x.clone())
        self.bias_source = "physics" if swap else "sampling" if self.continuous is not None else None
        self.note = None if self.bias_source else self.how
        # each copy: the graph that steps it and where its signals are in that graph
        self.copies = {"base": (self.base, {sig: sig for sig in self._signals("base")})}
        structure = (list(self.base.blocks), dict(self.base.sources))        # before any copy joins it
        plans = {name: ({est.name}, functools.partial(held_block, self.base, est.name, value))
                 for name, value in holds.items()}
        if swap:
            plans["physical"] = (set(swap), functools.partial(_physics_block, self.base, physics, swap))
        own = {name: own_blocks(structure, changed, self._signals(name)) for name, (changed, _) in plans.items()}
        self.joined = JOIN_COPIES and hooks_leave(self.base.hooks, set().union(*own.values()), est.name)
        if not self.joined:
            for name, value in holds.items():
                self.copies[name] = (_held_copy(self.base, value), {sig: sig for sig in self._signals(name)})
            if swap:
                self.copies["physical"] = (_physics_copy(graph, state, eta, physics, swap),
                                           {sig: sig for sig in self._signals("physical")})
        else:
            for name, (_, block) in plans.items():
                self.copies[name] = (self.base, join(self.base, structure, own[name], self._signals(name), name,
                                                      block))
        self.graphs = list({id(g): g for g, _ in self.copies.values()}.values())
        self.moved = [name for name in self.copies if name.startswith("moved")]
        self.buffers: dict = {}
        self.history = None

    def _signals(self, copy_: str) -> list:
        if copy_ != "base":
            return [self.z_sig] if copy_ != "physical" else [self.physical_y]
        out = [self.z_sig, self.y_sig] + ([self.w_sig] if self.w_sig is not None else [])
        out += list(self.regressor_inputs.values()) + [self.u_sig]
        if self.bias_source:
            out.append(self.graph.role_signal("prediction"))
        if self.continuous is not None:
            out += self.how["record"]
        return list(dict.fromkeys(out))

    def _run(self, C: int, graphs: list | None = None) -> dict:
        """Advance the copies' graphs (or ``graphs`` of them) ``C`` steps, recording the copies' signals into the
        kept buffers: {copy: {signal: (C, B, w)}} of the copies those graphs step."""
        out = {}
        for g in graphs or self.graphs:
            names = [name for name, (h, _) in self.copies.items() if h is g]
            wanted = list(dict.fromkeys(at for name in names for at in self.copies[name][1].values()))
            bufs = self.buffers.get(id(g))
            if bufs is None or next(iter(bufs.values())).shape[0] < C:
                bufs = self.buffers[id(g)] = {
                    sig: kernels.empty((C, g.batch_size, g.blocks[sig[0]].outputs[sig[1]]), self.base_est.theta.dtype,
                                       self.base_est.theta.device) for sig in wanted}
            g.advance(C, record={sig: buf[:C] for sig, buf in bufs.items()})
            got = {sig: buf[:C].to(torch.float64) for sig, buf in bufs.items()}
            out.update({name: {sig: got[at] for sig, at in self.copies[name][1].items()} for name in names})
        return out

    def settle(self, steps: int) -> None:
        """Advance every copy the first ``steps`` steps (nothing recorded), carrying the continuous simulation on
        over them where there is one."""
        for g in self.graphs:
            if g is not self.base or self.continuous is None:
                g.advance(steps)
        if self.continuous is None:
            return
        span = max(1, STRETCH_BYTES // max(1, 8 * self.base.batch_size * 8))
        for t0 in range(0, steps, span):
            C = min(span, steps - t0)
            self.continuous.predict(self._run(C, [self.base])["base"], C)

    def record(self, C: int) -> dict:
        """Step every copy ``C`` steps and return, float64, the base copy's z, y, w (None without an exogenous
        signal), regressor inputs {port: (C, B, w)} and u; the moved copies' z as ``'moved'`` (C, B, n_z, n); the
        initial copy's as ``'initial'``; and where a physics or a continuous feedback is simulated, its prediction
        less the refined model's as ``'d'`` (z_c - z_f, ``sampling``)."""
        self.history = self.base_est.regressor_history()
        runs = self._run(C)
        base = runs["base"]
        rec = {"z": base[self.z_sig], "y": base[self.y_sig], "w": None if self.w_sig is None else base[self.w_sig],
               "inputs": {p: base[sig] for p, sig in self.regressor_inputs.items()}, "u": base[self.u_sig]}
        rec["moved"] = torch.stack([runs[name][self.z_sig] for name in self.moved], dim=3)
        rec["initial"] = runs["initial"][self.z_sig]
        if "physical" in runs:
            rec["d"] = runs["physical"][self.physical_y] - base[self.graph.role_signal("prediction")]
        elif self.continuous is not None:
            rec["d"] = self.continuous.predict(base, C) - base[self.graph.role_signal("prediction")]
        return rec

    def regressors(self, rec: Mapping, C: int) -> torch.Tensor:
        """The base copy's regressors Psi^T over the stretch just recorded, (C, B, n_z, n) float64."""
        return self.base_est.regressors_over(self.history, rec["inputs"], rec["u"], 0, C)

    @property
    def physical_y(self):
        """The physics copy's noise-free measured output."""
        y_sig = self.graph.role_signal("measured")
        if y_sig[0] == "measurement":                      # the physical output before the measurement noise
            y_sig = self.graph.sources[("measurement", "clean")]
        return y_sig


class _WindowSums:
    """The sums over a replay's measured steps that the covariance (module docstring) and the output error's
    Gauss-Newton step need, added stretch by stretch. With J = Psi_true^T = dz / d eta (the moved copies' z less
    the base copy's, over eps), d the physics' prediction less the refined model's, and Psi, z as the update
    weighs them (rows divided by m where they are normalized: Psi_m, z_m), every sum is a block of one Gram
    matrix sum_t G(t)^T G(t) of the rows G = [J, z, d, Psi_m, J_m, z_m] (each row of z its own columns): sum
    J^T W J, J^T W z, J^T W d, z^T W z, sum Psi_m W Psi_m^T, Psi_m W J_m^T, z_m z_m^T. The scores Psi_m W z_m of
    each step go to ``_ScoreSums``."""

    PARTS = ("J", "z", "d", "psi", "J_m", "z_m")

    def __init__(self, B: int, n: int, n_z: int, score_lags: int, weight: torch.Tensor, eps: torch.Tensor,
                 settle_of: torch.Tensor, measured: int, device):
        self.B, self.n, self.n_z = B, n, n_z
        self.weight, self.eps = weight.to(torch.float64), eps.to(torch.float64)
        self.settle_of, self.measured = settle_of, measured
        self.upper = False                    # whether the native kernel summed the upper triangle only
        widths = {"J": n_z * n, "z": n_z, "d": n_z, "psi": n_z * n, "J_m": n_z * n, "z_m": n_z}
        self.cols, at = {}, 0
        for part in self.PARTS:
            self.cols[part] = slice(at, at + widths[part])
            at += widths[part]
        self.gram = torch.zeros(B, at, at, dtype=torch.float64, device=device)
        self.scores = _ScoreSums(B, n, score_lags, device)
        self.has_d = False

    def add(self, psi: torch.Tensor, rec: Mapping, t0: int, inside: torch.Tensor | None, est) -> None:
        """Add the stretch from step ``t0``: ``psi`` (C, B, n_z, n) the base copy's regressors, ``rec`` its records
        (``_Copies.record``), ``inside`` (C, B) 1 at each member's measured steps (None: all of them). On the CPU
        the native kernel (``kernels.window_sums``) takes a stretch in one pass."""
        B, n, n_z, C = self.B, self.n, self.n_z, psi.shape[0]
        z, d = rec["z"], rec.get("d")
        self.has_d = self.has_d or d is not None
        norm = getattr(est, "norm_inv_s2", None)
        sc = self.scores
        if kernels.window_sums(z, rec["moved"], psi, d, self.eps, self.settle_of, t0, self.measured, self.weight,
                               norm, self.gram, sc.ring, sc.gram, sc.moving):
            self.upper = True
            return
        jac = (rec["moved"] - z.unsqueeze(3)) / self.eps.reshape(1, B, 1, n)          # (C, B, n_z, n)
        m = est.row_scale(psi.transpose(0, 1).reshape(-1, n_z, n))          # the rows as weighed, (B C,)
        m = None if m is None else m.to(torch.float64).reshape(B, C).transpose(0, 1).unsqueeze(-1)   # (C, B, 1)
        flat_j, flat_psi = jac.reshape(C, B, n_z * n), psi.reshape(C, B, n_z * n)
        rows = [flat_j, z, d if d is not None else torch.zeros_like(z)]
        rows += [flat_psi, flat_j, z] if m is None else [flat_psi / m, flat_j / m, z / m]
        G = torch.cat(rows, dim=2)                                                     # (C, B, K)
        if inside is not None:
            G = G * inside.unsqueeze(-1)
        G = G.transpose(0, 1)                                                          # (B, C, K)
        self.gram += G.mT @ G
        psi_m, z_m = G[..., self.cols["psi"]].reshape(B, C, n_z, n), G[..., self.cols["z_m"]]
        self.scores.add(_tsum_rows(psi_m, z_m @ self.weight))

    def block(self, a: str, b: str) -> torch.Tensor:
        """The sum of G_a^T G_b, (B, width a, width b)."""
        if self.upper:                                  # the lower triangle from the upper one
            self.gram = self.gram.triu() + self.gram.triu(1).mT
            self.upper = False
        return self.gram[:, self.cols[a], self.cols[b]]

    def weighted(self, a: str, b: str) -> torch.Tensor:
        """sum_t a^T W b for parts a, b of n_z rows (each of width n or 1): (B, width a / n_z, width b / n_z)."""
        B, n_z = self.B, self.n_z
        g = self.block(a, b)
        wa, wb = g.shape[1] // n_z, g.shape[2] // n_z
        return torch.einsum("zy,bzkyl->bkl", self.weight, g.reshape(B, n_z, wa, n_z, wb))

    def pairs(self, a: str, b: str) -> torch.Tensor:
        """sum_t a[z, i] b[y, j] per pair of rows: (B, n_z, n_z, width a / n_z, width b / n_z)."""
        B, n_z = self.B, self.n_z
        g = self.block(a, b)
        return g.reshape(B, n_z, g.shape[1] // n_z, n_z, g.shape[2] // n_z).permute(0, 1, 3, 2, 4)

    def covariance(self, est, residuals: Residuals, steps: int, measured: int, copies: _Copies
                   ) -> ParameterCovariance:
        """The parameters' covariance X and what the end of the run reads with it, from the sums."""
        f64, B, n = torch.float64, self.B, self.n
        dev = self.gram.device
        V = self.block("z_m", "z_m") / measured
        eye = torch.eye(n, dtype=f64, device=dev)
        info = self.weighted("psi", "psi")                                            # sum Psi W Psi^T
        cross = self.weighted("psi", "J_m")                                           # sum Psi W Psi_true^T
        correlated = (residuals.whiteness_p < WHITE_P).to(dev)
        omega = self.scores.long_run(correlated)          # sum Psi W z z^T W Psi^T, lagged terms where z is not white
        omega_white = self.scores.long_run(torch.zeros_like(correlated))
        finite = torch.isfinite(self.gram).flatten(1).all(1) & torch.isfinite(omega).flatten(1).all(1)
        keep = finite.reshape(-1, 1, 1)
        info, cross = torch.where(keep, info, eye), torch.where(keep, cross, eye)       # frozen: NaN at the end
        omega, omega_white = torch.where(keep, omega, eye), torch.where(keep, omega_white, eye)
        info_inv = torch.linalg.pinv(info)
        A = info_inv @ cross
        P = est.P.detach().to(f64)
        lam = est.lam.to(f64).reshape(-1, 1, 1).expand(B, 1, 1)
        N = int(est.k)
        M = A - 0.5 * lam ** N * eye
        # The recursion has run for the time sum_k 1/n_k in the units of its gain (ln N + 0.58 for lam = 1): a
        # direction that relaxes slowly (an eigenvalue of A - cI near or below 0) has gathered its variance over
        # that time only, X_T = X - exp(-M T) X exp(-M T)^T (the integral of the variance's equation from 0 to T).
        T = _gain_time(est.lam.to(f64).cpu().reshape(-1).expand(B), N).to(dev).reshape(-1, 1, 1)
        E = torch.linalg.matrix_exp(-M * T)

        def variance(o: torch.Tensor) -> torch.Tensor:
            rhs = info_inv @ o @ P
            X = _lyapunov(M, 0.5 * (rhs + rhs.mT))
            X = X - E @ X @ E.mT
            return 0.5 * (X + X.mT)
        X = variance(omega)
        # how much wider the correlation of the residuals makes the intervals (1 where they are white)
        X_white = variance(omega_white) if bool(correlated.any()) else X
        widening = (X.diagonal(dim1=1, dim2=2) / X_white.diagonal(dim1=1, dim2=2).clamp_min(1e-300)).clamp_min(0).sqrt()
        widening = torch.where(correlated, widening.amax(1), 1.0)
        settles = torch.linalg.eigvals(torch.where(keep, A, eye)).real.amin(1) > EXCITED
        settles = settles & finite & est.alive.to(dev)
        ok = settles & torch.isfinite(X).flatten(1).all(1)
        X = torch.where(ok.reshape(-1, 1, 1), X, math.nan)
        step = self._output_error_step(ok, V, X, est)
        return ParameterCovariance(cov=X, gain=A, noise=V, settles=settles, replayed=steps, measured=measured,
                                   correlated=correlated, widening=widening, sampling_note=copies.note,
                                   bias_source=copies.bias_source, **step)

    def _output_error_step(self, ok: torch.Tensor, V: torch.Tensor, X: torch.Tensor, est) -> dict:
        """The output error's Gauss-Newton step over the window (where the frozen loop's error is smaller), its
        random error, the bias against the physics, and the share of z's energy the step leaves."""
        f64, B, W = torch.float64, self.B, self.weight
        eye = torch.eye(self.n, dtype=f64, device=self.gram.device)
        jwj, jwz = self.weighted("J", "J"), self.weighted("J", "z").squeeze(-1)
        zwz = self.weighted("z", "z").reshape(B)
        ok = ok & torch.isfinite(jwj).flatten(1).all(1) & torch.isfinite(jwz).all(1)
        jwj_inv = torch.linalg.pinv(torch.where(ok.reshape(-1, 1, 1), jwj, eye))

        def step(g: torch.Tensor) -> torch.Tensor:
            s = -(jwj_inv @ torch.where(ok.reshape(-1, 1), g, 0.0).unsqueeze(-1)).squeeze(-1)
            return torch.where(ok.reshape(-1, 1), s, math.nan)
        # its random error (sum J^T W J)^-1 (sum J^T W V W J) (sum J^T W J)^-1 for white residuals (the window's
        # output-error estimate's), with the parameters' own X added under forgetting (the two are then not nested)
        optimum_cov = jwj_inv @ torch.einsum("bzy,bzyij->bij", W @ V @ W, self.pairs("J", "J")) @ jwj_inv
        forgets = (est.lam.to(f64).reshape(-1).expand(B) < 1).to(ok.device).reshape(-1, 1, 1)
        offset_cov = torch.where(ok.reshape(-1, 1, 1), optimum_cov + torch.where(forgets, X, 0.0), math.nan)
        optimum_cov = torch.where(ok.reshape(-1, 1, 1), optimum_cov, math.nan)
        # the share of z's weighted energy that no parameter explains (what the Gauss-Newton step leaves)
        explained = (jwz.unsqueeze(1) @ jwj_inv @ jwz.unsqueeze(-1)).reshape(B)
        unexplained = torch.where(zwz > 0, (1 - explained / zwz.clamp_min(1e-300)).clamp(0, 1), 0.0)
        # the sampled estimate minus the physics' (``sampling``): the step the physics' output would add
        return {"offset": step(jwz), "offset_cov": offset_cov, "optimum_cov": optimum_cov, "unexplained": unexplained,
                "sampling": step(self.weighted("J", "d").squeeze(-1)) if self.has_d else None}


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


def _physics_block(base, physics, swap: Mapping[str, Any], name: str):
    """Block ``name`` of ``base`` with ``swap``'s blocks taken from ``physics`` (``_physics_copy``)."""
    if name not in swap:
        return copy.deepcopy(base.blocks[name])
    if name not in physics.blocks:
        raise ConfigError(f"intervals: the physics graph has no block '{name}' (the graph's physical system)")
    blk = copy.deepcopy(physics.blocks[name]).to(device=base.k.device)
    blk.reset(base.batch_size)
    mine = dict(blk.named_buffers(recurse=False))
    for key, value in base.blocks[name].named_buffers(recurse=False):
        if key in ("x", "k") and key in mine and mine[key].shape == value.shape:
            blk.set_state(**{key: value.clone()})
    return blk


def _physics_copy(graph, state, eta, physics, swap: Mapping[str, Any]):
    """A frozen copy of ``graph`` with ``swap``'s blocks taken from ``physics`` (their state from ``state`` where
    a buffer of the same name and shape exists): its measured output is the physics' at the estimates."""
    g, _ = _frozen_copy(graph, state, eta, engine=graph.engine)
    for name in swap:
        g.blocks[name] = _physics_block(g, physics, swap, name)
    return g


class _ScoreSums:
    """The long-run covariance of the scores s(k) = Psi(k) W z(k) with Bartlett weights (the Newey-West
    estimator), Omega_L = sum_k s(k) s(k)^T + sum_{lag=1..L} (1 - lag / (L + 1)) (G_lag + G_lag^T),
    G_lag = sum_k s(k) s(k - lag)^T. With S(k) = s(k) + ... + s(k - L), the moving sum of L + 1 scores (zero
    before the first score and after the last), sum_k S(k) S(k)^T over every k where S is not zero counts each
    pair of scores lag apart L + 1 - lag times: Omega_L = sum_k S S^T / (L + 1), one outer product per step for
    all the lags. For white z Omega_0 = sum Psi W V W Psi^T; where z is correlated (dynamics the refined model
    does not explain; its whiteness test's p-value below WHITE_P) the lagged terms widen the intervals."""

    def __init__(self, B: int, n: int, lags: int, device):
        self.L = lags
        self.ring = torch.zeros(B, lags, n, dtype=torch.float64, device=device)      # the last L scores
        self.gram = torch.zeros(B, n, n, dtype=torch.float64, device=device)          # sum s s^T
        self.moving = torch.zeros(B, n, n, dtype=torch.float64, device=device)        # sum S S^T

    def add(self, s: torch.Tensor) -> None:
        """Add the scores of consecutive steps, (C, B, n)."""
        L = self.L
        s = s.transpose(0, 1)                                                   # (B, C, n), batch first
        x = torch.cat([self.ring, s], dim=1)                                    # (B, L + C, n)
        S = x.unfold(1, L + 1, 1).sum(-1)                                       # (B, C, n): windows ending at s
        self.gram += s.mT @ s
        self.moving += S.mT @ S
        self.ring = x[:, x.shape[1] - L:].contiguous()

    def long_run(self, members: torch.Tensor) -> torch.Tensor:
        """Omega_0 for every member, Omega_L for ``members`` ((B,) bool) only: where z is white the lagged terms
        have expectation zero and would only add their sampling noise."""
        tail = self.ring.flip(1).cumsum(1)                      # S after the last score: its last 1, 2, ... L
        lagged = (self.moving + tail.mT @ tail) / (self.L + 1)
        return torch.where(members.reshape(-1, 1, 1), lagged, self.gram)


def _tsum_rows(psi: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The scores of each step, s(t) = Psi(t) v(t): psi (B, C, n_z, n), v (B, C, n_z) -> (C, B, n)."""
    return (psi * v.unsqueeze(-1)).sum(2).transpose(0, 1)


class _LagSums:
    """sum over t of a(t) * b(t - lag) (``outer``: the outer product a(t) b(t - lag)^T) for lag = 0 .. ``lags``,
    of series given stretch by stretch, time-major (C, B, n) and (C, B, m); b's last ``lags`` rows (zeros before
    the first) carry over to the next stretch."""

    def __init__(self, lags: int, outer: bool):
        self.L, self.outer, self.sum, self.ring = lags, outer, None, None

    def add(self, a: torch.Tensor, b: torch.Tensor) -> None:
        L = self.L
        if self.ring is None:
            self.ring = b.new_zeros(L, *b.shape[1:])
        x = torch.cat([self.ring, b])                                       # b from L steps before the stretch
        now = torch.cat([a.new_zeros(L, *a.shape[1:]), a])                  # a over the stretch only
        part = _lag_sums(now, x, L, self.outer)
        self.sum = part if self.sum is None else self.sum + part
        self.ring = x[x.shape[0] - L:]


def _lag_sums(a: torch.Tensor, b: torch.Tensor, lags: int, outer: bool) -> torch.Tensor:
    """sum over t = lag .. T-1 of a(t) * b(t - lag) (``outer``: the outer product a(t) b(t - lag)^T) for
    lag = 0 .. ``lags``, stacked: a (T, B, n), b (T, B, m) -> (lags + 1, B, n) or (lags + 1, B, n, m).

    Every lag at once by FFT over time (the cross-correlation, zero-padded to at least T + lags so that no lag
    wraps around), members taken in blocks whose spectra hold about CHUNK_BYTES: the residual checks' path where
    the native ``residual_sums`` does not run (off the CPU)."""
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
    """The sums of the residual checks over each member's measured steps, added stretch by stretch: lagged
    products of z and w, the fit's sums, and the first members' outputs."""

    def __init__(self, B: int, lags: int, keep: int, measured: int, settle_of: torch.Tensor, w_on: bool, device):
        self.B, self.L, self.keep, self.dev, self.n = B, lags, min(keep, B), device, measured
        self.settle_of = settle_of.tolist()[:self.keep]
        self.settle_all = settle_of
        self.zz, self.zw = _LagSums(lags, outer=False), _LagSums(lags, outer=True) if w_on else None
        self.sums: dict[str, torch.Tensor] = {}
        self.series: dict[str, torch.Tensor] = {}
        self.native: dict[str, torch.Tensor] | None = None    # the native kernel's sums, where it takes them

    def _sum(self, key: str, value: torch.Tensor) -> None:
        self.sums[key] = value if key not in self.sums else self.sums[key] + value

    def _add_native(self, t0: int, rec: Mapping) -> bool:
        """The stretch's sums by the native kernel (``kernels.residual_sums``), into ``self.native``; False where
        it does not apply (the sums taken so far then move to PyTorch's)."""
        z, y, w = rec["z"], rec["y"], rec["w"]
        if self.native is None:                # the first stretch, on the CPU with the kernels, starts it
            if self.sums or self.zz.sum is not None or z.device.type != "cpu" or not kernels.allowed():
                return False
            B, nz, L = z.shape[1], z.shape[2], self.L
            nw, ny = 0 if w is None else w.shape[2], y.shape[2]
            new = functools.partial(torch.zeros, dtype=torch.float64, device=z.device)
            self.native = {"zlag": new(L + 1, B, nz), "zring": new(B, L, nz), "sums": new(B, nz + 2 * nw + ny + 3),
                           "wlag": new(L + 1, B, nz, nw) if nw else None, "wring": new(B, L, nw) if nw else None,
                           "scratch": kernels.residual_scratch(B, nz, nw, L, z.shape[0])}
        nat = self.native
        if kernels.residual_sums(z, rec["initial"], y, w, self.settle_all, t0, self.n, nat["zlag"], nat["wlag"],
                                 nat["zring"], nat["wring"], nat["sums"], nat["scratch"]):
            return True
        self._from_native()
        return False

    def _from_native(self) -> None:
        """Move the native kernel's sums into PyTorch's (``_LagSums`` and ``sums``)."""
        nat, self.native = self.native, None
        if nat is None:
            return
        self.zz.sum, self.zz.ring = nat["zlag"], nat["zring"].transpose(0, 1).contiguous()
        if self.zw is not None and nat["wlag"] is not None:
            self.zw.sum, self.zw.ring = nat["wlag"], nat["wring"].transpose(0, 1).contiguous()
        nz = nat["zlag"].shape[2]
        nw = 0 if nat["wlag"] is None else nat["wlag"].shape[3]
        cols = nat["sums"].split([nz, nw, nw, 1, 1, nat["sums"].shape[1] - nz - 2 * nw - 3, 1], dim=1)
        for key, col in zip(("z", "w", "ww", "zz", "zi", "y", "yy"), cols):
            if key not in ("w", "ww") or nw:
                self.sums[key] = col.squeeze(1) if key in ("zz", "zi", "yy") else col

    def add(self, t0: int, rec: Mapping, inside: torch.Tensor | None) -> None:
        """Add the stretch of steps from ``t0`` (``_Copies.record``'s records; ``inside`` (C, B) 1 at each member's
        measured steps, None where all are measured). On the CPU the native kernel takes the sums in one pass."""
        z, y, z_init, w = rec["z"], rec["y"], rec["initial"], rec["w"]
        C = z.shape[0]
        if not self._add_native(t0, rec):
            if inside is not None:                 # outside a member's measured steps every sum counts zero
                z, y, z_init = (v * inside.unsqueeze(-1) for v in (z, y, z_init))
                w = None if w is None else w * inside.unsqueeze(-1)
            self.zz.add(z, z)                                                      # z(k) z(k - lag)
            self._sum("z", z.sum(0))
            if w is not None:
                self.zw.add(z, w)                                                  # z(k) w(k - lag)
                self._sum("ww", (w * w).sum(0))
                self._sum("w", w.sum(0))
            self._sum("zz", (z * z).sum((0, 2)))
            self._sum("zi", (z_init * z_init).sum((0, 2)))
            self._sum("y", y.sum(0))
            self._sum("yy", (y * y).sum((0, 2)))
        k = self.keep                          # the kept members' outputs only
        y, z, z_init = y[:, :k], z[:, :k], z_init[:, :k]
        for name, v in (("measured", y), ("refined", y - z), ("initial", y - z_init)):
            if name not in self.series:
                self.series[name] = v.new_zeros(self.n, self.keep, v.shape[2], device="cpu")
            for b, own in enumerate(self.settle_of):     # the member's own measured steps in this stretch
                lo, hi = max(t0, own), min(t0 + C, own + self.n)
                if hi > lo:
                    self.series[name][lo - own:hi - own, b] = v[lo - t0:hi - t0, b].cpu()

    def result(self) -> Residuals:
        self._from_native()
        N, L, s = self.n, self.L, self.sums
        counts = (N - torch.arange(L + 1, dtype=torch.float64, device=self.dev)).clamp_min(1).reshape(-1, 1, 1)
        mean_z = s["z"] / N
        cov_z = self.zz.sum / counts - mean_z.unsqueeze(0) ** 2                 # (L + 1, B, n_z)
        auto = (cov_z / cov_z[:1]).permute(1, 0, 2)                              # (B, L + 1, n_z)
        xcorr = None
        if self.zw is not None:
            mean_w = s["w"] / N
            cov_zw = self.zw.sum / counts.unsqueeze(-1) - (mean_z.unsqueeze(-1) * mean_w.unsqueeze(1)).unsqueeze(0)
            var_w = s["ww"] / N - mean_w ** 2
            scale = torch.sqrt(cov_z[0].unsqueeze(-1) * var_w.unsqueeze(1))         # (B, n_z, n_w)
            xcorr = (cov_zw / scale.unsqueeze(0)).permute(1, 0, 2, 3)
            if L == 0:                          # one product per pair of steps: no correlation to speak of
                xcorr = torch.full_like(xcorr, math.nan)
        r = auto[:, 1:]                                                          # lags 1..L
        lag = torch.arange(1, L + 1, dtype=torch.float64, device=self.dev).reshape(1, -1, 1)
        q = N * (N + 2) * (r * r / (N - lag).clamp_min(1)).sum(1)                 # Ljung-Box, (B, n_z)
        p = chi2_upper_tail(L, torch.nan_to_num(q, nan=math.inf).cpu()) if L > 0 else \
            torch.full(q.shape, math.nan, dtype=torch.float64)                    # too few steps for a lag
        spread = torch.sqrt(s["yy"] - (s["y"] ** 2).sum(1) / N).clamp_min(1e-300)   # |y - mean y|
        return Residuals(steps=N, autocorr=auto.cpu(), xcorr=None if xcorr is None else xcorr.cpu(),
                         bound=1.959964 / math.sqrt(N), whiteness_p=p.amin(1),
                         fit=(100 * (1 - torch.sqrt(s["zz"]) / spread)).cpu(),
                         fit_initial=(100 * (1 - torch.sqrt(s["zi"]) / spread)).cpu(),
                         series=dict(self.series))


def chi2_upper_tail(dof: int, x: torch.Tensor | float) -> torch.Tensor:
    """P(X > x) for X chi-squared with ``dof`` degrees of freedom: Q(dof / 2, x / 2), the regularized upper
    incomplete gamma function, float64."""
    x = torch.as_tensor(x, dtype=torch.float64)
    return torch.special.gammaincc(torch.tensor(dof / 2, dtype=torch.float64), x / 2)


def chi2_upper_quantile(dof: int, tail: float) -> float:
    """The x with P(X > x) = ``tail`` for X chi-squared with ``dof`` degrees of freedom (``chi2_upper_tail``
    inverted by bisection to the last bit)."""
    lo, hi = 0.0, float(dof) + 10.0
    while float(chi2_upper_tail(dof, hi)) > tail:
        lo, hi = hi, 2 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        lo, hi = (mid, hi) if float(chi2_upper_tail(dof, mid)) > tail else (lo, mid)
    return hi


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
    B, n = eta.shape
    h = 1e-3 * std.to(eta.dtype)
    fallback = 1e-6 * torch.maximum(eta.abs(), eta.abs().amax(1, keepdim=True)).clamp_min(1e-12)
    h = torch.where(torch.isfinite(h) & (h > 0), h, fallback)
    grads: dict[str, list] = {}
    with est.theta_kept():
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
    return ok & (stat <= chi2_upper_quantile(n, 1 - p))


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
    eta = est.theta_free().detach().clone()
    sd = pc.std[member].cpu()
    h = torch.where(sd > 0, 1e-3 * sd, 1e-6 * eta[member].abs().clamp_min(1e-12).cpu())
    value = np.asarray(fn(graph), dtype=float)
    grads = []
    with est.theta_kept():
        for j in range(eta.shape[1]):
            sides = []
            for sign in (1.0, -1.0):
                e = eta.clone()
                e[member, j] += sign * float(h[j])
                est.set_theta_free(e)
                sides.append(np.asarray(fn(graph), dtype=float))
            grads.append((sides[0] - sides[1]) / (2 * float(h[j])))
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
    below: dict[str, torch.Tensor] | None = None   # how far each interval reaches below its estimate (B,) ...
    above: dict[str, torch.Tensor] | None = None   # ... and above it (< 0: it lies to the other side); None: half_width

    def lower(self, key: str) -> torch.Tensor:
        return self.estimate[key] - (self.below or self.half_width)[key]

    def upper(self, key: str) -> torch.Tensor:
        return self.estimate[key] + (self.above or self.half_width)[key]

    def side_ratios(self, key: str) -> tuple[torch.Tensor, torch.Tensor]:
        """How far each side of the interval reaches in half-widths, (B,) each: 1 and 1 for a symmetric one (and
        where the half-width is 0 or not finite). A band drawn as half-width h about the estimate reaches
        h * below-ratio under it and h * above-ratio over it."""
        half = self.half_width[key]
        if self.below is None or self.above is None:
            return torch.ones_like(half), torch.ones_like(half)
        ok = torch.isfinite(half) & (half > 0)
        safe = torch.where(ok, half, 1.0)
        return (torch.where(ok, self.below[key] / safe, 1.0), torch.where(ok, self.above[key] / safe, 1.0))


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
      from what the data determine). Where the move is smaller than that but more than ``OFFSET_HOLD_Z`` of
      its own standard deviations sd_d (``pc.offset_cov``), the interval extends to hold the output error's own
      interval est + d - g b +- q sd_o (sd_o from ``pc.optimum_cov``, the optimum's own random error; g b the
      model class's bias against the physics, below, where it is measured): the data cannot tell a closed-loop
      bias of that size from the step's noise, and an interval that holds both covers where either is right;
    * **sampling a continuous feedback** (``pc.sampling``, where the graph declares one): the estimate's
      bias against the continuous physics, beta = g b - d (d as above where it widens the interval, else 0).
      Where |beta| is more than the half-width q sd and than ``NEGLIGIBLE`` of the estimate's size, the
      estimate is *biased* by beta (its cause the model where |g b| >= |d|, else the output error); otherwise
      each side reaches at least |beta| past q sd, so that the interval holds the physics' parameter.

    And the error the recursion has not yet forgotten (``transient``, ``remaining_transient``'s tau and its
    covariance): the estimate's part t = g tau, with standard deviation sd_t, says the physics' value lies
    near est - t, so where t exceeds ``DRIFT_HOLD_Z`` of its standard deviations the interval reaches
    |t| + ``DRIFT_NOISE`` sd_t past the estimate on that side (a test at ``DRIFT_Z`` first would leave the
    members whose drift did not stand out that far too narrow). Where t exceeds ``DRIFT_Z`` of its standard
    deviations and ``DRIFT_FAR`` half-widths (and ``NEGLIGIBLE`` of the estimate's size), the member is
    *drifting* (not converged).

    Last, the interval is chosen between the estimate's and the window's output-error optimum's
    (``_from_optimum``): where the joint test of the two (``optimum_test``) rejects at ``OPTIMUM_P`` or the
    optimum is the more precise, est + d - g b +- q sd_o, else est +- q sd; where the residuals are correlated
    or the drift exceeds ``OPTIMUM_DRIFT_Z`` of its sd (and disagrees with the optimum), it also holds the
    widened interval above. The biases and the drift found above stay the verdict's findings.

    An interval is therefore not always symmetric about its estimate, nor need it hold it: ``below`` and
    ``above`` hold its two sides (est - below, est + above; one of them negative where the interval lies to
    one side of the estimate), ``half_width`` half its width.

    A member's estimates are *determined* when its parameter recursion settles (``pc.settles``) and every
    interval's half-width is at most ``rel_tol`` times max(|estimate|, scale), ``scales[key]`` a size the
    user gives for an estimate that may be near zero (e.g. the nominal value a change is relative to)."""
    q = quantile(level)
    with torch.no_grad():
        values = {k: v.detach().to(torch.float64).reshape(-1).cpu() for k, v in estimates(graph).items()}
    grads = estimate_gradients(graph, estimates, pc.std)
    X = pc.cov.cpu()
    det = pc.settles.cpu().clone()
    half, below, above, bad, moved, biases, flagged = {}, {}, {}, [], {}, {}, []
    widened = torch.zeros_like(det)
    any_off, any_sampled, drifting = torch.zeros_like(det), torch.zeros_like(det), torch.zeros_like(det)
    drifts = {}
    correlated = torch.zeros_like(det) if pc.correlated is None else pc.correlated.cpu()
    factor = torch.where(correlated, OFFSET_FACTOR_CORRELATED, torch.full_like(X[:, 0, 0], OFFSET_FACTOR))
    p_optimum = optimum_test(pc)
    for key, v in values.items():
        g = grads[key].cpu()
        var = torch.einsum("bi,bij,bj->b", g, X, g)
        hw = q * var.clamp_min(0).sqrt()
        scale = float((scales or {}).get(key, 0.0))
        size = torch.clamp(v.abs(), min=scale)
        d, low, high, off, bias = _output_error_reach(pc, g, hw, size, factor, q, moved, widened, key)
        extra = d.abs()                                  # the move that widens both sides
        sampled = torch.zeros_like(det)
        if pc.sampling is not None:
            # the estimate minus the physics' parameter: the model's bias, less the part of it that the output
            # error's move already takes back
            model = torch.einsum("bi,bi->b", g, pc.sampling.cpu())
            total = model - d
            known = torch.isfinite(total) & torch.isfinite(hw)
            flag = known & (total.abs() > hw) & (total.abs() > NEGLIGIBLE * size)
            bias = torch.where(flag, total, bias)
            reach = total.abs() - extra                   # the physics' value, held on both sides
            low = torch.where(known & ~flag, torch.maximum(low, reach), low)
            high = torch.where(known & ~flag, torch.maximum(high, reach), high)
            sampled = flag & (model.abs() >= d.abs())      # the model's part dominates, else the output error's
            off = off | (flag & ~sampled)
        hw = hw + extra
        lo_w, hi_w = hw + low, hw + high
        drift = torch.full_like(hw, math.nan)            # the drift where it exceeds OPTIMUM_DRIFT_Z of its sd
        if transient is not None:
            t = torch.einsum("bi,bi->b", g, transient[0])
            sd_t = _sd(g, transient[1])
            found = torch.isfinite(t) & torch.isfinite(hw)
            moving = found & (t.abs() > DRIFT_Z * sd_t)
            held = found & (t.abs() > DRIFT_HOLD_Z * sd_t)
            drift = torch.where(found & (t.abs() > OPTIMUM_DRIFT_Z * sd_t), t, math.nan)
            drifts[key] = torch.where(moving, t, 0.0)
            far = moving & (t.abs() > DRIFT_FAR * torch.maximum(lo_w, hi_w)) & (t.abs() > NEGLIGIBLE * size)
            drifting |= far
            reach = torch.where(held & ~far, t.abs() + DRIFT_NOISE * sd_t, 0.0)   # towards est - t
            lo_w = torch.where(t > 0, lo_w + reach, lo_w)
            hi_w = torch.where(t < 0, hi_w + reach, hi_w)
        if p_optimum is not None:
            lo_w, hi_w = _from_optimum(pc, g, q * var.clamp_min(0).sqrt(), lo_w, hi_w, p_optimum, correlated,
                                       drift, q)
            off, bias = _bias_held(off, sampled, bias, lo_w, hi_w)
        finite = torch.isfinite(var)
        below[key] = torch.where(finite, lo_w, math.nan)
        above[key] = torch.where(finite, hi_w, math.nan)
        half[key] = (below[key] + above[key]) / 2
        biases[key] = bias
        ok = torch.isfinite(half[key]) & (torch.maximum(below[key], above[key]) <= rel_tol * size)
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
                     bias_reason=reason, drifting=drifting if transient is not None else None, drift=drifts or None,
                     below=below, above=above)


def _output_error_reach(pc: ParameterCovariance, g: torch.Tensor, hw: torch.Tensor, size: torch.Tensor,
                        factor: torch.Tensor, q: float, moved: dict, widened: torch.Tensor, key: str):
    """One estimate's part of the output error's step (``estimate_intervals``): its move d where it widens the
    interval on both sides by |d| (else 0), how much further each side reaches to hold the optimum's own
    interval (``OFFSET_HOLD_Z``), whether the estimate is biased by it, and that bias (NaN where not). Records
    the move in ``moved[key]`` and the members whose interval it widened in ``widened``."""
    zero = torch.zeros_like(hw)
    off, bias = torch.zeros_like(widened), torch.full_like(hw, math.nan)
    if pc.offset is None:
        return zero, zero, zero, off, bias
    low, high = zero, zero
    d, centre, sd_o = _optimum(pc, g)
    moved[key] = d
    beyond = torch.isfinite(d) & torch.isfinite(hw) & (d.abs() > factor * hw)
    widen = beyond if pc.correlated is None else beyond | (pc.correlated.cpu() & torch.isfinite(d))
    off = beyond & (d.abs() > BIAS_TOL * size)          # the data favour a point well away
    bias = torch.where(off, -d, bias)
    if pc.offset_cov is not None:   # a smaller move beyond its own noise: hold the optimum's own interval
        sd_d = _sd(g, pc.offset_cov)
        hold = torch.isfinite(d) & torch.isfinite(hw) & (d.abs() > OFFSET_HOLD_Z * sd_d) & ~widen
        low = torch.where(hold, (q * sd_o - centre - hw).clamp_min(0), 0.0)
        high = torch.where(hold, (q * sd_o + centre - hw).clamp_min(0), 0.0)
        widened |= hold & ((low > 0) | (high > 0))
    widened |= widen
    return torch.where(widen, d, 0.0), low, high, off, bias


def _optimum(pc: ParameterCovariance, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """One estimate's part of the window's output-error optimum (gradient ``g``): the estimate's move to it
    d = g ``pc.offset``, the physics' value less the estimate as the data place it, d - g b (g b the model class's
    own bias where the physics measured it), and the optimum's standard deviation (``pc.optimum_cov``, else
    ``pc.offset_cov``; None where neither is known)."""
    d = torch.einsum("bi,bi->b", g, pc.offset.cpu())
    centre = d
    if pc.sampling is not None:
        model = torch.einsum("bi,bi->b", g, pc.sampling.cpu())
        centre = d - torch.where(torch.isfinite(model), model, 0.0)
    cov = pc.offset_cov if pc.optimum_cov is None else pc.optimum_cov
    return d, centre, None if cov is None else _sd(g, cov)


def optimum_test(pc: ParameterCovariance) -> torch.Tensor | None:
    """(B,) the p-value of the joint test that the refinement's estimate and the window's output-error optimum
    estimate the same parameters: the step d = ``pc.offset`` against its covariance S = ``pc.offset_cov`` (that of
    the difference of the two estimates), d^T S^+ d chi-squared with n degrees of freedom (Hausman's test); NaN
    where the step is not known (None where the run has none)."""
    if pc.offset is None or pc.offset_cov is None:
        return None
    d, S = pc.offset.cpu(), pc.offset_cov.cpu()
    B, n = d.shape
    ok = torch.isfinite(d).all(1) & torch.isfinite(S).reshape(B, -1).all(1)
    eye = torch.eye(n, dtype=torch.float64)
    d0 = torch.where(ok.reshape(-1, 1), d, 0.0)
    stat = torch.einsum("bi,bij,bj->b", d0, torch.linalg.pinv(torch.where(ok.reshape(-1, 1, 1), S, eye)), d0)
    return torch.where(ok, chi2_upper_tail(n, stat.clamp_min(0)), math.nan)


def _from_optimum(pc: ParameterCovariance, g: torch.Tensor, hw: torch.Tensor, below: torch.Tensor, above: torch.Tensor,
                  p: torch.Tensor, correlated: torch.Tensor, drift: torch.Tensor,
                  q: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One estimate's sides from the window's output-error optimum (``estimate_intervals``): where the joint test
    rejects (``p`` below ``OPTIMUM_P``) or the optimum is at least as precise as the estimate, the interval is
    the optimum's, est + d - g b +- q sd_o (g b the model class's bias against the physics where measured; sd_o
    widened by the residuals' correlation where the whiteness test rejects), which need not hold the estimate
    (the estimate's closed-loop bias is what the data correct); elsewhere the estimate's own est +- ``hw``.

    The interval also holds the sides ``below`` and ``above`` of the widenings where the residuals are
    ``correlated`` (the linearized step may stop short of the optimum) and where the estimate drifts (``drift``,
    NaN where it does not exceed ``OPTIMUM_DRIFT_Z`` of its sd): about the estimate always, about the optimum
    only where the drift's own correction est - drift lies more than ``OPTIMUM_AGREE`` of the optimum's
    half-widths from it (the window's optimum does not depend on the recursion's drift where the two agree)."""
    _, centre, sd_o = _optimum(pc, g)
    if pc.widening is not None:
        sd_o = sd_o * torch.where(correlated, pc.widening.cpu(), 1.0)
    have = torch.isfinite(centre) & torch.isfinite(sd_o) & torch.isfinite(hw)
    use = have & ((p < OPTIMUM_P) | (sd_o <= hw / q))
    low = torch.where(use, q * sd_o - centre, hw)
    high = torch.where(use, q * sd_o + centre, hw)
    drifts = torch.isfinite(drift)
    apart = drifts & ((drift + centre).abs() > OPTIMUM_AGREE * q * sd_o)
    hold = correlated | torch.where(use, apart, drifts)
    return torch.where(hold, torch.maximum(low, below), low), torch.where(hold, torch.maximum(high, above), high)


def _bias_held(off: torch.Tensor, sampled: torch.Tensor, bias: torch.Tensor, below: torch.Tensor,
               above: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``off`` and ``bias`` less the biases the interval holds: a bias the output error's step found (a
    closed-loop bias, not the model class's own, ``sampled``) whose physics' value est - bias lies inside the
    interval (its sides ``below``, ``above``) is covered by it, not flagged."""
    shift = torch.where(torch.isfinite(bias), bias, 0.0)
    held = off & ~sampled & (shift <= below) & (-shift <= above)
    return off & ~held, torch.where(held, math.nan, bias)


def _sd(g: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """(B,) standard deviation of g eta where eta has the covariance ``cov`` (B, n, n), g (B, n)."""
    return torch.einsum("bi,bij,bj->b", g, cov.cpu(), g).clamp_min(0).sqrt()
