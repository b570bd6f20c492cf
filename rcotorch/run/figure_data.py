"""What a run's figures show, taken from the run as plain numbers (NumPy arrays, floats, strings), so that the
figures (``rcotorch.run.figures``) draw without the run, its graph or torch: in this process, or in a drawing
process that never imports torch (``rcotorch.run.drawing``). Importing this module imports neither torch nor
matplotlib; ``run_figure_data`` imports what reads the run."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

MAX_LINES = 8          # the members a figure draws at most
TRACE = 600            # the last samples of a window that the output panels draw


@dataclass
class IntervalData:
    """The final intervals of the drawn members (arrays over ``RunFigureData.members`` that are in the batch)."""
    level: float
    window_start: float                            # the convergence window's start, in the time axis' unit
    estimate: dict[str, np.ndarray]
    lower: dict[str, np.ndarray]
    upper: dict[str, np.ndarray]
    below: dict[str, np.ndarray]                   # each side's reach over the half-width (``side_ratios``)
    above: dict[str, np.ndarray]
    bias: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class ResidualData:
    """The residual checks of member 0 on the replayed window."""
    autocorr: np.ndarray                           # (L + 1, n_z)
    xcorr: np.ndarray | None                       # (L + 1, n_z, n_w)
    bound: float
    steps: int
    fit: float
    fit_initial: float
    measured: np.ndarray                           # (T, n_y)
    refined: np.ndarray
    initial: np.ndarray
    verdict: str                                   # what the whiteness test means for the estimates
    lags: int                                      # the lags a window long enough tests
    samples_per_lag: int                           # the window's samples each lag needs


@dataclass
class RunFigureData:
    """Everything ``rcotorch.run.figures.run_figures`` draws. ``members``: the traced members (at most
    ``MAX_LINES``); ``series`` and ``z_rms``: (T, members) paths at the logged times ``t``."""
    name: str                                      # the name in the figures' titles ('' for none)
    batch: int
    members: list[int]
    t: np.ndarray
    dt: float | None
    series: dict[str, np.ndarray]
    z_rms: np.ndarray | None
    units: dict[str, str]
    y_unit: str
    output_names: list[str]
    truth: dict[str, Any]                          # a float, or one value per drawn member
    truth_path: dict[str, tuple[np.ndarray, list[float]]]   # a truth that changes: (times, values)
    truth_now: dict[str, Any]
    changes: list[float]                           # the times at which a truth changes
    initial: dict[str, np.ndarray]                 # the initial model's estimates of the drawn members
    alarms: dict[str, np.ndarray]                  # a change detector's first alarm step per drawn member
    intervals: IntervalData | None
    band: dict[str, np.ndarray] | None             # the band's half-width over time (T, members)
    held_out: tuple[float, float] | None           # member 0's rms of z on held-out data: initial, refined
    trace: tuple[str, np.ndarray, np.ndarray, np.ndarray, int] | None
    residuals: ResidualData | None
    only: tuple[str, ...] | None = None            # the figures to draw (None: all of them)


@dataclass
class SweepFigureData:
    """Everything ``rcotorch.run.figures.sweep_figures`` draws: the sweep's table (``rows``, one dict per member,
    as sweep.json holds it), the settings drawn against (``swept``), the units of the estimates and settings, and
    the scenario's name in the titles ('' for none)."""
    rows: list[dict[str, Any]]
    swept: list[str]
    units: dict[str, str]
    name: str


def sweep_figure_data(rows, swept, scenario=None) -> SweepFigureData:
    """The figures' data of a finished sweep; ``scenario`` (an object, optional) gives the units and the name."""
    keys = list(dict.fromkeys(c[4:] for r in rows for c in r if c.startswith("est_")))
    units: dict[str, str] = {}
    if scenario is not None:
        units = {key: scenario.unit(key) for key in keys}
        units.update({s: scenario.unit(s) for s in swept if s in getattr(scenario, "settings", {})})
        name = shown_name(scenario)
    else:
        name = str(rows[0].get("scenario") or "") if rows else ""
    return SweepFigureData(rows=[dict(r) for r in rows], swept=list(swept), units=units, name=name)


RUN_FIGURES = ("estimates", "model_error", "residuals", "output_fit")   # the figures a run draws, where it has them
HELD_OUT_FIGURES = ("model_error",)      # those that draw what validation measured


def run_figure_data(run, held_out: bool = True, only=None) -> RunFigureData:
    """The figures' data of a run (``rcotorch.run.runner.Run``, or an object with its attributes). ``held_out``:
    False leaves validation out (not run, not read: no held-out rms or trace), for the figures other than
    ``HELD_OUT_FIGURES``, drawn while the run validates; ``only``: the names of the figures to draw (None: all)."""
    import torch
    h = run.history
    dt = run.graph.known_sample_time()
    t = np.asarray(h["step"], dtype=float) * (dt or 1.0)
    members = list(getattr(run, "history_members", range(MAX_LINES)))
    keys = [k for k in h if k not in ("step", "z_rms")]
    series = {key: _np(torch.stack(h[key]))[:, :MAX_LINES] for key in keys} if len(t) else {}
    members = members[:max([v.shape[1] for v in series.values()], default=len(members))]
    z_rms = _np(torch.stack(h["z_rms"]))[:, :MAX_LINES] if len(t) and h.get("z_rms") else None
    found = run.intervals() if hasattr(run, "intervals") else None
    res = run.residuals() if hasattr(run, "residuals") else None
    held = run.validation() if held_out and hasattr(run, "validation") and getattr(run, "validation_on", False) \
        else None
    history = getattr(run, "truth_history", None) or {}
    truth = dict(run.truth)
    scenario = run.scenario
    return RunFigureData(
        name=shown_name(scenario), batch=int(run.batch), members=members, t=t, dt=dt, series=series, z_rms=z_rms,
        units={key: scenario.unit(key) for key in keys}, y_unit=scenario.unit("y", run.settings),
        output_names=[str(n) for n in scenario.output_names(run.settings)] if hasattr(scenario, "output_names")
        else [],
        truth={k: _member_values(v, members) for k, v in truth.items()},
        truth_path={k: _truth_path(pairs, t) for k, pairs in history.items() if pairs and len(t)},
        truth_now={k: _member_values(v, members) for k, v in (run.truth_now() if hasattr(run, "truth_now")
                                                               else truth).items()},
        changes=sorted({x for pairs in history.values() for x, _ in pairs[1:]}),
        initial=_initial(run, members), alarms=_alarms(run.graph, members),
        intervals=_intervals(run, found, members, dt) if found is not None else None,
        band=_band(run, t, members), held_out=None if held is None else
        (float(held.rmse_initial[0]), float(held.rmse[0])),
        trace=_trace(held, res), residuals=_residuals(run, res) if res is not None else None,
        only=None if only is None else tuple(only))


def _np(t) -> np.ndarray:
    return t.detach().cpu().numpy() if hasattr(t, "detach") else np.asarray(t)


def shown_name(scenario) -> str:
    """The name a scenario (or figure data) shows in figures: ``figure_name`` where it has one (a graph built in
    Python: the name ``rcotorch.refine`` was given, else its output folder's; '' for neither), else its name."""
    name = getattr(scenario, "figure_name", None)
    if name is None:
        name = getattr(scenario, "name", "") or ""
    return str(name)


def _member_values(value, members: list[int]):
    """A truth as drawn: a shared number as it is, a per-member one as the drawn members' values."""
    if value is None:
        return None
    values = np.atleast_1d(np.asarray(_np(value), dtype=float))
    if values.size > 1:
        return values[[b for b in members if b < values.size]]
    return values


def _truth_path(pairs, t: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """A truth that changes as it was at the run's start, at each change within the logged times and at the end."""
    from .scenario import truth_at
    times = [x for x, _ in pairs if t[0] < x < t[-1]]
    xs = np.r_[t[0], times, t[-1]]
    return xs, [float(truth_at(pairs, x)) for x in xs]


def _initial(run, members: list[int]) -> dict[str, np.ndarray]:
    monitor = getattr(run, "monitor", None)
    if monitor is None or not monitor.initial:
        return {}
    return {k: _np(v).reshape(-1)[[b for b in members if b < v.numel()]] for k, v in monitor.initial.items()}


def _alarms(graph, members: list[int]) -> dict[str, np.ndarray]:
    from ..estimator.tracking import change_report
    out = {}
    for name, found in change_report(graph).items():
        first = _np(found["first_alarm_step"]).reshape(-1)
        out[name] = np.array([first[b] if b < len(first) else -1 for b in members])
    return out


def _intervals(run, found, members: list[int], dt) -> IntervalData:
    data = IntervalData(level=float(found.level), window_start=run.health.window_start * (dt or 1.0),
                        estimate={}, lower={}, upper={}, below={}, above={})
    for key in found.estimate:
        idx = [b for b in members if b < found.half_width[key].shape[0]]
        data.estimate[key] = _np(found.estimate[key])[idx]
        data.lower[key] = _np(found.lower(key))[idx]
        data.upper[key] = _np(found.upper(key))[idx]
        below, above = found.side_ratios(key)
        data.below[key], data.above[key] = _np(below)[idx], _np(above)[idx]
        bias = (found.bias or {}).get(key)
        if bias is not None:
            data.bias[key] = _np(bias)[idx]
    return data


def _band(run, t: np.ndarray, members: list[int]) -> dict[str, np.ndarray] | None:
    over = run.band_over_time() if hasattr(run, "band_over_time") else None
    if over is None or len(over[0]) != len(t):
        return None
    return {key: _np(hw)[:, :len(members)] for key, hw in over[1].items()}


def _trace(held, res):
    """(where, sample indices, z of the initial model, z of the refined one, the number of outputs) for member 0,
    output 0: on the held-out data where the run validated its model (after the samples that fixed the initial
    state), else on the replayed window (its last ``TRACE`` samples); None without either."""
    if held is not None:
        y = _np(held.measured[held.fit_steps:, 0, 0])
        return ("held-out data", np.arange(len(y)), y - _np(held.initial[held.fit_steps:, 0, 0]),
                y - _np(held.refined[held.fit_steps:, 0, 0]), int(held.measured.shape[-1]))
    if res is None:
        return None
    y = _np(res.series["measured"][:, 0, 0])
    n = min(len(y), TRACE)
    return ("replayed window", np.arange(len(y))[-n:], y[-n:] - _np(res.series["initial"][-n:, 0, 0]),
            y[-n:] - _np(res.series["refined"][-n:, 0, 0]), int(res.series["measured"].shape[-1]))


def _residuals(run, res) -> ResidualData:
    from ..verdict import intervals as ci
    return ResidualData(
        autocorr=_np(res.autocorr[0]), xcorr=None if res.xcorr is None else _np(res.xcorr[0]),
        bound=float(res.bound), steps=int(res.steps), fit=float(res.fit[0]), fit_initial=float(res.fit_initial[0]),
        measured=_np(res.series["measured"][:, 0]), refined=_np(res.series["refined"][:, 0]),
        initial=_np(res.series["initial"][:, 0]), verdict=residual_verdict(run, res), lags=ci.LAGS,
        samples_per_lag=ci.SAMPLES_PER_LAG)


def residual_verdict(run, res) -> str:
    """What the whiteness test of member 0's residuals says, and whether it matters for the estimates
    (``rcotorch.verdict.intervals.residuals_matter``, as ``health.residuals_matter`` of summary.json): white; or
    not white, and then either dynamics the model leaves unexplained that bias the estimates or widen their
    intervals, or a correlation that does not matter (a parameter error the model can take back, as a noise-free
    run still converging leaves, or one that hardly widens the intervals)."""
    from ..verdict import intervals as ci
    p = float(res.whiteness_p[0])
    if not np.isfinite(p):
        return (f"z's whiteness is not tested: the window held {res.steps} steps, fewer than "
                f"{ci.SAMPLES_PER_LAG} for a lag")
    test = f"Ljung-Box p = {p:.2g}"
    if p >= ci.WHITE_P:
        return f"z is white ({test})"
    graph = getattr(run, "graph", None)
    pc = getattr(graph.role("estimator"), "covariance", None) if graph is not None and "estimator" in graph.roles \
        else None
    found = run.intervals() if hasattr(run, "intervals") else None
    if not isinstance(pc, ci.ParameterCovariance) or found is None:
        return f"z is not white ({test})"
    matter, widening = ci.residuals_matter(pc, found)
    w = float(widening[0])
    if bool(matter[0]):
        return (f"z is not white ({test}), and it matters: dynamics the model leaves unexplained bias the "
                f"estimates or widen their intervals ({w:.3g} times)")
    unexplained = float(pc.unexplained[0]) if pc.unexplained is not None else 1.0
    if unexplained < ci.UNEXPLAINED_MIN:
        return (f"z is not white ({test}), which does not matter here: it is a parameter error the model can "
                f"take back (it leaves {unexplained:.2g} of z's energy unexplained)")
    return (f"z is not white ({test}), which does not matter here: its correlation widens the intervals "
            f"{_below(w, ci.WIDENING_MATTERS)} times (less than {ci.WIDENING_MATTERS:g}) and biases no estimate "
            "beyond its interval")


def _below(value: float, limit: float) -> str:
    """``value`` (below ``limit``) to three significant digits, or to as many more as keep it below the limit."""
    for digits in range(3, 10):
        text = f"{value:.{digits}g}"
        if float(text) < limit:
            return text
    return f"{value:.10g}"
