"""The estimates of runs on a GPU against the same runs on the CPU, side by side.

    python benchmarks/cuda_compare.py GPU_RUNS CPU_RUNS

Each folder holds one subfolder per run (``benchmarks/cuda_scenarios.sh`` writes them, with ``DEVICE=cpu`` for the
references); for every run present in both, prints its device, dtype, status and the largest relative
difference of its estimates, max |gpu - cpu| / max(|cpu|, 1e-12), over every member and estimate.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def largest_difference(gpu: dict, cpu: dict) -> float:
    worst = 0.0
    for key, want in cpu["estimates"].items():
        a = np.asarray(gpu["estimates"][key], dtype=float)
        b = np.asarray(want, dtype=float)
        both = np.isfinite(a) & np.isfinite(b)
        if not np.array_equal(np.isfinite(a), np.isfinite(b)):
            return float("inf")
        if both.any():
            worst = max(worst, float(np.max(np.abs(a[both] - b[both]) / np.maximum(np.abs(b[both]), 1e-12))))
    return worst


def main(gpu_dir: str, cpu_dir: str) -> None:
    print(f"{'run':<18} {'scenario':<28} {'B':>4} {'dtype':<8} {'steps':>6} {'device':<6} {'status':<32} vs CPU")
    for run in sorted(Path(gpu_dir).iterdir()):
        ref = Path(cpu_dir) / run.name / "summary.json"
        if not (run / "summary.json").is_file() or not ref.is_file():
            continue
        gpu, cpu = (json.loads(p.read_text()) for p in (run / "summary.json", ref))
        status = gpu["status"] if isinstance(gpu["status"], str) else ", ".join(
            f"{n} {k}" for k, n in sorted(_count(gpu["status"]).items()))
        print(f"{run.name:<18} {gpu['scenario']:<28} {gpu['batch']:>4} {gpu['dtype']:<8} {gpu['steps']:>6} "
              f"{gpu['device']:<6} {status:<32} {largest_difference(gpu, cpu):.1e}")


def _count(values) -> dict:
    out: dict = {}
    for v in values:
        out[v] = out.get(v, 0) + 1
    return out


if __name__ == "__main__":
    main(*sys.argv[1:3])
