"""The per-refinement NumPy loop of ``sdof-stiffness-damping`` timed, the speed baseline of the benchmarks.

The loop itself, one refinement at a time with the same equations as rcotorch's Figure-1 graph, is
``tests/numpy_loop.py``, where ``tests/test_numpy_reference.py`` checks it against the library;
``benchmarks/throughput.py`` compares against its rate (``steps_per_second``). Run it on its own:
``python benchmarks/numpy_reference.py [--steps N]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))   # the loop lives with the tests that check it
from numpy_loop import noise, refine  # noqa: E402


def steps_per_second(steps: int, settings: dict | None = None, repeat: int = 1) -> float:
    """Throughput of the loop (refinement steps per second, the excitation drawn inside the timing), best of
    ``repeat``."""
    noise(1, 0, 1)   # import torch and rcotorch.engine.rng outside the timing
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        refine(steps, settings)
        best = min(best, time.perf_counter() - t)
    return steps / best


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=20000)
    args = ap.parse_args(argv)
    noise(1, 0, 1)   # import torch and rcotorch.engine.rng outside the timing
    t = time.perf_counter()
    out = refine(args.steps)
    dt = time.perf_counter() - t
    print(f"{args.steps} steps in {dt:.2f} s ({args.steps / dt:.0f} steps/s): dK {out['dK']:.6f}, "
          f"dC {out['dC']:.6f}, theta {out['theta'][0]}")


if __name__ == "__main__":
    main()
