"""The numba peer (``tests/numba_loop.py``: ``sdof-stiffness-damping`` as a jitted loop in three variants) timed:
the first call of each variant (numba compiles it then), and the seconds per member-step of each.

    python benchmarks/numba_peer.py

``benchmarks/peer.py`` compares the variants with rcotorch's native engine.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))   # the peer lives with the tests that check it
from numba_loop import run  # noqa: E402


def compile_seconds() -> dict[str, float]:
    """Seconds of the first call of each variant (numba compiles it then)."""
    out = {}
    for variant in ("one", "prange", "lanes"):
        t = time.perf_counter()
        run(variant, 2, 2 if variant != "one" else 1)
        out[variant] = time.perf_counter() - t
    return out


if __name__ == "__main__":
    print("compile seconds:", compile_seconds())
    for variant, B in (("one", 1), ("prange", 4096), ("lanes", 4096)):
        t = time.perf_counter()
        run(variant, 2000, B)
        dt = time.perf_counter() - t
        print(f"{variant} B={B}: {dt / (2000 * B) * 1e9:.1f} ns per member-step")
