"""Command line: ``rcotorch list``, ``rcotorch show NAME``, ``rcotorch run NAME [options]``, ``rcotorch sweep``."""

from __future__ import annotations

import argparse
import os
import sys

from .errors import RcoError


def _settings(pairs: list[str]) -> dict[str, str]:
    out = {}
    for item in pairs:
        if "=" not in item:
            raise RcoError(f"--set expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def sweep_report(rows: list[dict], out: str) -> str:
    """Members, divergences and error quantiles of a finished sweep."""
    import numpy as np
    lines = [f"{len(rows)} members -> {out}/sweep.csv, sweep.json"]
    diverged = sum(bool(r["diverged"]) for r in rows)
    lines.append(f"diverged: {diverged}")
    for key in [k for k in rows[0] if k.startswith("err_")] if rows else []:
        v = np.array([abs(r[key]) for r in rows if r[key] is not None])
        if len(v):
            q = np.quantile(v, [0.5, 0.9, 1.0])
            lines.append(f"|{key}|: median {q[0]:.3g}, 90% {q[1]:.3g}, max {q[2]:.3g}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="rcotorch", description="Model refinement by retrospective cost "
                                     "optimization, batched in PyTorch.")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list the scenarios")
    sub.add_parser("show", help="print a scenario's settings: defaults, units and meanings").add_argument(
        "name", help="scenario name (see `rcotorch list`)")
    run = sub.add_parser("run", help="run a scenario and write runs/NAME/")
    run.add_argument("name", nargs="?", help="scenario name (see `rcotorch list`)")
    run.add_argument("--steps", type=int, help="number of steps (default: the scenario's)")
    run.add_argument("--batch", type=int, default=1, help="parallel refinements B (default 1)")
    run.add_argument("--seed", type=int, help="excitation seed (default: the scenario's)")
    run.add_argument("--device", default="cpu", help="cpu or cuda")
    run.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    run.add_argument("--out", help="output directory (default runs/NAME)")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override a scenario setting (repeatable)")
    run.add_argument("--checkpoint-every", type=int, help="save a checkpoint every N steps")
    run.add_argument("--resume", metavar="DIR", help="resume from DIR/checkpoint.pt (--steps may extend it)")
    run.add_argument("--no-figures", action="store_true", help="skip the PNG/TensorBoard figures")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--threads", type=int, help="CPU threads for torch (default: 1 below batch 1024, where "
                     "threading costs more than it gives, else torch's default)")
    sw = sub.add_parser("sweep", help="run a parameter sweep (TOML/JSON config) as batched shards")
    sw.add_argument("config", help="sweep config file (.toml or .json)")
    sw.add_argument("--device", default="cpu", help="cpu or cuda")
    sw.add_argument("--backend", default="local", choices=["local", "ray"])
    sw.add_argument("--ray-address", help="address of an existing Ray cluster (default: start a local one)")
    sw.add_argument("--out", help="output directory (default runs/sweep-SCENARIO)")
    sw.add_argument("--threads", type=int, help="CPU threads for torch in this process")
    for p in (run, sw):
        p.add_argument("--engine", choices=["auto", "native", "torch"],
                       help="how graphs step: native (lowered to C, CPU float64), torch, or auto (default: native "
                            "where it applies; also $RCOTORCH_ENGINE)")
    args = parser.parse_args(argv)
    if getattr(args, "engine", None):
        os.environ["RCOTORCH_ENGINE"] = args.engine

    if getattr(args, "threads", None) or (args.command == "run" and args.batch < 1024):
        import torch
        torch.set_num_threads(getattr(args, "threads", None) or 1)
    try:
        from . import scenario as scenarios
        from .runner import Run, result_table
        if args.command == "list":
            for name, sc in sorted(scenarios.available().items()):
                print(f"{name:<28} {('[' + sc.section + '] ') if sc.section else ''}{sc.description}")
            return 0
        if args.command == "show":
            print(scenarios.describe(scenarios.get(args.name)))
            return 0
        if args.command == "sweep":
            from .sweep import Sweep, run_sweep
            sweep = Sweep.from_file(args.config)
            rows = run_sweep(sweep, backend=args.backend, device=args.device, out=args.out,
                             ray_address=args.ray_address)
            out = args.out or f"runs/sweep-{sweep.scenario}"
            print(sweep_report(rows, out))
            return 0
        if args.resume:
            r = Run.resume(args.resume, steps=args.steps, device=args.device if args.device != "cpu" else None,
                           out=args.out)
        else:
            if not args.name:
                parser.error("run needs a scenario NAME (or --resume DIR)")
            r = Run(args.name, steps=args.steps, batch=args.batch, seed=args.seed, device=args.device,
                    dtype=args.dtype, out=args.out, overrides=_settings(args.overrides))
            r.clear_outputs()
        r.advance(progress=False if args.quiet else None, checkpoint_every=args.checkpoint_every)
        summary = r.finish(figures=not args.no_figures)
        print(f"{summary['scenario']}: {summary['steps']} steps, batch {summary['batch']}, {summary['dtype']}, "
              f"{summary['device']}, {summary['engine']} engine -> {r.out}")
        print(result_table(summary))
        return 0 if all(c["pass"] for c in summary["requirements"].values()) else 1
    except RcoError as e:
        print(f"rcotorch: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
