"""The thermosphere scenario's results table: identified-subsystem structure x measured altitudes x metrics.

    python benchmarks/thermosphere_table.py [--only LABEL ...] [--steps N] [--set KEY=VALUE ...] [--figures]
                                            [--markdown] [--out FILE]

Runs ``thermosphere-no-cooling`` once per configuration, one after the other (each run is single-threaded work
on the column; run the table while nothing else is heavy), and writes benchmarks/results/thermosphere_table.json:
for each configuration its settings, the goals' metrics over the evaluation window (``density_err_ratio`` at 407
km over the last day, ``cooling_corr_152km`` and ``cooling_rel_rms_152km`` from one day on), the per-node and
profile cooling errors, whether each goal is met, and the frozen replay on the other space weather (the same
metrics over the whole replay, the density against the initial model). ``--only`` reruns some configurations
and keeps the others' rows of an existing file. ``--set`` changes a setting of the scenario in every
configuration (a coarser column for a quick look: ``--set dz_km=10 --set Ts=3600``). ``--figures`` writes each
run's figures under runs/thermosphere-table/LABEL/.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch
from common import RESULTS, ROOT, machine, table

from rcotorch.run.runner import Run

NAME = "thermosphere-no-cooling"
#: Tuning per structure: the RLS covariance of the temperature basis (normalized features near 1) is larger.
TUNING = {"kockarts": {}, "temperature": {"p0": 50.0}, "error": {}}
MEASURED = ("407", "407,250", "407,150")
CONFIGS = {f"{structure}@{km}": {"structure": structure, "measured_km": km, **TUNING[structure]}
           for structure in ("temperature", "kockarts", "error") for km in MEASURED}
CONFIGS["temperature-shared@407,150"] = {"structure": "temperature", "measured_km": "407,150", "shared": True,
                                         **TUNING["temperature"]}
#: The known form with a strength per node: interpolated in the strength (the Kockarts shape between the nodes) or,
#: ``-linear``, in the cooling.
for km in ("407", "407,150"):
    CONFIGS[f"kockarts-node@{km}"] = {"structure": "kockarts", "measured_km": km, "strengths": "node"}
    CONFIGS[f"kockarts-node-linear@{km}"] = {"structure": "kockarts", "measured_km": km, "strengths": "node",
                                             "interpolate": "cooling"}
GOALS = {"density_err_ratio": ("<", 0.25), "cooling_corr_152km": (">=", 0.8), "cooling_rel_rms_152km": ("<=", 0.3)}
REPLAY = ("replay_density_err_ratio", "replay_cooling_corr_152km", "replay_cooling_rel_rms_152km",
          "replay_cooling_profile_rel_rms")
COLUMNS = (*GOALS, "cooling_rel_rms_120km", "cooling_rel_rms_200km", "cooling_profile_rel_rms", *REPLAY)


def met(metrics: dict) -> dict[str, bool]:
    """Which goals the metrics meet."""
    ops = {"<": lambda v, b: v < b, ">=": lambda v, b: v >= b, "<=": lambda v, b: v <= b}
    return {k: metrics.get(k) is not None and ops[op](metrics[k], bound) for k, (op, bound) in GOALS.items()}


def run_config(overrides: dict, steps: int | None = None, out: Path | None = None, figures: bool = False) -> dict:
    """One run: its settings, the table's metrics, the goals met, and its wall time [s]."""
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:              # without ``out`` the run's logs are not kept
        run = Run(NAME, steps=steps, overrides=overrides, out=out or scratch)
        run.advance(progress=False)
        summary = run.finish(figures=figures) if out is not None else run.summary()
    metrics = {k: summary["metrics"].get(k) for k in COLUMNS}
    health = {k: summary["health"][k] for k in ("status", "reason", "theta_change", "z_ratio")}
    return {"overrides": overrides, "steps": summary["steps"], "metrics": metrics, "goals_met": met(metrics),
            "all_goals_met": all(met(metrics).values()), "diverged": summary["diverged"], "health": health,
            "seconds": round(time.perf_counter() - start, 1)}


def health_cell(h: dict | None) -> str:
    """A row's health: the status, with theta's change over the window or the divergence reason."""
    if h is None:
        return "-"
    if h["status"] == "diverged":
        return f"diverged ({h['reason']})"
    change = h["theta_change"]
    return h["status"] if change is None else f"{h['status']} ({100 * change:.1f}%)"


def markdown(rows: dict, columns=COLUMNS, health: bool = False) -> str:
    """The table as Markdown (docs/thermosphere.md), goals met in bold; ``health``: a column with each run's
    health status (theta's change over the window in per cent)."""
    head = ["structure", "measured km", *(f"`{c}`" for c in columns), *(["health"] if health else [])]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for label, r in rows.items():
        structure, km = label.split("@")
        cells = ["-" if r["metrics"][k] is None else f"**{r['metrics'][k]:.3f}**" if r["goals_met"].get(k) else
                 f"{r['metrics'][k]:.3f}" for k in columns]
        if health:
            cells.append(health_cell(r.get("health")))
        lines.append("| " + " | ".join([structure, km.replace(",", ", "), *cells]) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", default=None, help=f"labels among {list(CONFIGS)}")
    ap.add_argument("--steps", type=int, default=None, help="steps per run (default: the scenario's 480)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a setting of the scenario in every configuration (dz_km=10, ...)")
    ap.add_argument("--figures", action="store_true", help="write each run's figures under runs/thermosphere-table/")
    ap.add_argument("--markdown", action="store_true", help="also print the table as Markdown")
    ap.add_argument("--out", default=None, help="JSON file (default: benchmarks/results/thermosphere_table.json)")
    args = ap.parse_args(argv)
    labels = args.only or list(CONFIGS)
    unknown = [lab for lab in labels if lab not in CONFIGS]
    if unknown:
        print(f"unknown configurations {unknown}; choose among {list(CONFIGS)}", file=sys.stderr)
        return 2
    path = Path(args.out) if args.out else RESULTS / "thermosphere_table.json"
    result = json.loads(path.read_text()) if path.is_file() and args.only else {"rows": {}}
    result["goals"] = {k: f"{op} {b:g}" for k, (op, b) in GOALS.items()}
    for label in labels:
        out = ROOT / "runs" / "thermosphere-table" / label.replace(",", "+") if args.figures else None
        settings = {**CONFIGS[label], **dict(item.split("=", 1) for item in args.set)}
        result["rows"][label] = run_config(settings, args.steps, out, args.figures)
        result["machine"] = machine(torch.device("cpu"))
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(result, indent=2) + "\n")        # after each run: a partial table survives
        print(f"{label}: {result['rows'][label]['metrics']} ({result['rows'][label]['seconds']} s)", flush=True)
    rows = [[label, *(f"{r['metrics'][k]:.3f}" if r["metrics"][k] is not None else "-" for k in COLUMNS),
             "yes" if r["all_goals_met"] else "no"] for label, r in result["rows"].items()]
    print(table(rows, ["configuration", *COLUMNS, "goals"]))
    if args.markdown:
        print(markdown(result["rows"], COLUMNS[:6], health=True))
        print(markdown(result["rows"], REPLAY))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
