"""What a member-step costs through ``rcotorch run`` against the engine alone, with the numba peer in the same run.

    python benchmarks/cli_cost.py --threads 1            # about a minute
    python benchmarks/cli_cost.py --threads 1 --quick    # shorter runs, for a check

``sdof-stiffness-damping`` (the scenario of ``benchmarks/numba_peer.py``) at B = 1 for 2,000,000 steps and at
B = 4096 for its 20,000 default steps, each measured three ways in one process:

* **the command line**: ``Run`` as ``rcotorch run NAME --batch B --steps S`` makes it (health checks, TensorBoard
  logs, figures' history, the output folder's checks), stepped with ``Run.advance`` after a first stretch of
  S / 20 steps (the first stretch pays for one-time work: lowering the graph, opening the TensorBoard files and
  the imports they need; it is reported apart, as is ``finish``: the summary, intervals, validation, figures and
  the final checkpoint);
* **the engine alone**: a copy of the same graph, ``Graph.advance`` for the same steps;
* **the numba peer**: the best of its variants (``numba_peer.py``) for the same number of member-steps.

Goal: the command line's member-step within 1.5x the engine's at both B. Writes
benchmarks/results/cli_cost.json.
"""

from __future__ import annotations

import argparse
import copy
import tempfile
import time
from pathlib import Path

import numba
import torch
from common import add_common_args, machine, setup_cpu, table, write_json
from peer import _numba_call

from rcotorch.run.runner import Run

NAME = "sdof-stiffness-damping"
GOAL = 1.5


def measure(B: int, steps: int, threads: int) -> dict:
    torch.set_num_threads(threads)
    numba.set_num_threads(threads)
    first = max(1, steps // 20)
    with tempfile.TemporaryDirectory() as folder:
        run = Run(NAME, batch=B, steps=first + steps, out=Path(folder) / "run")
        graph = copy.deepcopy(run.graph)
        t = time.perf_counter()
        run.advance(until=first, progress=False)
        first_s = time.perf_counter() - t
        graph.advance(first)
        t = time.perf_counter()
        run.advance(progress=False)
        cli_s = time.perf_counter() - t
        t = time.perf_counter()
        graph.advance(steps)
        engine_s = time.perf_counter() - t
        t = time.perf_counter()
        run.finish(figures=True)
        finish_s = time.perf_counter() - t
        run.close()
    peers = {}
    for variant in (("one", "prange", "lanes") if B == 1 else ("prange", "lanes")):
        fn = _numba_call(variant, B)
        fn(4)
        t = time.perf_counter()
        fn(steps)
        peers[variant] = (time.perf_counter() - t) / (steps * B) * 1e9
    best = min(peers, key=peers.get)
    ns = lambda s: s / (steps * B) * 1e9            # noqa: E731
    return {"B": B, "steps": steps, "threads": threads, "log_every": run.log_every, "logs": steps // run.log_every,
            "cli_ns_per_member_step": ns(cli_s), "engine_ns_per_member_step": ns(engine_s),
            "numba_ns_per_member_step": peers, "best_numba": best, "cli_over_engine": cli_s / engine_s,
            "goal": GOAL, "met": cli_s / engine_s <= GOAL, "first_stretch_s": first_s, "finish_s": finish_s}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(ap)
    args = ap.parse_args(argv)
    dev = setup_cpu(args, "the command line's cost is measured on the CPU")
    if dev is None:
        return {}
    cases = [(1, 200_000), (4096, 2_000)] if args.quick else [(1, 2_000_000), (4096, 20_000)]
    results = [measure(B, steps, args.threads or 1) for B, steps in cases]
    rows = [[r["B"], r["steps"], r["logs"], f"{r['cli_ns_per_member_step']:.1f}",
             f"{r['engine_ns_per_member_step']:.1f}", f"{r['numba_ns_per_member_step'][r['best_numba']]:.1f}",
             f"{r['cli_over_engine']:.2f}x", "yes" if r["met"] else "NO", f"{r['first_stretch_s']:.2f}",
             f"{r['finish_s']:.2f}"] for r in results]
    print(table(rows, ["B", "steps", "logs", "run ns", "engine ns", "numba ns", "run / engine", f"<= {GOAL}x",
                       "first stretch s", "finish s"]))
    out = {"benchmark": "cli_cost", "machine": machine(dev), "scenario": NAME, "results": results}
    print("->", write_json(out, "cli_cost", args.out))
    return out


if __name__ == "__main__":
    main()
