"""A benchmark script run as its users run it, in a fresh interpreter: the tests check what the scripts print and
write, not their insides."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_script(name: str, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """``python benchmarks/NAME.py ARGS`` from the repository's root, with one thread as the tests' own process
    (conftest.py); fails the test, with the end of the script's output, where it exits with an error."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / f"{name}.py"), *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT, env=env)
    assert done.returncode == 0, (f"benchmarks/{name}.py {' '.join(args)} exited {done.returncode}:\n"
                                  f"{done.stdout[-2000:]}\n{done.stderr[-3000:]}")
    return done
