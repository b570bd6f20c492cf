"""Robustness study: how many members of each shipped scenario converge, over many seeds.

For each scenario, ``--seeds`` seeds (64 by default) run in one batch (the members differ only in their seed;
a scenario whose seed fixes its structure runs one batch per seed, one without a seed runs once), at the
scenario's defaults and with each ``--variant`` (settings applied to every member, e.g. a robustness option).
Each member's health (``rcotorch.health``) is tabulated with whether it meets the scenario's requirements,
so the table also shows how well the health verdict agrees with the truth.

    .venv/bin/python benchmarks/robustness.py --threads 1                      # every scenario at defaults
    .venv/bin/python benchmarks/robustness.py --scenarios sdof-stiffness --variant lam:lam=0.999

Writes ``benchmarks/results/robustness.json`` and prints a Markdown table (docs/health.md shows it).
"""

from __future__ import annotations

import argparse
import collections
import tempfile
import time
from pathlib import Path

import common

from rcotorch import scenario as scenarios
from rcotorch.health import STATUSES
from rcotorch.runner import Run, member_truth


def _variant(text: str) -> tuple[str, dict[str, str]]:
    """'NAME:key=value,key=value' -> (NAME, {key: value})."""
    name, _, pairs = text.partition(":")
    settings = dict(p.split("=", 1) for p in pairs.split(",") if p)
    return name, settings


def _runs(name: str, seeds: list[int], overrides: dict, steps: int | None, device: str, tmp: Path) -> list[dict]:
    """Summaries of the runs that cover ``seeds`` (one batch when the seed may differ between members)."""
    sc = scenarios.get(name)
    if "seed" in sc.per_member:
        plans = [dict(members=[{"seed": s} for s in seeds])]
    elif "seed" in sc.settings:
        plans = [dict(seed=s) for s in seeds]
    else:
        plans = [{}]
    out = []
    for i, plan in enumerate(plans):
        with Run(name, steps=steps, overrides=overrides, out=tmp / f"{name}-{i}", device=device, **plan) as run:
            run.advance(progress=False)
            out.append(run.summary())
    return out


def _members(summaries: list[dict], requirements) -> list[dict]:
    """Per member: its status and reason, and whether it meets every requirement."""
    rows = []
    for s in summaries:
        B, h = s["batch"], s["health"]
        status, reason = member_truth(h["status"], B), member_truth(h["reason"], B)
        passes = [True] * B
        for req in requirements:
            group, key = req.key.split(".", 1)
            if key not in s[group]:
                continue
            values, truth = member_truth(s[group][key], B), member_truth(s["truth"].get(key), B)
            for b in range(B):
                passes[b] &= values[b] is not None and req.check(values[b], truth[b])[1]
        rows += [{"status": status[b], "reason": reason[b], "pass": passes[b]} for b in range(B)]
    return rows


def study(name: str, seeds: list[int], overrides: dict, steps: int | None, device: str = "cpu") -> dict:
    sc = scenarios.get(name)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        summaries = _runs(name, seeds, overrides, steps, device, Path(tmp))
    members = _members(summaries, sc.requirements)
    n = len(members)
    counts = collections.Counter(m["status"] for m in members)
    return {
        "scenario": name, "overrides": overrides, "steps": summaries[0]["steps"], "members": n,
        "batched": "seed" in sc.per_member, "seeded": "seed" in sc.settings,
        "fraction": {st: counts[st] / n for st in STATUSES},
        "reasons": dict(collections.Counter(m["reason"] for m in members if m["reason"])),
        "pass": {st: sum(m["pass"] for m in members if m["status"] == st) for st in STATUSES},
        "counts": {st: counts[st] for st in STATUSES},
        "seconds": time.perf_counter() - start,
    }


def table(results: list[dict]) -> str:
    lines = ["| scenario | variant | members | converged | not converged | diverged (reasons) | "
             "meet requirements: converged / not converged |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in results:
        c, p, f = r["counts"], r["pass"], r["fraction"]
        reasons = ", ".join(f"{k} {v}" for k, v in r["reasons"].items())
        lines.append(f"| `{r['scenario']}` | {r['variant']} | {r['members']} | {100 * f['converged']:.0f}% | "
                     f"{100 * f['not_converged']:.0f}% | {100 * f['diverged']:.0f}%{f' ({reasons})' if reasons else ''}"
                     f" | {p['converged']}/{c['converged']} / {p['not_converged']}/{c['not_converged']} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.add_common_args(ap)
    ap.add_argument("--scenarios", help="comma-separated names (default: every shipped scenario)")
    ap.add_argument("--seeds", type=int, default=64, help="seeds per scenario (default 64)")
    ap.add_argument("--steps", type=int, help="steps (default: each scenario's)")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE,...",
                    help="also run with these settings (repeatable)")
    args = ap.parse_args()
    dev = common.setup(args)
    if dev is None:
        return
    names = args.scenarios.split(",") if args.scenarios else sorted(scenarios.available())
    seeds = list(range(2 if args.quick else args.seeds))
    steps = 200 if args.quick else args.steps
    variants = [("defaults", {})] + [_variant(v) for v in args.variant]
    results = []
    for name in names:
        for label, overrides in variants:
            r = study(name, seeds, overrides, steps, str(dev))
            r["variant"] = label
            results.append(r)
            print(table([r]).splitlines()[-1], flush=True)
    print(table(results))
    common.write_json({"machine": common.machine(dev), "seeds": len(seeds), "results": results}, "robustness",
                      args.out)


if __name__ == "__main__":
    main()
