"""Reading a large CSV with ``rcotorch.data.recording.load``: wall time and peak memory against the bytes of the columns
asked for, with ``numpy.loadtxt(usecols=...)`` (numpy's C reader) measured on the same file for reference.

    python benchmarks/csv_memory.py                      # a ~200 MB CSV of 8 columns, 2 loaded; about a minute
    python benchmarks/csv_memory.py --rows 200000 --repeats 1

The CSV (``--rows`` x ``--columns`` float64 values written with 17 significant digits) is generated in a
temporary folder and deleted afterwards. Each load runs in a fresh subprocess: peak memory is the resident-set
high-water mark during the load (VmHWM, reset after importing rcotorch and a warm load of a small file) minus
the resident set before it, so library start-up is not counted (ru_maxrss where the reset is not possible);
time is the best of ``--repeats`` subprocesses. A further subprocess traces the load with ``tracemalloc``
(Python and NumPy allocations; slower, so not timed; skipped with ``--quick``). Goal: peak at most 2x the
bytes of the columns asked for (float64 x rows x columns asked for). The values of both readers must agree bit
for bit.
Writes benchmarks/results/csv_memory.json.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from common import machine, proc_status, reset_peak_rss, table, write_json


def write_csv(path: Path, rows: int, columns: int, seed: int = 0) -> None:
    """``rows`` x ``columns`` standard normal values, header ``c0,c1,...``, written 100,000 rows at a time."""
    rng = np.random.default_rng(seed)
    with open(path, "w", encoding="utf-8") as f:
        f.write(",".join(f"c{i}" for i in range(columns)) + "\n")
        for start in range(0, rows, 100_000):
            np.savetxt(f, rng.standard_normal((min(100_000, rows - start), columns)), delimiter=",", fmt="%.17g")


def child(reader: str, path: str, asked: list[str]) -> None:
    """Run in a subprocess: load ``asked`` columns of ``path`` with ``reader`` and print time, memory and a
    hash of the values as JSON."""
    import resource
    import tracemalloc
    if reader != "loadtxt":
        import rcotorch as rt
    header = Path(path).open(encoding="utf-8").readline().strip().split(",")
    usecols = [header.index(c) for c in asked]

    def load(p):
        if reader == "loadtxt":
            return np.loadtxt(p, delimiter=",", skiprows=1, usecols=usecols, comments=None, ndmin=2)
        return rt.load(p, columns=asked).values

    with tempfile.TemporaryDirectory() as tmp:                   # warm: imports and first-call costs
        small = Path(tmp) / "small.csv"
        small.write_text(",".join(header) + "\n" + ",".join(["1.5"] * len(header)) + "\n")
        load(small)
    if reader == "tracemalloc":
        tracemalloc.start()
    rss0 = proc_status("VmRSS")
    exact = rss0 is not None and reset_peak_rss()
    base = rss0 if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    t0 = time.perf_counter()
    values = load(path)
    seconds = time.perf_counter() - t0
    peak = proc_status("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    out = {"reader": reader, "seconds": seconds, "method": "VmHWM reset" if exact else "ru_maxrss",
           "rss_baseline_bytes": base, "peak_bytes": peak - base, "shape": list(values.shape)}
    if reader == "tracemalloc":
        out["traced_peak_bytes"] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    out["sha256"] = hashlib.sha256(np.ascontiguousarray(values).tobytes()).hexdigest()
    print(json.dumps(out))


def measure(reader: str, path: Path, asked: list[str]) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--_child", reader, str(path), ",".join(asked)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
    if res.returncode != 0:
        raise RuntimeError(f"{reader} subprocess failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "--_child":
        child(argv[1], argv[2], argv[3].split(","))
        return {}
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=None, help="JSON file to write (default: benchmarks/results/csv_memory.json)")
    ap.add_argument("--quick", action="store_true", help="a 20,000-row file, one run per reader (a smoke test)")
    ap.add_argument("--rows", type=int, default=1_250_000, help="data rows of the generated CSV (~200 MB at 8 columns)")
    ap.add_argument("--columns", type=int, default=8, help="columns of the generated CSV")
    ap.add_argument("--ask", default="c1,c5", help="the columns loaded")
    ap.add_argument("--repeats", type=int, default=3, help="timed subprocesses per reader (the best is kept)")
    args = ap.parse_args(argv)
    rows, repeats = (20_000, 1) if args.quick else (args.rows, args.repeats)
    asked = args.ask.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "large.csv"
        t0 = time.perf_counter()
        write_csv(path, rows, args.columns)
        size = path.stat().st_size
        print(f"wrote {rows} rows x {args.columns} columns, {size / 1e6:.1f} MB in {time.perf_counter() - t0:.1f} s")
        runs = {reader: [measure(reader, path, asked) for _ in range(repeats)] for reader in ("rcotorch", "loadtxt")}
        traced = None if args.quick else measure("tracemalloc", path, asked)
    asked_bytes = 8 * rows * len(asked)
    summary = {}
    for reader, rs in runs.items():
        summary[reader] = {"seconds": min(r["seconds"] for r in rs), "peak_bytes": max(r["peak_bytes"] for r in rs),
                           "method": rs[0]["method"], "runs": rs}
        summary[reader]["peak_over_asked"] = summary[reader]["peak_bytes"] / asked_bytes
    hashes = {r["sha256"] for rs in runs.values() for r in rs}
    if traced is not None:
        traced["traced_peak_over_asked"] = traced["traced_peak_bytes"] / asked_bytes
        hashes.add(traced["sha256"])
    equal = len(hashes) == 1
    ratio = summary["rcotorch"]["peak_over_asked"]
    out = {
        "benchmark": "csv_memory", "machine": machine(torch.device("cpu")),
        "definition": "peak = resident-set high-water mark during rt.load(path, columns=asked) - resident set "
                      "before it, in a fresh subprocess after importing rcotorch and a warm load of a small file; "
                      "asked bytes = 8 * rows * len(asked); seconds = best of the repeats; loadtxt = "
                      "numpy.loadtxt(usecols=...) on the same file, for reference; traced = tracemalloc's peak "
                      "of the same load (Python and NumPy allocations)",
        "file": {"rows": rows, "columns": args.columns, "bytes": size}, "asked": asked, "asked_bytes": asked_bytes,
        "rcotorch": summary["rcotorch"], "loadtxt": summary["loadtxt"], "tracemalloc": traced,
        "values_equal": equal,
        "goals": {"peak <= 2x the bytes of the columns asked for": {"value": ratio, "met": ratio <= 2.0}},
    }
    rows_out = [[reader, f"{s['seconds']:.2f}", f"{s['peak_bytes'] / 2**20:.1f}", f"{s['peak_over_asked']:.2f}"]
                for reader, s in summary.items()]
    if traced is not None:
        rows_out.append(["rcotorch (tracemalloc)", "-", f"{traced['traced_peak_bytes'] / 2**20:.1f}",
                         f"{traced['traced_peak_over_asked']:.2f}"])
    print(table(rows_out, ["reader", "seconds", "peak MiB", "peak / asked bytes"]))
    print(f"{size / 1e6:.1f} MB file, {len(asked)} of {args.columns} columns asked for "
          f"({asked_bytes / 2**20:.1f} MiB); values equal: {equal}; goal peak <= 2x: "
          f"{'met' if ratio <= 2 else 'NOT met'} ({ratio:.2f})")
    print("wrote", write_json(out, "csv_memory", args.out))
    return out


if __name__ == "__main__":
    main()
