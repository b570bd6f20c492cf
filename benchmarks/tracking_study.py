"""Tracking a change: the scenario shear-building-damage (a 3-storey shear building whose storey 2 loses 20% of its
stiffness during the run) refined with lam = 1, with constant forgetting, and with the CUSUM detector and
covariance restart (rcotorch.estimator.tracking), over many seeds in one batch each: every variant is the scenario's own
graph with other settings.

    python benchmarks/tracking_study.py                    # 200 seeds, a few minutes: the scenario as shipped
    python benchmarks/tracking_study.py --sensor velocity  # the three floors' velocities instead
    python benchmarks/tracking_study.py --cases            # other damages, open- against closed-loop Markov

The building: floors of 2e4 kg, storeys of 2e7 N/m, 2% Rayleigh damping (periods 0.446, 0.159, 0.110 s), the ground
acceleration white noise of 1 m/s^2 at Ts = 0.01 s; the scenario's accelerometers on floors 2 and 3 with noise of
0.01 m/s^2 (detector reference window from 2,000 to 3,000 steps), or (``--sensor velocity``) the three floors'
velocities measured with noise of 2e-4 m/s (window from 500 to 1,000 steps); the identified subsystem is a static
gain from the storey drifts to the storey force pairs, masked to its diagonal (dk_j = -theta_jj / k); nu = 100
(other values as variants), p0 = 1e20. Storey 2 changes at t_d = 60 s (134 periods); the estimate is judged 50
periods after it. A variant without a detector sets its alarm level out of reach. Writes
benchmarks/results/tracking_study_acceleration.json (tracking_study.json for velocities); docs/tracking.md has the
tables. ``--cases``: other storeys, sizes of change and seeds, each with both sensors and both kinds of Markov
parameters while following the change (the known model's own, and the loop closed at the estimate); writes
benchmarks/results/tracking_cases.json.
"""

from __future__ import annotations

import argparse
import time

import torch
from common import machine, table, write_json
from rcotorch.scenarios.shear_building_damage import first_period

from rcotorch.run import scenario as scenarios

NAME = "shear-building-damage"
NO_DETECTOR = {"threshold": 1e300}
SENSORS = {"acceleration": {},
           "velocity": {"sensor": "velocity", "measured": "1,2,3", "noise": 2e-4, "warmup": 500, "window": 500}}


def graph(batch: int, variant: dict):
    """The scenario's graph with the variant's settings, member b drawing the scenario's stream (seed, b)."""
    sc = scenarios.get(NAME)
    s = sc.resolve(variant)
    return sc.build(s, batch, torch.float64, "cpu"), s


def errors(g, s) -> torch.Tensor:
    """max over storeys of |dk_j - truth_j| per member, the truth as it is at the graph's step (dk relative to k:
    0.004 is 2% of the change, 0.016 2% of the new stiffness 0.8 k)."""
    sc = scenarios.get(NAME)
    d = torch.stack(list(sc.estimates(g, s).values()), 1)
    changed = int(g.k) > sc.change_step(s)
    truth = torch.tensor([v if changed else 0.0 for v in sc.truth(s).values()], dtype=d.dtype)
    return (d - truth).abs().amax(1)


def study(batch: int, name: str, variant: dict, T1: float) -> dict:
    g, s = graph(batch, variant)
    kd = scenarios.get(NAME).change_step(s)
    judge = kd + int(round(50 * T1 / s["Ts"]))
    t = time.perf_counter()
    g.advance(kd - 1)
    before = errors(g, s)
    g.advance(judge - int(g.k))
    after = errors(g, s)
    seconds = time.perf_counter() - t
    first = g.blocks["detector"].first_alarm()
    detected = first >= kd
    delay = (first[detected] - kd).double() * s["Ts"] / T1
    out = {"variant": name, "settings": variant, "members": batch, "steps": judge, "seconds": seconds,
           "error_before": {"median": float(before.median()), "max": float(before.max())},
           "error_after_50_periods": {"median": float(after.median()), "p95": float(after.quantile(0.95)),
                                      "max": float(after.max()), "within_2pct": float((after < 0.004).double().mean()),
                                      "within_2pct_of_stiffness": float((after < 0.016).double().mean())},
           "false_alarms": int((first >= 0).logical_and(first < kd).sum()),
           "detected": int(detected.sum()),
           "delay_periods": {"max": float(delay.max()), "median": float(delay.median())} if len(delay) else None}
    return out


CASES = [{}, {"seed": 7}, {"storey": 1}, {"storey": 1, "change": -0.3}, {"storey": 2, "change": -0.3, "seed": 11},
         {"change": -0.4}, {"storey": 3, "change": -0.3}, {"storey": 3, "change": -0.4, "seed": 13},
         {"storey": 1, "change": -0.1, "seed": 17}, {"storey": 3, "change": -0.15, "seed": 19}]


def cases(members: int, out) -> None:
    """Each case with both sensors and both kinds of Markov parameters, judged 50 periods after the change."""
    sc = scenarios.get(NAME)
    T1 = first_period(sc.resolve())
    results, rows = [], []
    for case in CASES:
        for sensor, base in SENSORS.items():
            for markov in ("open-loop", "closed-loop"):
                r = study(members, markov, {**base, **case, "track_markov": markov}, T1)
                r.update(case=case, sensor=sensor)
                results.append(r)
                a = r["error_after_50_periods"]
                rows.append([", ".join(f"{k} {v}" for k, v in case.items()) or "the scenario", sensor, markov,
                             f"{a['median']:.5f}", f"{a['p95']:.4f}", f"{a['max']:.4f}",
                             f"{100 * a['within_2pct_of_stiffness']:.1f}%", r["false_alarms"], r["detected"]])
                print(rows[-1], flush=True)
    print(table(rows, ["case", "sensor", "Markov", "median", "p95", "max", "within 0.016", "false alarms",
                       "detected"]))
    write_json({"benchmark": "tracking_cases", "machine": machine(torch.device("cpu")), "period_s": T1,
                "members": members, "results": results}, "tracking_cases", out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=200)
    ap.add_argument("--sensor", choices=list(SENSORS), default="acceleration")
    ap.add_argument("--cases", action="store_true", help="other damages, open- against closed-loop Markov")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.cases:
        cases(args.members, args.out)
        return
    sc = scenarios.get(NAME)
    T1 = first_period(sc.resolve())
    plain = {**NO_DETECTOR, "restart_p0": 0.0, "track_lam": 1.0, "track_hold": 0}
    variants = {
        "lam = 1": dict(plain),
        "lam = 0.999": {**plain, "lam": 0.999},
        "lam = 0.995": {**plain, "lam": 0.995},
        "detector, restart p0 = 1e20": {"restart_p0": 1e20, "track_lam": 1.0, "track_hold": 0},
        "detector, restart p0 = 1e14, lam 0.997 for 1500 steps": {"restart_p0": 1e14, "track_lam": 0.997,
                                                                   "track_hold": 1500},
        "detector, lam 0.995 for 3000 steps (P kept)": {"restart_p0": 0.0, "track_lam": 0.995, "track_hold": 3000},
        "detector, restart p0 = 1e14, lam 0.995 for 3000 steps": {"track_lam": 0.995},
        "detector, lam 0.99 for 3000 steps (P kept)": {"restart_p0": 0.0, "track_lam": 0.99, "track_hold": 3000},
        "detector, restart p0 = 1e14, lam 0.99 for 3000 steps": {"track_markov": "open-loop"},
        "detector, restart p0 = 1e14, lam 0.99 for 3000 steps, closed-loop Markov from 200 steps (the scenario's "
        "default)": {},
        "the default with nu = 60": {"nu": 60},
        "the default with nu = 150": {"nu": 150},
        "the default with nu = 300": {"nu": 300},
        "the default with nu = 300, lam 0.995": {"nu": 300, "track_lam": 0.995},
        "the default with closed-loop Markov from 100 steps": {"markov_after": 100},
        "the default with closed-loop Markov from 500 steps": {"markov_after": 500},
    }
    base = SENSORS[args.sensor]
    results = [study(args.members, name, {**base, **v}, T1) for name, v in variants.items()]
    rows = [[r["variant"], f"{r['error_before']['max']:.2g}", f"{r['error_after_50_periods']['median']:.3f}",
             f"{r['error_after_50_periods']['p95']:.3f}", f"{r['error_after_50_periods']['max']:.3f}",
             f"{100 * r['error_after_50_periods']['within_2pct']:.0f}%",
             f"{100 * r['error_after_50_periods']['within_2pct_of_stiffness']:.0f}%", r["false_alarms"], r["detected"],
             "-" if r["delay_periods"] is None else f"{r['delay_periods']['max']:.3f}", f"{r['seconds']:.1f}"]
            for r in results]
    kd = sc.change_step(sc.resolve())
    print(f"{NAME}: storey 2 -20% at step {kd}; first period {T1:.4f} s; {args.members} seeds; {args.sensor}")
    print(table(rows, ["variant", "err before (max)", "err 50 T1 after (median)", "p95", "max", "within 0.004",
                       "within 0.016", "false alarms", "detected", "delay max [T1]", "s"]))
    write_json({"benchmark": "tracking_study", "machine": machine(torch.device("cpu")), "period_s": T1,
                "sensor": args.sensor, "change_step": kd, "results": results},
               "tracking_study" + ("_acceleration" if args.sensor == "acceleration" else ""), args.out)


if __name__ == "__main__":
    main()
