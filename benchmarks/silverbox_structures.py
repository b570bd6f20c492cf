"""Which identified subsystem does the Silverbox need? Structures searched on held-out estimation rows, offline
and online (scenario ``silverbox-cubic-stiffness``).

Every structure refines the scenario's known model (the linear fit y'' = -a y' - b y + g (w + u) + d0 on the
estimation rows) through u(k) = sum_(l=0..nc) sum_i theta_(l,i) phi_i(k - l) + sum_(l=1..nc) alpha_l u(k - l):
monomials phi_i = q^i v^j w^m of the position q and velocity v the known model predicts half a sample ahead and
of the input w, the signals the scenario's identified subsystem sees. nc = 0 is a static basis (the scenario's
``basis``; 'all' is q, q^3, v, w, 1); nc >= 1 a dynamic one (an ``RCOEstimator`` with nc past samples of the
lagged terms, and of u where alpha is free).

1. Offline, for the choice: theta, alpha and the initial state fitted by ``scipy.optimize.least_squares`` on
   the free-run error over the first rows of the estimation multisine, [40650, HOLD), with the known model
   fitted to the same rows (the scenario's ``prepare`` with fit_stop = est_stop = HOLD); scored on the held-out
   rest, [HOLD, 105712), free run from the state fitted to its first 50 outputs, the error from sample BURN on.
2. Offline, for the report: each structure fitted again on all estimation rows (known model and theta, as the
   scenario does; started from the fit of step 1) and scored on the benchmark's three test sets (the
   scenario's ``TEST_SETS``: the multisine, the arrow, the arrow without extrapolation), from the state fitted
   to their first 50 outputs. The fit of step 1 is scored on the test sets too (``offline_held_out``).
   The scenario's own offline fit of 'all' (a, b, g, d0 and the cubic coefficient) gives 0.912 / 0.984 /
   0.759 mV; the fit here of theta over the fixed known model, 0.919 / 0.991 / 0.765.
3. Online (RCMR, one pass over the estimation rows, the scenario's nu and lam): 'all' through the scenario
   itself; the best static structure on the held-out rows and every dynamic one in the scenario's graph (its
   known model, data and Markov parameters) with the ``RCOEstimator`` the structure needs, over regressors
   scaled like the offline fit's, p0 chosen on the held-out split among ``P0``; the same started at the
   offline optimum (is it a fixed point of the online update?).

    python benchmarks/silverbox_structures.py              # about 1.5 minutes on 2 idle cores
    python benchmarks/silverbox_structures.py --extended   # also nc = 3: about 3 minutes (the results on record)
    python benchmarks/silverbox_structures.py --table      # the table of the results on record (docs/scenarios.md)

Needs the Silverbox data (``rt.datasets.silverbox_files``: the cache, a download, or ``$RCOTORCH_SILVERBOX``).
Writes benchmarks/results/silverbox_structures.json.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numba
import numpy as np
import scipy.optimize
import torch
from common import RESULTS, machine, write_json
from rcotorch.scenarios import silverbox_cubic_stiffness as box

from rcotorch.models.identification import rmse
from rcotorch.run.runner import Run

NAME = box.SCENARIO.name
EST = (40650, 105712)                      # the benchmark's estimation multisine
HOLD = 92000                               # [HOLD, 105712): held-out estimation rows, the last 21 %
N_INIT = 50                                # outputs that fix the initial state of a free run
# The held-out error counts from this sample on: a dynamic subsystem starts with zero history (past phi and u)
# that the 50 outputs cannot fix, and its start-up transient would otherwise decide the choice (nc = 2 fitted
# on [40650, HOLD): 3.1 mV over the first 2000 held-out samples, 0.6 mV after).
BURN = 2000
GOAL = {"multisine": 0.45, "arrow": 0.39, "arrow_noextrap": 0.39}     # mV
PUBLISHED = {"best (GP-NARX, PNLSS)": (0.30, 0.26, 0.26), "polynomial NARX": (0.64, 2.25, 0.57),
             "linear state space": (6.96, 14.4, 6.58)}               # Champneys et al. 2024, arXiv 2405.10779

# Monomials q^i v^j w^m by exponents (i, j, m); '1' is the constant.
TERMS = {"q": (1, 0, 0), "q^2": (2, 0, 0), "q^3": (3, 0, 0), "q^4": (4, 0, 0), "q^5": (5, 0, 0),
         "v": (0, 1, 0), "v^2": (0, 2, 0), "v^3": (0, 3, 0), "q v": (1, 1, 0), "q^2 v": (2, 1, 0),
         "q v^2": (1, 2, 0), "w": (0, 0, 1), "1": (0, 0, 0)}
ALL = ("q", "q^3", "v", "w", "1")          # the scenario's basis 'all'
# name: (terms, nc, the terms with lags 1..nc, past u in phi)
STATIC = {
    "all": ALL,
    "all+q^2": ALL + ("q^2",),
    "all+q^2+q^5": ALL + ("q^2", "q^5"),
    "all+v^3": ALL + ("v^3",),
    "all+v^2+v^3": ALL + ("v^2", "v^3"),
    "all+q^2 v+q v^2": ALL + ("q^2 v", "q v^2"),
    "cubic in q, v": ALL + ("q^2", "q v", "v^2", "q^2 v", "q v^2", "v^3"),
}
DYNAMIC = ("q", "q^3", "v", "w")            # the lagged terms of the dynamic candidates (a lagged 1 is redundant)
CANDIDATES = {
    **{name: (terms, 0, (), False) for name, terms in STATIC.items()},
    "all, w FIR 4": (ALL, 4, ("w",), False),
    "all, nc=1": (ALL, 1, DYNAMIC, True),
    "all, nc=2": (ALL, 2, DYNAMIC, True),
    "all+q^2, nc=2": (ALL + ("q^2",), 2, DYNAMIC + ("q^2",), True),
}
P0 = (1e-2, 1.0, 1e2)                      # p0 tried online over the scaled regressors
# Left out of the default run for its fitting time (about 2 minutes on an idle core): with --extended.
EXTENDED = {
    "all, nc=3": (ALL, 3, DYNAMIC, True),
}


# The study's known model: the input interpolated linearly between samples, the spring at mid-sample (the
# scenario's structure before its spline input; docs/scenarios.md shows what the spline changes).
STUDIED = {"spline": False, "u_ahead": False, "lead": 0.5, "basis": "all"}


def settings(**over) -> dict:
    return box.SCENARIO.resolve({k: str(v) for k, v in {**STUDIED, **over}.items()})


@numba.njit(cache=True)
def free_run(A, bw, bu, cy, dy, cs, ds, w, x0, E, theta, alpha, out):
    """y of the free run of the known model with u(k) = sum_l theta[l] . phi(k - l) + sum_l alpha[l] u(k-1-l),
    phi_i = prod_c s_c^E[i, c] of the seen signals s = cs x + ds w(k) (scaled q, v, w); NaN after a blow-up."""
    n, nf, L, nc = A.shape[0], E.shape[0], theta.shape[0], alpha.shape[0]
    phi = np.zeros((L, nf))
    past = np.zeros(max(nc, 1))
    s = np.empty(cs.shape[0])
    x = x0.copy()
    nxt = np.empty(n)
    for k in range(w.shape[0]):
        wk = w[k]
        yk = dy * wk
        for i in range(n):
            yk += cy[i] * x[i]
        out[k] = yk
        if not abs(yk) < 1e3:
            out[k:] = np.nan
            return
        for c in range(cs.shape[0]):
            acc = ds[c] * wk
            for i in range(n):
                acc += cs[c, i] * x[i]
            s[c] = acc
        for l in range(L - 1, 0, -1):
            phi[l] = phi[l - 1]
        u = 0.0
        for j in range(nf):
            p = 1.0
            for c in range(cs.shape[0]):
                for _ in range(E[j, c]):
                    p *= s[c]
            phi[0, j] = p
        for l in range(L):
            for j in range(nf):
                u += theta[l, j] * phi[l, j]
        for l in range(nc):
            u += alpha[l] * past[l]
        for l in range(nc - 1, 0, -1):
            past[l] = past[l - 1]
        past[0] = u
        for i in range(n):
            acc = bw[i] * wk + bu[i] * u
            for m in range(n):
                acc += A[i, m] * x[m]
            nxt[i] = acc
        x[:] = nxt


class Structure:
    """One candidate over one known model: the free run, its fit and its scores; theta in scaled signals
    (q / y_rms, v / (y_rms sqrt(b)), w / w_rms), ``physical`` converts."""

    def __init__(self, model, terms, nc: int, y_rms: float, w_rms: float, lagged=None, feed_u: bool = True):
        self.model, self.terms, self.nc = model, tuple(terms), int(nc)
        lti = model.lti(sees=("position", "velocity", "input"))
        C, D = lti.C[0].numpy(), lti.D[0].numpy()           # rows y, q, v, w; columns of D: w, u
        d = model.discrete
        self.scale = np.array([y_rms, y_rms * math.sqrt(model.b), w_rms])
        self.args = (d.A, d.B[:, 0].copy(), d.B[:, 1].copy(), C[0].copy(), float(D[0, 0]),
                     C[1:] / self.scale[:, None], D[1:, 0] / self.scale)
        self.E = np.array([TERMS[t] for t in self.terms], dtype=np.int64)
        lagged = self.terms if lagged is None else tuple(lagged)
        self.mask = np.zeros((self.nc + 1, len(self.terms)), dtype=bool)
        self.mask[0] = True
        self.mask[1:, [self.terms.index(t) for t in lagged]] = True
        self.n_theta = int(self.mask.sum())
        self.n_alpha = self.nc if feed_u else 0
        self.n = self.n_theta + self.n_alpha

    def split(self, p):
        p = np.asarray(p, dtype=np.float64)
        theta = np.zeros(self.mask.shape)
        theta[self.mask] = p[:self.n_theta]
        alpha = np.zeros(self.nc)
        alpha[:self.n_alpha] = p[self.n_theta:self.n]
        return theta, alpha

    def run(self, w, x0, p) -> np.ndarray:
        theta, alpha = self.split(p)
        out = np.empty(len(w))
        free_run(*self.args, w, np.asarray(x0, dtype=np.float64), self.E, theta, alpha, out)
        return out

    def physical(self, p) -> np.ndarray:
        """theta per term and lag in the signals' own units (V, V/s), as the scenario's features take them."""
        theta, _ = self.split(p)
        return theta / np.prod(self.scale[None, :] ** self.E, axis=1)[None, :]

    def state(self, w, y, p) -> np.ndarray:
        """The state at the first sample that best fits y with the subsystem p: the linear model's
        (``MassSpringDamper.initial_state``), then least squares over the feedback's free run."""
        m = self.model
        x = m.initial_state(w, y)
        base, e = m.state(0.0, 0.0, w[0]), np.eye(3)[:2]
        if not np.any(p):
            return x
        ys = max(float(np.abs(y).max()), 1e-12)

        def res(c):
            r = self.run(w, base + c @ e, p) - y
            return np.where(np.isfinite(r), r, 1e3 * ys)

        c = scipy.optimize.least_squares(res, x[:2] - base[:2], x_scale=[ys, ys * math.sqrt(m.b)]).x
        return base + c @ e

    def fit(self, w, y, start=None) -> tuple[np.ndarray, float]:
        """theta, alpha and the initial state by least squares on the free-run error over all of w, y (as
        ``MassSpringDamper.fit_with_spring``), from zero or from ``start``; (p, fit rms)."""
        m = self.model
        ys = max(float(np.abs(y).max()), 1e-12)
        x = m.initial_state(w[:N_INIT], y[:N_INIT])
        base = m.state(0.0, 0.0, w[0])

        def res(q):
            r = self.run(w, base + np.r_[q[-2:], 0.0], q[:-2]) - y
            return np.where(np.isfinite(r), r, 1e3 * ys)

        q0 = np.r_[np.zeros(self.n) if start is None else start, x[:2] - base[:2]]
        # u is in the units of w; a scaled regressor of size 1 moves it by about w_rms / 10 per unit theta.
        scale = np.r_[np.full(self.n_theta, 0.1 * self.scale[2]), np.full(self.n_alpha, 0.1), ys, ys * math.sqrt(m.b)]
        sol = scipy.optimize.least_squares(res, q0, x_scale=scale)
        return sol.x[:-2], rmse(sol.fun, 0.0)

    def score(self, w, y, p, skip: int = N_INIT) -> float:
        """Free-run RMS error [V] from sample ``skip`` on, from the state fitted to the first N_INIT samples."""
        ys = self.run(w, self.state(w[:N_INIT], y[:N_INIT], p), p)
        return rmse(ys[skip:], y[skip:]) if np.all(np.isfinite(ys)) else math.nan


# --- the study ---------------------------------------------------------------------------------------------
def columns(s, rows) -> tuple[np.ndarray, np.ndarray]:
    """w and y of the recording's rows [start, stop) under settings s."""
    rec = box.prepare(s)[0].rows(*rows)
    return rec.column(s["w_column"]), rec.column(s["y_column"])


def structure(s, name: str, y_rms: float, w_rms: float) -> Structure:
    terms, nc, lagged, feed_u = CANDIDATES[name]
    return Structure(box.prepare(s)[1], terms, nc, y_rms, w_rms, lagged, feed_u)


def offline(s, name: str, fit_rows, scored: dict, y_rms: float, w_rms: float, start=None) -> dict:
    """The structure fitted offline on fit_rows (known model of settings s) and scored on each of ``scored``."""
    st = structure(s, name, y_rms, w_rms)
    t0 = time.perf_counter()
    p, fit_rms = st.fit(*columns(s, fit_rows), start=start)
    seconds = time.perf_counter() - t0
    scores = {k: 1e3 * st.score(*columns(s, rows), p, BURN if k == "held_out" else N_INIT)
              for k, rows in scored.items()}
    return {"fit_rmse_mv": 1e3 * fit_rms, **{f"{k}_mv": v for k, v in scores.items()}, "fit_seconds": seconds,
            "p": p.tolist(), "theta_scaled": st.split(p)[0].tolist(), "theta": st.physical(p).tolist(),
            "alpha": st.split(p)[1].tolist()}


def held_out_settings(**over) -> dict:
    """The scenario's settings with the held-out rows left out of every fit: the known model and the refinement
    on [40650, HOLD), the validation on [HOLD, 105712)."""
    return settings(fit_stop=HOLD, est_stop=HOLD, val_start=HOLD, val_stop=EST[1], test_sets=False, **over)


def online_scenario(basis: str, held_out: bool, out: Path) -> dict:
    """One run of the scenario with ``basis``: on the held-out split its validation error, else its test sets."""
    over = {**STUDIED, "basis": basis}
    if held_out:
        over.update(fit_stop=HOLD, est_stop=HOLD, val_start=HOLD, val_stop=EST[1], test_sets=False)
    t0 = time.perf_counter()
    r = Run(NAME, overrides=over, out=out, overwrite=True)
    r.advance(progress=False)
    m = r.finish(figures=False)["metrics"]
    seconds = time.perf_counter() - t0
    if held_out:
        return {"held_out_mv": 1e3 * burned(box.SCENARIO.held_out(r.graph, r.settings, (HOLD, EST[1]))),
                "seconds": seconds}
    return {**{f"{k}_mv": m[f"test_{k}_rmse_mv"] for k in box.TEST_SETS}, "seconds": seconds}


def burned(v) -> float:
    """The RMS error [V] of an ``rt.validate`` result from sample BURN on."""
    e = (v.refined[BURN:, 0, 0] - v.measured[BURN:, 0, 0]).double()
    return float(e.square().mean().sqrt()) if bool(e.isfinite().all()) else math.nan


def estimator(s, name: str, p0: float, scale, theta0=None):
    """The candidate as the scenario's identified subsystem would be: an RCOEstimator over the monomials of
    y0 = (q, v, w), each divided by its size (``scale`` of q, v, w: the regressors of the offline fit, so that
    one p0 suits all of them; the velocity monomials reach 1e5 unscaled), with nc past samples of the lagged
    ones and of u; ``theta0`` is (theta by lag and term, alpha) of the offline fit, in those units."""
    import rcotorch as rt
    terms, nc, lagged, feed_u = CANDIDATES[name]
    f = rt.features
    feats = []
    for t in terms:
        term = f.constant()
        for ch, e in enumerate(TERMS[t]):
            if e:
                term = term * f.power(f"y0[{ch}]", e)
        feats.append(float(1 / np.prod(np.asarray(scale) ** np.array(TERMS[t]))) * term)
    mask = []
    for t in terms:
        mask += [True] + [t in lagged] * nc
    mask += [True] * (nc if feed_u else 0)
    kw = {}
    if theta0 is not None:
        theta, alpha = theta0
        th = [theta[lag][j] for j in range(len(terms)) for lag in range(nc + 1)]     # phi's order
        kw["theta0"] = np.array([th + list(alpha[:nc if feed_u else 0])])
    if nc == 0:
        return rt.RCOEstimator.static_gain({"y0": 3}, features=feats, p0=p0, lam=float(s["lam"]), **kw)
    return rt.RCOEstimator({"y0": 3}, nc=nc, proper=True, feed_u=feed_u, features=feats, mask=np.array([mask]),
                           p0=p0, lam=float(s["lam"]), **kw)


def online_graph(s, name: str, p0: float, scale, scored: dict, theta0=None) -> dict:
    """The candidate refined online (RCMR, one pass over the estimation rows of settings s) in the scenario's
    graph with its known model, theta frozen at the end and scored on each of ``scored`` (rt.validate)."""
    import rcotorch as rt
    rec, model = box.prepare(s)
    est = rec.rows(int(s["est_start"]), int(s["est_stop"]))
    w, y = est.column(s["w_column"]), est.column(s["y_column"])
    n = int(s["n_init"])
    cols = {"w": s["w_column"], "y": s["y_column"]}
    known = model.lti(x0=model.initial_state(w[:n], y[:n]), sees=("position", "velocity", "input"))
    ident = estimator(s, name, p0, scale, theta0)
    g = rt.refinement(known, ident, data=rt.Recorded(est, cols, name="data"), nu=int(s["nu"]))
    t0 = time.perf_counter()
    g.run(len(w))
    out = {}
    for k, rows in scored.items():
        v = rt.validate(g, data=rt.Recorded(rec.rows(*rows), cols, name="held_out"), fit_steps=n)
        out[f"{k}_mv"] = 1e3 * (burned(v) if k == "held_out" else float(v.rmse[0]))
    return {**out, "p0": p0, "seconds": time.perf_counter() - t0, "theta": ident.theta[0, 0].tolist()}


def study(extended: bool) -> dict:
    torch.set_num_threads(1)
    cands = {**CANDIDATES, **(EXTENDED if extended else {})}
    CANDIDATES.update(cands)                             # structure() and estimator() look names up there
    s_h, s_f = held_out_settings(), settings()
    w, y = columns(s_f, EST)
    y_rms, w_rms = float(y.std()), float(w.std())          # one scaling of theta for both splits
    held = {"held_out": (HOLD, EST[1])}
    rows = {}
    for name in cands:
        terms, nc, lagged, feed_u = cands[name]
        h = offline(s_h, name, (EST[0], HOLD), {**held, **box.TEST_SETS}, y_rms, w_rms)
        f = offline(s_f, name, EST, box.TEST_SETS, y_rms, w_rms, start=np.array(h["p"]))
        rows[name] = {"terms": list(terms), "nc": nc, "lagged": list(lagged), "feed_u": feed_u,
                      "parameters": structure(s_f, name, y_rms, w_rms).n,
                      "offline_held_out": h, "offline_test": f}
        print(f"{name}: held-out {h['held_out_mv']:.3f} mV, test "
              + " / ".join(f"{f[f'{k}_mv']:.3f}" for k in box.TEST_SETS) + f" mV ({h['fit_seconds']:.0f} + "
              f"{f['fit_seconds']:.0f} s)", flush=True)
    ranked = sorted(rows, key=lambda n: rows[n]["offline_held_out"]["held_out_mv"])
    static = [n for n in ranked if rows[n]["nc"] == 0]
    dynamic = [n for n in ranked if rows[n]["nc"] > 0]
    # Online: 'all' through the scenario; the best static structure and every dynamic one in the scenario's
    # graph with the RCOEstimator each needs (the scenario's basis names only 'all' of them) over scaled
    # regressors, p0 chosen on the held-out rows among three values.
    scale = structure(s_f, "all", y_rms, w_rms).scale
    with tempfile.TemporaryDirectory() as tmp:
        rows["all"].update(online_held_out=online_scenario("all", True, Path(tmp) / "h"),
                           online_test=online_scenario("all", False, Path(tmp) / "f"), online="scenario, basis=all")
    for name in dict.fromkeys([static[0], *dynamic]):
        if name == "all":
            continue
        tries = [online_graph(s_h, name, p0, scale, held) for p0 in P0]
        h = min(tries, key=lambda r: r["held_out_mv"] if math.isfinite(r["held_out_mv"]) else math.inf)
        rows[name].update(online_held_out=h, online_test=online_graph(s_f, name, h["p0"], scale, box.TEST_SETS),
                          online="scenario graph, estimator built here",
                          online_p0_tries={str(t["p0"]): t["held_out_mv"] for t in tries})
    # Is the offline optimum a fixed point of the online update? Started there (theta0 = the offline fit on the
    # same rows and known model), one pass at the p0 chosen above: where it ends and its test errors.
    fixed = {}
    for name in dynamic:
        off, p0 = rows[name]["offline_test"], rows[name]["online_held_out"]["p0"]
        fixed[name] = online_graph(s_f, name, p0, scale, box.TEST_SETS, theta0=(off["theta_scaled"], off["alpha"]))
        by_term = [lag[j] for j in range(len(off["theta"][0])) for lag in off["theta_scaled"]]   # phi's order
        fixed[name]["offline_theta"] = by_term + (off["alpha"] if rows[name]["feed_u"] else [])
    best = dynamic[0]
    return {"rows": rows, "ranked": ranked, "best_static": static[0], "best_dynamic": best,
            "started_at_offline_optimum": fixed}


def fmt(v) -> str:
    return "-" if v is None else ("diverged" if not math.isfinite(v) else f"{v:.3f}")


def table(result: dict) -> str:
    """The structures as a Markdown table: RMS errors [mV], offline fit / online refinement."""
    head = ("| structure (u = ...) | nc | parameters | held-out estimation rows | multisine | arrow | "
            "arrow without extrapolation |\n|---|---|---|---|---|---|---|")
    lines = [head]
    for name in result["ranked"]:
        r = result["rows"][name]
        cells = []
        for key, test in (("held_out", "held_out"), *((k, "test") for k in box.TEST_SETS)):
            off = r["offline_held_out" if test == "held_out" else "offline_test"][f"{key}_mv"]
            on = r.get("online_held_out" if test == "held_out" else "online_test", {}).get(f"{key}_mv")
            cells.append(fmt(off) + ("" if on is None else f" / {fmt(on)}"))
        lines.append(f"| {name} | {r['nc']} | {r['parameters']} | " + " | ".join(cells) + " |")
    for name, (ms, ar, an) in PUBLISHED.items():
        lines.append(f"| {name} (published) | | | | {ms:.2f} | {ar:.2f} | {an:.2f} |")
    g = GOAL
    lines.append(f"| goal | | | | {g['multisine']:.2f} | {g['arrow']:.2f} | {g['arrow_noextrap']:.2f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--extended", action="store_true", help="also the slow candidates (several minutes each)")
    ap.add_argument("--table", action="store_true", help="print the table of the results on record and stop")
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/silverbox_structures.json)")
    args = ap.parse_args()
    path = Path(args.out) if args.out else RESULTS / "silverbox_structures.json"
    if args.table:
        print(table(json.loads(path.read_text())))
        return
    t0 = time.perf_counter()
    result = study(args.extended)
    result.update(seconds=time.perf_counter() - t0, hold=HOLD, goal_mv=GOAL, machine=machine(torch.device("cpu")))
    write_json(result, "silverbox_structures", str(path))
    print(table(result))
    print(f"{result['seconds']:.0f} s; wrote {path}")


if __name__ == "__main__":
    main()
