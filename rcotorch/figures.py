"""Matplotlib figures of a run: estimates vs time with the truth, model error, frequency responses; PNG bytes of
figures, drawn on a second thread where the caller has other work meanwhile.

The figures here are made with matplotlib's ``Figure`` (Agg), not pyplot: pyplot keeps one list of open figures
for the whole process, so only figures made without it can be drawn off the main thread.
"""

from __future__ import annotations

import io
import threading
from collections.abc import Callable

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

MAX_LINES = 8
DPI = 110


def run_figures(run) -> dict:
    """Estimates against time (one panel per estimate: the estimate of each member up to ``MAX_LINES``, the truth
    dashed, the initial model's value dotted) and the rms model error against time, with units and legends."""
    h = run.history
    dt = run.graph.role("known").dt if "known" in run.graph.roles else None
    t = np.asarray(h["step"], dtype=float) * (dt or 1.0)
    xlabel = "time [s]" if dt else "step"
    figs = {}
    keys = [k for k in h if k not in ("step", "z_rms")]
    if keys and len(t):
        found = run.intervals() if hasattr(run, "intervals") else None
        start = run.health.window_start * (dt or 1.0) if found is not None else None
        zoom = found is not None and bool((t >= start).sum() >= 2)
        fig = Figure(figsize=(10.5 if zoom else 7.5, 2.4 * len(keys) + 0.8), layout="tight")
        axes = fig.subplots(len(keys), 2 if zoom else 1, sharex="col", squeeze=False,
                            gridspec_kw={"width_ratios": [2.4, 1]} if zoom else None)
        for row, key in zip(axes, keys):
            v = torch.stack(h[key]).numpy()
            _estimate_panel(row[0], run, key, t, v)
            if zoom:
                _window_panel(row[1], run, key, t[t >= start], v[t >= start], found)
        axes[-1, 0].set_xlabel(xlabel)
        _title(axes[0, 0], f"{run.scenario.name}: estimates")
        if zoom:
            axes[-1, 1].set_xlabel(xlabel)
            _title(axes[0, 1], f"window: final {found.level:.0%} intervals")
        figs["estimates"] = fig
    if len(t):
        fig = Figure(figsize=(7.5, 3.0), layout="tight")
        ax = fig.subplots()
        z = torch.stack(h["z_rms"]).numpy()[:, :MAX_LINES]
        ax.semilogy(t, z, lw=1, label=_member_labels(z.shape[1], run.batch))
        ax.set_xlabel(xlabel)
        ax.set_ylabel(_with_unit("rms of z = y - y_hat", run.scenario.unit("y")))
        _title(ax, f"{run.scenario.name}: model error (rms over each log interval)")
        ax.grid(alpha=0.3, which="both")
        if z.shape[1] > 1:
            ax.legend(fontsize=8, ncol=2)
        figs["model_error"] = fig
    res = run.residuals() if hasattr(run, "residuals") else None
    if res is not None:
        figs.update(residual_figures(run, res, dt))
    return figs


def residual_figures(run, res, dt: float | None) -> dict:
    """The refined model checked on the replayed window (member 0): z's autocorrelation and its
    cross-correlation with w against the 95% band of white, independent signals; the measured output against
    the refined and the initial model's outputs, with their fit in percent."""
    figs = {}
    lags = np.arange(res.autocorr.shape[1])
    n_panels = 2 if res.xcorr is not None else 1
    fig = Figure(figsize=(7.5, 2.6 * n_panels + 0.6), layout="tight")
    axes = fig.subplots(n_panels, 1, squeeze=False)[:, 0]
    ax = axes[0]
    auto = res.autocorr[0].numpy()                               # (L + 1, n_z)
    for c in range(auto.shape[1]):
        ax.plot(lags[1:], auto[1:, c], "o-", ms=3, lw=1, label=f"z[{c}]" if auto.shape[1] > 1 else "z")
    ax.axhspan(-res.bound, res.bound, color="tab:blue", alpha=0.15, label="95% band of white noise")
    ax.set_xlabel("lag [samples]")
    ax.set_ylabel("autocorrelation")
    _title(ax, f"{run.scenario.name}: residual z of the refined model, member 0 "
               f"(Ljung-Box p = {float(res.whiteness_p[0]):.2g})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if res.xcorr is not None:
        ax = axes[1]
        x = res.xcorr[0].numpy()                                  # (L + 1, n_z, n_w)
        for c in range(x.shape[1]):
            for d in range(x.shape[2]):
                ax.plot(lags, x[:, c, d], "o-", ms=3, lw=1, label=f"z[{c}], w[{d}]" if x.shape[1] * x.shape[2] > 1
                        else "z(k), w(k - lag)")
        ax.axhspan(-res.bound, res.bound, color="tab:blue", alpha=0.15, label="95% band of independence")
        ax.set_xlabel("lag [samples]")
        ax.set_ylabel("cross-correlation")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    figs["residuals"] = fig
    y = res.series["measured"][:, 0].numpy()
    n = min(len(y), 600)                                          # the last samples of the window
    t = (np.arange(len(y)) - len(y) + 1) * (dt or 1.0)            # 0 at the window's end
    fig = Figure(figsize=(7.5, 3.2), layout="tight")
    ax = fig.subplots()
    ax.plot(t[-n:], res.series["initial"][-n:, 0, 0].numpy(), color="tab:gray", ls=":", lw=1.2,
            label=f"initial model (fit {float(res.fit_initial[0]):.1f}%)")
    ax.plot(t[-n:], res.series["refined"][-n:, 0, 0].numpy(), color="tab:orange", lw=1.2,
            label=f"refined model (fit {float(res.fit[0]):.1f}%)")
    ax.plot(t[-n:], y[-n:, 0], color="k", lw=0.8, label="measured", zorder=3)
    ax.set_xlabel("time before the window's end [s]" if dt else "steps before the window's end")
    ax.set_ylabel(_with_unit("y", run.scenario.unit("y")))
    _title(ax, f"{run.scenario.name}: measured and model outputs, member 0 (theta frozen)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    figs["output_fit"] = fig
    return figs


def _estimate_panel(ax, run, key: str, t: np.ndarray, v: np.ndarray) -> None:
    """One estimate against time: its members, the truth and the initial model's value."""
    lines = v[:, :MAX_LINES]
    labels = ["estimate"] if lines.shape[1] == 1 else _member_labels(lines.shape[1], run.batch)
    ax.plot(t, lines, lw=1.2, label=labels)
    found = run.intervals() if hasattr(run, "intervals") else None
    if found is not None and key in found.estimate and len(t):
        half = found.half_width[key].numpy()[:lines.shape[1]]
        est = found.estimate[key].numpy()[:lines.shape[1]]
        ax.errorbar(np.full(len(est), t[-1]), est, yerr=half, fmt="none", ecolor="k", elinewidth=1.5, capsize=4,
                    zorder=4, label=f"{found.level:.0%} interval at the end")
    truth = run.truth.get(key)
    if truth is not None:
        for i, tv in enumerate(np.atleast_1d(truth)[:MAX_LINES]):
            ax.axhline(tv, color="k", ls="--", lw=1, label="truth" if i == 0 else None)
    initial = (run.monitor.initial or {}).get(key) if run.monitor is not None else None
    if initial is not None:
        for i, iv in enumerate(np.unique(initial.numpy()[:MAX_LINES])):
            ax.axhline(iv, color="tab:gray", ls=":", lw=1.2, label="initial model" if i == 0 else None)
    ax.set_ylabel(_with_unit(key, run.scenario.unit(key)))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best", ncol=2 if lines.shape[1] > 2 else 1)


def _window_panel(ax, run, key: str, t: np.ndarray, v: np.ndarray, found) -> None:
    """The convergence window of one estimate, zoomed: each drawn member's path and its final interval shaded
    in its colour, the truth on top."""
    lines = ax.plot(t, v[:, :MAX_LINES], lw=1.2)
    if key in found.estimate:
        lo, hi = found.lower(key).numpy(), found.upper(key).numpy()
        for b, line in enumerate(lines):
            if np.isfinite(lo[b]) and np.isfinite(hi[b]):
                ax.axhspan(lo[b], hi[b], color=line.get_color(), alpha=0.18, lw=0)
    truth = run.truth.get(key)
    if truth is not None:
        for tv in np.atleast_1d(truth)[:MAX_LINES]:
            ax.axhline(tv, color="k", ls="--", lw=1, zorder=3)
    ax.grid(alpha=0.3)
    ax.ticklabel_format(axis="y", useOffset=False)


def _title(ax, text: str) -> None:
    """A title on the axes' top edge: where matplotlib puts it on axes without tick labels above them, which it
    would otherwise confirm by laying out every tick label of the figure once more."""
    ax.set_title(text, y=1.0)


def _member_labels(n: int, batch: int) -> list[str]:
    labels = [f"member {b}" for b in range(n)]
    if batch > n:
        labels[-1] += f" (first {n} of {batch})"
    return labels


def _with_unit(label: str, unit: str) -> str:
    return f"{label} [{unit}]" if unit else label


def frequency_figure(omega, curves: dict, title: str, nyquist: float | None = None, unit: str = "",
                     bands: dict | None = None):
    """Bode magnitude (in ``unit``, the unit of output per unit of input) and phase of named complex responses
    {label: (F,) array}; the Nyquist frequency dotted. ``bands``: {label: (lower, upper)} magnitude bands, e.g.
    a confidence region of an identified response, shaded. A curve whose label says 'true' is drawn dashed and
    on top, so that it stays visible where another curve covers it."""
    fig = Figure(figsize=(7, 5), layout="tight")
    am, ap = fig.subplots(2, 1, sharex=True)
    for label, (lo, hi) in (bands or {}).items():
        am.fill_between(omega, np.maximum(np.asarray(lo), 1e-300), np.asarray(hi), color="tab:orange", alpha=0.25,
                        lw=0, label=label)
    for label, resp in curves.items():
        resp = np.asarray(resp)
        true = "true" in label.lower()
        style, z = ("--", 3) if true else ("-", 2)
        am.loglog(omega, np.abs(resp), style, label=label, lw=1.3, zorder=z)
        ap.semilogx(omega, np.degrees(np.unwrap(np.angle(resp))), style, label=label, lw=1.3, zorder=z)
    for ax in (am, ap):
        if nyquist:
            ax.axvline(nyquist, color="gray", lw=0.8, ls=":", label="Nyquist frequency" if ax is am else None)
        ax.grid(alpha=0.3, which="both")
    am.set_ylabel(_with_unit("magnitude", unit))
    ap.set_ylabel("phase [deg]")
    ap.set_xlabel("frequency [rad/s]")
    am.legend()
    _title(am, title)
    return fig


def png(fig) -> bytes:
    """The figure as PNG bytes at ``DPI``, laid out tightly unless it has a layout of its own (one drawing); a
    figure that pyplot made is closed (removed from pyplot's list)."""
    if fig.get_layout_engine() is None:
        fig.set_layout_engine("tight")             # laid out while it is drawn
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    if fig.canvas.manager is not None:
        import matplotlib.pyplot as plt
        plt.close(fig)
    return buf.getvalue()


def pngs(figs: dict) -> dict[str, bytes]:
    """{name: PNG bytes} of {name: figure}."""
    return {name: png(fig) for name, fig in figs.items()}


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
