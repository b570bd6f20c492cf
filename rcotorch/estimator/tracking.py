"""Physics that changes while it is watched: detecting a change in the model error and tracking it.

A refinement with lam = 1 weighs all its past alike: after a change (a storey that lost stiffness, a drifted
component) its covariance P has shrunk and theta moves towards the new value only as 1 / k. A constant
forgetting factor lam < 1 tracks, at the price of noisier estimates all the time and covariance windup when the
excitation is poor. Detecting the change and resetting the covariance then (covariance resetting, a classic of
adaptive estimation) keeps lam = 1's accuracy while nothing changes and re-identifies quickly when something
does.

``ChangeDetector``: a one-sided CUSUM on the normalized squared model error, per member,

    s(k) = (1 / n_z) sum_i z_i(k)^2 / sigma_i^2,      g(k) = max(0, g(k-1) + s(k) - 1 - drift),

alarm when g(k) > threshold. sigma_i^2 is the mean of z_i^2 over a reference window of ``window`` steps that
starts ``warmup`` steps after the detector starts, and ``holdoff`` steps after each alarm (so that a second
change is detected too, once the refinement has settled again). While the model is right, s has mean 1 and g
stays near 0; a change that adds to z even a fraction of the noise's power drives g up at the rate of the added
power (relative to the noise's) less ``drift``. It is a ``Nonlinear`` block written with operations that NumPy,
numba and torch share, so it runs in the native engine and on a GPU alike.

``ResetOnChange``: a step hook that, at the steps it acts (every ``every`` steps), sets P = p0 I for the members
whose detector alarmed since (theta is kept) and lets them forget for a while; with ``markov='closed-loop'`` it
also gives the members that are following a change the Markov parameters of the loop as it now is
(``closed_loop_markov``). ``at_step``: a hook that calls a function once, at one step (a simulated change of the
truth).

``closed_loop_markov``: the retrospective cost weighs a change of theta by the Markov parameters of u -> z, which
``refinement`` takes from the known model alone. The known model, though, runs inside the loop that theta
closes (u = theta phi, phi made of the model's own signals), so a perturbation of u reaches z through the known
model *with that loop closed*. While theta is near zero the two agree; after a change, with theta far from zero,
the open-loop parameters differ from the loop's by a growing phase over the window (the loop's modes have other
frequencies), and the regression is biased. The closed-loop parameters at the present theta remove that bias;
they are exact for a linear known model and regressors that are its output ports.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable

import torch

from ..blocks.base import DEFAULT_DTYPE
from ..blocks.lti import LTI
from ..blocks.nonlinear import Nonlinear
from ..engine import kernels, lowering
from ..engine.codegen import tuple_map
from ..errors import ConfigError

# The detector's state, per member.
PHASE, TIME, POWER, G, FIRST, LAST, COUNT, PENDING = range(8)
N_STATE = 8
# After the reference sums: the settings (start and end of the reference window, the phase after an alarm,
# drift, threshold, 1 / window).
N_SETTINGS = 6


def _power(x, z, inv_window):
    """s = (1 / n_z) sum_i z_i^2 / sigma_i^2, sigma_i^2 the reference sum of z_i^2 over the window (times
    ``inv_window``, 1 / window), or 1 until the reference window has data."""
    n_z = len(z)
    s = x[PHASE] * 0.0
    for i in range(n_z):
        r = x[N_STATE + i]
        s = s + z[i] * z[i] / (r * inv_window + (r <= 0.0) * 1.0) * (1.0 / n_z)
    return s


def _reference_sum(i, x, z, in_ref, keep):
    """Channel i's reference sum after the step: z_i^2 added inside the reference window, 0 after an alarm."""
    return (x[N_STATE + i] + in_ref * z[i] * z[i]) * keep


@functools.cache
def _cusum(n_z: int) -> Callable:
    """The detector's state map in the components form (``Nonlinear``), made once for each width of z: x[i] is
    one entry of the state, each a float per member in compiled code and a (B,) tensor on PyTorch. Written with
    arithmetic and comparisons times 1.0, which floats, numba and torch tensors all accept. Its settings are
    entries of the state (the ``N_SETTINGS`` after the reference sums, carried unchanged), so one compilation
    serves every setting. The phase counts the steps since the start (from 0) or since the last alarm (from
    warmup - holdoff, so that the reference window starts holdoff steps after it).

    The new state is returned as one tuple, the reference sums made by ``tuple_map`` for this n_z: a list or
    an array built in compiled code would be allocated on the heap for every member and step."""
    sums = tuple_map(_reference_sum, n_z)
    p = N_STATE + n_z

    def step(x, ins):
        z = ins["z"]
        phase, t = x[PHASE], x[TIME] + 1.0
        start, armed_at, restart = x[p], x[p + 1], x[p + 2]
        drift, threshold, inv_window = x[p + 3], x[p + 4], x[p + 5]
        in_ref = (phase >= start) * (phase < armed_at) * 1.0
        armed = (phase >= armed_at) * 1.0
        s = _power(x, z, inv_window)
        g = x[G] + s - 1.0 - drift
        g = armed * g * (g > 0.0)                       # max(0, g) once armed, else 0
        alarm = (g > threshold) * 1.0
        keep = 1.0 - alarm
        first = x[FIRST]
        # the new state in its order: PHASE, TIME, POWER, G, FIRST, LAST, COUNT, PENDING, the sums, the settings
        return ((phase + 1.0) * keep + restart * alarm, t, s, g * keep,
                first + (first < 0.0) * alarm * (t - first), x[LAST] + alarm * (t - x[LAST]),
                x[COUNT] + alarm, x[PENDING] + alarm) + sums(x, z, in_ref, keep) + \
            (x[p], x[p + 1], x[p + 2], x[p + 3], x[p + 4], x[p + 5])

    return step


def _statistic(x):
    return x[G]


class ChangeDetector(Nonlinear):
    """CUSUM change detector on the model error z (module docstring), one per member.

    s(k) = (1 / n_z) sum_i z_i(k)^2 / sigma_i^2, g(k) = max(0, g(k-1) + s(k) - 1 - drift); an alarm when
    g(k) > threshold.

    Parameters
    ----------
    n_z : int, optional
        Width of z (its input port ``z``).
    warmup : int, optional
        Steps after the start before the reference window; long enough for the refinement to settle.
    window : int, optional
        Steps of the reference window that sets each channel's scale sigma_i^2.
    holdoff : int, optional
        Steps after an alarm before the next reference window (default ``warmup``): long enough for the
        refinement to re-converge.
    drift : float, optional
        Allowance subtracted from s each step: changes smaller than ``drift`` times the noise's power are
        ignored (0.5-1 is usual).
    threshold : float, optional
        Alarm level of g; the mean time between false alarms grows about exponentially with it.
    dt : float, optional
        Sample time [s] (for times in seconds); by default the sample time of the graph's known model
        (``change_report``), else one step.
    name : str, optional
        The block's name.
    dtype : torch.dtype, optional
        Floating-point type (float64 by default).

    Raises
    ------
    ConfigError
        If n_z < 1, warmup < 0, window < 1, holdoff < 0, drift < 0 or threshold <= 0 (or one is not finite).

    Shape
    -----
    - Input ``z``: (B, n_z).
    - Output ``g``: (B, 1), the statistic.
    - State ``x``: (B, 8 + n_z), per member: phase, step, s, g, the step of the first alarm (-1: none), of the
      last, the number of alarms, alarms not yet acted on, then the reference sums of z_i^2.
    """

    def __init__(self, n_z: int = 1, warmup: int = 200, window: int = 200, holdoff: int | None = None,
                 drift: float = 1.0, threshold: float = 50.0, dt: float | None = None, name: str = "detector",
                 dtype=DEFAULT_DTYPE):
        n_z, warmup, window = int(n_z), int(warmup), int(window)
        holdoff = warmup if holdoff is None else int(holdoff)
        if n_z < 1 or warmup < 0 or window < 1 or holdoff < 0:
            raise ConfigError(f"block '{name}': n_z >= 1, warmup >= 0, window >= 1 and holdoff >= 0 are needed, "
                              f"got n_z={n_z}, warmup={warmup}, window={window}, holdoff={holdoff}")
        if not (math.isfinite(drift) and drift >= 0 and math.isfinite(threshold) and threshold > 0):
            raise ConfigError(f"block '{name}': drift must be >= 0 and threshold > 0, got drift={drift}, "
                              f"threshold={threshold}")
        self.n_z, self.warmup, self.window, self.holdoff = n_z, warmup, window, holdoff
        self.drift, self.threshold = float(drift), float(threshold)
        self.sample_time = None if dt is None else float(dt)       # None: the known model's (change_report)
        x0 = torch.zeros(N_STATE + n_z + N_SETTINGS, dtype=dtype)
        x0[FIRST] = x0[LAST] = -1.0
        x0[N_STATE + n_z:] = torch.tensor([warmup, warmup + window, warmup - holdoff, self.drift, self.threshold,
                                           1.0 / window], dtype=dtype)
        super().__init__(_cusum(n_z), _statistic, N_STATE + n_z + N_SETTINGS, {"z": n_z}, {"g": 1}, dt=dt or 1.0, x0=x0,
                         name=name, dtype=dtype, form="components")

    def first_alarm(self) -> torch.Tensor:
        """The step of each member's first alarm.

        Returns
        -------
        torch.Tensor
            (B,) int64, -1 where there was none.
        """
        return self.x[:, FIRST].round().long()

    def alarms(self) -> torch.Tensor:
        """The number of alarms of each member.

        Returns
        -------
        torch.Tensor
            (B,) int64.
        """
        return self.x[:, COUNT].round().long()


class ResetOnChange:
    """A step hook (``graph.add_hook``) that restarts the estimator of the members whose ``ChangeDetector``
    alarmed since it last acted: their covariance becomes P = p0 I (the estimator's own p0 unless ``p0`` is
    given; theta is kept; ``restart=False`` keeps P), and, with ``lam``, they forget with that factor for the
    ``hold`` steps after each alarm and return to their own factor after. It acts every ``every`` steps, so the
    native engine runs the steps in between (and renews its program when the factors change).

    What the restart can and cannot do is measured in docs/tracking.md: after a change, the known model's
    state has drifted from the truth's, so the first post-change data regress on the model's signals while they
    differ from the truth's; a moderate p0 (one step moves theta part of the way) with a while of forgetting
    follows the change, a very large p0 fits that transient exactly and goes astray.

    Parameters
    ----------
    graph : Graph
        The graph, with a ``ChangeDetector`` and an estimator.
    every : int, optional
        Act after the steps k with k % every == 0.
    detector : str, optional
        The name of the ``ChangeDetector`` block.
    estimator : str, optional
        The name of the estimator block; by default the graph's 'estimator' role.
    p0 : float, optional
        The restarted covariance P = p0 I (> 0); by default the estimator's own p0.
    lam : float, optional
        Forgetting factor in (0, 1] of a member for the ``hold`` steps after each of its alarms; None keeps
        the estimator's factors.
    hold : int, optional
        How many steps after an alarm ``lam`` applies (>= 0).
    restart : bool, optional
        Reset P at an alarm; False keeps P (only ``lam`` acts).
    markov : {'open-loop', 'closed-loop'}, optional
        'closed-loop' (a static identified subsystem, nc = 0): every ``markov_every`` steps, the members between
        ``markov_after`` and ``markov_until`` steps after their last alarm get the Markov parameters of the loop
        closed at their present theta (``closed_loop_markov``), where that loop is stable; the others keep theirs
        (from the first such member on, the estimator holds one set per member). 'open-loop' (the default) keeps
        the Markov parameters as they are.
    markov_after : int, optional
        Steps after an alarm before the first closed-loop Markov parameters (>= 0), so that theta has moved
        from its first jumps after the restart before the loop is closed at it.
    markov_every : int, optional
        Steps between two renewals of the closed-loop Markov parameters, a multiple of ``every`` (by default
        ``every``).
    markov_until : int, optional
        Steps after an alarm after which a member's closed-loop Markov parameters are kept as they are (by
        default ``hold``).
    markov_tol : float, optional
        A member's are renewed only where its theta has moved since they were made by more than ``markov_tol``
        times its size (Frobenius norms); 0 renews them every time. The theta they were made at is kept in the
        estimator's buffer ``theta_closed`` (zeros at the start: the known model's own parameters are the loop
        opened).

    Raises
    ------
    ConfigError
        If ``every``, ``p0``, ``lam``, ``hold``, ``markov``, ``markov_after``, ``markov_every`` or ``markov_tol`` is
        out of range, the graph has no ``ChangeDetector`` named ``detector``, or (closed-loop) the identified
        subsystem is dynamic (nc >= 1), the loop cannot be closed (``closed_loop_markov``) or the estimator's
        Markov parameters are not the known model's own (the loop closed at theta = 0).
    """

    def __init__(self, graph, every: int = 5, detector: str = "detector", estimator: str | None = None,
                 p0: float | None = None, lam: float | None = None, hold: int = 0, restart: bool = True,
                 markov: str = "open-loop", markov_after: int = 0, markov_every: int | None = None,
                 markov_until: int | None = None, markov_tol: float = 0.0):
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ConfigError(f"ResetOnChange: every must be a positive integer, got {every!r}")
        if detector not in graph.blocks or not isinstance(graph.blocks[detector], ChangeDetector):
            raise ConfigError(f"ResetOnChange: the graph has no ChangeDetector named '{detector}'")
        if p0 is not None and not (math.isfinite(p0) and p0 > 0):
            raise ConfigError(f"ResetOnChange: p0 must be positive, got {p0!r}")
        if lam is not None and not 0 < lam <= 1:
            raise ConfigError(f"ResetOnChange: lam must lie in (0, 1], got {lam!r}")
        if isinstance(hold, bool) or not isinstance(hold, int) or hold < 0:
            raise ConfigError(f"ResetOnChange: hold must be a non-negative integer, got {hold!r}")
        if markov not in ("open-loop", "closed-loop"):
            raise ConfigError(f"ResetOnChange: markov must be 'open-loop' or 'closed-loop', got {markov!r}")
        if isinstance(markov_after, bool) or not isinstance(markov_after, int) or markov_after < 0:
            raise ConfigError(f"ResetOnChange: markov_after must be a non-negative integer, got {markov_after!r}")
        self.graph, self.every, self.detector = graph, every, detector
        markov_every = every if markov_every is None else markov_every
        if isinstance(markov_every, bool) or not isinstance(markov_every, int) or markov_every < 1 or \
                markov_every % every:
            raise ConfigError(f"ResetOnChange: markov_every must be a positive multiple of every = {every}, got "
                              f"{markov_every!r}")
        self.closed, self.markov_after, self.markov_every = markov == "closed-loop", markov_after, markov_every
        self.markov_until = hold if markov_until is None else markov_until
        if not (math.isfinite(markov_tol) and markov_tol >= 0):
            raise ConfigError(f"ResetOnChange: markov_tol must be >= 0, got {markov_tol!r}")
        self.markov_tol = float(markov_tol)
        self.estimator, self.p0, self.lam, self.hold, self.restart = estimator, p0, lam, hold, bool(restart)
        est = self._est()
        if lam is not None:
            # Each member's own factor, kept beside the estimator's (so it moves with the graph; not saved, as
            # the graph's builder makes it again); and one factor per member from the start, so that a
            # checkpoint's layout does not depend on when the first alarm came.
            own = est.lam.detach().clone().expand(graph.batch_size).clone()
            est.register_buffer("lam_own", own, persistent=False)
            est.lam = own.clone()
        if self.closed:
            self._closed_loop_start(est)

    def _closed_loop_start(self, est) -> None:
        """Check that the identified subsystem is a static map and that the loop opened (theta = 0) gives the
        estimator's Markov parameters."""
        if est.nc:
            raise ConfigError(f"ResetOnChange: markov='closed-loop' needs a static identified subsystem (nc = 0), "
                              f"but '{est.name}' has nc = {est.nc}: a loop closed through a dynamic subsystem "
                              "carries the subsystem's own poles, which move with the estimate (docs/tracking.md); "
                              "use markov='open-loop'")
        B = self.graph.batch_size
        theta = torch.zeros(B, est.n_u, est.n_phi, dtype=est.theta0.dtype, device=est.theta0.device)
        open_loop = closed_loop_markov(self.graph, theta, estimator=self.estimator)
        beta = est.beta.expand(B, -1, -1, -1)
        scale = float(beta.abs().amax())
        tol = torch.finfo(beta.dtype).eps ** 0.5 * max(scale, torch.finfo(beta.dtype).tiny)     # rounding of dtype
        if open_loop.shape != beta.shape or float((open_loop - beta).abs().amax()) > tol:
            raise ConfigError(f"ResetOnChange: markov='closed-loop', but the Markov parameters of '{est.name}' are "
                              "not those of its known model's u -> y (as refinement() derives them); the loop "
                              "cannot be closed on them")
        if "theta_closed" not in est._buffers:
            est.register_buffer("theta_closed", theta)      # saved with the graph: a resumed run renews alike

    def _est(self):
        return self.graph.blocks[self.estimator] if self.estimator else self.graph.role("estimator")

    keeps_theta = True      # it restarts P and sets the forgetting and the Markov parameters, never theta

    @property
    def acts_on(self) -> frozenset[str]:
        """The blocks it changes (``Graph.add_hook``): the detector and the estimator."""
        return frozenset({self.detector, self._est().name})

    def __call__(self, graph=None) -> bool:
        """Act after a step: restart the members that alarmed since the last call, and set the factors.

        Parameters
        ----------
        graph : Graph, optional
            Ignored (the hook acts on the graph it was made for); given by ``Graph`` when it calls hooks.

        Returns
        -------
        bool
            Whether it changed the estimator (P or the forgetting factors).
        """
        g = self.graph
        k = int(g.k)
        if k % self.every:
            return False
        det, est = g.blocks[self.detector], self._est()
        hit = det.x[:, PENDING] > 0
        acted = False
        if bool(hit.any()) and self.restart:
            n = est.P.shape[-1]
            p0 = est.p0 if self.p0 is None else torch.full((1,), self.p0, dtype=est.P.dtype)
            fresh = p0.to(est.P).reshape(-1, 1, 1) * torch.eye(n, dtype=est.P.dtype, device=est.P.device)
            est.P.copy_(torch.where(hit.reshape(-1, 1, 1), fresh.expand_as(est.P), est.P))
            acted = True
        det.x[:, PENDING] = 0.0
        if self.lam is not None:
            last = det.x[:, LAST]
            tracking = (last >= 0) & (k - last <= self.hold)
            want = torch.where(tracking, torch.full_like(last, self.lam), est.lam_own.to(last)).to(est.lam)
            if want.shape != est.lam.shape or not torch.equal(want, est.lam):
                est.lam = want
                acted = True
        if self.closed:
            acted = self._close_loop(det, est, k) or acted
        return acted

    def _close_loop(self, det, est, k: int) -> bool:
        """Closed-loop Markov parameters at their present theta for the living members between markov_after and
        hold steps after their last alarm, at the steps that are multiples of markov_every."""
        if k % self.markov_every:
            return False
        last = det.x[:, LAST]
        since = k - last
        now = (last >= 0) & (since >= self.markov_after) & (since <= self.markov_until) & est.alive.to(last.device)
        if self.markov_tol > 0:
            # ||theta - theta_closed|| > tol ||theta||
            moved = (est.theta - est.theta_closed).flatten(1).norm(dim=1) > \
                self.markov_tol * est.theta.flatten(1).norm(dim=1)
            now = now & moved.to(now.device)
        if not bool(now.any()):
            return False
        idx = now.nonzero().reshape(-1).to(est.theta.device)
        system = _closed_loop(self.graph, est.theta[idx], self.estimator, None, "u", "y", idx)
        # A loop that theta makes unstable has Markov parameters that grow over the window: those members keep
        # the ones they have. The native kernel writes the stable ones in place where it shows them stable by
        # a power of the loop's matrix; the eigenvalues decide the rest.
        written = est._refill_from_system(idx, *system, stable=True)
        if written is not None:
            doubt = (~written).nonzero().reshape(-1)
            if doubt.numel():
                doubt = doubt[torch.linalg.eigvals(system[0][doubt]).abs().amax(-1) < 1.0]
                est._refill_from_system(idx[doubt], *(m[doubt] for m in system), stable=False)
                written[doubt] = True
            idx = idx[written.to(idx.device)]
            in_place = True
        else:
            stable = torch.linalg.eigvals(system[0]).abs().amax(-1) < 1.0
            idx, system = idx[stable], tuple(m[stable] for m in system)
            beta = _markov_parameters(*system, est.first_delay, est.nu) if idx.numel() else None
            in_place = beta is not None and est.set_markov(beta, est.first_delay, members=idx)
        if not idx.numel():
            return False
        est.theta_closed.index_copy_(0, idx, est.theta[idx])
        if in_place:
            # beta and the program's copy of it (NativeCopy) were written together: the program stays valid
            lowering.refilled(self.graph, est.beta, est.theta_closed)   # theta_closed: not read by it
        return True


class at_step:
    """A step hook that calls ``action(graph)`` once, when the graph reaches step ``step``.

    It acts after that step's update: a change of the simulated truth at a known time, on either engine.

    Parameters
    ----------
    step : int
        The step count (``graph.k``) at which to act, >= 1.
    action : Callable
        Called with the graph.
    acts_on : list of str, optional
        The blocks the action changes (``Graph.add_hook``), e.g. the truth whose change it simulates. Where it
        is given, the intervals' replay shares the blocks the action leaves alone among its copies.

    Raises
    ------
    ConfigError
        If ``step`` is not a positive integer, or ``acts_on`` is not a list of block names.
    """

    def __init__(self, step: int, action: Callable, acts_on: Iterable[str] | None = None):
        if isinstance(step, bool) or not isinstance(step, int) or step < 1:
            raise ConfigError(f"at_step: step must be a positive integer, got {step!r}")
        self.every, self.step, self.action = step, step, action
        if acts_on is not None:
            if isinstance(acts_on, str) or not all(isinstance(a, str) for a in acts_on):
                raise ConfigError(f"at_step: acts_on must be a list of block names, got {acts_on!r}")
            self.acts_on = frozenset(acts_on)

    def __call__(self, graph) -> bool:
        """Call the action if the graph is at the step.

        Parameters
        ----------
        graph : Graph
            The graph, after a step.

        Returns
        -------
        bool
            Whether the action ran.
        """
        if int(graph.k) != self.step:
            return False
        self.action(graph)
        return True


def change_report(graph) -> dict[str, dict[str, torch.Tensor]]:
    """What each ``ChangeDetector`` of a graph found, per member.

    Parameters
    ----------
    graph : Graph
        The graph.

    Returns
    -------
    dict[str, dict[str, torch.Tensor]]
        Detector name -> 'first_alarm_step', 'first_alarm_s', 'last_alarm_step', 'alarms', each (B,): the step
        and time [s] of its first and last alarm (-1 / NaN: none) and the number of alarms.
    """
    out = {}
    for name, blk in graph.blocks.items():
        if isinstance(blk, ChangeDetector) and blk.x.shape[0]:
            dt = blk.sample_time or graph.known_sample_time() or 1.0
            first, last = blk.x[:, FIRST].round(), blk.x[:, LAST].round()
            nan = torch.full_like(first, math.nan)
            out[name] = {"first_alarm_step": first, "first_alarm_s": torch.where(first >= 0, first * dt, nan),
                         "last_alarm_step": last, "alarms": blk.x[:, COUNT].round()}
    return out


def closed_loop_markov(graph, theta: torch.Tensor | None = None, estimator: str | None = None,
                       known: str | None = None, actuation: str = "u", measured: str = "y",
                       members: torch.Tensor | None = None) -> torch.Tensor:
    """The Markov parameters of u -> z with the estimator's loop closed at ``theta``, one set per member.

    The known model (an ``LTI``) runs with u(k) = sum_l N_l s(k-l) + sum_l M_l u(k-l) + v(k), the estimator's
    identified subsystem at ``theta`` (``RCOEstimator.coefficients``), where each regressor port s that the graph
    feeds from a known-model output is that output; regressor ports fed by a source (a block without inputs: the
    excitation, recorded data) do not depend on u and are left out of the loop. The result is beta_i = -H_i, i =
    d..d+nu-1, of the map v -> y (z = y - y_hat, as ``derive_markov``), with the estimator's own d and nu: at theta
    = 0 it is the known model's own Markov parameters.

    Parameters
    ----------
    graph : Graph
        A refinement: its known model an ``LTI``, its estimator an ``RCOEstimator`` without features.
    theta : torch.Tensor, optional
        (B', n_u, n_phi), the estimates to close the loop with; by default the estimator's own.
    estimator, known : str, optional
        Block names; by default the graph's roles 'estimator' and 'known'.
    actuation, measured : str, optional
        The known model's input port for u and its output port y.
    members : torch.Tensor, optional
        (B',) indices of the members ``theta`` belongs to, where the known model's matrices are per member; by
        default all of them.

    Returns
    -------
    torch.Tensor
        (B', nu, n_z, n_u).

    Raises
    ------
    ConfigError
        If the known model is not linear (no state-space matrices), the estimator has features, a regressor
        port is fed by a block that is neither the known model nor a source (its path from u is not known
        here), or a regressor with no delay reads a known-model output that u reaches at once in a way that makes
        the loop singular.
    """
    est = graph.blocks[estimator] if estimator else graph.role("estimator")
    Acl, Bcl, Ccl, D0 = _closed_loop(graph, theta, estimator, known, actuation, measured, members)
    return _markov_parameters(Acl, Bcl, Ccl, D0, est.first_delay, est.nu)


def _closed_loop(graph, theta, estimator, known, actuation, measured, members):
    """The loop of ``closed_loop_markov`` as a state-space system per member, from v to y: (Acl, Bcl, Ccl, D0)."""
    est = graph.blocks[estimator] if estimator else graph.role("estimator")
    kn = graph.blocks[known] if known else graph.role("known")
    if not isinstance(kn, LTI):
        raise ConfigError(f"closed_loop_markov: the known model '{kn.name}' is not an LTI block; closed-loop Markov "
                          "parameters need its state-space matrices")
    if est.features is not None:
        raise ConfigError(f"closed_loop_markov: the estimator '{est.name}' has features; closed-loop Markov "
                          "parameters need regressors that are ports (linear in the known model's state)")
    theta = est.theta if theta is None else theta
    dt = kn.A.dtype
    theta = theta.to(dtype=dt, device=kn.A.device)
    Bm, n = theta.shape[0], kn.A.shape[-1]
    cu, ry = kn._in_slices[actuation], kn._out_slices[measured]
    n_u, n_sig, nc = est.n_u, est.n_sig, est.nc

    def batch(M):
        if M.shape[0] == 1:
            return M.expand(Bm, -1, -1)
        return M if members is None else M[members.to(M.device)]

    A, Bu = batch(kn.A), batch(kn.B[:, :, cu])
    Cy, Dy = batch(kn.C[:, ry]), batch(kn.D[:, ry, cu])
    # s(k) = Cs x(k) + Ds u(k): the rows of the ports that the known model feeds, zeros for the others
    Cs, Ds = theta.new_zeros(Bm, n_sig, n), theta.new_zeros(Bm, n_sig, n_u)
    at = 0
    for port, w in est.ports.items():
        src = graph.sources.get((est.name, port))
        if src is not None and src[0] == kn.name:
            rows = kn._out_slices[src[1]]
            Cs[:, at:at + w], Ds[:, at:at + w] = batch(kn.C[:, rows]), batch(kn.D[:, rows, cu])
        elif src is not None and graph.blocks[src[0]].inputs:
            raise ConfigError(f"closed_loop_markov: the regressor port '{est.name}.{port}' is fed by "
                              f"'{src[0]}.{src[1]}', which is neither the known model '{kn.name}' nor a source; the "
                              "loop can be closed only through the known model's outputs")
        at += w
    N, M = est.coefficients(theta)
    lags = est.lags
    # The loop's state X = [x; s(k-1) .. s(k-nc); u(k-1) .. u(k-nc)]; u(k) = Fu X + Gu v(k).
    size = n + nc * (n_sig + n_u)
    eye_u = torch.eye(n_u, dtype=dt, device=theta.device)
    N0 = N[:, 0] if lags[0] == 0 else theta.new_zeros(Bm, n_u, n_sig)
    K = eye_u - N0 @ Ds                                      # u = N0 (Cs x + Ds u) + ...: (I - N0 Ds) u = ...
    Kinv, info = torch.linalg.inv_ex(K)
    if bool((info != 0).any()) or not bool(torch.isfinite(Kinv).all()):
        raise ConfigError(f"closed_loop_markov: the loop through '{est.name}' with no delay is singular "
                          "(I - N_0 D_s has no inverse)")
    rest = theta.new_zeros(Bm, n_u, size)
    rest[:, :, :n] = N0 @ Cs
    for li, lag in enumerate(lags):
        if lag >= 1:
            c = n + (lag - 1) * n_sig
            rest[:, :, c:c + n_sig] += N[:, li]
    if est.feed_u:
        for lag in range(1, nc + 1):
            c = n + nc * n_sig + (lag - 1) * n_u
            rest[:, :, c:c + n_u] = M[:, lag - 1]
    Fu, Gu = Kinv @ rest, Kinv                               # (Bm, n_u, size), (Bm, n_u, n_u)
    Acl = theta.new_zeros(Bm, size, size)
    Bcl = theta.new_zeros(Bm, size, n_u)
    Acl[:, :n, :n] = A
    Acl[:, :n] += Bu @ Fu
    Bcl[:, :n] = Bu @ Gu
    if nc:
        s_now = theta.new_zeros(Bm, n_sig, size)
        s_now[:, :, :n] = Cs
        s_now += Ds @ Fu
        Acl[:, n:n + n_sig] = s_now
        Bcl[:, n:n + n_sig] = Ds @ Gu
        Acl[:, n + n_sig:n + nc * n_sig, n:n + (nc - 1) * n_sig] = torch.eye((nc - 1) * n_sig, dtype=dt,
                                                                            device=theta.device)
        u0 = n + nc * n_sig
        Acl[:, u0:u0 + n_u] = Fu
        Bcl[:, u0:u0 + n_u] = Gu
        Acl[:, u0 + n_u:, u0:u0 + (nc - 1) * n_u] = torch.eye((nc - 1) * n_u, dtype=dt, device=theta.device)
    # y(k) = Cy x + Dy u = (Cy [I 0] + Dy Fu) X + Dy Gu v
    Ccl = Dy @ Fu
    Ccl[:, :, :n] += Cy
    return Acl, Bcl, Ccl, Dy @ Gu


def _markov_parameters(Acl: torch.Tensor, Bcl: torch.Tensor, Ccl: torch.Tensor, D0: torch.Tensor, d: int,
                       nu: int) -> torch.Tensor:
    """beta_i = -H_i, i = d..d+nu-1, of the system (Acl, Bcl, Ccl, D0), one per member: (Bm, nu, p, m)."""
    Bm, n_u = Bcl.shape[0], Bcl.shape[-1]
    # H_0 = D0, H_i = Ccl Acl^(i-1) Bcl: in the native kernel where it applies, else the columns [Bcl, Acl Bcl,
    # .., Acl^(n-1) Bcl] by doubling ([C, Acl^m C] from C of m blocks), a few products of the batch instead of one
    # per parameter
    beta = kernels.lti_markov(Acl, Bcl, Ccl, D0, d, nu)
    if beta is not None:
        return beta
    first = max(d, 1)
    n_blocks = d + nu - first
    cols, power = Bcl, Acl
    while cols.shape[-1] < n_blocks * n_u:
        cols = torch.cat([cols, power @ cols], dim=-1)
        power = power @ power
    left = Ccl if first == 1 else Ccl @ torch.linalg.matrix_power(Acl, first - 1)
    H = (left @ cols[..., :n_blocks * n_u]).reshape(Bm, -1, n_blocks, n_u).transpose(1, 2)       # H_first ..
    if d == 0:
        H = torch.cat([D0.unsqueeze(1), H], dim=1)
    return -H[:, :nu]
