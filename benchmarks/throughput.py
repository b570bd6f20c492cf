"""Full refinement throughput of a scenario against a per-refinement NumPy loop, and peak memory, in one run.

    python benchmarks/throughput.py [--device cpu|cuda] [--threads N] [--batches 1,64,4096,65536]
                                    [--scenario sdof-stiffness-damping] [--seconds 3] [--engine auto]
                                    [--no-compare-torch]

Writes benchmarks/results/throughput.json and prints a table.

* torch: the scenario's whole Figure-1 graph (excitation, truth, known model, error, estimator with its RLS
  update) built for B members and advanced with ``Graph.advance`` after a warm-up, on the native engine where
  it applies (``--engine``), and on the PyTorch engine (step after step) for comparison; refinement-steps per second =
  B * steps / seconds, the best of 3 runs of ``--seconds / 3`` each (the excitation is drawn inside the
  timing; the best run is the one least disturbed by other processes on a shared machine).
* numpy: ``tests/numpy_loop.py``, the same equations for one refinement in a plain Python loop, timed by
  ``benchmarks/numpy_reference.py`` (refinement-steps per second, best of 3) before and after the torch runs; the
  ratio uses their mean.
* peak memory: each B in a fresh subprocess, the resident-set high-water mark during the run (VmHWM, reset
  after a warm batch-of-one step) minus the resident set before it, so library start-up is not counted; on
  CUDA ``torch.cuda.max_memory_allocated``. ``state_bytes`` is the graph's registered state alone.
  Also ``sdof-dynamic-impedance`` (n_theta = 10) at the largest batch.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy_reference
import torch
from common import add_common_args, machine, proc_status, reset_peak_rss, setup, sync, table, write_json

from rcotorch.run import scenario as scenarios

GOALS = {"B=4096 ratio": 500.0, "B=1 ratio": 1.0, "n_theta=10 peak KiB per member": 16.0}


def build(name: str, B: int, dev: torch.device, overrides: dict | None = None):
    sc = scenarios.get(name)
    return sc.build(sc.resolve(overrides), B, torch.float64, dev)


def torch_rate(name: str, B: int, dev: torch.device, seconds: float, engine: str = "auto", warmup: int = 20,
               repeats: int = 3) -> dict:
    """Refinement-steps per second of the scenario's graph at batch B, advanced by ``Graph.advance`` on the
    given engine: the best of ``repeats`` runs of ``seconds / repeats`` each (each run is long enough to
    include its share of excitation draws)."""
    g = build(name, B, dev)
    g.engine = engine
    used = "torch" if g.native_status() else "native"
    g.advance(warmup)
    sync(dev)
    probe = 5 if used == "torch" else 64
    t = time.perf_counter()
    g.advance(probe)
    sync(dev)
    per_step = (time.perf_counter() - t) / probe
    steps = max(10, int(seconds / repeats / max(per_step, 1e-7)))
    best = float("inf")
    for _ in range(repeats):
        sync(dev)
        t = time.perf_counter()
        g.advance(steps)
        sync(dev)
        best = min(best, (time.perf_counter() - t) / steps)
    return {"B": B, "engine": used, "steps": steps, "repeats": repeats, "seconds_per_step": best,
            "graph_steps_per_s": 1 / best, "refinement_steps_per_s": B / best}


def numpy_rate(seconds: float, repeats: int = 3) -> dict:
    steps = max(500, int(seconds / repeats * 40000))
    rate = numpy_reference.steps_per_second(steps, repeat=repeats)
    return {"steps": steps, "repeats": repeats, "refinement_steps_per_s": rate}


def memory_child(name: str, B: int, device: str, steps: int, threads: int | None) -> None:
    """Run in a subprocess: print peak memory of a B-member run as JSON. The peak is the resident-set
    high-water mark during the run (reset after a warm batch-of-one step) minus the resident set before it;
    where that reset is not possible, ru_maxrss after minus ru_maxrss before (then library start-up can mask
    a small run)."""
    import gc
    import resource
    if threads:
        torch.set_num_threads(threads)
    dev = torch.device(device)
    warm = build(name, 1, dev)
    warm.advance(3)
    del warm
    gc.collect()
    sync(dev)
    rss0 = proc_status("VmRSS")
    exact = rss0 is not None and reset_peak_rss()
    base = rss0 if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
        base_cuda = torch.cuda.memory_allocated(dev)
    g = build(name, B, dev)
    est = g.blocks["identified"]
    g.advance(steps)
    sync(dev)
    peak = proc_status("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    out = {"scenario": name, "B": B, "n_theta": est.n_theta, "steps": steps,
           "method": "VmHWM reset" if exact else "ru_maxrss", "rss_baseline_bytes": base,
           "rss_peak_bytes": peak, "peak_bytes": peak - base,
           "state_bytes": sum(t.numel() * t.element_size() for t in g.buffers())}
    if dev.type == "cuda":
        out["cuda_peak_bytes"] = torch.cuda.max_memory_allocated(dev) - base_cuda
        out["peak_bytes"] = out["cuda_peak_bytes"]
    print(json.dumps(out))


def memory(name: str, B: int, device: str, steps: int, threads: int | None) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--_memory", name, str(B), str(steps),
           "--device", device] + (["--threads", str(threads)] if threads else [])
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    if res.returncode != 0:
        return {"scenario": name, "B": B, "error": res.stderr.strip()[-500:]}
    return json.loads(res.stdout.strip().splitlines()[-1])


def run(args) -> dict | None:
    dev = setup(args)
    if dev is None:
        return None
    batches = [int(b) for b in args.batches.split(",")]
    seconds = 0.3 if args.quick else args.seconds
    np_before = numpy_rate(seconds)
    rates = [torch_rate(args.scenario, B, dev, seconds, args.engine) for B in batches]
    eager = [torch_rate(args.scenario, B, dev, seconds, "torch") for B in batches] if args.compare_torch else []
    np_after = numpy_rate(seconds)
    np_rate = 0.5 * (np_before["refinement_steps_per_s"] + np_after["refinement_steps_per_s"])
    mem_steps = 5 if args.quick else 50
    mems = {}
    if args.memory:
        for B in batches:
            mems[(args.scenario, B)] = memory(args.scenario, B, args.device, mem_steps, args.threads)
        big = max(batches)
        mems[(args.theta10, big)] = memory(args.theta10, big, args.device, mem_steps, args.threads)
    rows = []
    for r in eager:
        r["ratio_vs_numpy"] = r["refinement_steps_per_s"] / np_rate
    for r, e in zip(rates, eager or [None] * len(rates)):
        if e is not None:
            r["speedup_vs_torch_engine"] = r["refinement_steps_per_s"] / e["refinement_steps_per_s"]
    for r in rates:
        r["ratio_vs_numpy"] = r["refinement_steps_per_s"] / np_rate
        m = mems.get((args.scenario, r["B"]), {})
        r["peak_memory"] = m
        rows.append([r["B"], r["engine"], r["steps"], f"{r['seconds_per_step'] * 1e3:.3f}",
                     f"{r['graph_steps_per_s']:.1f}",
                     f"{r['refinement_steps_per_s']:.4g}", f"{r['ratio_vs_numpy']:.3g}",
                     f"{m['peak_bytes'] / 2**20:.1f}" if "peak_bytes" in m else "-"])
    extra = [m for (name, _), m in mems.items() if name != args.scenario]
    goals = {}
    by_b = {r["B"]: r for r in rates}
    if 4096 in by_b:
        goals["B=4096: >= 500x the NumPy loop"] = {"value": by_b[4096]["ratio_vs_numpy"],
                                                   "met": by_b[4096]["ratio_vs_numpy"] >= 500}
    if 1 in by_b:
        goals["B=1: no slower than the NumPy loop"] = {"value": by_b[1]["ratio_vs_numpy"],
                                                       "met": by_b[1]["ratio_vs_numpy"] >= 1}
    for m in extra:
        if "peak_bytes" in m:
            # 1 GiB at B = 65,536: 16 KiB a member, the bound at any batch
            bound = 2**30 * m["B"] / 65536
            goals[f"B={m['B']} with {m['n_theta']} theta entries under {bound / 2**30:.3g} GiB (16 KiB a member)"] = {
                "value_mib": m["peak_bytes"] / 2**20, "met": m["peak_bytes"] < bound}
    out = {
        "benchmark": "throughput", "scenario": args.scenario, "machine": machine(dev),
        "definition": "refinement-steps per second = B * graph steps / seconds (whole Figure-1 graph advanced by "
                      "Graph.advance on the named engine, "
                      "excitation drawn inside the timing, best of 3 runs); numpy = one refinement per Python "
                      "loop (benchmarks/numpy_reference.py, best of 3), mean of the rates before and after the "
                      "torch runs; "
                      "peak memory = resident-set high-water mark during the run - resident set before it "
                      "(after a warm batch-of-one step), fresh subprocess per batch",
        "numpy": {"before": np_before, "after": np_after, "refinement_steps_per_s": np_rate},
        "torch": rates, "torch_engine": eager, "memory_extra": extra, "goals": goals,
    }
    print(f"{args.scenario} on {dev} ({torch.get_num_threads()} threads); NumPy loop "
          f"{np_before['refinement_steps_per_s']:.0f} / {np_after['refinement_steps_per_s']:.0f} steps/s "
          "(before / after)")
    print(table(rows, ["B", "engine", "steps", "ms/step", "graph steps/s", "refinement steps/s", "x NumPy",
                       "peak MiB"]))
    if eager:
        print("PyTorch engine: " + ", ".join(f"B={e['B']}: {e['seconds_per_step'] * 1e3:.3f} ms/step "
                                              f"({e['ratio_vs_numpy']:.3g}x NumPy)" for e in eager))
    for m in extra:
        if "peak_bytes" in m:
            print(f"{m['scenario']} B={m['B']} (n_theta={m['n_theta']}): peak {m['peak_bytes'] / 2**20:.1f} MiB")
        else:
            print(f"{m['scenario']} B={m['B']}: {m.get('error')}")
    for k, v in goals.items():
        print(f"goal {k}: {'met' if v['met'] else 'NOT met'} ({v.get('value', v.get('value_mib')):.3g})")
    return out


def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "--_memory":
        name, B, steps = argv[1], int(argv[2]), int(argv[3])
        ap = argparse.ArgumentParser()
        ap.add_argument("--device", default="cpu")
        ap.add_argument("--threads", type=int, default=None)
        a = ap.parse_args(argv[4:])
        memory_child(name, B, a.device, steps, a.threads)
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(ap)
    ap.add_argument("--batches", default="1,64,4096,65536")
    ap.add_argument("--scenario", default="sdof-stiffness-damping")
    ap.add_argument("--theta10", default="sdof-dynamic-impedance",
                    help="scenario with 10 theta entries for the memory goal (at the largest batch)")
    ap.add_argument("--seconds", type=float, default=3.0, help="timing per measurement")
    ap.add_argument("--no-memory", dest="memory", action="store_false", help="skip the peak-memory subprocesses")
    ap.add_argument("--engine", default="auto", choices=["auto", "native", "torch"],
                    help="engine of the main rows (auto: native where it applies)")
    ap.add_argument("--no-compare-torch", dest="compare_torch", action="store_false",
                    help="skip the rows of the PyTorch engine (step by step)")
    args = ap.parse_args(argv)
    out = run(args)
    if out is not None:
        print("wrote", write_json(out, "throughput", args.out))


if __name__ == "__main__":
    main()
