"""The batched RLS kernel alone: bytes of P moved per second against the machine's memory-copy bandwidth.

    python benchmarks/rls_kernel.py [--device cpu|cuda] [--threads N] [--batches 4096,65536] [--n 3,10]

Writes benchmarks/results/rls_kernel.json and prints a table.

Definitions (all measured in the same run):

* one kernel step = ``rls_update`` for all B members with l = 1 (one z channel), lambda = 1, R = 1: the
  estimator's case in every scenario so far;
* effective P bandwidth = 2 * B * n^2 * 8 bytes per step / seconds per step: the least traffic any
  implementation needs (read P once, write it once, float64), whatever it actually moves;
* memory-copy bandwidth = 2 * bytes / seconds of ``dst.copy_(src)`` on a buffer much larger than the
  last-level cache (read + write), the same accounting; also for a buffer the size of P;
* percent = effective P bandwidth / memory-copy bandwidth.

Variants: ``inplace`` (``rls_update(..., inplace=True)``, what the estimator runs: on the CPU in float64 the
native single-pass kernel of ``rcotorch.engine._engine``, each member's P read once and written once),
``inplace_torch`` (the same in PyTorch operations, ``kernel='torch'``), ``functional`` (new tensors returned;
a copy of theta and P, then the native kernel), ``before`` (the kernel as it was before the speed work, for
reference) and ``compiled`` (``torch.compile`` of the PyTorch in-place kernel; ``--no-compile`` skips it).
"""

from __future__ import annotations

import argparse
import time

import torch
from common import add_common_args, machine, setup, sync, table, timed, write_json

from rcotorch.engine.rls import rls_update


def rls_before(theta, P, psi, z_r, lam=1.0, r_inv=1.0, active=None):
    """The l = 1 kernel as it was before the speed work (rcotorch 56956e7): several passes over P."""
    B, n = theta.shape
    lam = torch.as_tensor(lam, dtype=P.dtype, device=P.device)
    lam = lam.reshape(-1, 1, 1) if lam.dim() else lam
    a = torch.bmm(P, psi)
    s = lam * torch.as_tensor(r_inv, dtype=P.dtype, device=P.device).reshape(()) + psi.mT @ a
    go = torch.isfinite(s) & (s > 0)
    ok = go.reshape(B)
    if active is not None:
        go = go & active.reshape(B, 1, 1)
    step = (a / torch.where(go, s, 1.0)).squeeze(-1) * z_r
    finite = torch.isfinite(step.sum(1))
    ok = ok & finite
    go = go & finite.reshape(B, 1, 1)
    a = torch.where(go, a, 0.0)
    P_new = P - (a @ a.mT) / torch.where(go, s, 1.0)
    P_new = P_new / torch.where(go, lam, 1.0)
    theta_new = torch.where(go.reshape(B, 1), theta - step, theta)
    return theta_new, P_new, ok if active is None else ok | ~active


def memcpy_bandwidth(nbytes: int, dev: torch.device, seconds: float) -> float:
    """Bytes moved per second (read + write) by ``dst.copy_(src)`` of ``nbytes``."""
    src = torch.ones(nbytes // 8, dtype=torch.float64, device=dev)
    dst = torch.empty_like(src)
    t, _ = timed(lambda: dst.copy_(src), dev, seconds)
    return 2 * src.numel() * 8 / t


def problem(B: int, n: int, dev: torch.device, seed: int = 0):
    g = torch.Generator(device="cpu").manual_seed(seed)
    theta = torch.zeros(B, n, dtype=torch.float64)
    P = 1e6 * torch.eye(n, dtype=torch.float64).expand(B, n, n).clone()
    psi = torch.randn(B, n, 1, generator=g, dtype=torch.float64)
    z_r = torch.randn(B, 1, generator=g, dtype=torch.float64)
    active = torch.ones(B, dtype=torch.bool)
    for _ in range(2 * n):   # make P a dense, well-scaled covariance
        theta, P, _ = rls_update(theta, P, torch.randn(B, n, 1, generator=g, dtype=torch.float64), z_r, inplace=True)
    return [t.to(dev) for t in (theta, P, psi, z_r, active)]


def run(args) -> dict | None:
    dev = setup(args)
    if dev is None:
        return None
    batches = [int(b) for b in args.batches.split(",")]
    ns = [int(n) for n in args.n.split(",")]
    seconds = 0.3 if args.quick else args.seconds
    big = (8 << 20) if args.quick else args.copy_mib << 20
    copy_bw = memcpy_bandwidth(big, dev, seconds)
    rows, results = [], []
    compiled = None
    for n in ns:
        for B in batches:
            theta, P, psi, z_r, active = problem(B, n, dev)
            pbytes = B * n * n * 8
            entry = {"B": B, "n_theta": n, "P_bytes": pbytes, "min_bytes_per_step": 2 * pbytes,
                     "memcpy_same_size_bytes_per_s": memcpy_bandwidth(max(pbytes, 1 << 16), dev, seconds),
                     "variants": {}}
            a = (theta, P, psi, z_r, 1.0, 1.0, active)
            variants = {
                "inplace": lambda a=a: rls_update(*a, inplace=True),
                "inplace_torch": lambda a=a: rls_update(*a, inplace=True, kernel="torch"),
                "functional": lambda a=a: rls_update(*a),
                "before": lambda a=a: rls_before(*a),
            }
            if args.compile:
                if compiled is None:
                    compiled = torch.compile(rls_update, dynamic=False)
                variants["compiled"] = lambda a=a, f=compiled: f(*a, inplace=True, kernel="torch")
            for name, fn in variants.items():
                try:
                    t0 = time.perf_counter()
                    fn()
                    sync(dev)
                    first = time.perf_counter() - t0   # includes compilation for 'compiled'
                    t, calls = timed(fn, dev, seconds)
                except Exception as e:  # a variant that cannot run here (e.g. no C compiler for compile)
                    entry["variants"][name] = {"error": f"{type(e).__name__}: {e}"[:500]}
                    rows.append([n, B, name, "error", "", "", ""])
                    continue
                bw = 2 * pbytes / t
                entry["variants"][name] = {"seconds_per_step": t, "calls": calls, "first_call_seconds": first,
                                           "effective_P_bytes_per_s": bw, "percent_of_memcpy": 100 * bw / copy_bw}
                rows.append([n, B, name, f"{t * 1e3:.3f}", f"{bw / 1e9:.2f}", f"{100 * bw / copy_bw:.1f}",
                             f"{first:.1f}"])
            results.append(entry)
    out = {
        "benchmark": "rls_kernel",
        "definition": "effective P bandwidth = 2*B*n^2*8 bytes per step (read P + write P once, float64) / "
                      "seconds per step; memcpy bandwidth = 2*bytes/seconds of dst.copy_(src) on a "
                      f"{big >> 20} MiB buffer; l = 1, lambda = 1, R = 1, all members active",
        "machine": machine(dev), "memcpy_bytes_per_s": copy_bw, "memcpy_buffer_bytes": big, "results": results,
    }
    print(f"memcpy bandwidth ({big >> 20} MiB buffer, read + write): {copy_bw / 1e9:.2f} GB/s on {dev}, "
          f"{torch.get_num_threads()} threads")
    print(table(rows, ["n", "B", "variant", "ms/step", "P GB/s", "% memcpy", "first s"]))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(ap)
    ap.add_argument("--batches", default="4096,65536,262144")
    ap.add_argument("--n", default="3,10")
    ap.add_argument("--seconds", type=float, default=2.0, help="timing per measurement")
    ap.add_argument("--copy-mib", type=int, default=512, help="size of the memory-copy buffer")
    ap.add_argument("--no-compile", dest="compile", action="store_false", help="skip the torch.compile variant")
    args = ap.parse_args(argv)
    out = run(args)
    if out is not None:
        print("wrote", write_json(out, "rls_kernel", args.out))


if __name__ == "__main__":
    main()
