"""Matplotlib figures of a run: estimates vs time with the truth, model error of the initial and the refined
model, residual checks, frequency responses; a sweep's estimates and errors against its swept settings; PNG
bytes of figures, drawn on a second thread where the caller has other work meanwhile (or in the process
``rcotorch.run.drawing`` starts beside a run), and on every core the process may use. A run's figures are drawn
from its figure data (``rcotorch.run.figure_data``: NumPy arrays and text), so that this module imports no torch.

Conventions of every figure here: the truth is drawn dashed in black on top of everything else (so that it stays
visible where an estimate covers it), the initial model dotted in grey below the estimates; legends sit below the
axes, outside them, so that they never cover a curve. Where the estimates settle early (they move little in the
second half of the run) and the run spans two decades of logged times or more, the time axis is logarithmic, so
that the transient and the end are both visible. Titles start with the name the run shows (``_named``) and are
broken into lines that fit the figure; each measured output is drawn under its name (``output_names``).

The figures are made with matplotlib's ``Figure`` (Agg), not pyplot: pyplot keeps one list of open figures
for the whole process, so only figures made without it can be drawn off the main thread.
"""

from __future__ import annotations

import dataclasses
import gc
import io
import os
import pickle
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.backend_bases import FigureCanvasBase  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.font_manager import FontProperties  # noqa: E402
from matplotlib.layout_engine import ConstrainedLayoutEngine  # noqa: E402
from matplotlib.ticker import Formatter, NullLocator  # noqa: E402

from .figure_data import (  # noqa: E402
    MAX_LINES,
    RUN_FIGURES,
    TRACE,
    SweepFigureData,
    shown_name,
    sweep_figure_data,
)

DPI = 110
TRUTH_STYLE = dict(color="k", ls="--", lw=1.4, zorder=6)              # on top of every estimate
INITIAL_STYLE = dict(color="tab:gray", ls=":", lw=1.3, zorder=1.5)     # below the estimates
CHANGE_STYLE = dict(color="tab:brown", ls="-.", lw=1.2, zorder=4)       # a change of the truth
# a change detector's first alarm: above the change's line (they are often close) and the truth, marked by a
# triangle at the top of the panel so that an alarm just after the change still shows
DETECTION_STYLE = dict(color="tab:red", ls=":", lw=1.6, zorder=7)
LATE_MOVE = 0.2        # the estimates settled early: they move less than this share of their range in the 2nd half
EARLY = 0.02           # on a linear time axis, the first share of the run whose values may fall outside the y-axis
FOCUS = 3.0            # ... where the paths' whole range is more than this many times their range after it
STATUS_COLOURS = {"converged": "tab:green", "undetermined": "tab:purple", "biased": "tab:brown",
                  "not_converged": "tab:orange",
                  "diverged": "tab:red", "finished": "tab:gray"}
MAX_CATEGORIES = 12    # a sweep's numeric setting with at most this many values may be drawn as categories
CROWDED = 0.5          # ... when two neighbours lie closer than this share of the mean spacing
TITLE_MARGIN = 90.0    # points of a figure's width beside an axes' title: its tick labels and y label
TITLE_OVERHANG = 60.0  # points by which a title may be wider than its axes (over their tick labels)
_MEASURE_LOCK = threading.Lock()


def figures_of(data) -> dict:
    """The figures of figure data: a sweep's (``SweepFigureData``: ``sweep_figures``) or a run's
    (``rcotorch.run.figure_data.RunFigureData``: ``run_figures``)."""
    return sweep_figures(data) if isinstance(data, SweepFigureData) else run_figures(data)


def run_figures(data) -> dict:
    """Estimates against time (one row per estimate: the traced members' paths up to ``MAX_LINES``, the truth
    dashed on top, the initial model's value dotted; beside it the convergence window with the final
    intervals) and the model error: the rms of z over each log interval, and z of the initial model beside the
    refined one's on held-out data (or on the replayed window), with units and legends below the axes.
    ``data``: the run's figure data (``rcotorch.run.figure_data.run_figure_data``), or a run, whose data are
    taken then; where the data name the figures to draw (``only``), those of them the run has."""
    if not hasattr(data, "series"):
        from .figure_data import run_figure_data
        data = run_figure_data(data)
    d = data

    def wanted(name: str) -> bool:
        return d.only is None or name in d.only
    t = d.t
    xlabel = "time [s]" if d.dt else "step"
    figs = {}
    keys = list(d.series)
    log_t = not d.changes and log_time_axis(t, d.series.values())          # a run with a change: linear time
    if keys and len(t) and wanted("estimates"):
        found = d.intervals
        start = found.window_start if found is not None else None
        zoom = found is not None and bool((t >= start).sum() >= 2)
        fig = Figure(figsize=(10.5 if zoom else 7.5, 2.3 * len(keys) + 1.2), layout="constrained")
        axes = fig.subplots(len(keys), 2 if zoom else 1, sharex="col", squeeze=False,
                            gridspec_kw={"width_ratios": [2.4, 1]} if zoom else None)
        for row, key in zip(axes, keys):
            v = d.series[key]
            _estimate_panel(row[0], d, key, t, v)
            if log_t:
                row[0].set_xscale("log")
            else:
                _focus_after_start(row[0], d, key, t, v)
            if zoom:
                _window_panel(row[1], d, key, t[t >= start], v[t >= start])
        axes[-1, 0].set_xlabel(xlabel + (", log scale" if log_t else ""))
        shown = _members_shown(len(d.members), d.batch)
        _title(axes[0, 0], _named(d, f"estimates{shown}"))
        if zoom:
            axes[-1, 1].set_xlabel(xlabel)
            _title(axes[0, 1], f"window: final {found.level:.0%} intervals")
        _legend_below(fig, axes[0, 0], more=list(axes.flat[1:]))
        figs["estimates"] = fig
    if len(t) and d.z_rms is not None and wanted("model_error"):
        figs["model_error"] = _model_error_figure(d, xlabel, log_t)
    if d.residuals is not None and (wanted("residuals") or wanted("output_fit")):
        figs.update({name: fig for name, fig in residual_figures(d).items() if wanted(name)})
    return figs


def log_time_axis(t: np.ndarray, series) -> bool:
    """Whether a time axis should be logarithmic: the logged times span two decades or more, and every series
    (T, ...) moved by less than ``LATE_MOVE`` of its whole range in the second half of the run (it settled
    early; a change in the second half, as in a tracking run, keeps the axis linear)."""
    if len(t) < 3 or not t[0] > 0 or t[-1] / t[0] < 100:
        return False
    late = t >= t[-1] / 2
    for v in series:
        v = np.asarray(v, dtype=float)
        whole = np.nanmax(v, axis=0) - np.nanmin(v, axis=0) if np.isfinite(v).any() else np.zeros(1)
        tail = v[late]
        moved = np.nanmax(tail, axis=0) - np.nanmin(tail, axis=0) if np.isfinite(tail).any() else np.zeros(1)
        with np.errstate(invalid="ignore"):
            if np.any(moved > LATE_MOVE * whole):
                return False
    return True


def _model_error_figure(d, xlabel: str, log_t: bool) -> Figure:
    """The rms of z over each log interval (with the held-out rms of the initial and the refined model where
    the run validated them), and z of the initial and the refined model side by side on held-out data (else
    on the replayed window), member 0."""
    t = d.t
    trace = d.trace
    fig = Figure(figsize=(7.5, 6.4 if trace else 3.4), layout="constrained")
    # a panel per subfigure, each with its legend below it, for which the layout makes room
    parts = fig.subfigures(2, 1, height_ratios=[1.35, 1.0]) if trace else [fig]
    axes = [part.subplots() for part in parts]
    ax = axes[0]
    z = d.z_rms
    labels = ["refined model, during the run"] if z.shape[1] == 1 else [f"member {b}" for b in d.members[:z.shape[1]]]
    ax.semilogy(t, z, lw=1, label=labels)
    _change_marks(ax, d, t)
    if d.held_out is not None:
        ax.axhline(d.held_out[0], **INITIAL_STYLE, label="initial model, held-out data (member 0)")
        ax.axhline(d.held_out[1], color="tab:red", ls="-.", lw=1.3, zorder=5,
                   label="refined model, held-out data (member 0)")
    if log_t:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel + (", log scale" if log_t else ""))
    y_unit = d.y_unit
    ax.set_ylabel(_with_unit("rms of z = y - y_hat", y_unit))
    shown = _members_shown(len(d.members), d.batch)
    _title(ax, _named(d, f"model error (rms over each log interval){shown}"))
    ax.grid(alpha=0.3, which="both")
    _legend_below(parts[0], ax)
    if trace:
        where, k, z_init, z_ref, n_y = trace
        ax = axes[1]
        x = k * (d.dt or 1.0)
        rms = [f"rms {float(np.sqrt(np.mean(v ** 2))):.3g} {y_unit}".rstrip() for v in (z_init, z_ref)]
        ax.plot(x, z_init, color="tab:gray", lw=1.0, label=f"initial model ({rms[0]})")
        ax.plot(x, z_ref, color="tab:red", lw=1.0, zorder=3, label=f"refined model ({rms[1]})")
        ax.set_xlabel(("time" if d.dt else "samples") + f" into the {where}" + (" [s]" if d.dt else ""))
        ax.set_ylabel(_with_unit("z = y - y_hat", y_unit))
        output = f", output {output_names(d, n_y)[0]}" if n_y > 1 else ""
        _title(ax, f"z of the initial and the refined model on the {where}, member 0{output}")
        ax.grid(alpha=0.3)
        _legend_below(parts[1], ax)
    return fig


def residual_figures(d) -> dict:
    """The refined model checked on the replayed window (member 0): z's autocorrelation and its
    cross-correlation with w against the 95% band of white, independent signals, one line per measured output
    (named, ``output_names``), under a line that says how small z is against the measured output and whether
    its correlation matters for the estimates (``rcotorch.run.figure_data.residual_verdict``); the measured
    output against the refined and the initial model's outputs, with their fit in percent, one panel per output.
    ``d``: the run's figure data (``rcotorch.run.figure_data.run_figure_data``) with its residual checks."""
    figs = {}
    res, dt = d.residuals, d.dt
    lags = np.arange(res.autocorr.shape[0])
    y, refined, initial = res.measured, res.refined, res.initial                 # (T, n_y), member 0
    names = output_names(d, y.shape[1])
    y_unit = d.y_unit
    z_rms, y_rms = _rms(y - refined), _rms(y)
    n_panels = 2 if res.xcorr is not None else 1
    fig = Figure(figsize=(7.5, 2.6 * n_panels + 1.5), layout="constrained")
    axes = fig.subplots(n_panels, 1, squeeze=False)[:, 0]
    ax = axes[0]
    auto = res.autocorr                                                # (L + 1, n_z)
    several = auto.shape[1] > 1
    for c in range(auto.shape[1]):
        label = f"z of {names[c]} (rms {_share(z_rms[c], y_rms[c])} of the output's)" if several else "z"
        ax.plot(lags[1:], auto[1:, c], "o-", ms=3, lw=1, label=label)
    tested = len(lags) > 1                       # a window too short for a lag tests none
    if tested:
        ax.axhspan(-res.bound, res.bound, color="tab:blue", alpha=0.15, label="95% band of white noise")
    else:
        _untested(ax, res)
    ax.set_xlabel("lag [samples]")
    ax.set_ylabel("autocorrelation")
    if several:
        size = f"z rms at most {_share(float(np.max(z_rms / np.maximum(y_rms, 1e-300))), 1.0)} of its output's rms"
    else:
        size = f"z rms {z_rms[0]:.2g}{' ' + y_unit if y_unit else ''}, {_share(z_rms[0], y_rms[0])} of y's rms"
    fig.suptitle(_wrap(_named(d, "residual z = y - y_hat of the refined model, member 0"),
                       fig.get_figwidth() * 72.0 - 20, 12.0), fontsize=12)
    _title(ax, f"{size}; {res.verdict}", fontsize=9)
    ax.grid(alpha=0.3)
    _legend_below(fig, ax, axes=ax)
    if res.xcorr is not None:
        ax = axes[1]
        x = res.xcorr                                                   # (L + 1, n_z, n_w)
        for c in range(x.shape[1]):
            for j in range(x.shape[2]):
                w = f"w[{j}]" if x.shape[2] > 1 else "w"
                ax.plot(lags, x[:, c, j], "o-", ms=3, lw=1, label=f"z of {names[c]}, {w}" if x.shape[1] * x.shape[2] > 1
                        else "z(k), w(k - lag)")
        if tested:
            ax.axhspan(-res.bound, res.bound, color="tab:blue", alpha=0.15, label="95% band of independence")
        else:
            _untested(ax, res)
        ax.set_xlabel("lag [samples]")
        ax.set_ylabel("cross-correlation")
        ax.grid(alpha=0.3)
        _legend_below(fig, ax, axes=ax)
    figs["residuals"] = fig
    n = min(len(y), TRACE)                                        # the last samples of the window
    t = (np.arange(len(y)) - len(y) + 1) * (dt or 1.0)            # 0 at the window's end
    n_y = y.shape[1]
    fig = Figure(figsize=(7.5, 3.8 if n_y == 1 else 2.4 * n_y + 1.4), layout="constrained")
    axes = fig.subplots(n_y, 1, sharex=True, squeeze=False)[:, 0]
    fits = [(res.fit, res.fit_initial)] if n_y == 1 else \
        [(_fit(y[:, c], refined[:, c]), _fit(y[:, c], initial[:, c])) for c in range(n_y)]
    for c, (ax, (fit, fit_initial)) in enumerate(zip(axes, fits)):
        ax.plot(t[-n:], y[-n:, c], color="k", lw=1.6, label="measured", zorder=2)
        ax.plot(t[-n:], initial[-n:, c], color="tab:gray", ls=":", lw=1.3, zorder=3,
                label="initial model" + (f" (fit {fit_initial:.1f}%)" if n_y == 1 else ""))
        ax.plot(t[-n:], refined[-n:, c], color="tab:orange", ls="--", lw=1.2, zorder=4,
                label="refined model" + (f" (fit {fit:.1f}%)" if n_y == 1 else ""))
        ax.set_ylabel(_with_unit(names[c], y_unit))
        ax.grid(alpha=0.3)
        if n_y > 1:
            _title(ax, f"{names[c]}: fit {fit:.1f}% (initial model {fit_initial:.1f}%)", fontsize=9)
    axes[-1].set_xlabel("time before the window's end [s]" if dt else "steps before the window's end")
    what = "measured and model outputs, member 0 (theta frozen)"
    if n_y == 1:
        _title(axes[0], _named(d, what))
    else:
        fig.suptitle(_wrap(_named(d, what), fig.get_figwidth() * 72.0 - 20, 12.0), fontsize=12)
    _legend_below(fig, axes[0])
    figs["output_fit"] = fig
    return figs


def _untested(ax, res) -> None:
    """A correlation panel of a window too short for a lag: what it would show, and why it shows nothing."""
    ax.set_xlim(0, res.lags)
    ax.set_ylim(-1.05, 1.05)
    ax.text(0.5, 0.5, f"not tested: the window held {res.steps} steps, {res.samples_per_lag} per lag are needed",
            transform=ax.transAxes, ha="center", va="center", fontsize=9, color="tab:gray")


def output_names(d, n: int) -> list[str]:
    """The names of a run's ``n`` measured outputs: the scenario's (``Scenario.output_names``, as the figure data
    ``d`` hold them), else 'y' for one and 'y[0]', 'y[1]', ... for several (the channels of the known model's
    measured port)."""
    names = list(d.output_names)
    if len(names) == n:
        return [str(name) for name in names]
    return ["y"] if n == 1 else [f"y[{c}]" for c in range(n)]


def _rms(v: np.ndarray) -> np.ndarray:
    """The rms of each column of ``v`` (T, n)."""
    return np.sqrt(np.mean(np.asarray(v, dtype=float) ** 2, axis=0))


def _share(part: float, whole: float) -> str:
    """``part`` in percent of ``whole``, to two significant digits ('0.046 %')."""
    return f"{100.0 * part / whole:.2g} %" if whole > 0 else "-"


def _fit(y: np.ndarray, y_hat: np.ndarray) -> float:
    """The fit of a model output in percent: 100 (1 - |y - y_hat| / |y - mean y|)."""
    spread = float(np.linalg.norm(y - y.mean()))
    return 100.0 * (1.0 - float(np.linalg.norm(y - y_hat)) / spread) if spread > 0 else float("nan")


def _estimate_panel(ax, d, key: str, t: np.ndarray, v: np.ndarray) -> None:
    """One estimate against time: the drawn members, the truth on top and the initial model's value below."""
    members = d.members
    lines = v[:, :MAX_LINES]
    labels = ["estimate"] if lines.shape[1] == 1 else [f"member {b}" for b in members[:lines.shape[1]]]
    ax.plot(t, lines, lw=1.2, label=labels, zorder=2)
    found = d.intervals
    if d.band is not None and key in d.band:           # the band over time, in each colour
        hw = d.band[key][:, :lines.shape[1]]
        below, above = np.ones(hw.shape[1]), np.ones(hw.shape[1])
        if found is not None and key in found.estimate:     # each side as the final interval's
            n = min(hw.shape[1], len(found.below[key]))
            below[:n], above[:n] = found.below[key][:n], found.above[key][:n]
        finite = lines[np.isfinite(lines)]
        span = float(np.ptp(finite)) if finite.size else 0.0
        low, high = (finite.min() - 0.25 * span, finite.max() + 0.25 * span) if span > 0 else (-np.inf, np.inf)
        for i in range(hw.shape[1]):               # clipped near the paths: a restarted P's band is far wider
            ax.fill_between(t, np.clip(lines[:, i] - hw[:, i] * below[i], low, high),
                            np.clip(lines[:, i] + hw[:, i] * above[i], low, high),
                            color=f"C{i}", alpha=0.18, lw=0, zorder=1,
                            label=f"{found.level:.0%} band over time" if i == 0 and found is not None else None)
    if found is not None and key in found.estimate and len(t):
        est = found.estimate[key][:lines.shape[1]]
        lower, upper = found.lower[key][:len(est)], found.upper[key][:len(est)]   # need not hold the estimate
        ax.errorbar(np.full(len(est), t[-1]), (lower + upper) / 2, yerr=(upper - lower) / 2, fmt="none", ecolor="k",
                    elinewidth=1.5, capsize=4, zorder=4, label=f"{found.level:.0%} interval at the end")
        bias = found.bias.get(key)
        if bias is not None:                   # a biased estimate: where the physics' parameter lies
            b = bias[:len(est)]
            shown = np.isfinite(b)
            if shown.any():
                ax.plot(np.full(int(shown.sum()), t[-1]), (est - b)[shown], ls="none", marker="x", ms=8, mew=2,
                        color=STATUS_COLOURS["biased"], zorder=5, label="estimate - bias (biased)")
    truth = d.truth.get(key)
    path = d.truth_path.get(key)
    if path is not None and len(t):              # a truth that changes: as it was at each time
        ax.step(path[0], path[1], where="post", **TRUTH_STYLE, label="truth")
    elif truth is not None:
        values = np.atleast_1d(np.asarray(truth, dtype=float))
        for i, tv in enumerate(np.unique(values[np.isfinite(values)])[:MAX_LINES]):
            ax.axhline(tv, **TRUTH_STYLE, label="truth" if i == 0 else None)
    _change_marks(ax, d, t)
    initial = d.initial.get(key)
    if initial is not None:
        for i, iv in enumerate(np.unique(initial)[:MAX_LINES]):
            ax.axhline(iv, **INITIAL_STYLE, label="initial model" if i == 0 else None)
    ax.set_ylabel(_with_unit(key, d.units.get(key, "")))
    ax.grid(alpha=0.3, which="both")


def _focus_after_start(ax, d, key: str, t: np.ndarray, v: np.ndarray) -> None:
    """On a linear time axis, the y-axis fitted to the paths after the first ``EARLY`` of the run (with the
    truth and the final intervals) where the first steps' values, the estimate's jumps before it has data, would
    squeeze everything after them into a sliver; the axis says so."""
    lines = np.asarray(v[:, :MAX_LINES], dtype=float)
    late = t >= t[0] + EARLY * (t[-1] - t[0])
    every, after = lines[np.isfinite(lines)], lines[late][np.isfinite(lines[late])]
    if not after.size or not every.size:
        return
    truth = d.truth.get(key)
    extra = [x for x in np.atleast_1d(np.asarray([] if truth is None else truth, dtype=float)) if np.isfinite(x)]
    path = d.truth_path.get(key)
    extra += [float(value) for value in (path[1] if path is not None else [])]
    found = d.intervals
    if found is not None and key in found.estimate:
        for b in (found.lower[key], found.upper[key]):
            extra += [float(x) for x in b[np.isfinite(b)][:MAX_LINES]]
    low, high = min(after.min(), *extra) if extra else after.min(), max(after.max(), *extra) if extra else after.max()
    span = high - low if high > low else max(abs(high), 1e-12)
    if np.ptp(every) <= FOCUS * span:
        return
    ax.set_ylim(low - 0.15 * span, high + 0.15 * span)
    unit = " s" if d.dt else " steps"
    ax.text(0.01, 0.97, f"values before {t[0] + EARLY * (t[-1] - t[0]):.3g}{unit} off the axis",
            transform=ax.transAxes, ha="left", va="top", fontsize=7, color="0.35")


def _change_marks(ax, d, t: np.ndarray) -> None:
    """Vertical lines at each change of a truth (``Scenario.truth_history``) and at each drawn member's first
    alarm of a change detector (``rcotorch.estimator.tracking.change_report``), within the plotted times."""
    if not len(t):
        return
    for i, x in enumerate(c for c in d.changes if t[0] <= c <= t[-1]):
        ax.axvline(x, **CHANGE_STYLE, label="change" if i == 0 else None)
    labelled = False
    for name, first in d.alarms.items():
        for step in first[:MAX_LINES]:
            if step >= 0:
                x = step * (d.dt or 1.0)
                if t[0] <= x <= t[-1]:
                    ax.axvline(x, **DETECTION_STYLE, label=None if labelled else f"{name}: first alarm")
                    ax.plot([x], [1.0], marker="v", ms=7, color=DETECTION_STYLE["color"], clip_on=False,
                            transform=ax.get_xaxis_transform(), zorder=8)
                    labelled = True


def _window_panel(ax, d, key: str, t: np.ndarray, v: np.ndarray) -> None:
    """The convergence window of one estimate, zoomed: each drawn member's path and its final interval shaded
    in its colour, the truth on top."""
    lines = ax.plot(t, v[:, :MAX_LINES], lw=1.2, zorder=2)
    found = d.intervals
    if key in found.estimate:
        lo, hi = found.lower[key], found.upper[key]
        for i, line in enumerate(lines[:len(lo)]):
            if np.isfinite(lo[i]) and np.isfinite(hi[i]):
                ax.axhspan(lo[i], hi[i], color=line.get_color(), alpha=0.18, lw=0, zorder=1)
        bias = found.bias.get(key)
        if bias is not None:                   # a biased member: the physics' parameter, estimate - bias
            est = found.estimate[key]
            shown = [i for i in range(min(len(lines), len(bias))) if np.isfinite(bias[i])]
            for j, i in enumerate(shown):
                ax.axhline(est[i] - bias[i], color=STATUS_COLOURS["biased"], ls="--", lw=1.2, zorder=3,
                           label="estimate - bias (biased)" if j == 0 else None)
    truth = d.truth_now.get(key)
    if truth is not None:
        values = np.atleast_1d(np.asarray(truth, dtype=float))
        for tv in np.unique(values[np.isfinite(values)])[:MAX_LINES]:
            ax.axhline(tv, **TRUTH_STYLE)
    ax.grid(alpha=0.3)
    ax.ticklabel_format(axis="y", useOffset=False)


def _members_shown(n: int, batch: int) -> str:
    return f" ({n} of {batch} members)" if batch > n else ""


def _legend_below(fig, ax, axes=None, more=()) -> None:
    """A legend of ``ax``'s labelled artists (and those of the axes ``more`` whose labels ``ax`` lacks) below the
    figure (or, with ``axes``, below those axes), outside them, in as many columns as fit."""
    handles, labels = ax.get_legend_handles_labels()
    for other in more:
        for h, label in zip(*other.get_legend_handles_labels()):
            if label not in labels:
                handles.append(h)
                labels.append(label)
    if not handles:
        return
    ncol = min(len(handles), 4 if max(len(s) for s in labels) < 28 else 2)
    if axes is None:
        fig.legend(handles, labels, loc="outside lower center", ncol=ncol, fontsize=8, frameon=False)
    else:
        axes.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.22), ncol=ncol, fontsize=8,
                    frameon=False)


def _title(ax, text: str, fontsize: float | None = None) -> None:
    """A title on the axes' top edge (where matplotlib puts it on axes without tick labels above them, which it
    would otherwise confirm by laying out every tick label of the figure once more), broken into lines that fit
    the axes' width, so that no title runs off the figure."""
    size = FontProperties(size=fontsize or matplotlib.rcParams["axes.titlesize"]).get_size_in_points()
    fig = ax.get_figure()
    if not hasattr(fig, "get_figwidth"):              # a subfigure: the figure it belongs to
        fig = fig.figure
    wide = fig.get_figwidth() * 72.0
    # the axes' width once laid out (about its width before the layout over the default subplot share, 0.775)
    # and a little beyond its edges, within the figure less the room of the tick labels and the y label
    width = min(ax.get_position().width * wide / 0.775 + TITLE_OVERHANG, wide - TITLE_MARGIN)
    ax.set_title(_wrap(text, width, size), y=1.0, fontsize=size)


def _wrap(text: str, width: float, size: float) -> str:
    """``text`` broken at spaces into lines at most ``width`` points wide in the default font at ``size`` points
    (a word longer than that stays whole on its line); its own line breaks are kept."""
    out = []
    for paragraph in text.split("\n"):
        line = ""
        for word in paragraph.split(" "):
            longer = f"{line} {word}" if line else word
            if line and _text_width(longer, size) > width:
                out.append(line)
                line = word
            else:
                line = longer
        out.append(line)
    return "\n".join(out)


_MEASURE: list = []     # one renderer that measures text, made on first use


def _text_width(text: str, size: float) -> float:
    """The width in points of one line of text in the default font at ``size`` points."""
    with _MEASURE_LOCK:                    # figures are drawn on more than one thread
        if not _MEASURE:
            from matplotlib.backends.backend_agg import RendererAgg
            _MEASURE.append(RendererAgg(10, 10, 72))
        return _MEASURE[0].get_text_width_height_descent(text, FontProperties(size=size), ismath=False)[0]


def _with_unit(label: str, unit: str) -> str:
    return f"{label} [{unit}]" if unit else label


def _named(d, what: str) -> str:
    """A figure's title 'NAME: what', NAME being the name a run's figure data or a scenario shows in figures
    (``rcotorch.run.figure_data.shown_name``), the title ``what`` alone for none."""
    name = shown_name(d)
    return f"{name}: {what}" if name else what


def frequency_figure(omega, curves: dict, title: str, nyquist: float | None = None, unit: str = "",
                     bands: dict | None = None):
    """Bode magnitude (in ``unit``, the unit of output per unit of input) and phase of named complex responses
    {label: (F,) array}; the Nyquist frequency dotted. ``bands``: {label: (lower, upper)} magnitude bands, e.g.
    a confidence region of an identified response, shaded. A curve whose label says 'true' is drawn dashed, in
    black (a second one in grey, with longer dashes) and on top of the others, so that it stays visible where a
    refined curve covers it; the legend sits below the axes."""
    fig = Figure(figsize=(7, 6), layout="constrained")
    am, ap = fig.subplots(2, 1, sharex=True)
    for label, (lo, hi) in (bands or {}).items():
        am.fill_between(omega, np.maximum(np.asarray(lo), 1e-300), np.asarray(hi), color="tab:orange", alpha=0.25,
                        lw=0, label=label, zorder=1)
    colours = iter(["tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive",
                    "tab:cyan", "tab:red"])
    true_styles = iter([dict(color="k", dashes=(4, 3), lw=1.5), dict(color="dimgray", dashes=(8, 4), lw=1.5)])
    for label, resp in curves.items():
        resp = np.asarray(resp)
        if "true" in label.lower():
            style = dict(next(true_styles, dict(color="k", dashes=(2, 2), lw=1.5)), zorder=6)
        else:
            style = dict(color=next(colours, None), ls="-", lw=1.6, zorder=3)
        am.loglog(omega, np.abs(resp), label=label, **style)
        ap.semilogx(omega, np.degrees(np.unwrap(np.angle(resp))), label=label, **style)
    for ax in (am, ap):
        if nyquist:
            ax.axvline(nyquist, color="gray", lw=0.8, ls=":", label="Nyquist frequency" if ax is am else None)
        ax.grid(alpha=0.3, which="both")
    am.set_ylabel(_with_unit("magnitude", unit))
    ap.set_ylabel("phase [deg]")
    ap.set_xlabel("frequency [rad/s]")
    _title(am, title)
    _legend_below(fig, am)
    return fig


def sweep_figures(rows: Sequence[Mapping] | SweepFigureData, swept: Sequence[str] = (), scenario=None) -> dict:
    """The figures of a finished sweep, one per swept setting: for each estimate (the rows' ``est_<key>``
    columns) the estimate against the setting, the truth on top (``truth_<key>``, black crosses), and its
    |error| (``err_<key>``) against the setting, each member a dot coloured by its status. Where members share a
    setting's value (seeds, a grid), the median over them is drawn at each value, joined by a line, with their
    range, and the |error| panel's title names the value of the smallest median |error|. Tick labels write each
    value in full (no offset above the axis). ``rows``: the sweep's table (``rcotorch.run.sweep.run_sweep``,
    sweep.json); ``swept``: the settings to draw against (columns of the rows; numbers, or words drawn as
    categories; numbers too, where a few values crowd together, as 0.999 and 1 beside 0.99 do); ``scenario`` (a
    name or object, optional): the units of the axes. ``rows`` may instead be the figures' data
    (``rcotorch.run.figure_data.SweepFigureData``: the rows, settings, units and name), as a drawing process gets
    them. Returns {``sweep_<setting>``: Figure}."""
    d = rows if isinstance(rows, SweepFigureData) else sweep_figure_data(rows, swept, _scenario(scenario))
    rows, swept = d.rows, d.swept
    keys = list(dict.fromkeys(c[4:] for r in rows for c in r if c.startswith("est_")))
    figs = {}
    if not rows or not keys:
        return figs
    status = [str(r.get("status", "finished")) for r in rows]
    for setting in swept:
        raw = [r.get(setting) for r in rows]
        if all(v is None for v in raw):
            continue
        x, ticks = _axis_values(raw)
        groups = _groups(x)
        fig = Figure(figsize=(9, 2.4 * len(keys) + 1.2), layout="constrained")
        axes = fig.subplots(len(keys), 2, sharex=True, squeeze=False)
        for i, (row, key) in enumerate(zip(axes, keys)):
            est = _column(rows, f"est_{key}")
            truth = _column(rows, f"truth_{key}")
            err = np.abs(_column(rows, f"err_{key}"))
            unit = d.units.get(key, "")
            for name in dict.fromkeys(status):
                sel = np.array([s == name for s in status])
                colour = STATUS_COLOURS.get(name, "tab:blue")
                row[0].scatter(x[sel], est[sel], s=18, color=colour, label=name.replace("_", " "), zorder=3)
                row[1].scatter(x[sel], err[sel], s=18, color=colour, zorder=3)
            if np.isfinite(truth).any():
                row[0].scatter(x, truth, marker="x", s=40, color="k", lw=1.3, zorder=6, label="truth")
            row[0].set_ylabel(_with_unit(key, unit))
            row[1].set_ylabel(_with_unit(f"|error| of {key}", unit))
            positive = err[np.isfinite(err)]
            if positive.size and (positive > 0).all() and positive.max() / positive.min() > 100:
                row[1].set_yscale("log")
            best = None
            if groups:
                _median_and_range(row[0], groups, est)
                medians = _median_and_range(row[1], groups, err)
                if np.isfinite(medians).any():
                    best = int(np.nanargmin(medians))
                    row[1].plot([groups[best][0]], [medians[best]], ls="none", marker="*", ms=13, mec="k",
                                mfc="gold", zorder=7, label="smallest median |error|")
            for ax in row:
                ax.grid(alpha=0.3, which="both")
                for axis in (ax.xaxis, ax.yaxis):              # a log axis keeps its powers of ten
                    if axis.get_scale() == "linear":
                        axis.set_major_formatter(FullTicks())
            head = "|estimate - truth|" if i == 0 else f"|error| of {key}"
            if best is not None:
                value = ticks[int(groups[best][0])] if ticks is not None else _value_text(groups[best][0])
                head += f": smallest median at {setting} = {value}"
            _title(row[1], head, fontsize=10)
        s_unit = d.units.get(setting, "")
        for ax in axes[-1]:
            ax.set_xlabel(_with_unit(setting, s_unit))
            if ticks is not None:
                ax.set_xticks(range(len(ticks)), ticks)
            elif _log_spread(x):
                ax.set_xscale("log")
        _title(axes[0, 0], _named(d, f"estimates against {setting} ({len(rows)} members)"))
        _legend_below(fig, axes[0, 0], more=list(axes.flat[1:]))
        figs[f"sweep_{setting}"] = fig
    return figs


class FullTicks(Formatter):
    """Tick labels that each write their value in full ('0.50001', '1.5e-05'), to as many significant digits as
    the ticks' spacing needs: no offset or multiplier above the axis (matplotlib's '1e-5+5e-1'), which would meet
    the title and leave the values to be added up."""

    ticks: Sequence[float] = ()

    def set_locs(self, locs) -> None:
        """Keep the ticks' positions: their spacing sets the digits."""
        self.ticks = list(locs)
        super().set_locs(locs)

    def __call__(self, x, pos=None) -> str:
        locs = np.asarray(self.ticks, dtype=float)
        locs = np.unique(locs[np.isfinite(locs)])
        step = float(np.min(np.diff(locs))) if len(locs) > 1 else abs(float(x)) or 1.0
        if not np.isfinite(x):
            return ""
        if step <= 0 or abs(x) < 1e-9 * step:
            return "0"
        # the spacing's own significant digits (1 for 0.002, 2 for 0.0025), then those of x down to its last one
        own = next((n for n in range(1, 16) if abs(float(f"{step:.{n}g}") - step) <= 1e-9 * step), 15)
        power = int(np.floor(np.log10(abs(x))))
        digits = power - int(np.floor(np.log10(step))) + own
        if 0 <= power < 5:                      # every digit before the point: '10', '20', not '1e+01'
            digits = max(digits, power + 1)
        return f"{x:.{min(max(digits, 1), 15)}g}"


def _groups(x: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """(value, the members' indices) of each distinct finite position, in order, where members share one (a
    value drawn more than once); [] where every member has a value of its own (nothing to take a median of)."""
    finite = np.isfinite(x)
    values = np.unique(x[finite])
    if len(values) == int(finite.sum()):
        return []
    return [(float(v), np.flatnonzero(x == v)) for v in values]


def _median_and_range(ax, groups, y: np.ndarray) -> np.ndarray:
    """The median of ``y`` over the members at each value of ``groups`` (``_groups``), drawn as a line through the
    values with the range of the members' values as a bar at each; returns the medians (NaN where none is
    finite)."""
    medians = np.full(len(groups), np.nan)
    bars = []                                      # (value, lowest, highest): one collection for every bar
    for i, (value, idx) in enumerate(groups):
        v = y[idx][np.isfinite(y[idx])]
        if v.size:
            medians[i] = float(np.median(v))
            bars.append((value, v.min(), v.max()))
    if bars:
        at, low, high = np.array(bars).T
        ax.vlines(at, low, high, color="tab:blue", lw=5, alpha=0.2, zorder=2, label="range over members")
    xs = np.array([g[0] for g in groups])
    shown = np.isfinite(medians)
    ax.plot(xs[shown], medians[shown], color="tab:blue", lw=1.2, marker="_", ms=16, mew=2, zorder=4,
            label="median over members")
    return medians


def _value_text(v: float) -> str:
    """A setting's value as a label: '0.999', '1', '1e+06'."""
    return f"{v:.6g}"


def _column(rows: Sequence[Mapping], name: str) -> np.ndarray:
    """A column of the rows as floats (NaN where missing or not a number)."""
    out = np.full(len(rows), np.nan)
    for i, r in enumerate(rows):
        v = r.get(name)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            out[i] = v
    return out


def _axis_values(raw: list) -> tuple[np.ndarray, list[str] | None]:
    """Positions of a swept setting's values: the numbers themselves, or the index of each distinct value (in
    order of appearance for words or a mix, in increasing order for numbers) with those values as tick labels,
    for words and for a few numbers that would crowd each other on a linear axis (``_crowded``)."""
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in raw):
        x = np.asarray(raw, dtype=float)
        values = np.unique(x[np.isfinite(x)])
        if not _crowded(values):
            return x, None
        index = {v: i for i, v in enumerate(values)}
        return np.array([index.get(v, np.nan) for v in x], dtype=float), [_value_text(v) for v in values]
    labels = list(dict.fromkeys(str(v) for v in raw))
    return np.array([labels.index(str(v)) for v in raw], dtype=float), labels


def _crowded(values: np.ndarray) -> bool:
    """Whether a few distinct values (3 to ``MAX_CATEGORIES``; not spread over two decades, which a log axis
    shows) have two neighbours closer than ``CROWDED`` of the mean spacing: on a linear axis their members and
    medians would crowd together while the others lie far apart (lam at 0.99, 0.995, 0.999 and 1). Evenly
    spaced values stay on a linear axis."""
    if not 3 <= len(values) <= MAX_CATEGORIES or _log_spread(values):
        return False
    gaps = np.diff(values)
    return bool(gaps.min() < CROWDED * gaps.mean())


def _log_spread(x: np.ndarray) -> bool:
    x = x[np.isfinite(x)]
    return bool(x.size and (x > 0).all() and x.max() / x.min() >= 100)


def _scenario(which):
    """A scenario object from a name or object (None for None or a name no scenario has)."""
    if which is None or not isinstance(which, str):
        return which
    from ..errors import RcoError
    from . import scenario as scenarios
    try:
        return scenarios.get(which)
    except RcoError:
        return None


def png(fig) -> bytes:
    """The figure as PNG bytes at ``DPI``, laid out tightly unless it has a layout of its own (one drawing); a
    figure that pyplot made is closed (removed from pyplot's list). A figure of its own (not pyplot's) is laid out
    and drawn on one Agg canvas at ``DPI``. A constrained layout is computed before the
    drawing: it sizes the axes with the tick labels the locators pick at the axes' size before the layout. Where
    they pick other ticks at the laid-out size (-0.075 for -0.05, a wider label), the drawing lays the figure out
    again with those; where they pick the same, that second layout would change nothing and is left out."""
    if fig.canvas.manager is None and type(fig.canvas) is FigureCanvasBase:
        # laid out and drawn by one Agg renderer at the PNG's resolution: the text's extents that the layout
        # measures are those the drawing reuses, instead of being measured again by a renderer of its own
        FigureCanvasAgg(fig)
        fig.set_dpi(DPI)
    _minor_grid_as_lines(fig)
    engine = fig.get_layout_engine()
    if engine is None:
        fig.set_layout_engine("tight")             # laid out while it is drawn
    elif isinstance(engine, ConstrainedLayoutEngine):
        before = _tick_locations(fig)
        engine.execute(fig)
        if _tick_locations(fig) == before:
            fig.set_layout_engine("none")          # the layout stands as computed
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    _close(fig)
    return buf.getvalue()


def _minor_grid_as_lines(fig) -> None:
    """On a log axis spanning more than a decade (its minor ticks unlabelled), the minor grid drawn as one set of
    lines at the minor ticks' places, in their style, and no minor ticks: each tick is a handful of artists that
    the layout measures and the drawing updates, a third of a figure's time where its axes are logarithmic. Every
    axis is read before any locator is changed: axes that share an axis share its locator."""
    found = []
    for ax in fig.axes:
        for axis, transform in ((ax.xaxis, ax.get_xaxis_transform()), (ax.yaxis, ax.get_yaxis_transform())):
            if axis.get_scale() != "log" or isinstance(axis.get_minor_locator(), NullLocator):
                continue
            lo, hi = sorted(axis.get_view_interval())
            if 0 < 10 * lo < hi:
                places = [v for v in axis.get_minor_locator().tick_values(lo, hi) if lo < v < hi]
                found.append((ax, axis, transform, places, axis.get_minor_ticks(1)[0].gridline))
    for ax, axis, transform, places, grid in found:
        axis.set_minor_locator(NullLocator())
        if grid.get_visible() and places:
            ends = [[(v, 0.0), (v, 1.0)] if axis is ax.xaxis else [(0.0, v), (1.0, v)] for v in places]
            ax.add_collection(LineCollection(ends, transform=transform, colors=grid.get_color(),
                                             linewidths=grid.get_linewidth(), linestyles=grid.get_linestyle(),
                                             alpha=grid.get_alpha(), zorder=axis.get_zorder()), autolim=False)


def warm() -> None:
    """Load what the first figure drawn would load (the fonts, the parser of a log axis' labels, Agg), so that
    processes forked after it draw without loading them again."""
    fig = Figure(figsize=(1.0, 1.0))
    ax = fig.subplots()
    ax.semilogy([1.0, 2.0], [1.0, 100.0])
    ax.set_title("x")
    fig.savefig(io.BytesIO(), format="png", dpi=20)
    _text_width("x", 10.0)


def _tick_locations(fig) -> list:
    """The major and minor tick locations every axis of ``fig`` would show at its present size and limits (the
    locators alone: no tick or label is made)."""
    out = []
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_visible():
                out.append((tuple(axis.get_majorticklocs()), tuple(axis.get_minorticklocs())))
    return out


def _close(fig) -> None:
    """Remove a figure that pyplot made from pyplot's list."""
    if fig.canvas.manager is not None:
        import matplotlib.pyplot as plt
        plt.close(fig)


def draw(data) -> dict[str, bytes]:
    """{name: PNG bytes} of the figures of figure data (``figures_of``). A run's figures are shared out among the
    cores the process may use before they are made, each share made and drawn in a process of its own
    (``_drawn_in_shares``), so that making the figures is shared out as well as drawing them (a sweep's figure,
    and figures already made, go to ``pngs``)."""
    names = [] if isinstance(data, SweepFigureData) else \
        [n for n in RUN_FIGURES if data.only is None or n in data.only]
    weight = {n: 2 * max(1, len(data.series)) if n == "estimates" else 2 for n in names}   # about their axes
    shares = _shares(weight, min(len(names), _cores()))
    if len(shares) < 2:
        return pngs(figures_of(data))
    out = _drawn_in_shares([lambda share=share: figures_of(dataclasses.replace(data, only=tuple(share)))
                            for share in shares])
    return {name: out[name] for name in names if name in out}


def pngs(figs: dict) -> dict[str, bytes]:
    """{name: PNG bytes} of {name: figure}. Where the process may use more than one core (Linux), the figures
    are shared out, balanced by their number of axes, and all shares but one are drawn at once in forked
    processes (``_drawn_in_shares``); the bytes are those drawn here."""
    names = list(figs)
    shares = _shares({name: len(fig.axes) for name, fig in figs.items()}, min(len(names), _cores()))
    out = _drawn_in_shares([lambda share=share: {name: figs[name] for name in share} for share in shares])
    for name in names:
        _close(figs[name])
    return {name: out[name] for name in names}


def _drawn_in_shares(makers: list[Callable[[], dict]]) -> dict[str, bytes]:
    """{name: PNG bytes} of the figures each of ``makers`` returns ({name: figure}): the first share made and
    drawn here, each other in a forked process at the same time (``_DrawnApart``)."""
    apart = [_DrawnApart(make) for make in makers[1:]]
    out: dict[str, bytes] = {}
    try:
        if makers:
            out.update((name, png(fig)) for name, fig in makers[0]().items())
        for wait in apart:
            out.update(wait())
    finally:
        for wait in apart:
            wait.cancel()
    return out


def _cores() -> int:
    """How many cores this process may draw on at once: 1 where forking a drawing is not safe (off Linux)."""
    if not sys.platform.startswith("linux") or not hasattr(os, "fork"):
        return 1
    return len(os.sched_getaffinity(0))


def _shares(work: Mapping[str, int], n: int) -> list[list[str]]:
    """The names of ``work`` ({figure: its work, e.g. its axes}) in ``n`` shares of about equal work, largest
    first."""
    shares: list[list[str]] = [[] for _ in range(max(1, n))]
    sums = [0] * len(shares)
    for name in sorted(work, key=lambda k: -work[k]):
        i = sums.index(min(sums))
        shares[i].append(name)
        sums[i] += max(1, work[name])
    return [share for share in shares if share]


_STOPS = (signal.SIGINT, signal.SIGTERM)


class _DrawnApart:
    """Draw the figures ``make()`` returns ({name: figure}) in a forked process, which makes them; calling the
    object waits for their PNG bytes, and makes and draws them here instead where the process failed. The forked
    process only makes and draws (matplotlib's Agg, no torch), writes the bytes to a pipe and ends at once
    (``os._exit``: nothing of the parent's is flushed or closed twice), with the default action for SIGINT and
    SIGTERM, so that the run's own handlers (which save a checkpoint) never run there. ``cancel`` ends it where
    it was not waited for; ``drawn_here`` says whether the caller drew them."""

    def __init__(self, make: Callable[[], dict]):
        self.make, self.pid, self.r = make, None, None
        self.drawn_here = False
        r, w = os.pipe()
        # SIGINT and SIGTERM wait until the forked process has its own actions for them
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, _STOPS)
        pid = -1
        try:
            with warnings.catch_warnings():  # Python 3.12+ warns of forking with threads: only Agg runs there
                warnings.simplefilter("ignore", DeprecationWarning)
                pid = os.fork()
        except OSError:                      # no process to spare: the figures are drawn here when waited for
            os.close(r)
            os.close(w)
            return
        finally:
            if pid != 0:
                signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        if pid == 0:
            _draw_and_exit(make, r, w, blocked)
        os.close(w)
        self.pid, self.r = pid, r

    def __call__(self) -> dict[str, bytes]:
        status = 1
        if self.pid is not None:
            with os.fdopen(self.r, "rb") as f:
                self.r = None
                data = f.read()
            _, status = os.waitpid(self.pid, 0)
            self.pid = None
        if status != 0:
            self.drawn_here = True
            return {name: png(fig) for name, fig in self.make().items()}
        return pickle.loads(data)

    def cancel(self) -> None:
        if self.r is not None:
            os.close(self.r)
            self.r = None
        if self.pid is not None:
            os.kill(self.pid, signal.SIGKILL)
            os.waitpid(self.pid, 0)
            self.pid = None


def _draw_and_exit(make: Callable[[], dict], r: int, w: int, blocked) -> None:
    """In the forked process: make the figures and draw them, write their pickled PNG bytes to ``w`` and end,
    with status 0 only where all of that succeeded."""
    code = 1
    try:
        gc.disable()        # no collection here: the finalizers of the parent's garbage (files, folders) stay its own
        os.close(r)
        for sig in _STOPS:
            signal.signal(sig, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        data = pickle.dumps({name: png(fig) for name, fig in make().items()})
        with os.fdopen(w, "wb") as f:
            f.write(data)
        code = 0
    finally:
        os._exit(code)


def draw_meanwhile(make: Callable[[], dict]) -> Callable[[], dict[str, bytes]]:
    """Start drawing the figures ``make()`` returns on a second thread; the returned function waits for their
    PNG bytes (and raises what the drawing raised). ``make`` must make its figures without pyplot and read only
    what the caller leaves unchanged until it waits. The figures are the same bytes as drawn in the caller's
    thread; what the thread gains is the caller's time in file writes, hashing and fsync (which leave Python)."""
    out: dict = {}

    def draw() -> None:
        try:
            out["pngs"] = pngs(make())
        except BaseException as e:     # handed to the caller when it waits
            out["error"] = e
    thread = threading.Thread(target=draw, name="rcotorch-figures", daemon=True)   # a 2nd Ctrl-C quits at once
    thread.start()

    def wait() -> dict[str, bytes]:
        thread.join()
        if "error" in out:
            raise out["error"]
        return out["pngs"]
    return wait
