"""Per-step cost of the native engine on graphs beyond the textbook case, recording, and an end-to-end run.

    python benchmarks/engine_cost.py [--threads 1] [--seconds 1] [--quick] [--out FILE]

Writes benchmarks/results/engine_cost.json and prints a table. Everything is measured in one run, the sides
of each comparison interleaved (best of 3 rounds), so the ratios hold on a shared machine:

* ``per_step``: member-steps per second of ``Graph.advance`` on the native engine at B = 1 and B = 4096 for
  (a) ``silverbox-cubic-stiffness`` (recorded data, first-order-hold known model, basis feature y0^3),
  (b) ``twodof-stiffness`` (4 states, u of width 2, masked 2 x 2 static gain, 60 Markov parameters),
  (c) a features graph: ``sdof-stiffness`` with u = theta [x, x^3, sign(x')] (``rt.features``),
  each against the NumPy loop of the same equations (``numpy_graph.py``; its final theta is checked against
  the engine's to 1e-9 first). Goals: >= 10x at B = 1, >= 300x at B = 4096.
* ``recording``: ``Graph.run`` recording every output port of the graph at every step against the same run
  unrecorded (the recording buffers are allocated inside the timing, as ``run`` does). Goal: <= 2x.
* ``end_to_end``: ``silverbox-cubic-stiffness`` as the scenario does it: fit of the linear model, refinement
  over the whole estimation record, free-run validation of the initial and refined models; with the native
  refinement and with the NumPy loop's refinement (the fit and the validation are the same NumPy code on both
  sides). Goal: the native run faster.

Silverbox needs the data (``rt.datasets``: downloaded once, or a local copy in $RCOTORCH_SILVERBOX).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import numpy_graph
import torch
from common import machine, setup, table, write_json

import rcotorch as rt
from rcotorch.run import scenario as scenarios

f = rt.features
GOALS = {"B=1": 10.0, "B=4096": 300.0, "recording": 2.0}
FEATURES = [f.port("y0[0]"), f.power("y0[0]", 3), f.sign("y0[1]")]


# silverbox-cubic-stiffness as this comparison was made: the input interpolated linearly, the spring y0^3 (the
# NumPy loop's feedback), a known model of three states
SILVERBOX = {"basis": "cubic", "spline": "false", "u_ahead": "false"}


def _scenario_graph(name: str, **over):
    def build(B: int):
        sc = scenarios.get(name)
        return sc.build(sc.resolve(over), B, torch.float64, "cpu")
    return build


def features_graph(B: int):
    """sdof-stiffness with a static gain on the basis [x, x^3, sign(x')] of the known model's [x, x']."""
    s = scenarios.get("sdof-stiffness").resolve()
    sdof = rt.models.sdof_matrices
    known = rt.LTI.continuous(*sdof(s["m"], s["C"], s["K"], sees=["position", "velocity"]), inputs=["w", "u"],
                              outputs={"y": 1, "y0": 2}, dt=s["Ts"], name="known")
    plant = rt.LTI.continuous(*sdof(s["m"], s["C"] + s["dC"], s["K"] + s["dK"], sees=[], actuation=False),
                              inputs=["w"], outputs=["y"], dt=s["Ts"], name="plant")
    ident = rt.RCOEstimator.static_gain({"y0": 2}, features=FEATURES, p0=s["p0"], lam=s["lam"])
    return rt.refinement(known, ident, physical=plant, excitation=rt.WhiteNoise(1, std=s["w_std"], seed=s["seed"]),
                         nu=s["nu"], batch_size=B)


# name: (graph builder, the same basis features in NumPy)
CASES = {
    "silverbox-cubic-stiffness": (_scenario_graph("silverbox-cubic-stiffness", **SILVERBOX), lambda y0: y0 ** 3),
    "twodof-stiffness": (_scenario_graph("twodof-stiffness"), lambda y0: y0),
    "features (x, x^3, sign x')": (features_graph, lambda y0: np.array([y0[0], y0[0] ** 3, np.sign(y0[1])])),
}


def _best(fns: dict, rounds: int) -> dict:
    """Seconds of each fn(), best of ``rounds`` rounds, the fns interleaved within each round."""
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(rounds):
        for key, fn in fns.items():
            t = time.perf_counter()
            fn()
            best[key] = min(best[key], time.perf_counter() - t)
    return best


def _steps_for(fn, seconds: float, lo: int = 20) -> int:
    """Steps of ``fn(steps)`` that take about ``seconds`` (from a short probe)."""
    t = time.perf_counter()
    fn(lo)
    per = (time.perf_counter() - t) / lo
    return max(lo, int(seconds / max(per, 1e-9)))


def check(name: str, steps: int = 2000) -> float:
    """Largest relative difference of the NumPy loop's final theta from the native engine's (batch of one)."""
    build, feats = CASES[name]
    g = build(1)
    loop = numpy_graph.from_graph(g, steps, feats)
    theta = numpy_graph.refine(loop, steps)
    g.engine = "native"
    g.advance(steps)
    ref = g.role("estimator").theta[0].numpy()
    return float(np.max(np.abs(theta - ref)) / np.max(np.abs(ref)))


def per_step(name: str, seconds: float, rounds: int, batches=(1, 4096)) -> dict:
    build, feats = CASES[name]
    graphs = {B: build(B) for B in batches}
    for g in graphs.values():
        g.engine = "native"
        g.advance(50)                                           # warm: program lowered, noise drawn
    np_steps = _steps_for(lambda n: numpy_graph.refine(numpy_graph.from_graph(graphs[1], n, feats), n),
                          seconds / 2, 50)
    horizon = max(graphs[1].max_steps or 10**9, 1)
    loop = numpy_graph.from_graph(build(1), min(np_steps, horizon), feats)
    np_steps = min(np_steps, horizon)
    steps = {B: min(_steps_for(g.advance, seconds / 2, 200), (horizon - 250) // rounds)
             for B, g in graphs.items()}
    fns = {"numpy": lambda: numpy_graph.refine(loop, np_steps)}
    fns.update({B: (lambda g=g, n=steps[B]: g.advance(n)) for B, g in graphs.items()})
    best = _best(fns, rounds)
    np_rate = np_steps / best["numpy"]
    out = {"numpy_steps": np_steps, "numpy_us_per_step": 1e6 / np_rate, "theta_rel_diff": check(name)}
    for B in batches:
        rate = B * steps[B] / best[B]
        out[f"B={B}"] = {"steps": steps[B], "us_per_member_step": 1e6 / rate, "member_steps_per_s": rate,
                         "x_numpy": rate / np_rate, "goal": GOALS[f"B={B}"], "met": rate / np_rate >= GOALS[f"B={B}"]}
    return out


def recording(name: str, B: int, seconds: float, rounds: int) -> dict:
    """Graph.run with every output port recorded at every step vs the same run unrecorded, each from a reset
    graph (the reset in both timings)."""
    build = CASES[name][0]
    g = build(B)
    g.engine = "native"
    g.run(50)
    record = {f"{b}.{p}": f"{b}.{p}" for b, blk in g.blocks.items() for p in blk.outputs}

    def run(steps, rec=None):
        g.reset(B)
        g.run(steps, record=rec)

    steps = min(_steps_for(run, seconds / 2, 200), (g.max_steps or 10**9))
    best = _best({"plain": lambda: run(steps), "recorded": lambda: run(steps, record)}, rounds)
    return {"scenario": name, "B": B, "steps": steps, "signals": sorted(record), "plain_s": best["plain"],
            "recorded_s": best["recorded"], "ratio": best["recorded"] / best["plain"], "goal": GOALS["recording"],
            "met": best["recorded"] / best["plain"] <= GOALS["recording"]}


def end_to_end(rounds: int) -> dict:
    """silverbox-cubic-stiffness: fit, refinement over the estimation record, validation; native vs NumPy."""
    import importlib
    mod = importlib.import_module("rcotorch.scenarios.silverbox_cubic_stiffness")
    sc = scenarios.get("silverbox-cubic-stiffness")
    s = sc.resolve(SILVERBOX)                                # the NumPy loop's feedback: theta y0^3
    steps = sc.steps

    def fresh():
        mod._prepare.cache_clear()
        mod._validate.cache_clear()

    def native():
        fresh()
        g = sc.build(s, 1, torch.float64, "cpu")              # fits the linear model
        g.engine = "native"
        g.advance(steps)
        return float(sc.metrics(g, s)["val_rmse_refined"][0])

    def numpy_loop():
        fresh()
        g = sc.build(s, 1, torch.float64, "cpu")              # the same fit; the graph only supplies numbers
        theta = numpy_graph.refine(numpy_graph.from_graph(g, steps, lambda y0: y0 ** 3), steps)
        mod.validate(s, 0.0)
        return float(mod.validate(s, float(theta[0, 0]))[0])

    results = {}
    fns = {"native": lambda: results.__setitem__("native", native()),
           "numpy": lambda: results.__setitem__("numpy", numpy_loop())}
    best = _best(fns, rounds)
    return {"steps": steps, "native_s": best["native"], "numpy_s": best["numpy"],
            "x_numpy": best["numpy"] / best["native"], "val_rmse_native": results["native"],
            "val_rmse_numpy": results["numpy"], "met": best["native"] < best["numpy"]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=1, help="threads of the native engine (torch's setting)")
    ap.add_argument("--seconds", type=float, default=1.0, help="rough timing per side of a comparison per round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/engine_cost.json)")
    ap.add_argument("--quick", action="store_true", help="tiny timings, no end-to-end run (a smoke test)")
    ap.add_argument("--no-end-to-end", dest="e2e", action="store_false")
    args = ap.parse_args(argv)
    args.device = "cpu"
    dev = setup(args)
    seconds, rounds = (0.05, 1) if args.quick else (args.seconds, args.rounds)
    load_before = machine(dev)["load_average"]
    costs = {name: per_step(name, seconds, rounds) for name in CASES}
    rec = [recording(name, B, seconds, rounds + 2) for name in ("silverbox-cubic-stiffness", "twodof-stiffness")
           for B in (1, 64)]
    e2e = end_to_end(min(rounds, 2)) if args.e2e and not args.quick else None
    out = {"benchmark": "engine_cost", "machine": machine(dev), "load_average_before": load_before,
           "definition": "member-steps per second of Graph.advance (native engine) vs steps per second of the "
                         "NumPy loop of the same equations (numpy_graph.py), best of the interleaved rounds; "
                         "recording: Graph.run with every output port recorded every step / unrecorded",
           "per_step": costs, "recording": rec, "end_to_end": e2e}
    rows = []
    for name, c in costs.items():
        for B in (1, 4096):
            r = c[f"B={B}"]
            rows.append([name, B, f"{r['us_per_member_step']:.4f}", f"{c['numpy_us_per_step']:.1f}",
                         f"{r['x_numpy']:.0f}", f">= {r['goal']:.0f}", "yes" if r["met"] else "NO",
                         f"{c['theta_rel_diff']:.1e}"])
    print(table(rows, ["graph", "B", "us/member-step", "NumPy us/step", "x NumPy", "goal", "met", "theta diff"]))
    for r in rec:
        print(f"recording {r['scenario']} B={r['B']} ({len(r['signals'])} signals, {r['steps']} steps): "
              f"{r['ratio']:.2f}x unrecorded (goal <= 2x: {'met' if r['met'] else 'NOT met'})")
    if e2e:
        print(f"silverbox end to end: native {e2e['native_s']:.2f} s, NumPy loop {e2e['numpy_s']:.2f} s "
              f"({e2e['x_numpy']:.1f}x); validation rms {e2e['val_rmse_native'] * 1e3:.3f} / "
              f"{e2e['val_rmse_numpy'] * 1e3:.3f} mV")
    print("wrote", write_json(out, "engine_cost", args.out))


if __name__ == "__main__":
    main()
