"""Seed Section VII: the NO 5.3 um cooling a thermosphere model lacks, refined from measured mass densities.

Physical system ("truth"): the reduced 1-D thermosphere column of ``rcotorch.models.thermosphere`` (100-600 km, 5 km
levels) *with* Kockarts' NO cooling, driven by w = [F10.7, storm power]: F10.7 = 150 and a storm starting on day
2 (peak 4 mW/m^2 six hours after onset). Measured: the mass density at the altitudes ``measured_km`` (default 407
km, the seed paper's case; e.g. ``'407,150'`` for two satellites), y in units of 1e-12 kg/m^3. With several
densities, each counts by its relative error: the weight on z is R = diag((rho_1 / rho_i)^2), rho_i the initial
density at altitude i.

Known model ("initial model"): the same column *without* NO cooling, with an input u: the cooling at three
altitudes (120, 152, 200 km, nW/m^3), filled in between (``interpolate``) and subtracted in the energy equation:
linearly in the cooling, or, for the known form, in proportion to the model's own Kockarts rate y0(z) (linearly
in the strength u_j / y0_j, so the profile is y0(z) times the interpolated strength). Both columns start from the
truth's state after a 3-day quiet spin-up.

Identified subsystem, ``structure``:

* ``'kockarts'`` (the default), the *known-form* variant: u_j = theta_j y0_j with y0_j the Kockarts cooling rate
  that the known model's own state (its T, O and NO densities) would have at node j at unit strength. RCMR finds
  only the strength of the law: one for the whole profile (``strengths='one'``, the default: one density fixes
  one number) or one per node (``'node'``, a diagonal theta). theta = 1 is the truth. theta is projected onto
  [0, theta_max].
* ``'temperature'``, the seed paper's premise (the cooling's form is unknown, "most likely a function of
  temperature"): u_j = sum_i theta_ji f_i(T_j), where the f_i are the basis functions ``features`` of the known
  model's temperature at node j and their low-pass memories (``TemperatureFeatures``), nothing else. Per node
  by default; ``shared=True`` ties theta across the nodes (one function of temperature for every node).
* ``'error'``, the seed paper's literal form: u = theta [z(k-1..k-nc); u(k-1..k-nc)], driven by the model error.

Every structure saturates u >= 0 (``u_bounds``: a cooling cannot heat).

Markov parameters of u -> z: by linearizing the known model (``markov_method``: 'autograd' or 'fd') along its
trajectory with w and u held, nu of them (2 days, the thermal memory of the lower thermosphere), refreshed every
``refresh_every`` steps from the model's present state and inputs.

Metrics (docs/scenarios.md): ``density_err_ratio`` = rms(refined - truth) / rms(initial - truth) of the density at
407 km over the last day, whether or not 407 km is measured (the initial model is the known model run with u = 0
on the same driver), and ``density_err_ratio_<alt>km`` at every other measured altitude; ``cooling_corr_152km``
and ``cooling_rel_rms_152km`` = rms(est - true)/rms(true) of the estimated and true NO cooling at 152 km, over the
samples from ``cooling_window_start_h`` (one day of adaptation) to the end; ``cooling_rel_rms_<node>km`` at the
other nodes and ``cooling_profile_rel_rms`` over 100-300 km, the same window.

Generalization (``replay``): after the run the identified subsystem is frozen (theta held, P = 0) and both
columns are driven, from a quiet spin-up at ``replay_f107``, by another space-weather history (a storm of
``replay_storm_peak`` at ``replay_storm_start_h``). The ``replay_*`` metrics score the frozen cooling over the
whole replay, and ``replay_density_err_ratio`` compares it with the initial model at 407 km. (The ``'error'``
structure's frozen controller is still fed by the replay's measured density.)
"""

from __future__ import annotations

import math
import weakref
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

import rcotorch as rt
from rcotorch.errors import ConfigError
from rcotorch.run.scenario import NON_NEGATIVE, POSITIVE, Requirement, Scenario, member_values

if TYPE_CHECKING:
    import torch

    from rcotorch.models.thermosphere import Column, Observation, TemperatureFeatures

EVAL_ALTITUDE = 152e3          # cooling metrics
DENSITY_ALTITUDE = 407e3       # density_err_ratio
PROFILE_TOP = 300e3            # cooling_profile_rel_rms covers 100-300 km
FIGURE12_DAYS = (0.5, 0.8, 1.6, 2.7)   # the seed's Figure 12: days after adaptation starts
STRUCTURES = ("kockarts", "temperature", "error")
REPLAY = ("f107", "storm_peak", "storm_start_h", "storm_rise_h")


def measured_altitudes(s) -> list[float]:
    """The measured altitudes [m] of setting ``measured_km`` ('407' or '407,150')."""
    text = str(s["measured_km"])
    try:
        km = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise ConfigError(f"setting measured_km must be altitudes in km separated by commas (e.g. '407,150'), "
                          f"got {text!r}") from None
    if not km or any(not 100.0 < a < 600.0 for a in km) or len(set(km)) != len(km):
        raise ConfigError(f"setting measured_km: give distinct altitudes between 100 and 600 km, got {text!r}")
    return [a * 1e3 for a in km]


def interpolation(s) -> str:
    """How the known model fills the cooling between the nodes (setting ``interpolate``; ``auto``: the strength
    for the known-form structure, the cooling for the others)."""
    if s["interpolate"] == "auto":
        return "strength" if s["structure"] == "kockarts" else "cooling"
    if s["interpolate"] == "strength" and s["structure"] != "kockarts":
        raise ConfigError(f"setting interpolate='strength' shapes the cooling by the Kockarts rate, which only "
                          f"structure='kockarts' may know; structure={s['structure']!r} interpolates the cooling")
    return s["interpolate"]


def columns(s, dtype: torch.dtype | None = None) -> tuple[Column, Column]:
    """The truth column (with NO cooling) and the known model (without it, with the cooling input u), in
    ``dtype`` (default float64)."""
    import torch

    from rcotorch.models.thermosphere import Column
    dtype = torch.float64 if dtype is None else dtype
    common = dict(dz=s["dz_km"] * 1e3, latitude=s["latitude"], local_time0=s["local_time0"], dt=s["Ts"],
                  substeps=int(s["substeps"]), dtype=dtype)
    nodes = (s["node1_km"] * 1e3, s["node2_km"] * 1e3, s["node3_km"] * 1e3)
    return (Column(no_cooling=True, **common),
            Column(no_cooling=False, cooling_nodes=nodes, interpolate=interpolation(s), **common))


@lru_cache(maxsize=8)
def _spin_up(f107: tuple, days: float, dz_km: float, latitude: float, local_time0: float, Ts: float,
             substeps: int, native: bool) -> torch.Tensor:
    import torch

    from rcotorch.models.thermosphere import Column
    truth = Column(dz=dz_km * 1e3, latitude=latitude, local_time0=local_time0, dt=Ts, substeps=substeps)
    if not native:
        return truth.spin_up(torch.tensor(f107, dtype=torch.float64), days)
    from rcotorch.models.thermosphere_native import NativeColumn
    return NativeColumn(truth).spin_up(torch.tensor(f107, dtype=torch.float64), days)


def initial_state(s, native: bool = False) -> torch.Tensor:
    """The truth's state after the quiet spin-up, (1 or B, 2n + 1), float64 (cached); ``native``: stepped by the
    column's native code."""
    f107 = tuple(float(v) for v in member_values(s, "f107").reshape(-1))
    return _spin_up(f107, float(s["spinup_days"]), float(s["dz_km"]), float(s["latitude"]),
                    float(s["local_time0"]), float(s["Ts"]), int(s["substeps"]), native).clone()


def replay_settings(s) -> dict:
    """The settings of the generalization replay: the run's, with the replay's space weather."""
    return {**s, **{key: s[f"replay_{key}"] for key in REPLAY}}


def densities(column: Column, altitudes) -> Observation:
    """State -> mass densities at ``altitudes`` [1e-12 kg/m^3], (B, len(altitudes))."""
    from rcotorch.models.thermosphere import Observation
    return Observation(column, "density", altitudes)


def _rms(v: torch.Tensor) -> torch.Tensor:
    return v.pow(2).mean(1).sqrt()


def _corr(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    da, db = a - a.mean(1, keepdim=True), b - b.mean(1, keepdim=True)
    return (da * db).sum(1) / (da.pow(2).sum(1) * db.pow(2).sum(1)).sqrt()


class ThermosphereNoCooling(Scenario):
    name = "thermosphere-no-cooling"
    section = "VII"
    description = ("reduced thermosphere column: NO cooling at three altitudes refined from the mass density at "
                   "407 km or more altitudes (truth with NO cooling, initial model without)")
    steps = 480                       # 5 days at Ts = 900 s
    # The estimates are the cooling rates of the last step (u, a function of the column's state as well as
    # of theta): the intervals' delta method in theta does not describe them.
    intervals = False
    validation_steps = 0            # held-out data on request: setting validate_h (see ``validation``)
    settings = dict(Ts=900.0, substeps=2, dz_km=5.0, f107=150.0, storm_peak=4.0, storm_start_h=48.0,
                    storm_rise_h=6.0, latitude=30.0, local_time0=0.0, spinup_days=3.0, measured_km="407",
                    node1_km=120.0, node2_km=152.0, node3_km=200.0, structure="kockarts", strengths="one",
                    interpolate="auto", features="r2,lp12:r2,lp3:r3", shared=False, nc=2, p0=1.0, lam=1.0, nu=192,
                    theta_max=10.0, markov_method="autograd", refresh_every=24, cooling_window_start_h=24.0,
                    replay=True, replay_f107=110.0, replay_storm_peak=6.0, replay_storm_start_h=30.0,
                    replay_storm_rise_h=4.0, validate_h=0.0)
    requirements = (Requirement("metrics.density_err_ratio", "max", 0.25),
                    Requirement("metrics.cooling_corr_152km", "min", 0.8),
                    Requirement("metrics.cooling_rel_rms_152km", "max", 0.3, inclusive=True))
    per_member = frozenset({"f107", "storm_peak", "p0", "lam"})
    bounds = dict(Ts=POSITIVE, substeps=POSITIVE, dz_km=POSITIVE, f107=POSITIVE, storm_peak=NON_NEGATIVE,
                  spinup_days=NON_NEGATIVE, nc=NON_NEGATIVE, refresh_every=NON_NEGATIVE, validate_h=NON_NEGATIVE,
                  replay_f107=POSITIVE, replay_storm_peak=NON_NEGATIVE)
    units = {"y": "1e-12 kg/m^3", **{f"cooling_{km}km": "nW/m^3" for km in (120, 152, 200)},
             "cooling_152km_true": "nW/m^3"}
    about = dict(
        validate_h=("h", "held-out validation (what `rcotorch tune` scores): the refined column, theta frozen, run "
                         "this long on the same drivers after the run against the truth's density (0: none; it "
                         "fits the column's state, about 10 s for the default column)"),
        Ts=("s", "sample time (one refinement step)"),
        substeps=("", "backward-Euler substeps of the column per sample"),
        dz_km=("km", "altitude spacing of the column's levels"),
        f107=("sfu", "solar 10.7 cm flux F10.7 (1 sfu = 1e-22 W m^-2 Hz^-1)"),
        storm_peak=("mW/m^2", "peak Joule and particle heating of the storm"),
        storm_start_h=("h", "storm onset after the start of the run"),
        storm_rise_h=("h", "time from storm onset to its peak"),
        latitude=("deg", "latitude of the column"),
        local_time0=("h", "local solar time at the start"),
        spinup_days=("d", "quiet spin-up of the truth before the run (both columns start from it)"),
        measured_km=("km", "altitudes of the measured mass densities, separated by commas (e.g. 407,150), each "
                           "between 100 and 600 km"),
        node1_km=("km", "lowest altitude where the cooling is estimated"),
        node2_km=("km", "middle altitude where the cooling is estimated"),
        node3_km=("km", "highest altitude where the cooling is estimated"),
        strengths=("", "structure=kockarts: one strength of the Kockarts law for the whole profile, or one per "
                       "node", ("one", "node")),
        interpolate=("", "how the known model fills the cooling between the nodes: linearly in the cooling, or "
                         "(structure=kockarts) in proportion to its own Kockarts rate, linearly in the strength "
                         "u_j / y0_j; auto: strength for kockarts, cooling otherwise",
                     ("auto", "strength", "cooling")),
        structure=("", "what the identified subsystem sees: the Kockarts rate of the model's own state "
                       "(known form), its node temperatures only, or the density error (docs/thermosphere.md)",
                   STRUCTURES),
        features=("", "basis of structure=temperature: r<p> = (exp(-2700 K/T) / exp(-2700 K/T_ref))^p, T_ref the "
                      "node's initial temperature (with shared, the middle node's); lp<h>:r<p> its low-pass memory "
                      "with time constant h hours"),
        shared=("", "structure=temperature: one function of temperature for every node (tied theta) instead of "
                    "one per node"),
        nc=("", "order of the error-driven identified subsystem (structure=error)"),
        nu=("", "number of Markov parameters of u -> z (nu Ts: how far ahead the cost looks)"),
        theta_max=("", "structure=kockarts: upper bound of theta (projection onto [0, theta_max])"),
        markov_method=("", "how the column is linearized for the Markov parameters", ("autograd", "fd")),
        refresh_every=("steps", "refresh the Markov parameters every N steps (0: never)"),
        cooling_window_start_h=("h", "start of the window over which the cooling metrics are computed"),
        replay=("", "after the run, replay the frozen identified subsystem on another space weather (replay_* "
                    "metrics and figure)"),
        replay_f107=("sfu", "F10.7 of the replay"),
        replay_storm_peak=("mW/m^2", "peak storm heating of the replay"),
        replay_storm_start_h=("h", "storm onset in the replay"),
        replay_storm_rise_h=("h", "time from storm onset to its peak in the replay"),
    )

    def __init__(self):
        self._initial_runs: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self._replays: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    def build(self, s, batch, dtype, device):
        return self._graph(s, batch, dtype, device)

    def output_names(self, settings) -> list[str]:
        """The mass density at each measured altitude: 'density at 407 km', ..."""
        return [f"density at {a / 1e3:g} km" for a in measured_altitudes(settings)]

    def _graph(self, s, batch, dtype, device, frozen: rt.Graph | None = None) -> rt.Graph:
        """The refinement graph; with ``frozen`` (a trained graph) its identified subsystem, held fixed."""
        import torch

        from rcotorch.models.thermosphere import (
            ColumnBlock,
            Observation,
            Record,
            SpaceWeather,
            TemperatureFeatures,
            native_here,
        )
        truth, model = columns(s, dtype)
        x0 = initial_state(s, native_here(dtype, device)).to(dtype)
        measured = measured_altitudes(s)
        alts = [DENSITY_ALTITUDE, *measured]
        outputs = {"y": densities(model, measured)}
        if s["structure"] == "kockarts":
            outputs["y0"] = Observation(model, "no_cooling_at_nodes")
        elif s["structure"] == "temperature":
            outputs["T"] = Observation(model, "temperature_at_nodes")
        # densities, u, w and, for interpolate='strength', the model's Kockarts rate
        shape = [Observation(model, "no_cooling_profile")] if model.interpolate == "strength" else []
        known = ColumnBlock(model, outputs, x0=x0, name="known", dtype=dtype,
                            record=Record(densities(model, alts), "u", "w", *shape))
        plant = ColumnBlock(truth, {"y": densities(truth, measured)}, x0=x0, name="plant", dtype=dtype,
                            record=Record(densities(truth, alts), Observation(truth, "no_cooling_profile")))
        f107, peak = member_values(s, "f107", dtype), member_values(s, "storm_peak", dtype)
        driver = SpaceWeather(s["Ts"], f107, peak, start=s["storm_start_h"], rise=s["storm_rise_h"], dtype=dtype)
        if frozen is None:
            w0 = torch.stack([f107.reshape(-1), torch.zeros_like(f107).reshape(-1)], 1)
            H = known.markov("u", "y", int(s["nu"]) + 1, inputs={"w": w0}, method=s["markov_method"])
            beta = (-H[:, 1:]).expand(batch, -1, -1, -1).contiguous()
        else:
            beta = frozen.role("estimator").beta
        rho = densities(truth, measured)(x0[:1])[0]
        common = dict(p0=member_values(s, "p0", dtype), lam=member_values(s, "lam", dtype), markov=beta,
                      first_delay=1, u_bounds=(0.0, math.inf), n_z=len(measured),
                      R=torch.diag((rho[0] / rho) ** 2), dtype=dtype)     # a cooling cannot heat
        if frozen is not None:
            common["theta0"] = frozen.role("estimator").theta.detach()
        extra, wiring, feeds = [], [], None
        if s["structure"] == "kockarts":
            labels = torch.arange(3) if s["strengths"] == "node" else 0      # one strength: one label for all
            tie = torch.where(torch.eye(3, dtype=torch.bool), labels, -1)
            ident = rt.RCOEstimator.static_gain({"y0": 3}, n_u=3, tie=tie, theta_bounds=(0.0, s["theta_max"]),
                                                **common)
        elif s["structure"] == "temperature":
            T_ref = frozen.blocks["features"].T_ref if frozen is not None else self._reference(s, model, x0)
            features = TemperatureFeatures(s["features"], T_ref, s["Ts"], T_init=model.temperature_at_nodes(x0),
                                           dtype=dtype)
            ident = self._temperature_estimator(s, features, model, common)
            extra, wiring, feeds = [features], ["known.T -> features.T"], {"f": "features.f"}
        else:
            ident = rt.RCOEstimator({"e": len(measured)}, n_u=3, nc=int(s["nc"]), **common)
            feeds = {"e": "error.out"}
        graph = rt.refinement(known, ident, physical=plant, excitation=driver, feeds=feeds, blocks=extra,
                              connections=wiring, batch_size=batch, dtype=dtype, device=device)
        if frozen is not None:     # theta held at theta0, the trained graph's theta
            ident.hold(alive=frozen.role("estimator").alive)
        elif s["refresh_every"] > 0:   # Markov parameters from the column at its present state, w and u
            graph.add_hook(rt.MarkovRefresh(graph, s["refresh_every"], method=s["markov_method"]))
        return graph

    @staticmethod
    def _reference(s, model: Column, x0: torch.Tensor) -> torch.Tensor:
        """Reference temperatures of the Arrhenius basis: each node's initial temperature, or with ``shared``
        one value for every node (the middle node's), so that one function of temperature serves them all."""
        T0 = model.temperature_at_nodes(x0)
        return T0[:, 1:2].expand(-1, T0.shape[1]).clone() if s["shared"] else T0

    @staticmethod
    def _temperature_estimator(s, features: TemperatureFeatures, model: Column, common) -> rt.RCOEstimator:
        """u_j = sum_i theta_ji f_i(T_j): node j sees only its own features; ``shared`` ties theta_ji across j."""
        import torch
        n, nt = model.n_nodes, len(features.terms)
        tie = torch.full((n, n * nt), -1, dtype=torch.int64)
        for j in range(n):
            tie[j, j * nt:(j + 1) * nt] = torch.arange(nt) + (0 if s["shared"] else j * nt)
        km = [f"{float(a) / 1e3:g}km" for a in model.nodes]
        names = [f"{t}@{km[j]}" for j in range(n) for t in features.terms]
        columns_of = {name: rt.features.port(f"f[{c}]") for c, name in enumerate(names)}
        return rt.RCOEstimator.static_gain({"f": n * nt}, n_u=n, features=columns_of, tie=tie, **common)

    # --- traces ------------------------------------------------------------------------------------------------
    def traces(self, g, s) -> dict[str, torch.Tensor]:
        """Per member and sample (B, K): the densities of truth, refined and initial model at 407 km and the measured
        altitudes (B, K, 1 + n_z) [1e-12 kg/m^3], the true and estimated NO cooling at 152 km [nW/m^3], the storm
        power [mW/m^2]; the profiles (B, K, n) of true and estimated cooling; the time t [h] (K,)."""
        import torch
        truth, model = g.role("physical").column, g.role("known").column
        kn, pl = g.role("known").history, g.role("physical").history
        B, K = kn.shape[:2]
        m = 1 + len(measured_altitudes(s))
        rate = kn[:, :, m + 5:].reshape(B * K, -1) if model.interpolate == "strength" else None
        est_profile = 1e9 * model.identified_cooling(kn[:, :, m:m + 3].reshape(B * K, 3), rate)

        def f64(t):
            return t.detach().to(device="cpu", dtype=torch.float64)

        return {"t": torch.arange(K, dtype=torch.float64) * s["Ts"] / 3600.0,
                "y_true": f64(pl[:, :, :m]), "y_refined": f64(kn[:, :, :m]), "y_initial": f64(self.initial_model(g, s)),
                "cooling_true": f64(truth.at(pl[:, :, m:].reshape(B * K, -1), EVAL_ALTITUDE).reshape(B, K)),
                "cooling_est": f64(model.at(est_profile, EVAL_ALTITUDE).reshape(B, K)),
                "true_profile": f64(pl[:, :, m:]), "est_profile": f64(est_profile.reshape(B, K, -1)),
                "storm": f64(kn[:, :, m + 4])}

    def initial_model(self, g, s) -> torch.Tensor:
        """Densities (B, K, 1 + n_z) of the initial model (the known column with u = 0) on the recorded driver, at
        407 km and the measured altitudes."""
        import torch

        from rcotorch.models.thermosphere import few_threads, native_here
        known = g.role("known")
        m = 1 + len(measured_altitudes(s))
        w = known.history[:, :, m + 3:m + 5]
        B, K = w.shape[:2]
        cached = self._initial_runs.get(g)
        if cached is not None and cached.shape[1] == K:
            return cached
        x = known.x0.expand(B, -1).clone()
        observe = densities(known.column, [DENSITY_ALTITUDE, *measured_altitudes(s)])
        if g.engine != "torch" and native_here(x.dtype, x.device):     # the same loop, compiled
            from rcotorch.models.thermosphere_native import NativeColumn
            out = NativeColumn(known.column).trajectory(x, w, x.new_zeros(B, K, 3), observe.reads())[0].to(x)
        else:
            u = x.new_zeros(B, 3)
            ys = []
            with torch.no_grad(), few_threads(x.numel()):
                for k in range(K):
                    ys.append(observe(x))
                    x = known.column.step(x, w[:, k], u)
            out = torch.stack(ys, 1) if ys else x.new_zeros(B, 0, m)
        self._initial_runs[g] = out
        return out

    def replay(self, g, s) -> dict[str, torch.Tensor]:
        """Traces of the frozen identified subsystem on the replay's space weather, as many steps as the run."""
        import torch
        K = g.role("known").history.shape[1]
        cached = self._replays.get(g)
        if cached is not None and cached[0] == K:
            return cached[1]
        rs = replay_settings(s)
        est = g.role("estimator")
        rg = self._graph(rs, g.batch_size, est.theta.dtype, est.theta.device, frozen=g)
        rg.engine = g.engine
        with torch.no_grad():
            rg.advance(K)
        tr = self.traces(rg, rs)
        self._replays[g] = (K, tr)
        return tr

    # --- summary -----------------------------------------------------------------------------------------------
    def validation(self, g, s):
        """Held-out data where ``validate_h`` > 0: that many hours of the same drivers after the run (the
        sources continue), the refined column against the truth's; the free run on other storms is the
        scenario's replay (``replay``)."""
        steps = int(round(float(s["validate_h"]) * 3600.0 / float(s["Ts"])))
        return {"steps": steps} if steps > 0 else None

    def estimates(self, g, s):
        import torch
        ident, model, plant = g.role("estimator"), g.role("known").column, g.role("physical")
        u = ident.u_now.to(torch.float64)
        out = {f"cooling_{int(round(float(z) / 1e3))}km": u[:, j] for j, z in enumerate(model.nodes)}
        rate = model.no_cooling_profile(g.role("known").x) if model.interpolate == "strength" else None
        out["cooling_152km"] = model.at(1e9 * model.identified_cooling(ident.u_now, rate), EVAL_ALTITUDE)[:, 0]
        if plant.history.shape[1]:
            last = plant.history[:, -1, 1 + len(measured_altitudes(s)):]
            out["cooling_152km_true"] = plant.column.at(last, EVAL_ALTITUDE)[:, 0]
        return {k: v.to(torch.float64) for k, v in out.items()}

    def metrics(self, g, s):
        import torch
        tr = self.traces(g, s)
        K = tr["cooling_true"].shape[1]
        if K == 0:
            nan = torch.full((g.batch_size,), math.nan, dtype=torch.float64)
            return {"density_err_ratio": nan, "cooling_corr_152km": nan, "cooling_rel_rms_152km": nan}
        day = min(K, int(round(86400.0 / s["Ts"])))
        start = int(math.ceil(s["cooling_window_start_h"] * 3600.0 / s["Ts"]))
        out = self._scores(tr, s, g.role("known").column, K - day, start if start < K - 1 else 0)
        if s["replay"]:
            rtr = self.replay(g, s)
            scores = self._scores(rtr, replay_settings(s), g.role("known").column, 0, 0)
            out.update({f"replay_{k}": scores[k] for k in ("density_err_ratio", "cooling_corr_152km",
                                                          "cooling_rel_rms_152km", "cooling_profile_rel_rms")})
        return out

    @staticmethod
    def _scores(tr, s, model: Column, density_from: int, cooling_from: int) -> dict[str, torch.Tensor]:
        """Density error ratios from sample ``density_from``, cooling scores from ``cooling_from``."""
        refined = _rms((tr["y_refined"] - tr["y_true"])[:, density_from:])       # (B, 1 + n_z)
        initial = _rms((tr["y_initial"] - tr["y_true"])[:, density_from:])
        est, true = tr["cooling_est"][:, cooling_from:], tr["cooling_true"][:, cooling_from:]
        out = {"density_err_ratio": refined[:, 0] / initial[:, 0], "cooling_corr_152km": _corr(est, true),
               "cooling_rel_rms_152km": _rms(est - true) / _rms(true),
               "density_rms_err_refined": refined[:, 0], "density_rms_err_initial": initial[:, 0],
               "cooling_rms_true_152km": _rms(true)}
        for i, a in enumerate(measured_altitudes(s)):
            if a != DENSITY_ALTITUDE:
                out[f"density_err_ratio_{a / 1e3:g}km"] = refined[:, 1 + i] / initial[:, 1 + i]
        for a in model.nodes.tolist():
            if a != EVAL_ALTITUDE:
                e = model.at(tr["est_profile"].flatten(0, 1), a).reshape(est.shape[0], -1)[:, cooling_from:]
                t = model.at(tr["true_profile"].flatten(0, 1), a).reshape(est.shape[0], -1)[:, cooling_from:]
                out[f"cooling_rel_rms_{a / 1e3:g}km"] = _rms(e - t) / _rms(t)
        low = model.z <= PROFILE_TOP
        diff = (tr["est_profile"] - tr["true_profile"])[:, cooling_from:, low.cpu()]
        out["cooling_profile_rel_rms"] = _rms(diff.flatten(1)) / _rms(tr["true_profile"][:, cooling_from:,
                                                                                          low.cpu()].flatten(1))
        return out

    # --- figures -----------------------------------------------------------------------------------------------
    def figures(self, g, s):
        tr = self.traces(g, s)
        if tr["t"].shape[0] < 2:
            return {}
        figs = {"cooling_152km": self._cooling_figure(tr, s, "NO cooling at 152 km: truth and estimate "
                                                              "(cf. seed Fig. 11)", s["cooling_window_start_h"]),
                "cooling_profiles": self._profile_figure(tr, g.role("known").column),
                "density_error": self._density_figure(tr, s)}
        if s["replay"]:
            figs["replay"] = self._replay_figure(self.replay(g, s), s)
        return figs

    @staticmethod
    def _cooling_figure(tr, s, title: str, adaptation_h: float | None, ax=None):
        import matplotlib.pyplot as plt

        fig = None
        if ax is None:
            fig, ax = plt.subplots(figsize=(8, 3.6))
        t = tr["t"].numpy()
        ax.plot(t, tr["cooling_true"][0].numpy(), "k", lw=1.6, label="true (Kockarts NO cooling)")
        ax.plot(t, tr["cooling_est"][0].numpy(), "--", color="tab:blue", lw=1.3,
                label="estimated (RCMR)" if adaptation_h is not None else "frozen identified subsystem")
        if adaptation_h is not None:
            ax.axvspan(t[0], min(adaptation_h, t[-1]), color="0.9", label="adaptation (outside the metric window)")
        ax.set_xlabel("time [h]")
        ax.set_ylabel("NO cooling at 152 km [nW/m^3]")
        ax2 = ax.twinx()
        ax2.plot(t, tr["storm"][0].numpy(), ":", color="tab:red", lw=1)
        ax2.set_ylabel("storm power [mW/m^2]", color="tab:red")
        ax.legend(loc="upper left", fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        return fig

    @staticmethod
    def _profile_figure(tr, model: Column):
        """True and estimated profiles at the times of the seed's Figure 12 (days after adaptation starts)."""
        import matplotlib.pyplot as plt

        t = tr["t"].numpy()
        dt_h = float(t[1] - t[0])
        idx = [(d, int(round(24.0 * d / dt_h))) for d in FIGURE12_DAYS if int(round(24.0 * d / dt_h)) < len(t)]
        if not idx:
            idx = [(t[-1] / 24.0, len(t) - 1)]
        z = model.z.cpu().numpy() / 1e3
        low = z <= PROFILE_TOP / 1e3
        nodes = model.nodes.cpu().numpy() / 1e3
        fig, axes = plt.subplots(1, len(idx), figsize=(2.6 * len(idx) + 1, 4), sharey=True, squeeze=False)
        for ax, (day, k) in zip(axes[0], idx):
            est = tr["est_profile"][0, k].numpy()
            ax.plot(tr["true_profile"][0, k].numpy()[low], z[low], "k", lw=1.6, label="true")
            ax.plot(est[low], z[low], "--", color="tab:blue", lw=1.3, label="estimated")
            ax.plot(np.interp(nodes, z, est), nodes, "o", color="tab:blue", ms=4)   # on the curve, off the grid too
            ax.set_title(f"{day:g} d (t = {t[k]:.1f} h)", fontsize=9)
            ax.set_xlabel("NO cooling [nW/m^3]")
            ax.grid(alpha=0.3)
        axes[0, 0].set_ylabel("altitude [km]")
        axes[0, 0].legend(fontsize=8)
        fig.suptitle("NO cooling profiles, days after adaptation starts: truth and estimate at the nodes "
                     "(cf. seed Fig. 12)", fontsize=10)
        fig.tight_layout()
        return fig

    @staticmethod
    def _density_figure(tr, s):
        import matplotlib.pyplot as plt

        t = tr["t"].numpy()
        fig, (ax, ae) = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
        yt, y0, y1 = (tr[k][0].numpy() for k in ("y_true", "y_initial", "y_refined"))
        ax.plot(t, yt[:, 0], "k", lw=1.6, label="truth (with NO cooling)")
        ax.plot(t, y0[:, 0], color="tab:orange", lw=1.2, label="initial model (no NO cooling)")
        ax.plot(t, y1[:, 0], "--", color="tab:blue", lw=1.2, label="refined model (RCMR)")
        ax.set_ylabel("density at 407 km [1e-12 kg/m^3]")
        ax.legend(fontsize=8)
        ax.set_title("Mass density at 407 km (cf. seed Fig. 13)")
        ae.plot(t, 100 * (y0[:, 0] - yt[:, 0]) / yt[:, 0], color="tab:orange", lw=1.2, label="initial - truth, 407 km")
        ae.plot(t, 100 * (y1[:, 0] - yt[:, 0]) / yt[:, 0], color="tab:blue", lw=1.2, label="refined - truth, 407 km")
        for i, a in enumerate(measured_altitudes(s)):
            if a != DENSITY_ALTITUDE:
                ae.plot(t, 100 * (y1[:, 1 + i] - yt[:, 1 + i]) / yt[:, 1 + i], lw=1.0,
                        label=f"refined - truth, {a / 1e3:g} km (measured)")
        ae.axvspan(max(t[0], t[-1] - 24.0), t[-1], color="0.9", label="last day (metric)")
        ae.set_ylabel("density error [%]")
        ae.set_xlabel("time [h]")
        ae.legend(fontsize=8)
        for a in (ax, ae):
            a.grid(alpha=0.3)
        fig.tight_layout()
        return fig

    def _replay_figure(self, tr, s):
        import matplotlib.pyplot as plt

        fig, (ax, ae) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        self._cooling_figure(tr, s, f"Frozen identified subsystem on another space weather: F10.7 = "
                                    f"{s['replay_f107']:g}, storm of {s['replay_storm_peak']:g} mW/m^2 at "
                                    f"{s['replay_storm_start_h']:g} h", None, ax=ax)
        t, yt, y0, y1 = tr["t"].numpy(), *(tr[k][0, :, 0].numpy() for k in ("y_true", "y_initial", "y_refined"))
        ae.plot(t, 100 * (y0 - yt) / yt, color="tab:orange", lw=1.2, label="initial model - truth")
        ae.plot(t, 100 * (y1 - yt) / yt, color="tab:blue", lw=1.2, label="frozen refined model - truth")
        ae.set_ylabel("density error at 407 km [%]")
        ae.set_xlabel("time [h]")
        ae.legend(fontsize=8)
        ae.grid(alpha=0.3)
        fig.tight_layout()
        return fig


SCENARIO = ThermosphereNoCooling()
