"""Experiment: would ``torch.compile`` of the estimator's update pay off? (Not used by the library.)

    python benchmarks/compile_experiment.py [--batches 1,64,4096,65536] [--threads N] [--device cpu|cuda]

The estimator's update (ring buffer, Markov filter, retrospective error, RLS, bookkeeping) is written as one
function of tensors (the step index as a tensor, no Python-side state) and compiled with ``torch.compile``;
the whole ``sdof-stiffness-damping`` graph is then stepped with it in place of ``RCOEstimator.update``, against
the eager graph, and the final theta of the two compared. Writes benchmarks/results/compile_experiment.json.
Limited to what the scenario needs (one z, one u, all theta entries free, lambda = 1, nc = 1).
"""

from __future__ import annotations

import argparse
import time

import torch
from common import add_common_args, machine, setup, sync, table, write_json

from rcotorch.engine.rls import rls_update
from rcotorch.run import scenario as scenarios

NAME = "sdof-stiffness-damping"


def core(win, k, phi_now, u_now, z, beta_rev, theta, P, alive, diverged_at, past, past_u, cur, r_inv):
    """RCOEstimator.update for n_z = n_u = 1, all free, lambda = 1, nc = 1, as a pure tensor program."""
    W, B, m = win.shape
    nu, n_phi = beta_rev.shape[-1], m - 1
    p = k % W
    row = torch.cat([phi_now, u_now], 1)
    win.index_copy_(0, p.reshape(1), row.unsqueeze(0))
    rows = win.index_select(0, (p + 1 + torch.arange(nu, device=win.device)) % W)
    prod = (beta_rev[0] @ rows.reshape(nu, B * m)).reshape(B, m)
    psi = prod[:, :n_phi]
    theta_flat = theta.view(B, -1)
    z_r = z - prod[:, n_phi:] + (psi.unsqueeze(1) @ theta_flat.unsqueeze(-1)).squeeze(-1)
    _, _, ok = rls_update(theta_flat, P, psi.unsqueeze(-1), z_r, 1.0, r_inv, alive, inplace=True)
    diverged_at.copy_(torch.where(alive & ~ok, k, diverged_at))
    alive.copy_(alive & ok)
    past.copy_(cur.unsqueeze(1))
    past_u.copy_(u_now.unsqueeze(1))
    k.add_(1)
    return z_r


def patch(graph, fn) -> None:
    est = graph.blocks["identified"]
    assert est.n_u == est.n_z == 1 and est.all_free and est.nc == 1 and bool((est.lam == 1).all())
    beta_rev = est.beta.flatten(2).mT.flip(-1).contiguous()   # entry j weighs delay nu - j

    def update(inputs):
        z_r = fn(est.win, est.k, est.phi_now, est.u_now, inputs["z"], beta_rev, est.theta, est.P, est.alive,
                 est.diverged_at, est.past, est.past_u, est._regressors(inputs), est.r_inv)
        est.set_state(z_r=z_r)
        est._k_cache = None

    est.update = update


def rate(graph, dev, seconds: float, warmup: int) -> tuple[float, float]:
    t = time.perf_counter()
    for _ in range(warmup):
        graph.step()
    sync(dev)
    first = time.perf_counter() - t
    steps, t = 0, time.perf_counter()
    while time.perf_counter() - t < seconds or steps < 5:
        graph.step()
        steps += 1
    sync(dev)
    return (time.perf_counter() - t) / steps, first


def run(args) -> dict | None:
    dev = setup(args)
    if dev is None:
        return None
    sc = scenarios.get(NAME)
    s = sc.resolve()
    seconds = 0.3 if args.quick else args.seconds
    compiled = torch.compile(core, dynamic=False)
    rows, results = [], []
    for B in [int(b) for b in args.batches.split(",")]:
        eager = sc.build(s, B, torch.float64, dev)
        fast = sc.build(s, B, torch.float64, dev)
        patch(fast, compiled)
        t_fast, first = rate(fast, dev, seconds, 3)
        t_eager, _ = rate(eager, dev, seconds, 3)
        # the same number of steps on both, then compare
        for g in (eager, fast):
            g.reset(B)
        for _ in range(300):
            eager.step()
            fast.step()
        a, b = eager.blocks["identified"].theta, fast.blocks["identified"].theta
        rel = float((a - b).abs().max() / a.abs().max())
        r = {"B": B, "eager_seconds_per_step": t_eager, "compiled_seconds_per_step": t_fast,
             "speedup": t_eager / t_fast, "compile_seconds": first, "theta_rel_diff_after_300": rel}
        results.append(r)
        rows.append([B, f"{t_eager * 1e6:.0f}", f"{t_fast * 1e6:.0f}", f"{t_eager / t_fast:.2f}", f"{first:.1f}",
                     f"{rel:.1e}"])
    print(f"{NAME} on {dev} ({torch.get_num_threads()} threads): whole graph step, estimator update eager vs "
          "compiled")
    print(table(rows, ["B", "eager us/step", "compiled us/step", "speedup", "compile s", "theta rel diff"]))
    return {"benchmark": "compile_experiment", "scenario": NAME, "machine": machine(dev), "results": results}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(ap)
    ap.add_argument("--batches", default="1,64,4096,65536")
    ap.add_argument("--seconds", type=float, default=3.0)
    args = ap.parse_args(argv)
    out = run(args)
    if out is not None:
        print("wrote", write_json(out, "compile_experiment", args.out))


if __name__ == "__main__":
    main()
