"""Matplotlib figures of a run: estimates vs time with the truth, model error, frequency responses."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

MAX_LINES = 8


def run_figures(run) -> dict:
    """Estimate-vs-time (one panel per estimate, truth dashed) and rms model error vs time."""
    g = run.graph
    h, dt = run.history, g.role("known").dt if "known" in g.roles else 1.0
    t = np.asarray(h["step"], dtype=float) * dt
    figs = {}
    keys = [k for k in h if k not in ("step", "z_rms")]
    if keys and len(t):
        fig, axes = plt.subplots(len(keys), 1, figsize=(7, 2.2 * len(keys) + 0.6), sharex=True, squeeze=False)
        for ax, key in zip(axes[:, 0], keys):
            v = torch.stack(h[key]).numpy()
            ax.plot(t, v[:, :MAX_LINES], lw=1)
            truth = run.truth.get(key)
            if truth is not None:
                for tv in np.atleast_1d(truth)[:MAX_LINES]:
                    ax.axhline(tv, color="k", ls="--", lw=1)
            ax.set_ylabel(key)
            ax.grid(alpha=0.3)
        axes[-1, 0].set_xlabel("time [s]")
        axes[0, 0].set_title(f"{run.scenario.name}: estimates (truth dashed)")
        figs["estimates"] = fig
    if len(t):
        fig, ax = plt.subplots(figsize=(7, 2.8))
        ax.semilogy(t, torch.stack(h["z_rms"]).numpy()[:, :MAX_LINES], lw=1)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("rms z per log interval")
        ax.set_title(f"{run.scenario.name}: model error z = y - y_hat")
        ax.grid(alpha=0.3, which="both")
        figs["model_error"] = fig
    return figs


def frequency_figure(omega, curves: dict, title: str, nyquist: float | None = None):
    """Bode magnitude and phase of named complex responses {label: (F,) array}."""
    fig, (am, ap) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for label, resp in curves.items():
        resp = np.asarray(resp)
        style = "--" if "true" in label.lower() else "-"
        am.loglog(omega, np.abs(resp), style, label=label, lw=1.3)
        ap.semilogx(omega, np.degrees(np.unwrap(np.angle(resp))), style, label=label, lw=1.3)
    for ax in (am, ap):
        if nyquist:
            ax.axvline(nyquist, color="gray", lw=0.8, ls=":")
        ax.grid(alpha=0.3, which="both")
    am.set_ylabel("magnitude")
    ap.set_ylabel("phase [deg]")
    ap.set_xlabel("frequency [rad/s]")
    am.legend()
    am.set_title(title)
    return fig
