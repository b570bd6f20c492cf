"""rcotorch's native engine against the numba peer (``tests/numba_loop.py``) on ``sdof-stiffness-damping``.

    python benchmarks/peer.py [--threads 1,2] [--batches 1,64,4096,65536] [--seconds 0.5] [--quick]

Writes benchmarks/results/peer.json and prints a table. For each thread count (rcotorch: torch's setting,
which the native engine uses; numba: ``numba.set_num_threads``) and batch B, the seconds per member-step of

* rcotorch: the scenario's graph built for B members, ``Graph.advance`` on the native engine (excitation drawn
  inside the timing), continuing from a warm-up;
* numba ``one``: the single-member jitted loop, called once per member (B = 1 only: it has no threads);
* numba ``prange``: members in parallel, each its own loop;
* numba ``lanes``: 16-lane chunks (vectorized), chunks in parallel;
* each numba variant also with its normals drawn two at a time (``pairs``: the same numbers, one log and
  square root per two steps);

the numba variants called on precomputed matrices (the scipy discretization outside the timing), each call a
whole refinement from step 0. The sides are interleaved, best of 3 rounds. Goal: rcotorch at least as fast as
the best numba variant at every B and thread count. Needs numba (``pip install -e .[bench]``).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numba
import numba_peer
import numpy as np
import torch
from common import machine, setup, table, write_json

from rcotorch.run import scenario as scenarios

sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))   # the peer lives with the tests that check it
import numba_loop  # noqa: E402

NAME = "sdof-stiffness-damping"
VARIANTS = ("numba one", "numba one pairs", "numba prange", "numba prange pairs", "numba lanes", "numba lanes pairs")


def _numba_call(variant: str, B: int, pairs: bool = False):
    """A call of the variant for B members (its argument: the steps), on precomputed arguments; ``pairs``: normals
    drawn two at a time."""
    m = numba_loop.model()
    seed = m.pop("seed")
    args = [m[k] for k in ("w_std", "Ad", "Bw", "Bu", "Atd", "Btd", "beta", "p0", "lam")]
    seeds, members = numba_loop.streams(B, seed)
    theta, P = np.empty((B, 3)), np.empty((B, 3, 3))
    if variant == "one":
        return lambda steps: numba_loop.refine_one(steps, seeds[0], members[0], *args, theta[0], P[0], pairs)
    fn = {"prange": numba_loop.refine_prange, "lanes": numba_loop.refine_lanes}[variant]
    return lambda steps: fn(steps, seeds, members, *args, theta, P, pairs)


def _steps_for(fn, B: int, seconds: float) -> int:
    """Steps for a call of about ``seconds``, from a trial call of at least 1/20 of it (so that a fixed cost per
    call, such as rcotorch's binding of the graph's tensors, does not shorten the timed calls)."""
    steps = 20
    while True:
        t = time.perf_counter()
        fn(steps)
        took = time.perf_counter() - t
        if took >= seconds / 20:
            return max(20, int(seconds * steps / took))
        steps *= 4


def measure(B: int, threads: int, seconds: float, rounds: int) -> dict:
    torch.set_num_threads(threads)
    numba.set_num_threads(threads)
    sc = scenarios.get(NAME)
    g = sc.build(sc.resolve(), B, torch.float64, "cpu")
    g.engine = "native"
    g.advance(64)
    fns = {"rcotorch": g.advance}
    for variant in (("one", "prange", "lanes") if B == 1 else ("prange", "lanes")):
        for pairs in (False, True):
            key = f"numba {variant}{' pairs' if pairs else ''}"
            fns[key] = _numba_call(variant, B, pairs)
            fns[key](4)                                         # compiled (first call)
    steps = {key: _steps_for(fn, B, seconds) for key, fn in fns.items()}
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(rounds):
        for key, fn in fns.items():
            t = time.perf_counter()
            fn(steps[key])
            best[key] = min(best[key], (time.perf_counter() - t) / (steps[key] * B))
    peers = {k: v for k, v in best.items() if k != "rcotorch"}
    top = min(peers, key=peers.get)
    return {"B": B, "threads": threads, "steps": steps, "ns_per_member_step": {k: v * 1e9 for k, v in best.items()},
            "best_numba": top, "x_best_numba": peers[top] / best["rcotorch"], "met": best["rcotorch"] <= peers[top]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", default="1,2", help="thread counts, comma-separated")
    ap.add_argument("--batches", default="1,64,4096,65536")
    ap.add_argument("--seconds", type=float, default=0.5, help="rough timing per side per round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/peer.json)")
    ap.add_argument("--quick", action="store_true", help="tiny timings (a smoke test)")
    args = ap.parse_args(argv)
    thread_counts = [int(t) for t in args.threads.split(",")]
    args.device, args.threads = "cpu", None
    dev = setup(args)
    seconds, rounds = (0.02, 1) if args.quick else (args.seconds, args.rounds)
    t0 = time.perf_counter()
    compile_s = numba_peer.compile_seconds()
    load_before = os.getloadavg()
    rows, results = [], []
    for threads in thread_counts:
        for B in (int(b) for b in args.batches.split(",")):
            r = measure(B, threads, seconds, rounds)
            results.append(r)
            ns = r["ns_per_member_step"]
            rows.append([threads, B, f"{ns['rcotorch']:.1f}",
                         *(f"{ns[k]:.1f}" if k in ns else "-" for k in VARIANTS),
                         r["best_numba"], f"{r['x_best_numba']:.2f}", "yes" if r["met"] else "NO"])
    out = {"benchmark": "peer", "scenario": NAME, "machine": machine(dev), "load_average_before": list(load_before),
           "numba": numba.__version__, "numba_threading_layer": numba.threading_layer(),
           "numba_compile_seconds": compile_s, "wall_seconds": time.perf_counter() - t0,
           "definition": "seconds per member-step (B members x steps / seconds), best of interleaved rounds; "
                         "x_best_numba = best numba variant's time / rcotorch's time (> 1: rcotorch ahead)",
           "results": results}
    print(table(rows, ["threads", "B", "rcotorch ns", *VARIANTS, "best numba", "x best numba", "met"]))
    print("wrote", write_json(out, "peer", args.out))


if __name__ == "__main__":
    main()
