"""thermosphere-no-cooling end to end on the native engine against the PyTorch engine, each in a fresh process.

A run as ``rcotorch run`` does it: ``Run`` (the scenario's spin-up and initial Markov parameters), ``advance``
(480 steps with the Markov refresh every 24 and a log at every step), ``finish`` (summary with the metrics and the
frozen replay, checkpoint and figures; ``--no-figures`` leaves them out). Each engine runs in its own process with
``RCOTORCH_ENGINE`` set, so the PyTorch run calls no compiled code at all and the native run pays for loading its
compiled code (numba's disk cache; a first native process compiles it, about a minute, and is reported apart).
Timed inside the process from the scenario's ``Run`` to the end of ``finish`` (``run_s``), and the whole process
(``process_s``: interpreter, imports, the scenario registry and the run). The two runs' metrics are compared.

    python benchmarks/thermosphere_native.py --threads 1          # about a minute (the PyTorch run)

Goal: the run at least 10x faster natively. Writes benchmarks/results/thermosphere_native.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import add_common_args, machine, setup_cpu, table, write_json

NAME = "thermosphere-no-cooling"


def child(args) -> None:
    """One run on the engine ``args.child``, its timings as JSON on the last line of stdout."""
    t0 = time.perf_counter()
    import torch

    from rcotorch.run import scenario as scenarios
    from rcotorch.run.runner import Run
    scenarios.get(NAME)                               # the registry imports every shipped scenario
    torch.set_num_threads(args.threads or 1)
    t1 = time.perf_counter()
    with tempfile.TemporaryDirectory() as out:
        run = Run(NAME, steps=args.steps, out=Path(out) / "run", overrides=json.loads(args.overrides))
        t2 = time.perf_counter()
        run.advance(progress=False)
        t3 = time.perf_counter()
        summary = run.finish(figures=args.figures)
        t4 = time.perf_counter()
    print(json.dumps({"engine": summary["engine"], "engine_reason": summary["engine_reason"],
                      "imports_s": t1 - t0, "build_s": t2 - t1, "advance_s": t3 - t2, "finish_s": t4 - t3,
                      "run_s": t4 - t1, "metrics": summary["metrics"], "estimates": summary["estimates"]}))


def spawn(engine: str, args) -> dict:
    env = {**os.environ, "RCOTORCH_ENGINE": engine}
    cmd = [sys.executable, __file__, "--child", engine, "--steps", str(args.steps), "--overrides", args.overrides,
           *(["--threads", str(args.threads)] if args.threads else []), *([] if args.figures else ["--no-figures"])]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["process_s"] = time.perf_counter() - t0
    return result


def _largest_difference(a: dict, b: dict) -> float:
    """The largest relative difference between two runs' metrics and estimates."""
    worst = 0.0
    for group in ("metrics", "estimates"):
        for key, v in a[group].items():
            w = b[group].get(key)
            if isinstance(v, float) and isinstance(w, float):
                worst = max(worst, abs(v - w) / max(abs(v), 1e-300))
    return worst


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(ap)
    ap.add_argument("--steps", type=int, default=None, help="steps of the run (default: the scenario's 480)")
    ap.add_argument("--overrides", default="{}", help="scenario settings as JSON, e.g. '{\"structure\": \"error\"}'")
    ap.add_argument("--no-figures", dest="figures", action="store_false",
                    help="skip the figures in finish (rcotorch run draws them)")
    ap.add_argument("--repeats", type=int, default=3, help="native runs after the first (the best counts)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args)
        return {}
    dev = setup_cpu(args)
    if dev is None:
        return {}
    if args.quick:
        args.steps, args.repeats = args.steps or 48, 0
        args.overrides = json.dumps({"dz_km": 10.0, "nu": 24, "spinup_days": 1.0, **json.loads(args.overrides)})
    args.steps = args.steps or 480
    first = spawn("native", args)                     # loads (or first compiles) the native code
    native = min([first] + [spawn("native", args) for _ in range(args.repeats)], key=lambda r: r["run_s"])
    torch_ = spawn("torch", args)
    assert native["engine"] == "native" and torch_["engine"] == "torch", (native["engine_reason"], torch_["engine"])
    keys = ("imports_s", "build_s", "advance_s", "finish_s", "run_s", "process_s")
    rows = [[k[:-2], f"{native[k]:.2f}", f"{torch_[k]:.2f}", f"{torch_[k] / native[k]:.1f}x"] for k in keys]
    print(table(rows, ["seconds", "native", "PyTorch", "PyTorch / native"]))
    difference = _largest_difference(torch_, native)
    print(f"run: {torch_['run_s'] / native['run_s']:.1f}x (goal >= 10x); first native process "
          f"{first['process_s']:.1f} s; metrics and estimates agree to {difference:.1e}")
    out = {"benchmark": "thermosphere_native", "machine": machine(dev), "steps": args.steps,
           "overrides": json.loads(args.overrides), "figures": args.figures,
           "native": {k: native[k] for k in keys}, "torch": {k: torch_[k] for k in keys},
           "run_ratio": torch_["run_s"] / native["run_s"], "process_ratio": torch_["process_s"] / native["process_s"],
           "first_native_process_s": first["process_s"], "metrics_relative_difference": difference}
    print("->", write_json(out, "thermosphere_native", args.out))
    return out


if __name__ == "__main__":
    main()
