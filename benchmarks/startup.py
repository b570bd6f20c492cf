"""Start-up: how long the command line and ``import rcotorch`` take, as ratios against ``import torch``.

Each command runs in a fresh interpreter, the commands in turn (so that the machine's load falls on all of
them alike), ``--repeats`` times; each one's time is its best run (the least disturbed by other processes).

* ``python -c "import torch"``: the reference, measured in the same run;
* ``python -c "import rcotorch"`` (the package's parts are imported on first use), and the same followed by the
  first use of its core (``rt.Graph``, ``rt.LTI``, ``rt.RCOEstimator``, ``rt.refinement``, ``rt.WhiteNoise``,
  ``rt.refine``: torch, the engine, the monitor);
* ``rcotorch --version``, ``rcotorch list``, ``rcotorch show sdof-stiffness`` (the console script installed
  next to the interpreter, or ``python -m rcotorch`` where there is none);
* ``python -c "pass"``: the interpreter's own start, for reference.

Goals: ``rcotorch --version``, ``list`` and ``show`` each under 1 s; ``import rcotorch``, with or without the
first use of its core, at most 0.5 s more than ``import torch``. The JSON also says which of torch, scipy,
python-control, matplotlib and numpy each command loads (one more run with ``python -X importtime``).
``RCOTORCH_SCENARIOS`` is unset for the measurement: a user's scenario folder whose files import torch at the
top makes ``list`` and ``show`` load it.

    python benchmarks/startup.py                  # about 40 s
    python benchmarks/startup.py --repeats 15

Writes benchmarks/results/startup.json.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from common import machine, table, write_json

GOALS = {"cli_s": 1.0, "import_over_torch_s": 0.5}
HEAVY = ("torch", "scipy", "control", "matplotlib", "numpy")
CLI_COMMANDS = ("--version", "list", "show sdof-stiffness")
CORE = "import rcotorch as rt; rt.Graph, rt.LTI, rt.RCOEstimator, rt.refinement, rt.WhiteNoise, rt.refine"
IMPORTS = ("import rcotorch", "import rcotorch, its core")


def commands() -> dict[str, list[str]]:
    """What is timed, by label: argument lists of fresh processes."""
    script = Path(sys.executable).parent / "rcotorch"
    cli = [str(script)] if script.is_file() else [sys.executable, "-m", "rcotorch"]
    out = {"import torch": [sys.executable, "-c", "import torch"],
           "import rcotorch": [sys.executable, "-c", "import rcotorch"],
           "import rcotorch, its core": [sys.executable, "-c", CORE]}
    for command in CLI_COMMANDS:
        out[f"rcotorch {command}"] = cli + command.split()
    out["python (nothing imported)"] = [sys.executable, "-c", "pass"]
    return out


def environment() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k != "RCOTORCH_SCENARIOS"}


def seconds(argv: list[str], env: dict[str, str]) -> float:
    start = time.perf_counter()
    done = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    elapsed = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} exited {done.returncode}: {done.stderr.strip()}")
    return elapsed


def loads(argv: list[str], env: dict[str, str]) -> list[str]:
    """Which of ``HEAVY`` the command imports (``python -X importtime``: one line per module, on stderr)."""
    if Path(argv[0]).name == "rcotorch":                 # the console script: run its module the same way
        argv = [sys.executable, "-m", "rcotorch", *argv[1:]]
    done = subprocess.run([argv[0], "-X", "importtime", *argv[1:]], stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True, env=env)
    names = {line.rsplit("|", 1)[-1].strip() for line in done.stderr.splitlines() if line.startswith("import time:")}
    return [m for m in HEAVY if m in names]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7, help="fresh processes per command (best of them)")
    ap.add_argument("--out", default=None, help="JSON file to write (default: benchmarks/results/startup.json)")
    ap.add_argument("--quick", action="store_true", help="two repetitions (a smoke test)")
    args = ap.parse_args(argv)
    repeats = 2 if args.quick else args.repeats
    env = environment()
    todo = commands()
    for argv_ in todo.values():                  # a first run of each fills the file cache; not counted
        seconds(argv_, env)
    runs: dict[str, list[float]] = {label: [] for label in todo}
    for _ in range(repeats):
        for label, argv_ in todo.items():
            runs[label].append(seconds(argv_, env))
    best = {label: min(times) for label, times in runs.items()}
    torch_s = best["import torch"]
    results, rows = [], []
    for label, argv_ in todo.items():
        cli = label.startswith("rcotorch ")
        r = {"command": label, "best_s": best[label], "median_s": statistics.median(runs[label]),
             "ratio_to_import_torch": best[label] / torch_s, "loads": loads(argv_, env)}
        if cli:
            r["goal_s"], r["met"] = GOALS["cli_s"], best[label] < GOALS["cli_s"]
        elif label in IMPORTS:
            r["over_import_torch_s"] = best[label] - torch_s
            r["met"] = best[label] - torch_s <= GOALS["import_over_torch_s"]
        results.append(r)
        goal = {True: "met", False: "MISSED"}.get(r.get("met"), "")
        rows.append([label, f"{best[label]:.3f}", f"{best[label] / torch_s:.2f}", ", ".join(r["loads"]) or "-",
                     goal])
    print(table(rows, ["command", "best s", "/ import torch", "loads", "goal"]))
    out = {"benchmark": "startup", "machine": machine(torch.device("cpu")), "repeats": repeats,
           "goals": {"rcotorch --version, list, show: seconds, each under": GOALS["cli_s"],
                     "import rcotorch (and its core) minus import torch: seconds, at most":
                         GOALS["import_over_torch_s"]},
           "core": CORE,
           "command_line": " ".join(Path(a).name for a in todo["rcotorch list"][:-1]),
           "import_torch_s": torch_s, "results": results,
           "met": all(r["met"] for r in results if "met" in r)}
    print("->", write_json(out, "startup", args.out))
    return out


if __name__ == "__main__":
    main()
