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
whose detector alarmed since (theta is kept) and lets them forget for a while. ``at_step``: a hook that calls
a function once, at one step (a simulated change of the truth).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import torch

from ..blocks.base import DEFAULT_DTYPE
from ..blocks.nonlinear import Nonlinear
from ..errors import ConfigError

# The detector's state, per member.
PHASE, TIME, POWER, G, FIRST, LAST, COUNT, PENDING = range(8)
N_STATE = 8
# After the reference sums: the settings (start and end of the reference window, the phase after an alarm,
# drift, threshold, 1 / window).
N_SETTINGS = 6


@functools.cache
def _cusum(n_z: int) -> Callable:
    """The detector's state map in the components form (``Nonlinear``), made once for each width of z: x[i] is
    one entry of the state, each a float per member in compiled code and a (B,) tensor on PyTorch. Written with
    arithmetic and comparisons times 1.0, which floats, numba and torch tensors all accept. Its settings are
    entries of the state (the ``N_SETTINGS`` after the reference sums, carried unchanged), so one compilation
    serves every setting. The phase counts the steps since the start (from 0) or since the last alarm (from
    warmup - holdoff, so that the reference window starts holdoff steps after it).

    The sums over the channels are written out for this n_z and the new state is returned as one tuple: a list
    built in compiled code would be allocated on the heap for every member and step."""
    p = N_STATE + n_z
    ref = [f"x[{N_STATE + i}]" for i in range(n_z)]
    lines = [
        "def step(x, ins):",
        "    z = ins['z']",
        f"    phase, t = x[{PHASE}], x[{TIME}] + 1.0",
        f"    start, armed_at, restart = x[{p}], x[{p + 1}], x[{p + 2}]",
        f"    drift, threshold, inv_window = x[{p + 3}], x[{p + 4}], x[{p + 5}]",
        "    in_ref = (phase >= start) * (phase < armed_at) * 1.0",
        "    armed = (phase >= armed_at) * 1.0",
        "    s = phase * 0.0",
    ]
    # sigma_i^2 is 1 until the reference window has data
    lines += [f"    s = s + z[{i}] * z[{i}] / ({r} * inv_window + ({r} <= 0.0) * 1.0) * {1.0 / n_z!r}"
              for i, r in enumerate(ref)]
    lines += [
        f"    g = x[{G}] + s - 1.0 - drift",
        "    g = armed * g * (g > 0.0)",                                 # max(0, g) once armed, else 0
        "    alarm = (g > threshold) * 1.0",
        "    keep = 1.0 - alarm",
        f"    first = x[{FIRST}]",
        # the new state in its order: PHASE, TIME, POWER, G, FIRST, LAST, COUNT, PENDING, the sums, the settings
        "    return ((phase + 1.0) * keep + restart * alarm, t, s, g * keep,",
        f"            first + (first < 0.0) * alarm * (t - first), x[{LAST}] + alarm * (t - x[{LAST}]),",
        f"            x[{COUNT}] + alarm, x[{PENDING}] + alarm,",
    ]
    lines += [f"            ({r} + in_ref * z[{i}] * z[{i}]) * keep," for i, r in enumerate(ref)]
    lines.append("            " + " ".join(f"x[{p + j}]," for j in range(N_SETTINGS)) + ")")
    namespace: dict = {"__name__": __name__}
    exec(compile("\n".join(lines) + "\n", f"<rcotorch CUSUM of {n_z} channels>", "exec"), namespace)
    step = namespace["step"]
    step.__qualname__ = f"_cusum.step_{n_z}"
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

    Raises
    ------
    ConfigError
        If ``every``, ``p0``, ``lam`` or ``hold`` is out of range, or the graph has no ``ChangeDetector`` named
        ``detector``.
    """

    def __init__(self, graph, every: int = 5, detector: str = "detector", estimator: str | None = None,
                 p0: float | None = None, lam: float | None = None, hold: int = 0, restart: bool = True):
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
        self.graph, self.every, self.detector = graph, every, detector
        self.estimator, self.p0, self.lam, self.hold, self.restart = estimator, p0, lam, hold, bool(restart)
        est = self._est()
        if lam is not None:
            # Each member's own factor, kept beside the estimator's (so it moves with the graph; not saved, as
            # the graph's builder makes it again); and one factor per member from the start, so that a
            # checkpoint's layout does not depend on when the first alarm came.
            own = est.lam.detach().clone().expand(graph.batch_size).clone()
            est.register_buffer("lam_own", own, persistent=False)
            est.lam = own.clone()

    def _est(self):
        return self.graph.blocks[self.estimator] if self.estimator else self.graph.role("estimator")

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
        return acted


class at_step:
    """A step hook that calls ``action(graph)`` once, when the graph reaches step ``step``.

    It acts after that step's update: a change of the simulated truth at a known time, on either engine.

    Parameters
    ----------
    step : int
        The step count (``graph.k``) at which to act, >= 1.
    action : Callable
        Called with the graph.

    Raises
    ------
    ConfigError
        If ``step`` is not a positive integer.
    """

    def __init__(self, step: int, action: Callable):
        if isinstance(step, bool) or not isinstance(step, int) or step < 1:
            raise ConfigError(f"at_step: step must be a positive integer, got {step!r}")
        self.every, self.step, self.action = step, step, action

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
