"""Shared helpers of the benchmarks: device and thread setup, timing, machine description, JSON output."""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def add_common_args(ap) -> None:
    ap.add_argument("--device", default="cpu", help="cpu or cuda (skipped cleanly when CUDA is not available)")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch intra-op threads (default: torch's own choice, all cores)")
    ap.add_argument("--out", default=None, help="JSON file to write (default: benchmarks/results/<name>.json)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes and short timings (a smoke test)")


def setup(args) -> torch.device | None:
    """Apply --threads; return the device, or None (after printing why) when CUDA was asked for but is absent."""
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        print(f"--device {args.device}: torch sees no CUDA device on this machine; skipped")
        return None
    return dev


def setup_cpu(args, why: str = "the native engine runs on the CPU") -> torch.device | None:
    """``setup`` for a measurement that only the CPU makes: None (after printing ``why``) on another device."""
    dev = setup(args)
    if dev is not None and dev.type != "cpu":
        print(f"{why}; nothing to measure on", args.device)
        return None
    return dev


def sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def timed(fn, dev: torch.device, min_seconds: float, min_calls: int = 3, repeats: int = 3) -> tuple[float, int]:
    """Seconds per call of ``fn()``: the best of ``repeats`` runs of at least ``min_seconds / repeats`` (and
    ``min_calls`` calls) each; the best run is the least disturbed by other processes on a shared machine.
    Returns (seconds per call, total calls)."""
    best, total = float("inf"), 0
    for _ in range(repeats):
        calls, elapsed, batch = 0, 0.0, 1
        sync(dev)
        start = time.perf_counter()
        while elapsed < min_seconds / repeats or calls < min_calls:
            for _ in range(batch):
                fn()
            calls += batch
            sync(dev)
            elapsed = time.perf_counter() - start
            batch *= 2
        best, total = min(best, elapsed / calls), total + calls
    return best, total


def machine(dev: torch.device) -> dict:
    """What the numbers were measured on."""
    info = {
        "platform": platform.platform(), "python": platform.python_version(), "torch": torch.__version__,
        "cpu": _cpu_model(), "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
        "device": str(dev), "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    if dev.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(dev)
    return info


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def write_json(result: dict, name: str, out: str | None) -> Path:
    path = Path(out) if out else RESULTS / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    return path


def table(rows: list[list], header: list[str]) -> str:
    cells = [header] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def proc_status(key: str) -> int | None:
    """A memory figure of this process from /proc/self/status (Linux), in bytes."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def reset_peak_rss() -> bool:
    """Reset the resident-set high-water mark (Linux: write 5 to /proc/self/clear_refs)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def ns_per_member_step(run, batch: int, seconds: float, steps: int) -> float:
    """Nanoseconds per member-step of ``run(steps)`` over ``batch`` members: the best of three stretches of
    ``seconds / 3`` each (the least disturbed by other processes on a shared machine)."""
    best = float("inf")
    for _ in range(3):
        t0, done = time.perf_counter(), 0
        while time.perf_counter() - t0 < seconds / 3:
            run(steps)
            done += steps
        best = min(best, (time.perf_counter() - t0) / (done * batch))
    return best * 1e9
