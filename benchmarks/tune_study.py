"""Tuning from a deliberately poor start: does ``rcotorch tune`` recover each shipped scenario's requirements
without looking at the truth?

For each scenario: a run with poor settings (p0 = 1, nu three times the default, lam = 0.98) and its
requirements; a random search (p0 log-uniform over 1e-2..1e10, lam uniform over 0.98..1, nu among a third,
one and three times the default), every candidate run with two seeds and scored on held-out validation only;
then the best candidate run with a seed the search never used, and its requirements. Cost: members and wall
time of the search.

    python benchmarks/tune_study.py                       # about 3 minutes on 2 cores
    python benchmarks/tune_study.py --scenarios sdof-stiffness --samples 8
    python benchmarks/tune_study.py --scenarios sdof-dynamic-impedance --lam 0.98,0.995,0.999,1 \
        --out benchmarks/results/tune_study_impedance.json

Writes benchmarks/results/tune_study.json.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch
from common import machine, table, write_json

from rcotorch.run import scenario as scenarios
from rcotorch.run.runner import Run
from rcotorch.run.tune import Tuning, run_tune

SCENARIOS = ("sdof-stiffness", "sdof-stiffness-damping", "twodof-stiffness", "sdof-dynamic-impedance",
             "rlc-circuit")
CHECK_SEED = 9001                     # a seed the search does not use


def passes(name: str, overrides: dict, out: Path) -> tuple[bool, dict]:
    run = Run(name, out=out, overrides=dict(overrides, seed=CHECK_SEED), overwrite=True, intervals=False)
    run.advance(progress=False)
    summary = run.finish(figures=False)
    return all(r["pass"] for r in summary["requirements"].values()), summary["estimates"]


def study(name: str, samples: int, seeds: int, work: Path, lam=None) -> dict:
    sc = scenarios.get(name)
    nu = int(sc.settings["nu"])
    poor = {"p0": 1.0, "nu": 3 * nu, "lam": 0.98}
    poor_pass, poor_est = passes(name, poor, work / f"{name}-poor")
    t = Tuning(scenario=name, method="random", samples=samples, seeds=seeds, fixed=poor,
               space={"p0": {"loguniform": [1e-2, 1e10]}, "lam": lam or {"uniform": [0.98, 1.0]},
                      "nu": sorted({max(1, nu // 3), nu, 3 * nu})})
    start = time.perf_counter()
    result = run_tune(t, out=work / f"{name}-tune", progress=False, overwrite=True)
    seconds = time.perf_counter() - start
    best = result.best
    best_pass, best_est = passes(name, best, work / f"{name}-best")
    return {"scenario": name, "poor": poor, "poor_pass": poor_pass, "poor_estimates": poor_est,
            "best": best, "best_score": result.candidates[0]["score"], "best_pass": best_pass,
            "best_estimates": best_est, "truth": sc.truth(sc.resolve()), "members": result.members,
            "candidates": len(result.candidates), "seconds": seconds}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--samples", type=int, default=24)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--lam", default=None, help="lam as a choice among these values (comma-separated) instead "
                    "of uniform over 0.98..1")
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true", help="two scenarios, 4 candidates (a smoke test)")
    args = ap.parse_args(argv)
    names = args.scenarios.split(",")
    samples = args.samples
    if args.quick:
        names, samples = names[:1], 4
    rows, results = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            lam = [float(v) for v in args.lam.split(",")] if args.lam else None
            r = study(name, samples, args.seeds, Path(tmp), lam)
            results.append(r)
            b = r["best"]
            rows.append([name, "PASS" if r["poor_pass"] else "FAIL",
                         f"p0={b['p0']:.3g} nu={b['nu']} lam={b['lam']:.4f}", f"{r['best_score']:.3g}",
                         "PASS" if r["best_pass"] else "FAIL", r["members"], f"{r['seconds']:.0f}"])
            print(table(rows[-1:], ["scenario", "poor start", "chosen", "held-out rmse", "chosen (new seed)",
                                    "members", "s"]), flush=True)
    print(table(rows, ["scenario", "poor start", "chosen", "held-out rmse", "chosen (new seed)", "members", "s"]))
    out = {"benchmark": "tune_study", "machine": machine(torch.device("cpu")), "results": results}
    print("->", write_json(out, "tune_study", args.out))
    return out


if __name__ == "__main__":
    main()
