"""Coverage of the confidence intervals over seeds: the share of members whose nominal interval holds the truth.

Each case is one batched run of a scenario in which every member has its own excitation and measurement-noise
streams (seed = 1 .. B); an estimate's coverage is the fraction of members whose interval contains the
truth. Calibrated intervals cover about their level (95%); intervals that are too narrow cover less.

    python benchmarks/interval_coverage.py                 # every case, 200 members each (several minutes)
    python benchmarks/interval_coverage.py --members 50 --case sdof-discrete

Writes benchmarks/results/interval_coverage.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

import rcotorch as rt
from rcotorch.run.runner import Run


def friction(members: int, out: Path, std: float = 20.0) -> dict:
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
    res = rt.refine(g, 20000, {"coulomb": lambda g: -g.role("estimator").theta[:, 0, 0],
                               "viscous": lambda g: -g.role("estimator").theta[:, 0, 1]},
                    truth={"coulomb": 2.0, "viscous": 0.5}, out=out, overwrite=True, figures=False, progress=False)
    return res.summary


CASES = {
    # name: (scenario, overrides, steps)
    "sdof-discrete": ("sdof-stiffness", {"truth": "discrete", "noise": 0.05}, 20000),
    "sdof-continuous": ("sdof-stiffness", {"truth": "continuous", "noise": 0.05}, 20000),
    "twodof-discrete": ("twodof-stiffness", {"truth": "discrete", "noise": 0.05, "lam": 1.0}, 20000),
    "twodof-discrete-default": ("twodof-stiffness", {"truth": "discrete", "noise": 0.05}, 20000),
    "rlc-circuit": ("rlc-circuit", {}, 20000),
    "impedance-noise": ("sdof-dynamic-impedance", {"noise": 0.05}, 20000),
    "friction-strong": (friction, {}, 20000),
}


def coverage(name: str, members: int, out: Path) -> dict:
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
    rows = {}
    for key, values in summary["estimates"].items():
        iv = summary["intervals"].get(key)
        truth = summary["truth"].get(key)
        if iv is None or truth is None:
            continue
        lo, hi, est = (np.array([np.nan if v is None else v for v in x], dtype=float)
                       for x in (iv["lower"], iv["upper"], values))
        t = np.asarray(truth, dtype=float)
        rows[key] = {"coverage": float(np.mean((lo <= t) & (t <= hi))),
                     "spread": float(np.nanstd(est)), "mean_error": float(np.nanmean(est - t)),
                     "predicted_sd": float(np.nanmean((hi - lo) / 2 / 1.959964))}
    h = summary["health"]
    return {"scenario": scenario, "overrides": overrides, "steps": steps, "members": members,
            "level": 0.95, "estimates": rows, "status": h["counts"],
            "determined": float(np.mean(h["determined"])),
            "whiteness_p_below_0.01": float(np.mean(np.array(summary["metrics"]["z_whiteness_p"]) < 0.01)),
            "seconds": round(time.perf_counter() - t0, 1)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--members", type=int, default=200)
    p.add_argument("--case", action="append", choices=sorted(CASES))
    p.add_argument("--out", default="runs/coverage")
    args = p.parse_args()
    results = {name: coverage(name, args.members, Path(args.out)) for name in args.case or CASES}
    for name, r in results.items():
        for key, row in r["estimates"].items():
            print(f"{name:16s} {key:4s} coverage {row['coverage']:.3f}  spread {row['spread']:.3g}  "
                  f"predicted sd {row['predicted_sd']:.3g}  mean error {row['mean_error']:+.3g}  ({r['seconds']} s)")
    path = Path(__file__).parent / "results" / "interval_coverage.json"
    path.parent.mkdir(exist_ok=True)
    kept = json.loads(path.read_text()) if path.is_file() else {}      # the cases not run this time stay
    path.write_text(json.dumps({**kept, **results}, indent=1) + "\n")
    print(f"-> {path}")


if __name__ == "__main__":
    main()
