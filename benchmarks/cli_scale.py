"""What the command line adds to the engine, at scale: time, peak memory, checkpoint size.

* **Overhead**: ``rcotorch run sdof-stiffness --batch 65536 --steps 2000`` (in this process, with figures,
  summary, TensorBoard, health checks and the final checkpoint) against the engine alone (the same graph built
  by the scenario and advanced 2000 steps with ``Graph.advance``), interleaved, best of ``--repeats``.
  Target: the command line adds at most 50% to the engine's time.
* **Peak memory**: the same command at B = 262,144 in a fresh process; the peak resident set of that
  process (library start-up included). Target: under 2 GiB.
* **Checkpoint size**: the final checkpoint of runs that differ only in their number of steps. Target: it
  does not grow with the steps.

    .venv/bin/python benchmarks/cli_scale.py --threads 1      # about 1.5 min on a 2-core machine
    .venv/bin/python benchmarks/cli_scale.py --threads 1 --overhead-only   # the overhead alone, printed

Writes ``benchmarks/results/cli_scale.json``.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import common
import torch

from rcotorch.run import scenario as scenarios
from rcotorch.run.cli import main as cli

SCENARIO = "sdof-stiffness"


def engine_seconds(batch: int, steps: int) -> float:
    sc = scenarios.get(SCENARIO)
    g = sc.build(sc.resolve(), batch, torch.float64, "cpu")
    acc = torch.zeros(batch, dtype=torch.float64)
    start = time.perf_counter()
    g.advance(steps, accumulate={g.role_signal("error"): acc})
    return time.perf_counter() - start


def cli_seconds(batch: int, steps: int, threads: int | None, tmp: Path) -> float:
    out = tempfile.mkdtemp(dir=tmp)
    args = ["run", SCENARIO, "--batch", str(batch), "--steps", str(steps), "--out", out, "--quiet"]
    if threads:
        args += ["--threads", str(threads)]
    start = time.perf_counter()
    rc = cli(args)
    elapsed = time.perf_counter() - start
    if rc not in (0, 1):
        raise RuntimeError(f"rcotorch {' '.join(args)} exited {rc}")
    return elapsed


def peak_memory(batch: int, steps: int, threads: int | None, tmp: Path) -> dict:
    """Peak resident set of a fresh ``rcotorch run`` process (ru_maxrss of the finished child)."""
    out = tempfile.mkdtemp(dir=tmp)
    cmd = [sys.executable, "-m", "rcotorch", "run", SCENARIO, "--batch", str(batch), "--steps", str(steps),
           "--out", out, "--quiet"] + (["--threads", str(threads)] if threads else [])
    start = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
    seconds = time.perf_counter() - start
    if res.returncode not in (0, 1):
        raise RuntimeError(res.stderr)
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss     # the largest child so far
    return {"batch": batch, "steps": steps, "peak_gib": peak_kib / 2 ** 20, "seconds": seconds,
            "checkpoint_bytes": (Path(out) / "checkpoint.pt").stat().st_size}


def checkpoint_sizes(batch: int, steps_list: list[int], tmp: Path) -> list[dict]:
    rows = []
    for steps in steps_list:
        out = Path(tempfile.mkdtemp(dir=tmp))
        cli(["run", SCENARIO, "--batch", str(batch), "--steps", str(steps), "--out", str(out), "--quiet",
             "--no-figures"])
        rows.append({"batch": batch, "steps": steps, "bytes": (out / "checkpoint.pt").stat().st_size})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.add_common_args(ap)
    ap.add_argument("--batch", type=int, default=65536, help="batch of the overhead measurement")
    ap.add_argument("--memory-batch", type=int, default=262144, help="batch of the peak-memory measurement")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--overhead-only", action="store_true",
                    help="measure only the overhead and print it (no peak memory, no checkpoint sizes, no JSON)")
    args = ap.parse_args()
    dev = common.setup(args)
    if dev is None:
        return
    if args.quick:
        args.batch, args.memory_batch, args.steps, args.repeats = 256, 1024, 200, 1
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        engine, whole = [], []
        for _ in range(args.repeats):            # interleaved: both sides see the same machine load
            engine.append(engine_seconds(args.batch, args.steps))
            whole.append(cli_seconds(args.batch, args.steps, args.threads, tmp))
        overhead = min(whole) / min(engine) - 1
        print(f"B = {args.batch}, {args.steps} steps: engine {min(engine):.2f} s, rcotorch run {min(whole):.2f} s "
              f"-> the command line adds {100 * overhead:.0f}%")
        if args.overhead_only:
            return
        memory = peak_memory(args.memory_batch, args.steps, args.threads, tmp)
        print(f"B = {args.memory_batch}, {args.steps} steps: peak {memory['peak_gib']:.2f} GiB "
              f"({memory['seconds']:.0f} s), checkpoint {memory['checkpoint_bytes'] / 2 ** 20:.1f} MiB")
        small = max(1, args.batch // 64)
        sizes = checkpoint_sizes(small, [args.steps // 2, args.steps * 4], tmp)
        print("checkpoint bytes: " + ", ".join(f"{r['steps']} steps {r['bytes']}" for r in sizes))
    common.write_json({
        "machine": common.machine(dev), "scenario": SCENARIO,
        "overhead": {"batch": args.batch, "steps": args.steps, "engine_seconds": engine, "cli_seconds": whole,
                     "added_fraction": overhead, "target": 0.5},
        "peak_memory": dict(memory, target_gib=2.0), "checkpoint_sizes": sizes,
    }, "cli_scale", args.out)


if __name__ == "__main__":
    main()
