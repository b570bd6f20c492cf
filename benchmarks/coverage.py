"""Coverage of the confidence intervals over seeds: the share of members whose nominal interval holds the truth.

Each case is one batched run of a scenario in which every member has its own excitation and measurement-noise
streams (seed = 1 .. B); an estimate's coverage is the fraction of members whose interval contains the
truth. Calibrated intervals cover about their level (95%); intervals that are too narrow cover less.

    python benchmarks/coverage.py                 # every case, 200 members each (several minutes)
    python benchmarks/coverage.py --members 50 --case sdof-discrete

Writes benchmarks/results/coverage.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from rcotorch.runner import Run

CASES = {
    # name: (scenario, overrides, steps)
    "sdof-discrete": ("sdof-stiffness", {"truth": "discrete", "noise": 0.05}, 20000),
    "sdof-continuous": ("sdof-stiffness", {"truth": "continuous", "noise": 0.05}, 20000),
    "twodof-discrete": ("twodof-stiffness", {"truth": "discrete", "noise": 0.05, "lam": 1.0}, 20000),
    "rlc-circuit": ("rlc-circuit", {}, 20000),
}


def coverage(name: str, members: int, out: Path) -> dict:
    scenario, overrides, steps = CASES[name]
    t0 = time.perf_counter()
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
            "determined": float(np.mean(h["determined"])), "seconds": round(time.perf_counter() - t0, 1)}


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
    path = Path(__file__).parent / "results" / "coverage.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(results, indent=1) + "\n")
    print(f"-> {path}")


if __name__ == "__main__":
    main()
