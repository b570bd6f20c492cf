"""Robustness study: how many members of each shipped scenario converge, over many seeds.

For each scenario, ``--seeds`` seeds (64 by default) run in one batch (the members differ only in their seed;
a scenario whose seed fixes its structure runs one batch per seed, one without a seed runs once), at the
scenario's defaults and with each ``--variant`` (settings applied to every member, e.g. a robustness option).
Each member's health (``rcotorch.verdict.health``) is tabulated with whether it meets the scenario's requirements,
so the table also shows how well the health verdict agrees with the truth.

    .venv/bin/python benchmarks/robustness.py --threads 1                      # every scenario at defaults
    .venv/bin/python benchmarks/robustness.py --scenarios sdof-stiffness --variant lam:lam=0.999
    .venv/bin/python benchmarks/robustness.py --variant penalty:r_delta=0.1psi2 --variant norm:normalize=1psi

A variant's value may be given relative to the scenario's own scales, which a pilot run (one member at the
scenario's defaults, the first fifth of its steps, at most 2000, at least 50 past the estimator's window)
measures: ``psi`` is the size of the update's regressor, the rms of |Psi(k)|_F (Psi = sum_i beta_i phi(k-i),
beta the Markov parameters of u -> z, phi the identified subsystem's regressor); ``psi2`` its square; ``np0``
is n_theta times p0 (the trace of P(0)), e.g. ``0.1psi2``. The values used are recorded per scenario and
variant (``overrides`` and ``scales`` in the JSON). ``--append`` merges the results into the JSON file instead
of replacing it (a scenario and variant run again replaces its earlier row).

Writes ``benchmarks/results/robustness.json`` and prints a Markdown table (docs/health.md shows it).
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import tempfile
import time
from pathlib import Path

import common
import torch

from rcotorch.run import scenario as scenarios
from rcotorch.run.runner import Run, member_truth
from rcotorch.verdict.health import STATUSES


def _variant(text: str) -> tuple[str, dict[str, str]]:
    """'NAME:key=value,key=value' -> (NAME, {key: value})."""
    name, _, pairs = text.partition(":")
    settings = dict(p.split("=", 1) for p in pairs.split(",") if p)
    return name, settings


_RELATIVE = re.compile(r"^\s*([-+0-9.eE]+)\s*\*?\s*(psi2|psi|np0)\s*$")


def scales(name: str) -> dict[str, float]:
    """The scenario's scales for relative variant values, from a pilot run of one member at its defaults (on
    the PyTorch engine, which lets the estimator's update be watched): the rms of |Psi|_F over the steps
    after the estimator's window first filled."""
    sc = scenarios.get(name)
    g = sc.build(sc.resolve(), 1, torch.float64, "cpu")
    est = g.role("estimator")
    steps = min(sc.steps, max(min(2000, sc.steps // 5), est.window + 50))
    seen: list[torch.Tensor] = []
    rows = est._rows

    def watched(psi_t, z_r):
        if int(g.k) >= est.window:
            seen.append(psi_t.detach().square().sum((1, 2)))
        return rows(psi_t, z_r)
    est._rows = watched
    for _ in range(steps):
        g.step()
    psi = float(torch.cat(seen).mean().sqrt()) if seen else float("nan")
    return {"psi": psi, "psi2": psi * psi, "np0": float(est.n_theta * est.p0.max())}


def resolve(name: str, settings: dict[str, str], cache: dict) -> dict[str, object]:
    """Variant settings with relative values ('0.1psi2') turned into numbers for scenario ``name``."""
    out: dict[str, object] = {}
    for key, value in settings.items():
        m = _RELATIVE.match(value) if isinstance(value, str) else None
        if m is None:
            out[key] = value
            continue
        if name not in cache:
            cache[name] = scales(name)
        out[key] = float(f"{float(m.group(1)) * cache[name][m.group(2)]:.3g}")
    return out


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


def agreement(r: dict) -> float:
    """The fraction of members whose verdict agrees with the requirements: converged and meeting them, or not
    converged or diverged and failing one."""
    c, p = r["counts"], r["pass"]
    return (p["converged"] + c["not_converged"] - p["not_converged"] + c["diverged"] - p["diverged"]) / r["members"]


def table(results: list[dict]) -> str:
    lines = ["| scenario | variant | members | converged | not converged | diverged (reasons) | "
             "meet requirements: converged / not converged | verdict agrees |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        c, p, f = r["counts"], r["pass"], r["fraction"]
        reasons = ", ".join(f"{k} {v}" for k, v in r["reasons"].items())
        values = ", ".join(f"{k}={_fmt(v)}" for k, v in r["overrides"].items())
        variant = f"{r['variant']} ({values})" if values else r["variant"]
        lines.append(f"| `{r['scenario']}` | {variant} | {r['members']} | {100 * f['converged']:.0f}% | "
                     f"{100 * f['not_converged']:.0f}% | {100 * f['diverged']:.0f}%{f' ({reasons})' if reasons else ''}"
                     f" | {p['converged']}/{c['converged']} / {p['not_converged']}/{c['not_converged']} | "
                     f"{100 * agreement(r):.0f}% |")
    return "\n".join(lines)


def _fmt(value) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.add_common_args(ap)
    ap.add_argument("--scenarios", help="comma-separated names (default: every shipped scenario)")
    ap.add_argument("--seeds", type=int, default=64, help="seeds per scenario (default 64)")
    ap.add_argument("--steps", type=int, help="steps (default: each scenario's)")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE,...",
                    help="also run with these settings (repeatable); a value may be relative, e.g. 0.1psi2")
    ap.add_argument("--append", action="store_true", help="merge into the JSON file instead of replacing it")
    args = ap.parse_args()
    dev = common.setup(args)
    if dev is None:
        return
    names = args.scenarios.split(",") if args.scenarios else sorted(scenarios.available())
    seeds = list(range(2 if args.quick else args.seeds))
    steps = 200 if args.quick else args.steps
    variants = [("defaults", {})] + [_variant(v) for v in args.variant]
    results, cache = [], {}
    for name in names:
        for label, given in variants:
            overrides = resolve(name, given, cache)
            r = study(name, seeds, overrides, steps, str(dev))
            r.update(variant=label, given=given, scales=cache.get(name))
            results.append(r)
            print(table([r]).splitlines()[-1], flush=True)
    if args.append:
        path = Path(args.out) if args.out else common.RESULTS / "robustness.json"
        done = {(r["scenario"], r["variant"]) for r in results}
        earlier = json.loads(path.read_text())["results"] if path.is_file() else []
        results = [r for r in earlier if (r["scenario"], r["variant"]) not in done] + results
        variants = {v: i for i, v in enumerate(dict.fromkeys(["defaults"] + [r["variant"] for r in results]))}
        results.sort(key=lambda r: (r["scenario"], variants[r["variant"]]))
    print(table(results))
    common.write_json({"machine": common.machine(dev), "seeds": len(seeds), "results": results}, "robustness",
                      args.out)


if __name__ == "__main__":
    main()
