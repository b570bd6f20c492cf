"""What a sweep costs per shard: 64 members of sdof-stiffness over a grid of 16 values of nu (a setting that fixes
the graph's structure, so each value is a shard of its own) with 4 seeds each, 2000 steps, as
``rcotorch sweep`` runs it (by default a worker process per core, each running one shard at a time on one thread;
the sweep's figures in the drawing process that ``rcotorch sweep`` starts, ``rcotorch.run.drawing``).

    python benchmarks/sweep_cost.py --threads 1          # about half a minute

Reports the whole sweep's wall time (goal: under 5 s on a 2-core machine), each shard's time and its parts as
the sweep logs them, and the engine's share: the same 16 graphs advanced alone. With ``--large`` (about half a
minute more) also 4096 members in 64 shards (nu = 5..68, 64 seeds each, 2000 steps) against one run of the
same 4096 members as one batch, its end included (goal: within 2x), on the same cores: the sweep with its default
workers (one per core) against the batch on as many threads, and the sweep with ``workers=1`` against the batch on
``--threads`` threads. Writes benchmarks/results/sweep_cost.json.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch
from common import add_common_args, machine, setup_cpu, table, write_json

from rcotorch.run import scenario as scenarios
from rcotorch.run.drawing import DrawingProcess
from rcotorch.run.sweep import Sweep, local_workers, run_sweep

NAME = "sdof-stiffness"
GOAL_S = 5.0
LARGE_GOAL = 2.0        # 4096 members in 64 shards against one batch of 4096


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(ap)
    ap.add_argument("--large", action="store_true", help="also 4096 members in 64 shards against one batch")
    args = ap.parse_args(argv)
    dev = setup_cpu(args, "the sweep's cost is measured on the CPU")
    if dev is None:
        return {}
    torch.set_num_threads(args.threads or 1)
    values = list(range(5, 21))[: 4 if args.quick else 16]
    steps = 2000
    spec = {"scenario": NAME, "steps": steps, "seeds": 4, "grid": {"nu": values}}
    sc = scenarios.get(NAME)
    sc.build(sc.resolve({"nu": values[0]}), 4, torch.float64, "cpu").advance(10)     # imports and compilation
    with tempfile.TemporaryDirectory() as folder:
        t = time.perf_counter()
        rows = run_sweep(Sweep.from_dict(spec), out=Path(folder) / "sweep", progress=False, drawing=DrawingProcess())
        total = time.perf_counter() - t
    t = time.perf_counter()
    for nu in values:
        g = sc.build(sc.resolve({"nu": nu}), 4, torch.float64, "cpu")
        g.advance(steps)
    engine = time.perf_counter() - t
    shards = len(values)
    result = {"benchmark": "sweep_cost", "machine": machine(dev), "scenario": NAME, "members": len(rows),
              "shards": shards, "workers": local_workers(None, shards, "cpu"), "steps": steps, "sweep_s": total,
              "per_shard_s": total / shards,
              "engine_s": engine, "engine_per_shard_s": engine / shards, "goal_s": GOAL_S,
              "met": total <= GOAL_S or args.quick}
    print(table([[len(rows), shards, f"{total:.1f}", f"{total / shards:.2f}", f"{engine / shards:.3f}",
                  "yes" if total <= GOAL_S else "NO"]],
                ["members", "shards", "sweep s", "per shard s", "engine per shard s", f"<= {GOAL_S:.0f} s"]))
    if args.large:
        result["large"] = large(steps, args.threads or 1)
    print("->", write_json(result, "sweep_cost", args.out))
    return result


def large(steps: int, threads: int) -> dict:
    """4096 members in 64 shards against the same members as one batch (``run`` with its end), seconds each: the
    sweep on a worker per core against the batch on a thread per core, and the sweep on one worker (this process)
    against the batch on ``threads`` threads."""
    from rcotorch.run.runner import Run
    spec = {"scenario": NAME, "steps": steps, "seeds": 64, "grid": {"nu": list(range(5, 69))}}
    cores = local_workers(None, 64, "cpu")

    def sweep_s(workers: int) -> float:
        torch.set_num_threads(threads)       # a worker runs on one thread whatever this process has
        with tempfile.TemporaryDirectory() as folder:
            t = time.perf_counter()
            run_sweep(Sweep.from_dict(spec), out=Path(folder) / "sweep", progress=False, drawing=DrawingProcess(),
                      workers=workers)
            return time.perf_counter() - t

    def one_s(n: int) -> float:
        torch.set_num_threads(n)
        with tempfile.TemporaryDirectory() as folder:
            t = time.perf_counter()
            run = Run(NAME, batch=4096, steps=steps, out=Path(folder) / "one")
            run.drawing = DrawingProcess()       # as rcotorch run starts it
            run.advance(progress=False)
            run.finish(progress=False)
            return time.perf_counter() - t

    rows, out = [], {"members": 4096, "shards": 64, "steps": steps, "goal": LARGE_GOAL, "cores": cores}
    for key, workers, n in (("", cores, cores), ("_one_worker", 1, threads)):
        s, one = sweep_s(workers), one_s(n)
        part = {f"sweep_s{key}": s, f"one_batch_s{key}": one, f"ratio{key}": s / one, f"workers{key}": workers,
                f"threads{key}": n}
        out.update(part)
        rows.append([4096, 64, workers, f"{s:.1f}", n, f"{one:.1f}", f"{s / one:.1f}x",
                     "yes" if s / one <= LARGE_GOAL else "NO"])
    torch.set_num_threads(threads)
    out["met"] = out["ratio"] <= LARGE_GOAL
    print(table(rows, ["members", "shards", "workers", "sweep s", "batch threads", "one batch s", "ratio",
                       f"<= {LARGE_GOAL:.0f}x"]))
    return out


if __name__ == "__main__":
    main()
