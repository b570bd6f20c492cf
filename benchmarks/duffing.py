"""A continuous Duffing oscillator as a user writes it (a ``Nonlinear`` block with NumPy f and h, RK4
substeps), driven by white noise, in the native engine against a numba loop of the same equations written
as a performance-minded user would (scalar RK4 per member, normals in pairs), and against the PyTorch engine.
The block is measured in both of its forms: ``components`` (f of the state's components, the form that
compiles to scalar code) and ``batch`` (f of the (B, n) array, whose compiled form makes arrays each call).

    python benchmarks/duffing.py --threads 1              # B = 1 and 4096, about a minute

Goal: the engine (components form) at least as fast as the numba loop at B = 1 and B = 4096.
Writes benchmarks/results/duffing.json.
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np
from common import add_common_args, machine, ns_per_member_step, setup_cpu, table, write_json

import rcotorch as rt

K, C, A, DT, SUB = 4.0, 0.3, 2.0, 0.01, 4


def duffing(x, ins):
    q, v = x
    return v, -K * q - C * v - A * q ** 3 + ins["w"][0]


def velocity(x):
    return x[1]


def duffing_batch(x, ins):
    q, v = x[:, 0:1], x[:, 1:2]
    return np.concatenate((v, -K * q - C * v - A * q ** 3 + ins["w"]), axis=1)


def velocity_batch(x):
    return x[:, 1:2]


def graph(batch: int, form: str = "components"):
    f, h = (duffing, velocity) if form == "components" else (duffing_batch, velocity_batch)
    blk = rt.Nonlinear(f, h, 2, inputs=["w"], outputs=["y"], dt=DT, continuous=True, substeps=SUB,
                       name="duffing", form=form)
    return rt.Graph([rt.WhiteNoise(1, seed=1, name="w"), blk], [("w.out", "duffing.w")], batch_size=batch)


@numba.njit(cache=False)
def numba_loop(x, steps, seed):
    """steps of every member: a normal force (drawn in pairs), SUB RK4 substeps of the Duffing equation."""
    np.random.seed(seed)
    h = DT / SUB
    B = x.shape[0]
    spare, have = 0.0, False
    for _ in range(steps):
        for b in range(B):
            if have:
                w, have = spare, False
            else:
                u1, u2 = np.random.random(), np.random.random()
                r = np.sqrt(-2.0 * np.log(1.0 - u1))
                w, spare, have = r * np.cos(2 * np.pi * u2), r * np.sin(2 * np.pi * u2), True
            q, v = x[b, 0], x[b, 1]
            for _s in range(SUB):
                k1q, k1v = v, -K * q - C * v - A * q ** 3 + w
                q2, v2 = q + 0.5 * h * k1q, v + 0.5 * h * k1v
                k2q, k2v = v2, -K * q2 - C * v2 - A * q2 ** 3 + w
                q3, v3 = q + 0.5 * h * k2q, v + 0.5 * h * k2v
                k3q, k3v = v3, -K * q3 - C * v3 - A * q3 ** 3 + w
                q4, v4 = q + h * k3q, v + h * k3v
                k4q, k4v = v4, -K * q4 - C * v4 - A * q4 ** 3 + w
                q, v = q + h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q), v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
            x[b, 0], x[b, 1] = q, v
    return x


def best_ns(run, batch: int, seconds: float) -> float:
    steps = max(1, int(2e5 / batch))
    run(steps)                                       # compile / warm
    return ns_per_member_step(run, batch, seconds, steps)


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
    rows, results = [], []
    for B in [int(b) for b in args.batches.split(",")]:
        engine = best_ns(graph(B).advance, B, seconds)
        engine_batch = best_ns(graph(B, "batch").advance, B, seconds)
        x = np.zeros((B, 2))
        peer = best_ns(lambda n, x=x: numba_loop(x, n, 1), B, seconds)
        gt = graph(B)
        gt.engine = "torch"
        gt.advance(2)
        t0 = time.perf_counter()
        gt.advance(20)
        torch_ = (time.perf_counter() - t0) / (20 * B) * 1e9
        r = {"batch": B, "engine_ns": engine, "engine_batch_form_ns": engine_batch, "numba_loop_ns": peer,
             "torch_ns": torch_, "numba_over_engine": peer / engine, "goal_met": peer / engine >= 1.0}
        results.append(r)
        rows.append([B, f"{engine:.1f}", f"{engine_batch:.1f}", f"{peer:.1f}", f"{peer / engine:.2f}x",
                     f"{torch_:.0f}"])
    print(table(rows, ["B", "engine ns", "engine ns, batch form", "numba loop ns", "numba / engine (goal >= 1)",
                       "PyTorch engine ns"]))
    out = {"benchmark": "duffing", "machine": machine(dev), "results": results}
    print("->", write_json(out, "duffing", args.out))
    return out


if __name__ == "__main__":
    main()
