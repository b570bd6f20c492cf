"""What a member-step costs through ``rcotorch run`` against the engine alone, with the numba peer in the same run.

    python benchmarks/cli_cost.py --threads 1            # about a minute
    python benchmarks/cli_cost.py --threads 1 --quick    # shorter runs, for a check

``sdof-stiffness-damping`` (the scenario of the numba peer, ``tests/numba_loop.py``) at B = 1 for 2,000,000 steps
and at B = 4096 for its 20,000 default steps, each measured three ways in one process:

* **the command line**: ``Run`` as ``rcotorch run NAME --batch B --steps S`` makes it (health checks, TensorBoard
  logs, figures' history, the output folder's checks, the process that draws the figures), stepped with
  ``Run.advance`` after a first stretch of S / 20 steps (the first stretch pays for one-time work: lowering the
  graph, opening the TensorBoard files and the imports they need; it is reported apart, as is ``finish``: the
  summary, intervals, validation, figures and the final checkpoint);
* **the engine alone**: a copy of the same graph, ``Graph.advance`` for the same steps;
* **the numba peer**: the best of its variants (``benchmarks/peer.py``) for the same number of member-steps.

Goals: the command line's member-step within 1.5x the engine's at both B; the end of the run (``finish``: the
intervals' replay, validation, summary, figures and files, reported part by part from ``Run.timings``) within
the engine's own time for the same steps, also for ``shear-building-damage`` at B = 200 (its defaults).

End to end, as a user waits for it, ``rcotorch run`` in a fresh process (``--end-to-end``): a long and a short
run at each B (the medians of three of each, alternating), whose difference gives the marginal member-step (goal: at
least 0.5x the numba peer's speed; at B = 1 the long run takes 20,000,000 steps, about a second of the engine), and
a 10-step run at B = 4096 (goal: under 3 s). Writes benchmarks/results/cli_cost.json.

    python benchmarks/cli_cost.py --table      # the results on record (and sweep_cost.json's), as docs/cli.md
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import RESULTS, add_common_args, machine, setup_cpu, table, write_json

NAME = "sdof-stiffness-damping"
GOAL = 1.5
END_GOAL = 1.0             # finish / engine
MARGINAL_GOAL = 0.5        # numba's member-step / rcotorch run's marginal member-step
SHORT_GOAL_S = 3.0         # a 10-step run at B = 4096, end to end
REPEATS = 3                # runs of each length for a marginal member-step (their medians)


def measure(B: int, steps: int, threads: int, name: str = NAME, peer: bool = True) -> dict:
    import numba
    import torch
    from peer import _numba_call

    from rcotorch.run.drawing import DrawingProcess
    from rcotorch.run.runner import Run
    torch.set_num_threads(threads)
    numba.set_num_threads(threads)
    first = max(1, steps // 20)
    with tempfile.TemporaryDirectory() as folder:
        drawing = DrawingProcess()          # as rcotorch run starts it, before the run
        run = Run(name, batch=B, steps=first + steps, out=Path(folder) / "run")
        run.drawing = drawing
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
        run.finish(figures=True, progress=False)
        finish_s = time.perf_counter() - t
        parts = {k: v for k, v in run.timings.items() if k != "end"}
        run.close()
        drawing.close()
    ns = lambda s: s / (steps * B) * 1e9            # noqa: E731
    own = {"scenario": name, "B": B, "steps": steps, "threads": threads, "log_every": run.log_every,
           "logs": steps // run.log_every, "cli_ns_per_member_step": ns(cli_s),
           "engine_ns_per_member_step": ns(engine_s),
           "cli_over_engine": cli_s / engine_s, "goal": GOAL, "met": cli_s / engine_s <= GOAL,
           "first_stretch_s": first_s, "engine_s": engine_s, "finish_s": finish_s, "finish_parts_s": parts,
           "finish_over_engine": finish_s / engine_s, "end_goal": END_GOAL, "end_met": finish_s <= END_GOAL * engine_s}
    if not peer:
        return own
    peers = {}
    for variant in (("one", "prange", "lanes") if B == 1 else ("prange", "lanes")):
        fn = _numba_call(variant, B)
        fn(4)
        t = time.perf_counter()
        fn(steps)
        peers[variant] = (time.perf_counter() - t) / (steps * B) * 1e9
    return dict(own, numba_ns_per_member_step=peers, best_numba=min(peers, key=peers.get))


def end_to_end(B: int, steps: int, threads: int) -> float:
    """Seconds of ``rcotorch run NAME --batch B --steps S`` in a fresh process, verdict and figures included."""
    with tempfile.TemporaryDirectory() as folder:
        cmd = [sys.executable, "-m", "rcotorch", "run", NAME, "--batch", str(B), "--steps", str(steps), "--quiet",
               "--threads", str(threads), "--out", str(Path(folder) / "run")]
        t = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True)
        seconds = time.perf_counter() - t
    if done.returncode not in (0, 1):
        raise RuntimeError(f"{' '.join(cmd)} exited {done.returncode}: {done.stderr}")
    return seconds


def marginal(B: int, short: int, long: int, threads: int, numba_ns: float, repeats: int = REPEATS) -> dict:
    """The member-step's cost through ``rcotorch run`` end to end: (long run - short run) / member-steps, from the
    medians of ``repeats`` runs of each, short and long alternating (a process's start varies by a few tenths of
    a second: one pair of runs cannot measure a difference of that size)."""
    shorts, longs = [], []
    for _ in range(repeats):
        shorts.append(end_to_end(B, short, threads))
        longs.append(end_to_end(B, long, threads))
    t_short, t_long = statistics.median(shorts), statistics.median(longs)
    ns = (t_long - t_short) / ((long - short) * B) * 1e9
    return {"B": B, "short_steps": short, "long_steps": long, "short_s": t_short, "long_s": t_long,
            "short_runs_s": shorts, "long_runs_s": longs,
            "marginal_ns_per_member_step": ns, "numba_ns_per_member_step": numba_ns,
            "speed_vs_numba": numba_ns / ns if ns > 0 else float("inf"), "goal": MARGINAL_GOAL,
            "met": ns > 0 and numba_ns / ns >= MARGINAL_GOAL}


def markdown(results: dict, sweeps: dict | None) -> str:
    """The results on record (``cli_cost.json``, and ``sweep_cost.json`` where given) as Markdown tables."""
    def f2(v: float) -> str:
        return f"{v:.2f}"

    def yes(m: dict) -> str:
        return "yes" if m["met"] else "no"
    parts = ["intervals", "validation", "summary", "figures", "files"]
    lines = ["| scenario | B | steps | engine s | " + " | ".join(parts) + " | end s | end / engine | run ns | "
             "engine ns |", "|" + "---|" * (8 + len(parts))]
    for r in results["results"]:
        cells = [r["scenario"], r["B"], r["steps"], f2(r["engine_s"]),
                 *(f2(r["finish_parts_s"].get(k, 0.0)) for k in parts), f2(r["finish_s"]),
                 f"{r['finish_over_engine']:.1f}x", f"{r['cli_ns_per_member_step']:.1f}",
                 f"{r['engine_ns_per_member_step']:.1f}"]
        lines.append("| " + " | ".join(map(str, cells)) + " |")
    e2e = results.get("end_to_end") or []
    if e2e:
        lines += ["", "| end to end, a fresh process | rcotorch run | the numba peer | goal | met |",
                  "|---|---|---|---|---|"]
        for m in e2e:
            if "marginal_ns_per_member_step" in m:
                lines.append(f"| marginal member-step at B = {m['B']} ({m['long_steps']:,} less "
                             f"{m['short_steps']:,} steps) | {m['marginal_ns_per_member_step']:.1f} ns | "
                             f"{m['numba_ns_per_member_step']:.1f} ns | at least {m['goal']}x the peer's speed "
                             f"({m['speed_vs_numba']:.2f}x) | {yes(m)} |")
            else:
                lines.append(f"| a {m['steps']}-step run at B = {m['B']} | {f2(m['seconds'])} s | | under "
                             f"{m['goal_s']} s | {yes(m)} |")
    if sweeps:
        lines += ["", "| sweep of sdof-stiffness, 2000 steps | seconds | against | goal | met |",
                  "|---|---|---|---|---|",
                  f"| {sweeps['members']} members in {sweeps['shards']} shards{_workers(sweeps.get('workers'))} | "
                  f"{f2(sweeps['sweep_s'])} | | under {sweeps['goal_s']} s | {yes(sweeps)} |"]
        big = sweeps.get("large")
        if big:
            lines.append(f"| {big['members']} members in {big['shards']} shards{_workers(big.get('workers'))} | "
                         f"{f2(big['sweep_s'])} | one batch of {big['members']}{_threads(big.get('threads'))}: "
                         f"{f2(big['one_batch_s'])} s ({big['ratio']:.1f}x) | within {big['goal']}x | {yes(big)} |")
            if "sweep_s_one_worker" in big:
                lines.append(f"| the same, one after another in one process | {f2(big['sweep_s_one_worker'])} | one "
                             f"batch{_threads(big['threads_one_worker'])}: {f2(big['one_batch_s_one_worker'])} s "
                             f"({big['ratio_one_worker']:.1f}x) | | |")
    return "\n".join(lines)


def _workers(n: int | None) -> str:
    return "" if n is None else f", {n} worker{'s' if n != 1 else ''}"


def _threads(n: int | None) -> str:
    return "" if n is None else f" on {n} thread{'s' if n != 1 else ''}"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(ap)
    ap.add_argument("--end-to-end", action="store_true", help="also time rcotorch run in fresh processes")
    ap.add_argument("--table", action="store_true", help="print the results on record as Markdown and stop")
    args = ap.parse_args(argv)
    if args.table:
        sweeps = RESULTS / "sweep_cost.json"
        print(markdown(json.loads((RESULTS / "cli_cost.json").read_text()),
                       json.loads(sweeps.read_text()) if sweeps.is_file() else None))
        return {}
    dev = setup_cpu(args, "the command line's cost is measured on the CPU")
    if dev is None:
        return {}
    cases = [(1, 200_000), (4096, 2_000)] if args.quick else [(1, 2_000_000), (4096, 20_000)]
    threads = args.threads or 1
    results = [measure(B, steps, threads) for B, steps in cases]
    results.append(measure(8 if args.quick else 200, 2000 if args.quick else 20_000, threads,
                           name="shear-building-damage", peer=False))
    rows = [[r["scenario"], r["B"], r["steps"], r["logs"], f"{r['cli_ns_per_member_step']:.1f}",
             f"{r['engine_ns_per_member_step']:.1f}",
             f"{r['numba_ns_per_member_step'][r['best_numba']]:.1f}" if "best_numba" in r else "",
             f"{r['cli_over_engine']:.2f}x", "yes" if r["met"] else "NO", f"{r['first_stretch_s']:.2f}"]
            for r in results]
    print(table(rows, ["scenario", "B", "steps", "logs", "run ns", "engine ns", "numba ns", "run / engine",
                       f"<= {GOAL}x", "first stretch s"]))
    parts = sorted({k for r in results for k in r["finish_parts_s"]},
                   key=["intervals", "validation", "summary", "figures", "files"].index)
    rows = [[r["scenario"], r["B"], f"{r['engine_s']:.2f}", *(f"{r['finish_parts_s'].get(k, 0):.2f}" for k in parts),
             f"{r['finish_s']:.2f}", f"{r['finish_over_engine']:.2f}x", "yes" if r["end_met"] else "NO"]
            for r in results]
    print("\nthe end of the run (finish), part by part, seconds:")
    print(table(rows, ["scenario", "B", "engine s", *parts, "finish s", "finish / engine", f"<= {END_GOAL}x"]))
    e2e = []
    if args.end_to_end:
        for r, (short, long) in zip(results[:2], [(20_000, 20_000_000), (200, 20_000)]):
            if args.quick:
                short, long = short // 10, long // 10
            e2e.append(marginal(r["B"], short, long, threads, r["numba_ns_per_member_step"][r["best_numba"]]))
        ten = end_to_end(4096, 10, threads)
        rows = [[m["B"], m["short_steps"], m["long_steps"], f"{m['short_s']:.2f}", f"{m['long_s']:.2f}",
                 f"{m['marginal_ns_per_member_step']:.1f}", f"{m['numba_ns_per_member_step']:.1f}",
                 f"{m['speed_vs_numba']:.2f}x", "yes" if m["met"] else "NO"] for m in e2e]
        print("\nrcotorch run end to end (a fresh process):")
        print(table(rows, ["B", "short", "long", "short s", "long s", "marginal ns", "numba ns", "vs numba",
                           f">= {MARGINAL_GOAL}x"]))
        met = "yes" if ten < SHORT_GOAL_S else "NO"
        print(f"a 10-step run at B = 4096: {ten:.2f} s (goal < {SHORT_GOAL_S} s: {met})")
        e2e.append({"B": 4096, "steps": 10, "seconds": ten, "goal_s": SHORT_GOAL_S, "met": ten < SHORT_GOAL_S})
    out = {"benchmark": "cli_cost", "machine": machine(dev), "scenario": NAME, "results": results,
           "end_to_end": e2e}
    print("->", write_json(out, "cli_cost", args.out))
    return out


if __name__ == "__main__":
    main()
