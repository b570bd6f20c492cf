"""Tracking a change: a 3-storey shear building whose storey 2 loses 20% of its stiffness during the run, refined
with lam = 1, with constant forgetting, and with the CUSUM detector and covariance restart (rcotorch.tracking),
over many seeds in one batch each.

    python benchmarks/tracking_study.py              # 200 seeds, about 2 minutes

The building: floors of 2e4 kg, storeys of 2e7 N/m, 2% Rayleigh damping (periods 0.446, 0.159, 0.110 s), the
ground acceleration white noise of 1 m/s^2 at Ts = 0.01 s, the three floors' velocities measured with noise of
2e-4 m/s; the identified subsystem is a static gain from the storey drifts to the storey force pairs, masked to
its diagonal (dk_j = -theta_jj / k); nu = 300, p0 = 1e20. Storey 2 changes at t_d = 60 s (134 periods); the
estimate is judged 50 periods after it. Writes benchmarks/results/tracking_study.json; docs/tracking.md has the
table.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from common import machine, table, write_json
from rcotorch.scenarios.shear_building_damage import first_period

import rcotorch as rt
from rcotorch import scenario as scenarios

M, K, TS = 2.0e4, 2.0e7, 0.01
T_CHANGE = 6000
CHANGE = np.array([0.0, -0.2, 0.0])


def graph(batch: int, variant: dict):
    G = rt.models.shear_building([M] * 3, [K] * 3, force="base",
                                 measured=["velocity[1]", "velocity[2]", "velocity[3]"], identified=[1, 2, 3])
    known = rt.LTI.from_control(G, inputs={"w": 1, "u": 3}, outputs={"y": 3, "y0": 3}, dt=TS, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 3}, n_u=3, n_z=3, mask=np.eye(3, dtype=bool), p0=1e20,
                                        lam=variant.get("lam", 1.0))
    det = rt.ChangeDetector(3, warmup=500, window=500, holdoff=3000, drift=1.0, threshold=30.0, dt=TS)
    g = rt.refinement(known, ident, truth=rt.Gain(np.zeros((3, 3)), name="unknown"),
                      excitation=rt.WhiteNoise(1, seed=1), noise=rt.WhiteNoise(3, std=2e-4, seed=2), nu=300,
                      batch_size=batch, blocks=[det], connections=[("error.out", "detector.z")])
    damage = torch.diag(torch.tensor(-CHANGE * K)).reshape(1, 3, 3)
    g.add_hook(rt.at_step(T_CHANGE, lambda gr: gr.blocks["unknown"].K.copy_(damage)))
    if "reset" in variant:
        g.add_hook(rt.ResetOnChange(g, every=5, **variant["reset"]))
    return g, det


def errors(g) -> torch.Tensor:
    """max over storeys of |dk_j - truth_j| per member, the truth as it is at the graph's step (dk relative to k:
    0.004 is 2% of the change, 0.016 2% of the new stiffness 0.8 k)."""
    d = -torch.diagonal(g.role("estimator").theta, dim1=1, dim2=2) / K
    truth = torch.tensor(CHANGE if int(g.k) > T_CHANGE else np.zeros(3))
    return (d - truth).abs().amax(1)


def study(batch: int, name: str, variant: dict, T1: float) -> dict:
    g, det = graph(batch, variant)
    judge = T_CHANGE + int(round(50 * T1 / TS))
    t = time.perf_counter()
    g.advance(T_CHANGE - 1)
    before = errors(g)
    g.advance(judge - int(g.k))
    after = errors(g)
    seconds = time.perf_counter() - t
    first = det.first_alarm()
    detected = first >= T_CHANGE
    delay = (first[detected] - T_CHANGE).double() * TS / T1
    out = {"variant": name, "settings": variant, "members": batch, "steps": judge, "seconds": seconds,
           "error_before": {"median": float(before.median()), "max": float(before.max())},
           "error_after_50_periods": {"median": float(after.median()), "p95": float(after.quantile(0.95)),
                                      "max": float(after.max()), "within_2pct": float((after < 0.004).double().mean()),
                                      "within_2pct_of_stiffness": float((after < 0.016).double().mean())},
           "false_alarms": int((first >= 0).logical_and(first < T_CHANGE).sum()),
           "detected": int(detected.sum()),
           "delay_periods": {"max": float(delay.max()), "median": float(delay.median())} if len(delay) else None}
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=200)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    T1 = first_period(scenarios.get("shear-building-damage").resolve({"m": M, "k": K}))
    variants = {
        "lam = 1": {},
        "lam = 0.999": {"lam": 0.999},
        "lam = 0.995": {"lam": 0.995},
        "detector, restart p0 = 1e20": {"reset": {}},
        "detector, restart p0 = 1e14, lam 0.997 for 1500 steps": {"reset": {"p0": 1e14, "lam": 0.997,
                                                                            "hold": 1500}},
        "detector, lam 0.995 for 3000 steps (P kept)": {"reset": {"restart": False, "lam": 0.995, "hold": 3000}},
        "detector, restart p0 = 1e14, lam 0.995 for 3000 steps": {"reset": {"p0": 1e14, "lam": 0.995,
                                                                            "hold": 3000}},
        "detector, lam 0.99 for 3000 steps (P kept)": {"reset": {"restart": False, "lam": 0.99, "hold": 3000}},
    }
    results = [study(args.members, name, v, T1) for name, v in variants.items()]
    rows = [[r["variant"], f"{r['error_before']['max']:.2g}", f"{r['error_after_50_periods']['median']:.3f}",
             f"{r['error_after_50_periods']['p95']:.3f}", f"{r['error_after_50_periods']['max']:.3f}",
             f"{100 * r['error_after_50_periods']['within_2pct']:.0f}%",
             f"{100 * r['error_after_50_periods']['within_2pct_of_stiffness']:.0f}%", r["false_alarms"], r["detected"],
             "-" if r["delay_periods"] is None else f"{r['delay_periods']['max']:.3f}", f"{r['seconds']:.1f}"]
            for r in results]
    print(f"3-storey building, storey 2 -20% at step {T_CHANGE}; first period {T1:.4f} s; {args.members} seeds")
    print(table(rows, ["variant", "err before (max)", "err 50 T1 after (median)", "p95", "max", "within 0.004",
                       "within 0.016", "false alarms", "detected", "delay max [T1]", "s"]))
    write_json({"benchmark": "tracking_study", "machine": machine(torch.device("cpu")), "period_s": T1,
                "change_step": T_CHANGE, "results": results}, "tracking_study", args.out)


if __name__ == "__main__":
    main()
