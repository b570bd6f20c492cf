"""Does a sequential optimizer earn its place in ``rcotorch tune``? Optuna's TPE sampler (``method = "tpe"``,
rounds of batched candidates) against random search at equal budget: the same space, the same number of
candidates and seeds per candidate, the same steps, the same search seeds.

For each scenario and search seed: a random search and a tpe search (``rounds`` rounds), from a deliberately poor
start (p0 = 1, nu three times the default, lam = 0.98) over p0 log-uniform 1e-2..1e10, lam uniform 0.98..1 and
nu among a third, one and three times the default, scored on held-out validation only. Reported per search:
the best held-out score found, the best after each round's share of the budget (random: in draw order), its
settings, members and wall time; then the chosen settings run with a seed neither search used, and the
scenario's requirements checked against the truth. A third search, ``random-wide``, draws ``--wide`` (3) times
the candidates at random: about the wall time of the tpe search, whose rounds run one after another, where the
random search's extra candidates only widen its batches. The scenario's default settings are scored on the
same held-out data as a reference.

    python benchmarks/tune_optimizer.py                   # about 10 minutes on 2 cores (4000 and 10000 steps)
    python benchmarks/tune_optimizer.py --quick           # one search seed, 8 candidates (a smoke test)

Writes benchmarks/results/tune_optimizer.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from common import machine, table, write_json

from rcotorch.run import scenario as scenarios
from rcotorch.run.runner import Run
from rcotorch.run.tune import Tuning, run_tune

SCENARIOS = ("sdof-dynamic-impedance",)
CHECK_SEED = 9001                     # a seed the searches do not use
METHODS = ("random", "tpe", "random-wide")


def space(name: str) -> tuple[dict, dict]:
    nu = int(scenarios.get(name).settings["nu"])
    poor = {"p0": 1.0, "nu": 3 * nu, "lam": 0.98}
    return poor, {"p0": {"loguniform": [1e-2, 1e10]}, "lam": {"uniform": [0.98, 1.0]},
                  "nu": sorted({max(1, nu // 3), nu, 3 * nu})}


def checked(name: str, settings: dict, steps: int, out: Path) -> tuple[bool, dict]:
    run = Run(name, steps=steps, out=out, overrides=dict(settings, seed=CHECK_SEED), overwrite=True,
              intervals=False, validation=False)
    run.advance(progress=False)
    summary = run.finish(figures=False)
    return all(r["pass"] for r in summary["requirements"].values()), summary["estimates"]


def candidate_score(rows: list[dict]) -> float:
    """As the tuning scores a candidate: the mean held-out RMS error over its seeds, infinity if one has none."""
    v = [r.get("validation_rmse") for r in rows]
    ok = all(isinstance(x, (int, float)) and math.isfinite(x) and not r.get("diverged") for x, r in zip(v, rows))
    return float(np.mean(v)) if ok else math.inf


def default_score(name: str, steps: int, seeds: list[int], out: Path) -> float:
    """The scenario's default settings, scored as a candidate on the held-out data of the searches' seeds."""
    run = Run(name, steps=steps, out=out, members=[{"seed": s} for s in seeds], intervals=False, overwrite=True)
    run.advance(progress=False)
    rmse = run.finish(figures=False)["metrics"]["validation_rmse"]
    rows = [{"validation_rmse": v, "diverged": False} for v in (rmse if isinstance(rmse, list) else [rmse])]
    return candidate_score(rows)


def best_by_round(rows: list[dict], searched: list[str], seeds: int, sizes: list[int]) -> list[float]:
    """The best candidate score after each share of the budget (rows in member order: candidate, then seed)."""
    scores = [candidate_score(rows[i:i + seeds]) for i in range(0, len(rows), seeds)]
    ends = np.cumsum(sizes)
    return [min(scores[:e]) for e in ends]


def search(name: str, method: str, seed: int, steps: int, args, work: Path) -> dict:
    """One search; method ``random-wide``: a random search of ``wide`` times the candidates (about the wall time
    of a tpe search, whose rounds run one after another)."""
    poor, sp = space(name)
    samples = args.samples * args.wide if method == "random-wide" else args.samples
    t = Tuning(scenario=name, method=method.removesuffix("-wide"), space=sp, fixed=poor, samples=samples,
               rounds=args.rounds, seeds=args.seeds, seed=seed, steps=steps)
    out = work / f"{name}-{steps}-{method}-{seed}"
    start = time.perf_counter()
    result = run_tune(t, out=out, progress=False, overwrite=True)
    seconds = time.perf_counter() - start
    sizes = Tuning(scenario=name, space=sp, samples=samples, rounds=args.rounds).round_sizes()
    if method == "tpe":
        rows = [r for k in range(args.rounds)
                for r in json.loads((out / "runs" / f"round_{k:03d}" / "sweep.json").read_text())]
    else:
        rows = json.loads((out / "runs" / "sweep.json").read_text())
    curve = best_by_round(rows, list(sp), args.seeds, sizes)
    best = result.best
    ok, est = checked(name, best, steps, work / f"{name}-{steps}-{method}-{seed}-check")
    return {"scenario": name, "steps": steps, "method": method, "search_seed": seed,
            "best_score": result.candidates[0]["score"],
            "best": {k: best[k] for k in sp}, "best_by_round": curve, "members": result.members,
            "candidates": len(result.candidates), "shards": sum(1 for _ in out.glob("runs/**/shard_*")),
            "seconds": seconds, "chosen_pass": ok, "chosen_estimates": est}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--search-seeds", default="0,1,2")
    ap.add_argument("--samples", type=int, default=24)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--wide", type=int, default=3, help="random-wide: this many times the candidates")
    ap.add_argument("--seeds", type=int, default=1, help="seeds per candidate")
    ap.add_argument("--steps", default="4000,10000", help="steps of every run (comma-separated: each in turn)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true", help="one search seed, 8 candidates (a smoke test)")
    args = ap.parse_args(argv)
    search_seeds = [int(s) for s in args.search_seeds.split(",")]
    steps_list = [int(s) for s in args.steps.split(",")]
    if args.quick:
        search_seeds, args.samples, args.rounds, steps_list = search_seeds[:1], 8, 2, [1000]
    results, defaults, rows = [], {}, []
    head = ["scenario", "steps", "seed", "method", "best held-out rmse", "after each round", "chosen",
            "chosen (new seed)", "members", "shards", "s"]
    with tempfile.TemporaryDirectory() as tmp:
        for name, steps, seed in itertools.product(args.scenarios.split(","), steps_list, search_seeds):
            defaults[f"{name}/{steps}/{seed}"] = default_score(name, steps, [seed + i for i in range(args.seeds)],
                                                                Path(tmp) / f"{name}-{steps}-{seed}-default")
            for method in METHODS:
                r = search(name, method, seed, steps, args, Path(tmp))
                results.append(r)
                b = r["best"]
                rows.append([name, steps, seed, method, f"{r['best_score']:.3g}",
                             " ".join(f"{v:.2g}" for v in r["best_by_round"]),
                             f"p0={b['p0']:.3g} nu={b['nu']} lam={b['lam']:.4f}",
                             "PASS" if r["chosen_pass"] else "FAIL", r["members"], r["shards"], f"{r['seconds']:.0f}"])
                print(table(rows[-1:], head), flush=True)
    print(table(rows, head))
    summary = {}
    for name, steps, method in itertools.product(args.scenarios.split(","), steps_list, METHODS):
        part = [r for r in results if (r["scenario"], r["steps"], r["method"]) == (name, steps, method)]
        summary[f"{name}/{steps}/{method}"] = {
            "geomean_best_score": float(np.exp(np.mean([math.log(r["best_score"]) for r in part]))),
            "chosen_pass": sum(r["chosen_pass"] for r in part), "searches": len(part),
            "mean_seconds": float(np.mean([r["seconds"] for r in part])),
            "mean_members": float(np.mean([r["members"] for r in part]))}
    print(json.dumps(summary, indent=1))
    out = {"benchmark": "tune_optimizer", "machine": machine(torch.device("cpu")),
           "budget": {"samples": args.samples, "rounds": args.rounds, "wide": args.wide,
                      "seeds_per_candidate": args.seeds, "steps": steps_list, "search_seeds": search_seeds},
           "default_settings_score": defaults, "summary": summary, "results": results}
    print("->", write_json(out, "tune_optimizer", args.out))
    return out


if __name__ == "__main__":
    main()
