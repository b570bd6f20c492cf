"""TensorBoard's own event writer against rcotorch's (``rcotorch.run.event_file.EventFile``), on what runs log.

rcotorch frames TensorBoard's event records itself, each checksummed by ``google-crc32c``, in the calling thread.
This measures whether TensorBoard's own writer would do as well. Each case is a real run (``Run.advance`` and
``Run.finish``: scalars every log, histograms from 16 members, the figures' images, the text, layout and HParams
session), timed; its event files are then read back and every event written again, in the same folders' layout,
by each writer:

* ``rcotorch``: ``EventFile.add_event`` (serialization, google-crc32c, a buffered file; the calling thread);
* ``tensorboard EventFileWriter``: ``tensorboard.summary.writer.event_file_writer.EventFileWriter.add_event``,
  what ``torch.utils.tensorboard.SummaryWriter`` writes through (serialization in the calling thread, the
  record's pure-Python CRC-32C and the write on its writer thread; ``close`` waits for it);
* ``tensorboard RecordWriter``: TensorBoard's record framing (``RecordWriter.write``, the same pure-Python CRC-32C)
  in the calling thread, which shows the checksum's share.

Each writer's time is the best of ``--repeats`` replays (wall and CPU time of all threads, from opening its files
to closing them), the writers taking turns. The imports: in a fresh interpreter that already holds what a run
imports anyway (torch, rcotorch, ``torch.utils.tensorboard.summary``, whose summary functions every run uses),
the time to import what each writer adds (``rcotorch.run.event_file`` and ``google_crc32c``; TensorBoard's
``event_file_writer``), best of ``--repeats``; "cold" the same with only torch and the event protocol buffers
loaded. ``total_s`` = the added import + the replay's wall time; the decision rule:
TensorBoard's writer replaces rcotorch's unless its total is more than ``THRESHOLD`` times rcotorch's.

    python benchmarks/tb_writer.py              # about 1.5 min
    python benchmarks/tb_writer.py --quick      # a smoke test

Writes benchmarks/results/tb_writer.json.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from common import machine, table, write_json

THRESHOLD = 1.5
CASES = [  # (label, scenario, batch, steps: None for the scenario's own)
    ("sdof-stiffness B=1 (default steps)", "sdof-stiffness", 1, None),
    ("sdof-stiffness B=64, 400000 steps", "sdof-stiffness", 64, 400_000),
    ("sdof-stiffness B=256, 1000000 steps (1000 logs)", "sdof-stiffness", 256, 1_000_000),
]
QUICK_CASES = [("sdof-stiffness B=1 (default steps)", "sdof-stiffness", 1, None),
               ("sdof-stiffness B=16, 20000 steps", "sdof-stiffness", 16, 20_000)]
IMPORTS = {  # what each writer adds to a run's imports
    "rcotorch": "import rcotorch.run.event_file, google_crc32c",
    "tensorboard EventFileWriter": "import tensorboard.summary.writer.event_file_writer",
    "tensorboard RecordWriter": "import tensorboard.summary.writer.record_writer",
}
LOADED = {"warm": "import torch, rcotorch, torch.utils.tensorboard.summary",
          "cold": "import torch, tensorboard.compat.proto.event_pb2"}


def run_case(scenario: str, batch: int, steps: int | None, out: Path) -> dict:
    """A real run into ``out``: its time and what its event files hold."""
    from rcotorch.run.runner import Run
    started = time.perf_counter()
    run = Run(scenario, batch=batch, steps=steps, out=out)
    run.advance(progress=False)
    run.finish(progress=False)
    return {"run_s": time.perf_counter() - started, "steps": run.steps, "batch": batch, "logs": run.monitor.n_logs}


def read_events(out: Path) -> dict[str, list]:
    """Each event file of a run folder (relative folder -> its events, without the file_version event each writer
    writes itself)."""
    from tensorboard.backend.event_processing.event_file_loader import RawEventFileLoader
    from tensorboard.compat.proto.event_pb2 import Event
    files = {}
    for path in sorted(out.rglob("events.out.tfevents.*")):
        events = [Event.FromString(raw) for raw in RawEventFileLoader(str(path)).Load()]
        files[str(path.parent.relative_to(out))] = [e for e in events if not e.HasField("file_version")]
    return files


def replay_rcotorch(files: dict[str, list], root: Path) -> None:
    from rcotorch.run.event_file import EventFile
    for folder, events in files.items():
        with EventFile(root / folder) as w:
            for e in events:
                w.add_event(e, wall=e.wall_time)


def replay_event_file_writer(files: dict[str, list], root: Path) -> None:
    from tensorboard.summary.writer.event_file_writer import EventFileWriter
    for folder, events in files.items():
        w = EventFileWriter(str(root / folder))
        for e in events:
            w.add_event(e)
        w.close()


def replay_record_writer(files: dict[str, list], root: Path) -> None:
    from tensorboard.summary.writer.record_writer import RecordWriter
    for i, (folder, events) in enumerate(files.items()):
        (root / folder).mkdir(parents=True, exist_ok=True)
        w = RecordWriter(open(root / folder / f"events.out.tfevents.{i:04d}", "wb"))
        for e in events:
            w.write(e.SerializeToString())
        w.close()


WRITERS = {"rcotorch": replay_rcotorch, "tensorboard EventFileWriter": replay_event_file_writer,
           "tensorboard RecordWriter": replay_record_writer}


def time_replays(files: dict[str, list], repeats: int) -> dict[str, dict]:
    """Best wall and CPU seconds of each writer's replay, the writers taking turns."""
    best = {name: {"wall_s": float("inf"), "cpu_s": float("inf")} for name in WRITERS}
    for _ in range(repeats):
        for name, replay in WRITERS.items():
            root = Path(tempfile.mkdtemp(prefix="tb_writer_"))
            try:
                wall, cpu = time.perf_counter(), time.process_time()
                replay(files, root)
                wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            finally:
                shutil.rmtree(root, ignore_errors=True)
            best[name]["wall_s"] = min(best[name]["wall_s"], wall)
            best[name]["cpu_s"] = min(best[name]["cpu_s"], cpu)
    return best


def import_seconds(repeats: int) -> dict[str, dict[str, float]]:
    """Seconds to import what each writer adds, in fresh interpreters (best and median of ``repeats``)."""
    out: dict[str, dict[str, float]] = {}
    for state, loaded in LOADED.items():
        times: dict[str, list[float]] = {name: [] for name in IMPORTS}
        for _ in range(repeats):
            for name, statement in IMPORTS.items():
                code = (f"{loaded}\nimport time\nt = time.perf_counter()\n{statement}\n"
                        "print(time.perf_counter() - t)")
                done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
                times[name].append(float(done.stdout.split()[-1]))
        for name, ts in times.items():
            out.setdefault(name, {})[f"{state}_best_s"] = min(ts)
            out[name][f"{state}_median_s"] = statistics.median(ts)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="small runs, two repeats (a smoke test)")
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/tb_writer.json)")
    args = ap.parse_args()
    repeats = 2 if args.quick else args.repeats
    torch.set_num_threads(1)
    imports = import_seconds(repeats)
    rows, cases = [], []
    for label, scenario, batch, steps in QUICK_CASES if args.quick else CASES:
        with tempfile.TemporaryDirectory(prefix="tb_writer_run_") as tmp:
            ran = run_case(scenario, batch, steps, Path(tmp) / "run")
            files = read_events(Path(tmp) / "run")
        events = sum(len(v) for v in files.values())
        size = sum(e.ByteSize() for v in files.values() for e in v)
        replays = time_replays(files, repeats)
        for name, r in replays.items():
            r["import_s"] = imports[name]["warm_best_s"]
            r["total_s"] = r["import_s"] + r["wall_s"]
            r["share_of_run"] = r["total_s"] / ran["run_s"]
        ratio = replays["tensorboard EventFileWriter"]["total_s"] / replays["rcotorch"]["total_s"]
        cases.append({"case": label, **ran, "event_files": len(files), "events": events, "event_bytes": size,
                      "writers": replays, "tensorboard_over_rcotorch": ratio})
        for name, r in replays.items():
            rows.append([label, name, f"{r['import_s'] * 1e3:.1f}", f"{r['wall_s'] * 1e3:.1f}",
                         f"{r['cpu_s'] * 1e3:.1f}", f"{r['total_s'] * 1e3:.1f}", f"{100 * r['share_of_run']:.2f}"])
        print(f"{label}: run {ran['run_s']:.2f} s, {ran['logs']} logs, {events} events in {len(files)} files, "
              f"{size / 1e3:.0f} kB; TensorBoard's writer / rcotorch's (total) = {ratio:.1f}", flush=True)
    print(table(rows, ["case", "writer", "import ms", "write wall ms", "write cpu ms", "total ms", "% of run"]))
    worst = min(c["tensorboard_over_rcotorch"] for c in cases)
    keep = worst > THRESHOLD
    verdict = (f"keep rcotorch's writer: TensorBoard's costs {worst:.1f} times as much or more (import and writing) "
               f"in every case, above the threshold of {THRESHOLD}" if keep else
               f"use TensorBoard's writer: in some case it costs at most {THRESHOLD} times rcotorch's ({worst:.1f})")
    print(verdict)
    write_json({"benchmark": "tb_writer", "machine": machine(torch.device("cpu")), "repeats": repeats,
                "threshold": THRESHOLD, "imports": imports,
                "imports_what": IMPORTS, "imports_loaded_before": LOADED, "cases": cases,
                "keep_rcotorch_writer": keep, "verdict": verdict}, "tb_writer", args.out)


if __name__ == "__main__":
    main()
