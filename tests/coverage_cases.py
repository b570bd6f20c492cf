"""The cases of the confidence intervals' coverage over seeds (``benchmarks/interval_coverage.py`` runs them all and
tabulates them; ``tests/test_bias.py`` runs the hard ones): the share of members whose nominal interval holds the
truth.

Each case is one batched run of a scenario, or of a graph built in Python, in which every member has its own
excitation and measurement-noise streams (seed = 1 .. B); an estimate's coverage is the fraction of members whose
interval contains the truth. Calibrated intervals cover about their level (95%); intervals that are too narrow
cover less.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

import rcotorch as rt
from rcotorch.run.runner import Run


def friction(members: int, out: Path, std: float = 20.0, steps: int = 20000) -> dict:
    """A mass on a spring with Coulomb and viscous friction u = -(2 sign(v) + 0.5 v) (a graph built in Python,
    truth a StaticMap), identified with the basis [sign(v), v] from the velocity with 1% noise, strong
    excitation (the mass slides most of the time)."""
    Ts, seeds = 0.01, list(range(1, members + 1))
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.2, 4.0, measured=["velocity"], sees=["velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=Ts, name="known")
    truth = rt.StaticMap(lambda v: -(2.0 * torch.sign(v) + 0.5 * v), 1)
    ident = rt.RCOEstimator.static_gain({"y0": 1}, features=[rt.features.sign("y0"), rt.features.port("y0")],
                                        p0=1e3)
    g = rt.refinement(known, ident, truth=truth, excitation=rt.WhiteNoise(1, std=std, seed=seeds), nu=50,
                      noise=rt.WhiteNoise(1, std=0.01 * std / 4, seed=[s + 100 for s in seeds]),
                      batch_size=members)
    res = rt.refine(g, steps, {"coulomb": lambda g: -g.role("estimator").theta[:, 0, 0],
                               "viscous": lambda g: -g.role("estimator").theta[:, 0, 1]},
                    truth={"coulomb": 2.0, "viscous": 0.5}, out=out, overwrite=True, figures=False, progress=False)
    return res.summary


def duffing(members: int, out: Path, steps: int = 20000) -> dict:
    """A user's own nonlinear truth (a graph built in Python): a Duffing oscillator q'' + 0.4 q' + q + 0.5 q^3 = w,
    continuous and integrated by RK4 substeps, its position measured with 1% noise; the known model is the linear
    oscillator, the identified subsystem a cubic spring u = theta q^3 (k3 = -theta)."""
    Ts, seeds = 0.05, list(range(1, members + 1))

    def field(x, inputs):
        q, v = x[:, :1], x[:, 1:]
        return torch.cat([v, -q - 0.4 * v - 0.5 * q ** 3 + inputs["w"]], dim=1)
    physical = rt.Nonlinear(field, lambda x: x[:, :1], 2, inputs={"w": 1}, outputs={"y": 1}, dt=Ts,
                            continuous=True, substeps=10, name="duffing")
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.4, 1.0, measured=["position"], sees=["position"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=Ts, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 1}, features=[rt.features.power("y0", 3)], p0=1e2)
    g = rt.refinement(known, ident, physical=physical, excitation=rt.WhiteNoise(1, std=1.0, seed=seeds), nu=30,
                      noise=rt.WhiteNoise(1, std=0.01, seed=[s + 100 for s in seeds]), batch_size=members)
    res = rt.refine(g, steps, {"k3": lambda g: -g.role("estimator").theta[:, 0, 0]}, truth={"k3": 0.5},
                    out=out, overwrite=True, figures=False, progress=False)
    return res.summary


def drag(members: int, out: Path, steps: int = 20000) -> dict:
    """Quadratic air drag (a graph built in Python, a problem of the kind no scenario ships): a mass on a spring
    q'' + 0.1 q' + 2 q + 0.3 v |v| = w, continuous and integrated by RK4 substeps, its velocity measured with noise
    of standard deviation 0.02; the known model is the linear oscillator, the identified subsystem
    u = theta [v |v|, v] (drag cd = -theta_0 = 0.3, extra viscous damping c = -theta_1 = 0)."""
    Ts, seeds = 0.02, list(range(1, members + 1))

    def field(x, inputs):
        q, v = x[:, :1], x[:, 1:]
        return torch.cat([v, -2.0 * q - 0.1 * v - 0.3 * v * (v * v) ** 0.5 + inputs["w"]], dim=1)
    physical = rt.Nonlinear(field, lambda x: x[:, 1:], 2, inputs={"w": 1}, outputs={"y": 1}, dt=Ts,
                            continuous=True, substeps=8, name="drag")
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.1, 2.0, measured=["velocity"], sees=["velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=Ts, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=1e2, features=[
        rt.features.absolute("y0") * rt.features.port("y0"), rt.features.port("y0")])
    g = rt.refinement(known, ident, physical=physical, excitation=rt.WhiteNoise(1, std=2.0, seed=seeds), nu=40,
                      noise=rt.WhiteNoise(1, std=0.02, seed=[s + 100 for s in seeds]), batch_size=members)
    res = rt.refine(g, steps, {"cd": lambda g: -g.role("estimator").theta[:, 0, 0],
                               "c": lambda g: -g.role("estimator").theta[:, 0, 1]},
                    truth={"cd": 0.3, "c": 0.0}, scales={"c": 0.1}, out=out, overwrite=True, figures=False,
                    progress=False)
    return res.summary


CASES = {
    # name: (scenario or graph, overrides, steps); the first group has the model class exact, the second not
    "sdof-discrete": ("sdof-stiffness", {"truth": "discrete", "noise": 0.05}, 20000),
    "twodof-discrete-default": ("twodof-stiffness", {"truth": "discrete", "noise": 0.05}, 20000),
    "friction-strong": (friction, {}, 20000),
    "twodof-discrete": ("twodof-stiffness", {"truth": "discrete", "noise": 0.05, "lam": 1.0}, 20000),
    "impedance-noise": ("sdof-dynamic-impedance", {"noise": 0.05}, 20000),
    "sdof-continuous": ("sdof-stiffness", {"truth": "continuous", "noise": 0.05}, 20000),
    "sdof-shipped": ("sdof-stiffness", {}, 20000),
    "sdof-shipped-100k": ("sdof-stiffness", {}, 100000),
    "rlc-circuit": ("rlc-circuit", {}, 20000),
    "sdof-damping-shipped": ("sdof-stiffness-damping", {}, 20000),
    "sdof-damping-noise": ("sdof-stiffness-damping", {"noise": 0.05}, 20000),
    "mass-friction-shipped": ("mass-friction", {}, 20000),
    "duffing": (duffing, {}, 20000),
    "drag": (drag, {}, 20000),
}


def clopper_pearson(k: int, n: int, level: float = 0.95) -> list[float]:
    """The exact (Clopper-Pearson) confidence interval of a share from k successes in n trials: the range of
    coverages that these members' count does not rule out at ``level``."""
    from scipy.stats import beta
    tail = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(tail, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - tail, k + 1, n - k))
    return [lo, hi]


def coverage(name: str, members: int, out: Path) -> dict:
    """One case: every member's status, and per estimate the coverage among the members called converged."""
    scenario, overrides, steps = CASES[name]
    t0 = time.perf_counter()
    if callable(scenario):
        summary = scenario(members, out / name)
        scenario = "graph: " + scenario.__name__
    else:
        run = Run(scenario, steps=steps, overrides=overrides, members=[{"seed": s} for s in range(1, members + 1)],
                  out=out / name, overwrite=True)
        run.advance(progress=False)
        summary = run.finish(figures=False)
    h = summary["health"]
    status = np.asarray(h["status"])
    converged = status == "converged"
    rows = {}
    for key, values in summary["estimates"].items():
        iv = summary["intervals"].get(key)
        truth = summary["truth"].get(key)
        if iv is None or truth is None:
            continue
        lo, hi, est = (np.array([np.nan if v is None else v for v in x], dtype=float)
                       for x in (iv["lower"], iv["upper"], values))
        t = np.asarray(truth, dtype=float)
        inside = (lo <= t) & (t <= hi)
        n_conv, n_in = int(converged.sum()), int(inside[converged].sum())
        rows[key] = {"coverage": float(np.mean(inside[converged])) if converged.any() else None,
                     "converged_members": n_conv,
                     "coverage_95": clopper_pearson(n_in, n_conv) if n_conv else None,
                     "coverage_all": float(np.mean(inside)),
                     "spread": float(np.nanstd(est)), "mean_error": float(np.nanmean(est - t)),
                     "predicted_sd": float(np.nanmean((hi - lo) / 2 / 1.959964))}
        if "bias" in iv:
            bias = np.array([np.nan if v is None else v for v in iv["bias"]], dtype=float)
            flagged = np.isfinite(bias)
            if flagged.any():     # the measured bias against the actual error, where one was reported
                rows[key]["bias_median"] = float(np.median(bias[flagged]))
                rows[key]["error_median_where_biased"] = float(np.median((est - t)[flagged]))
    shares = {s: float(np.mean(status == s)) for s in ("converged", "biased", "undetermined", "not_converged",
                                                       "diverged")}
    warned = np.array(h.get("residuals_matter") or [False] * len(status), dtype=bool).reshape(-1)
    return {"scenario": scenario, "overrides": overrides, "steps": steps, "members": members,
            "level": 0.95, "estimates": rows, "status": h["counts"], "shares": shares,
            "residual_warning": float(np.mean(warned)),
            "whiteness_p_below_0.01": float(np.mean(np.array(summary["metrics"]["z_whiteness_p"]) < 0.01)),
            "seconds": round(time.perf_counter() - t0, 1)}
