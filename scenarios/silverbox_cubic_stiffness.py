"""Real measured data: the Silverbox benchmark (an electronic Duffing oscillator), cubic spring refined by RCMR.

Data: ``SNLS80mV.csv`` of the Silverbox benchmark (Wigren and Schoukens, ECC 2013), obtained by
``rcotorch.data.datasets.silverbox_files`` (downloaded once and verified, or a local copy in ``$RCOTORCH_SILVERBOX``;
docs/data.md); setting ``data`` names another file. Input w = V1 (volts), output y = V2 (volts, the "position"),
fs = 1e7 / 2^14 Hz.

1. Known model (fitted here, not given): the linear part y'' = -a y' - b y + g (w + u) + d0, fitted by output
   error to the benchmark's estimation rows, [fit_start, fit_stop) (``rcotorch.models.identification.
   MassSpringDamper.fit``): the best linear model of data that hold the nonlinearity. w is the cubic spline
   through its samples between them (setting ``spline``; its slopes are the input's second channel), or
   interpolated linearly (``spline=false``, ``foh``).
2. Unknown subsystem: the cubic hardening spring, its asymmetry, and what the linear fit got wrong while it
   absorbed the spring. The identified subsystem is a basis regressor, linear in theta (setting ``basis``):

       all+quadratic (default):  u(k) = theta_q q + theta_2 q^2 + theta_3 q^3 + theta_v v + theta_w w(k) + theta_1
       all:                      u(k) = theta_q q + theta_3 q^3 + theta_v v + theta_w w(k) + theta_1
       linear+cubic:             u(k) = theta_q q + theta_3 q^3
       cubic:                    u(k) = theta_3 q^3
       cubic-qv:                 all+quadratic and theta q^i (v / omega0)^j for v^2, v^3, q v, q^2 v, q v^2

   static (``nc=0``), or with each term's and u's nc past samples (a dynamic subsystem, whose estimates are
   its static gains), where q and v are the position and velocity the known model predicts half a sample after
   t_k (setting ``lead``; u is held over the sample, so this is the midpoint rule of the continuous forces;
   with ``u_ahead`` the prediction includes the motion of the last sample's u). u enters as g u, like the input,
   so the refined model is y'' = -a' y' - k1 y - k2 y^2 - c y^3 + g' w + d0' with

       c = k3_over_m = -g theta_3,  k2_over_m = -g theta_2,  k1 = k1_over_m = b - g theta_q,
       a' = damping = a - g theta_v,  g' = gain = g (1 + theta_w),  d0' = offset = d0 + g theta_1.

3. Refinement: the recorded estimation multisine, rows [est_start, est_stop), is played back through
   ``rt.refinement(known, identified, data=rt.Recorded(...))``; the known model starts from the state fitted
   to the first ``n_init`` samples; its Markov parameters (nu of them, about 3 decay times of the lightly
   damped resonance) are derived from the model.
4. Validation: free-run simulation (no measurement fed back) on the validation multisine, rows
   [val_start, val_stop), of the initial linear model (theta = 0) and of the refined model (theta frozen at
   its final value), each from the initial state that best fits the first ``n_init`` validation outputs;
   RMS error in volts over the rest of the validation rows.
5. The benchmark's own test sets (with the Silverbox data): the multisine (rows 105712-127400), the arrow
   (rows 100-40575) and the arrow without extrapolation (its first 32000 samples); the first 50 outputs of
   each fix the initial state, and the RMS error in mV is over the rest. Beside the refined model, in the same
   run, two baselines: the linear model alone, and an offline output-error fit of the same linear +
   polynomial spring structure (a, b, g, d0, the spring's coefficients and the initial state by
   ``scipy.optimize.least_squares`` on the free-run error over the estimation rows,
   ``MassSpringDamper.fit_with_spring``); for cubic-qv and nc >= 1 its static polynomial in q only.
"""

from __future__ import annotations

import math
import os
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

import rcotorch as rt
from rcotorch.data.recording import SampleTimeConflict
from rcotorch.errors import ConfigError, DataError
from rcotorch.run.scenario import NON_NEGATIVE, POSITIVE, Requirement, Scenario

if TYPE_CHECKING:
    import torch

    from rcotorch.models.identification import MassSpringDamper, Polynomial

SILVERBOX = "silverbox"      # the default of setting ``data``: the benchmark's SNLS80mV.csv from rt.datasets
# The identified subsystem's terms per setting ``basis``: u = sum_i theta_i phi_i with phi_i among
#   stiffness q, cubic q^3 (q the position lead samples after t_k), damping v (the velocity there),
#   gain w(k), offset 1.
BASES = {"cubic": ("cubic",), "linear+cubic": ("stiffness", "cubic"),
         "all": ("stiffness", "cubic", "damping", "gain", "offset"),
         "all+quadratic": ("stiffness", "quadratic", "cubic", "damping", "gain", "offset"),
         "cubic-qv": ("stiffness", "quadratic", "cubic", "damping", "v2", "v3", "qv", "q2v", "qv2", "gain", "offset")}
# Velocity and product terms (basis cubic-qv: the full cubic polynomial in q and v): term -> (exponents of q
# and v, the estimate of its coefficient c in y'' = ... - c q^i v^j, and that coefficient's unit). The regressor
# is q^i (v / omega0)^j, omega0 = sqrt(b) the linear model's natural frequency, so that each term is of the size
# of the powers of q beside it and one p0 suits them all.
MIXED = {"v2": ((0, 2), "c_v2_over_m", "1/V"), "v3": ((0, 3), "c_v3_over_m", "s/V^2"),
         "qv": ((1, 1), "c_qv_over_m", "1/(V s)"), "q2v": ((2, 1), "c_q2v_over_m", "1/(V^2 s)"),
         "qv2": ((1, 2), "c_qv2_over_m", "1/V^2")}
POWERS = {"stiffness": 1, "quadratic": 2, "cubic": 3}      # the terms that are powers of the position
SLOPE = "w_slope"          # the derived column of the input's spline slopes (setting ``spline``)
# The benchmark's test sets (rows of SNLS80mV.csv): the first 50 outputs of each fix the initial state.
TEST_SETS = {"multisine": (105712, 127400), "arrow": (100, 40575), "arrow_noextrap": (100, 32100)}


@lru_cache(maxsize=4)
def _prepare(path: str, mtime: float, w_col: str, y_col: str, Ts: float, fit_rows: tuple[int, int],
             foh: bool, lead: float, spline: bool, u_ahead: bool) -> tuple[rt.Recording, MassSpringDamper]:
    from rcotorch.models.identification import MassSpringDamper
    silverbox = Path(path).name == "SNLS80mV.csv" and (w_col, y_col) == ("V1", "V2")
    try:
        rec = rt.load(path, columns=[w_col, y_col], dt=Ts, units={"V1": "V", "V2": "V"} if silverbox else None)
    except SampleTimeConflict as e:           # the file states its own sample time (a scalar, a time column)
        raise DataError(f"scenario 'silverbox-cubic-stiffness': {e.path} states the sample time {e.stated:.10g} s "
                        f"({e.where}), but the setting Ts is {Ts:.10g} s; pass --set Ts={e.stated:.10g} if the file "
                        "is right, or correct the file") from None
    fit = rec.rows(*fit_rows)
    try:
        model = MassSpringDamper.fit(fit.column(w_col), fit.column(y_col), Ts, foh=foh, lead=lead, spline=spline,
                                     u_ahead=u_ahead)
    except DataError as e:
        raise DataError(f"scenario 'silverbox-cubic-stiffness': {path}, rows {fit_rows[0]}-{fit_rows[1]} "
                        f"(columns {w_col!r}, {y_col!r}): {e}") from None
    return rec, model


def data_path(s) -> Path:
    """The data file of settings ``s``: the Silverbox benchmark's SNLS80mV.csv (verified, from
    ``rt.datasets``) for ``data=silverbox``, else the named file."""
    if s["data"] == SILVERBOX:
        try:
            return rt.datasets.silverbox_files()["SNLS80mV.csv"].resolve()
        except DataError as e:
            raise DataError(f"scenario 'silverbox-cubic-stiffness': {e}") from None
    path = Path(s["data"]).expanduser()
    if not path.is_file():
        raise DataError(f"scenario 'silverbox-cubic-stiffness': data file {path} not found. Pass another path with "
                        "--set data=PATH (a CSV, NPZ or .mat file with the input and output columns), or "
                        f"--set data={SILVERBOX} for the Silverbox benchmark.")
    return path.resolve()


def prepare(s) -> tuple[rt.Recording, MassSpringDamper]:
    """The recording (input and output columns) and the fitted linear model for settings ``s`` (cached)."""
    path = data_path(s)
    for a, b in (("fit_start", "fit_stop"), ("est_start", "est_stop"), ("val_start", "val_stop")):
        if not 0 <= s[a] < s[b]:
            raise ConfigError(f"scenario 'silverbox-cubic-stiffness': need 0 <= {a} < {b}, got {s[a]}, {s[b]}")
    for key in ("est", "val"):
        if s[f"{key}_stop"] - s[f"{key}_start"] <= s["n_init"]:
            raise ConfigError(f"scenario 'silverbox-cubic-stiffness': the {key} rows must be more than "
                              f"n_init = {s['n_init']}")
    return _prepare(str(path), os.path.getmtime(path), s["w_column"], s["y_column"], float(s["Ts"]),
                    (int(s["fit_start"]), int(s["fit_stop"])), bool(s["foh"]), float(s["lead"]), bool(s["spline"]),
                    bool(s["u_ahead"]))


def recorded(s, rows: tuple[int, int], name: str, dtype=None) -> rt.Recorded:
    """The recording's ``rows`` played back as block ``name`` with outputs w and y: w with the spline's slopes
    over these rows as its second channel where the setting ``spline`` is on (``MassSpringDamper.inputs``)."""
    from rcotorch.data.recording import function
    from rcotorch.models.identification import spline_slopes
    rec, _ = prepare(s)
    part = rec.rows(*rows)
    w = s["w_column"]
    if s["spline"]:
        part = part.derive(**{SLOPE: function(spline_slopes, w, unit=part.unit(w))})
        w = [w, SLOPE]
    kw = {} if dtype is None else {"dtype": dtype}
    return rt.Recorded(part, {"w": w, "y": s["y_column"]}, name=name, **kw)


@lru_cache(maxsize=64)
def _validate(path, mtime, w_col, y_col, Ts, fit_rows, foh, lead, spline, u_ahead, val_rows, n_init, spring,
              offline=None):
    from rcotorch.models.identification import rmse
    rec, model = _prepare(path, mtime, w_col, y_col, Ts, fit_rows, foh, lead, spline, u_ahead)
    if offline is not None:                  # the offline fit's model and spring, by its estimation rows
        model, spring = _offline(path, mtime, w_col, y_col, Ts, fit_rows, foh, lead, spline, u_ahead, *offline)
    val = rec.rows(*val_rows)
    w, y = model.inputs(val.column(w_col)), val.column(y_col)
    fb = None if spring is None or not any(spring.coefficients) else spring
    with np.errstate(over="ignore", invalid="ignore"):
        try:
            x0 = model.initial_state(w[:n_init], y[:n_init], fb)
            y_sim = model.simulate(w, x0, fb)
        except (ValueError, FloatingPointError):  # a diverged theta
            y_sim = np.full_like(y, math.nan)
    err = rmse(y_sim[n_init:], y[n_init:]) if np.all(np.isfinite(y_sim)) else math.nan
    return err, y_sim


@lru_cache(maxsize=4)
def _offline(path, mtime, w_col, y_col, Ts, fit_rows, foh, lead, spline, u_ahead, est_rows, powers
             ) -> tuple[MassSpringDamper, Polynomial]:
    rec, model = _prepare(path, mtime, w_col, y_col, Ts, fit_rows, foh, lead, spline, u_ahead)
    est = rec.rows(*est_rows)
    return model.fit_with_spring(est.column(w_col), est.column(y_col), powers=powers)


def _key(s) -> tuple:
    path = data_path(s)
    return (str(path), os.path.getmtime(path), s["w_column"], s["y_column"], float(s["Ts"]),
            (int(s["fit_start"]), int(s["fit_stop"])), bool(s["foh"]), float(s["lead"]), bool(s["spline"]),
            bool(s["u_ahead"]))


def offline_powers(s) -> tuple[int, ...]:
    """The powers of the position in the offline fit's spring: those of the basis, the cubic at least (the
    other terms of ``all`` are the linear model's own parameters, which the offline fit refits)."""
    return tuple(sorted({3} | {POWERS[t] for t in BASES[s["basis"]] if POWERS.get(t, 1) > 1}))


def sees(s) -> tuple[str, ...]:
    """The channels of y0 (``MassSpringDamper.lti``) the identified subsystem of settings ``s`` needs."""
    terms = BASES[s["basis"]]
    return ("position", "velocity", "input") if any(t not in POWERS for t in terms) else ("position",)


def features(s) -> list:
    """The regressor of settings ``s``: one ``rt.features`` term per entry of ``BASES[basis]``."""
    f = rt.features
    one = len(sees(s)) == 1
    q = "y0" if one else "y0[0]"
    made = {"stiffness": lambda: f.port(q), "quadratic": lambda: f.power(q, 2), "cubic": lambda: f.power(q, 3),
            "damping": lambda: f.port("y0[1]"),
            "gain": lambda: f.port("y0[2]"), "offset": lambda: f.constant()}
    if any(t in MIXED for t in BASES[s["basis"]]):
        omega = math.sqrt(prepare(s)[1].b)
        for term, ((i, j), _, _) in MIXED.items():
            made[term] = (lambda i=i, j=j: omega ** -j * f.monomial({k: e for k, e in (("y0[0]", i), ("y0[1]", j))
                                                                     if e}))
    return [made[t]() for t in BASES[s["basis"]]]


def spring(s, theta) -> Polynomial:
    """The identified subsystem u = sum_i theta_i y0^p_i for settings ``s`` whose basis holds powers of the
    position only, and one member's theta."""
    from rcotorch.models.identification import Polynomial
    terms = BASES[s["basis"]]
    if any(t not in POWERS for t in terms):
        raise ConfigError(f"scenario 'silverbox-cubic-stiffness': basis {s['basis']!r} is not a polynomial spring")
    return Polynomial(tuple(float(t) for t in np.atleast_1d(np.asarray(theta, dtype=float))),
                      tuple(POWERS[t] for t in terms))


def validate(s, theta, rows: tuple[int, int] | None = None, offline: bool = False) -> tuple[float, np.ndarray]:
    """Free-run RMS error [V] on the validation rows (or ``rows``; after the first n_init) and the simulated
    output: of the linear model with the identified subsystem of ``theta`` (zeros: the initial linear model),
    or with ``offline`` of the offline output-error fit of the linear + cubic structure."""
    prepare(s)
    rows = (int(s["val_start"]), int(s["val_stop"])) if rows is None else tuple(int(r) for r in rows)
    fit = ((int(s["est_start"]), int(s["est_stop"])), offline_powers(s)) if offline else None
    return _validate(*_key(s), rows, int(s["n_init"]), None if offline else spring(s, theta), fit)


def offline_fit(s) -> tuple[MassSpringDamper, Polynomial]:
    """The offline output-error fit of the linear model and the polynomial spring (``offline_powers``) on the
    estimation rows."""
    prepare(s)
    return _offline(*_key(s), (int(s["est_start"]), int(s["est_stop"])), offline_powers(s))


class SilverboxCubicStiffness(Scenario):
    name = "silverbox-cubic-stiffness"
    section = "real data"
    description = "Silverbox measurements: cubic spring k3/m refined on a linear m-d-k1 model fitted to the data"
    steps = 105712 - 40650          # the whole estimation multisine
    settings = dict(data=SILVERBOX, w_column="V1", y_column="V2", Ts=2 ** 14 / 1e7,
                    fit_start=40650, fit_stop=105712, est_start=40650, est_stop=105712, val_start=105712,
                    val_stop=127400, n_init=50, foh=True, spline=True, u_ahead=True, lead=0.5, basis="all+quadratic",
                    nc=0, p0=1e4, lam=1.0, nu=100, test_sets=True)
    requirements = (Requirement("metrics.val_rmse_refined", "max", 0.002, inclusive=True),
                    Requirement("metrics.val_rmse_ratio", "max", 0.2, inclusive=True))
    per_member = frozenset({"p0", "lam"})
    bounds = dict(Ts=POSITIVE, nc=NON_NEGATIVE, fit_start=NON_NEGATIVE, fit_stop=NON_NEGATIVE, est_start=NON_NEGATIVE,
                  est_stop=NON_NEGATIVE, val_start=NON_NEGATIVE, val_stop=NON_NEGATIVE, n_init=NON_NEGATIVE)
    units = {**{f"{x}{k}": u for k, u in (("k3_over_m", "1/(V^2 s^2)"), ("k2_over_m", "1/(V s^2)"),
                                                 ("k1_over_m", "1/s^2"), ("damping", "1/s"),
                                         ("gain", "1/s^2"), ("offset", "V/s^2")) for x in ("", "offline_")},
             **{key: unit for _, key, unit in MIXED.values()},
             "y": "V", "val_rmse_initial": "V", "val_rmse_refined": "V",
             **{f"test_{t}_rmse_mv{x}": "mV" for t in TEST_SETS for x in ("", "_linear", "_offline")}}
    about = dict(
        data=("", "'silverbox' (the benchmark, downloaded once or from $RCOTORCH_SILVERBOX) or a CSV/NPZ/.mat file"),
        w_column=("", "column of the input w (volts for the Silverbox)"),
        y_column=("", "column of the measured output y (volts for the Silverbox)"),
        Ts=("s", "sample time of the data"),
        fit_start=("row", "first data row (0-based) of the stretch the linear initial model is fitted to"),
        fit_stop=("row", "end (exclusive) of the fitting rows"),
        est_start=("row", "first data row of the refinement (the estimation multisine)"),
        est_stop=("row", "end (exclusive) of the refinement rows"),
        val_start=("row", "first data row of the free-run validation"),
        val_stop=("row", "end (exclusive) of the validation rows"),
        n_init=("samples", "samples used to fit the initial state before refinement and validation"),
        foh=("", "interpolate the input linearly between samples (first-order hold) in the model"),
        spline=("", "interpolate the input by the cubic spline through its samples in the model (overrides foh)"),
        u_ahead=("", "the position the spring sees lead samples ahead includes the motion of the last sample's u"),
        lead=("samples", "the cubic spring sees the position this far after each sample (0.5: mid-sample)"),
        basis=("", "what the identified subsystem refines: 'all+quadratic' (stiffness, quadratic and cubic spring, "
                   "damping, input gain and offset), 'cubic-qv' (those and v^2, v^3, q v, q^2 v, q v^2: the full "
                   "cubic polynomial in q and v), 'all' (without the quadratic term), 'linear+cubic' "
                   "(theta_1 y0 + theta_3 y0^3), or 'cubic' (theta_3 y0^3 alone)", tuple(BASES)),
        nc=("samples", "past samples of each basis term and of u in the identified subsystem: 0 a static basis, "
                       "nc >= 1 a dynamic one whose estimates are its static gains (the offline fit stays static)"),
        test_sets=("", "score the benchmark's test sets (multisine, arrow, arrow without extrapolation) against "
                       "the linear model and an offline output-error fit of the same structure (Silverbox data)"),
    )

    def default_steps(self, s) -> int:
        """The whole refinement rows, [est_start, est_stop)."""
        return int(s["est_stop"]) - int(s["est_start"])

    def build(self, s, batch, dtype, device):
        rec, model = prepare(s)
        est = rec.rows(int(s["est_start"]), int(s["est_stop"]))
        w, y, n = model.inputs(est.column(s["w_column"])), est.column(s["y_column"]), int(s["n_init"])
        known = model.lti(x0=model.initial_state(w[:n], y[:n]), dtype=dtype, sees=sees(s))
        if int(s["nc"]) == 0:
            ident = rt.RCOEstimator.static_gain({"y0": len(sees(s))}, features=features(s), p0=s["p0"],
                                                lam=s["lam"], dtype=dtype)
        else:                       # each term and u with nc past samples: a dynamic subsystem
            ident = rt.RCOEstimator({"y0": len(sees(s))}, nc=int(s["nc"]), proper=True, features=features(s),
                                    p0=s["p0"], lam=s["lam"], dtype=dtype)
        data = recorded(s, (int(s["est_start"]), int(s["est_stop"])), "data", dtype)
        return rt.refinement(known, ident, data=data, nu=int(s["nu"]), batch_size=batch, dtype=dtype,
                             device=device)

    def validation(self, g, s):
        """Held-out data: the validation rows (by default the benchmark's multisine test set; to tune without
        looking at a test set, hold out the end of the estimation rows: est_stop = val_start < val_stop <=
        105712)."""
        return {"data": recorded(s, (int(s["val_start"]), int(s["val_stop"])), "held_out",
                                 g.role("estimator").theta.dtype)}

    @staticmethod
    def model(s) -> MassSpringDamper:
        """The linear initial model fitted for settings ``s``."""
        return prepare(s)[1]

    @staticmethod
    def theta(graph) -> torch.Tensor:
        """Each basis term's static gain per member, (B, number of basis terms): theta of a static basis, the
        DC gain (I - sum_l M_l)^-1 sum_l N_l of a dynamic one (nc >= 1)."""
        est = graph.role("estimator")
        if est.nc == 0:
            return est.theta[:, 0, :]
        from rcotorch.estimator.transfer import dc_gain
        return dc_gain(est)[:, 0, :]

    def estimates(self, g, s):
        """k3/m and, by basis, the refined model's k1/m, damping a, input gain g and offset d0 (u enters as
        g u: y'' = -(a - g theta_v) y' - (b - g theta_q) y + g theta_3 y^3 + g (1 + theta_w) w + d0 + g theta_1)."""
        model, theta = prepare(s)[1], self.theta(g)
        terms = BASES[s["basis"]]
        th = {name: theta[:, i] for i, name in enumerate(terms)}
        out = {"k3_over_m": model.cubic_coefficient(th["cubic"])}
        if "quadratic" in th:
            out["k2_over_m"] = model.cubic_coefficient(th["quadratic"])
        if "stiffness" in th:
            out["k1_over_m"] = model.b - model.g * th["stiffness"]
        if "damping" in th:
            out["damping"] = model.a - model.g * th["damping"]
        if "gain" in th:
            out["gain"] = model.g * (1 + th["gain"])
        if "offset" in th:
            out["offset"] = model.d0 + model.g * th["offset"]
        for term, ((_, j), key, _) in MIXED.items():
            if term in th:
                out[key] = model.cubic_coefficient(th[term]) / math.sqrt(model.b) ** j
        return out

    @staticmethod
    def held_out(g, s, rows: tuple[int, int]):
        """``rt.validate`` of the refined graph on the recording's ``rows``: the refined model (theta frozen)
        and the initial linear model, free run from the state fitted to the first n_init outputs."""
        data = recorded(s, rows, "held_out", g.role("estimator").theta.dtype)
        return rt.validate(g, data=data, fit_steps=int(s["n_init"]))

    def metrics(self, g, s):
        import torch
        _, model = prepare(s)
        B = g.batch_size
        scored = {}

        def score(rows):
            if rows not in scored:
                v = self.held_out(g, s, rows)
                scored[rows] = (v.rmse.detach().to(torch.float64).cpu(), float(v.rmse_initial[0]))
            return scored[rows]

        def full(v):
            return torch.full((B,), float(v), dtype=torch.float64)

        refined, initial = score((int(s["val_start"]), int(s["val_stop"])))
        out = {"val_rmse_initial": full(initial), "val_rmse_refined": refined,
               "val_rmse_ratio": refined / initial, "linear_a": full(model.a), "linear_b": full(model.b),
               "linear_g": full(model.g), "linear_d0": full(model.d0), "linear_f0_hz": full(model.f0),
               "linear_fit_rmse": full(model.fit_rmse)}
        if s["test_sets"] and s["data"] == SILVERBOX:
            off, spring_off = offline_fit(s)
            for name, rows in TEST_SETS.items():
                refined, initial = score(rows)
                out[f"test_{name}_rmse_mv"] = 1e3 * refined
                out[f"test_{name}_rmse_mv_linear"] = full(1e3 * initial)
                out[f"test_{name}_rmse_mv_offline"] = full(1e3 * validate(s, None, rows, offline=True)[0])
            coef = dict(zip(spring_off.powers, spring_off.coefficients))
            out["offline_k3_over_m"] = full(off.cubic_coefficient(coef[3]))
            if 2 in coef:
                out["offline_k2_over_m"] = full(off.cubic_coefficient(coef[2]))
            out["offline_k1_over_m"], out["offline_damping"] = full(off.b), full(off.a)
            out["offline_gain"], out["offline_offset"] = full(off.g), full(off.d0)
        return out

    def figures(self, g, s):
        import matplotlib.pyplot as plt

        v = self.held_out(g, s, (int(s["val_start"]), int(s["val_stop"])))
        y = v.measured[:, 0, 0].cpu().numpy()
        y0, y1 = v.initial[:, 0, 0].cpu().numpy(), v.refined[:, 0, 0].cpu().numpy()
        e0, e1 = float(v.rmse_initial[0]), float(v.rmse[0])
        n = int(s["n_init"])
        centre = n + int(np.argmax(np.abs(y[n:])))           # the largest swing: where the cubic term matters
        lo = max(n, centre - 150)
        hi = min(len(y), lo + 300)
        t = (np.arange(lo, hi)) * float(s["Ts"])
        fig, (ax, ae) = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
        ax.plot(t, y[lo:hi], "k", lw=1.6, label="measured")
        ax.plot(t, y0[lo:hi], color="tab:orange", lw=1, label=f"initial linear model (rms err {e0 * 1e3:.2f} mV)")
        ax.plot(t, y1[lo:hi], "--", color="tab:blue", lw=1, label=f"refined (rms err {e1 * 1e3:.2f} mV)")
        ax.set_ylabel("output V2 [V]")
        ax.legend(loc="upper right", fontsize=8)
        ax.set_title(f"Silverbox validation multisine (rows {s['val_start']}..{s['val_stop']}), free run")
        ae.plot(t, (y0 - y)[lo:hi] * 1e3, color="tab:orange", lw=1, label="initial - measured")
        ae.plot(t, (y1 - y)[lo:hi] * 1e3, color="tab:blue", lw=1, label="refined - measured")
        ae.set_ylabel("error [mV]")
        ae.set_xlabel(f"time since validation start [s] (window of {hi - lo} samples)")
        ae.legend(loc="upper right", fontsize=8)
        for a in (ax, ae):
            a.grid(alpha=0.3)
        fig.tight_layout()
        return {"validation": fig}


SCENARIO = SilverboxCubicStiffness()
