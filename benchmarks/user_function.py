"""A user's own function in the native engine: the friction graph with its truth as a compiled StaticMap
against the same graph with a built-in Gain truth (the per-step cost a compiled function adds), and against the
PyTorch engine that ran it before (measured on a short run); and the same graph identified with a basis function
of the user's own (``features={"tanh": fn}``, NumPy, compiled) against the same basis as a built-in term
(``rt.features.tanh``) and against the PyTorch engine.

    python benchmarks/user_function.py                    # B = 1 and 4096, about two minutes
    python benchmarks/user_function.py --batches 1,64,4096 --threads 1

Goal: the compiled StaticMap within 3x the per-step cost of the Gain truth, and the compiled feature function
within 3x that of the built-in term, at B = 1 and B = 4096. Writes benchmarks/results/user_function.json.
"""

from __future__ import annotations

import argparse

import numpy as np
from common import add_common_args, machine, ns_per_member_step, setup_cpu, table, write_json

import rcotorch as rt


def friction(v):
    return -(2.0 * np.sign(v) + 0.5 * v)


def smooth_sign(s):
    """A basis function of the user's own: a smoothed sign of the velocity."""
    return np.tanh(s["y0"] / 0.1)


def graph(truth, batch: int, basis=None):
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.2, 4.0, measured=["velocity"], sees=["velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.01, name="known")
    features = [rt.features.sign("y0"), rt.features.port("y0")] if basis is None else \
        {"basis": basis, "v": rt.features.port("y0")}
    ident = rt.RCOEstimator.static_gain({"y0": 1}, features=features, p0=1e3)
    return rt.refinement(known, ident, truth=truth, excitation=rt.WhiteNoise(1, std=20.0, seed=1), nu=50,
                         batch_size=batch)


def gain_truth(batch: int, basis):
    """The friction graph with a Gain truth, identified with ``basis`` and the velocity."""
    return graph(rt.Gain([[-0.5]], name="unknown"), batch, basis)


def per_member_step(make, batch: int, seconds: float, engine: str = "auto") -> float:
    """ns per member-step: the graph advanced in calls of a fixed number of steps until ``seconds`` passed."""
    g = make(batch)
    g.engine = engine
    g.advance(10)                                    # lowering and compilation outside the timing
    steps = max(1, int(2e5 / batch)) if engine != "torch" else 20
    return ns_per_member_step(g.advance, batch, seconds, steps)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(ap)
    ap.add_argument("--batches", default="1,4096")
    ap.add_argument("--seconds", type=float, default=3.0)
    args = ap.parse_args(argv)
    dev = setup_cpu(args)
    if dev is None:
        return {}
    seconds = 0.3 if args.quick else args.seconds
    batches = [int(b) for b in args.batches.split(",")]
    rows, results = [], []
    for B in batches:
        compiled = per_member_step(lambda b: graph(rt.StaticMap(friction, 1, name="unknown"), b), B, seconds)
        gain = per_member_step(lambda b: graph(rt.Gain([[-0.5]], name="unknown"), b), B, seconds)
        torch_ = per_member_step(lambda b: graph(rt.StaticMap(friction, 1, name="unknown"), b), B,
                                 min(seconds, 1.0), engine="torch")
        own = per_member_step(lambda b: gain_truth(b, smooth_sign), B, seconds)
        term = per_member_step(lambda b: gain_truth(b, rt.features.tanh("y0", 0.1)), B, seconds)
        own_torch = per_member_step(lambda b: gain_truth(b, smooth_sign), B, min(seconds, 1.0), engine="torch")
        r = {"batch": B, "compiled_ns": compiled, "gain_ns": gain, "torch_ns": torch_,
             "compiled_over_gain": compiled / gain, "torch_over_compiled": torch_ / compiled,
             "feature_function_ns": own, "feature_term_ns": term, "feature_function_torch_ns": own_torch,
             "function_over_term": own / term, "torch_over_function": own_torch / own}
        results.append(r)
        rows.append([B, "StaticMap truth", f"{compiled:.1f}", "Gain", f"{gain:.1f}", f"{compiled / gain:.2f}x",
                     f"{torch_:.0f}", f"{torch_ / compiled:.0f}x"])
        rows.append([B, "feature function", f"{own:.1f}", "term", f"{term:.1f}", f"{own / term:.2f}x",
                     f"{own_torch:.0f}", f"{own_torch / own:.0f}x"])
    print(table(rows, ["B", "the user's function", "compiled ns", "built-in", "ns", "ratio (goal <= 3)",
                       "PyTorch engine ns", "speed-up"]))
    out = {"benchmark": "user_function", "machine": machine(dev), "results": results}
    print("->", write_json(out, "user_function", args.out))
    return out


if __name__ == "__main__":
    main()
