"""Not speed: the measured statements of docs/own-problem.md, from the doc's own code.

The code blocks are read from the Markdown and run as they stand (in a temporary folder, so their ``runs/``
folders do not stay): the building (and its variants: p0 = 1e8, nu = 30 and 100, a continuous truth, the roof's
velocity alone, each the doc's block with those settings replaced), the pendulum with a hinge's friction, the
fluid viscous damper and the friction at three strengths of the force. Per run: the estimates, intervals,
verdicts, held-out validation, warnings and wall time.

``--claims`` prints, from the results on record (this script's JSON and ``friction_study.json``), every number
docs/own-problem.md and docs/tuning.md state about them, as the docs print them (rounded as here);
``tests/test_docs_numbers.py`` checks that each line stands in the doc it names.

    python benchmarks/docs_examples.py              # about 1 minute on 2 shared cores
    python benchmarks/docs_examples.py --claims     # the docs' numbers from the JSON, no run

Writes benchmarks/results/docs_examples.json.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "own-problem.md"
RESULTS = ROOT / "benchmarks" / "results"


def blocks(path: Path = DOC) -> list[str]:
    """The ```python and ```py blocks of the doc, in order."""
    return re.findall(r"```py(?:thon)?\n(.*?)```", path.read_text(), flags=re.S)


def block(marker: str) -> str:
    """The one block of the doc that contains ``marker``."""
    found = [b for b in blocks() if marker in b]
    assert len(found) == 1, f"{len(found)} blocks of {DOC.name} contain {marker!r}"
    return found[0]


def replaced(code: str, *pairs: tuple[str, str]) -> str:
    """``code`` with each ``old`` (which must occur once) replaced by ``new``."""
    for old, new in pairs:
        assert code.count(old) == 1, f"{old!r} occurs {code.count(old)} times in the doc's block"
        code = code.replace(old, new)
    return code


def execute(code: str, ns: dict) -> tuple[dict, float, str]:
    """Run ``code`` in ``ns``; the namespace, the wall time and what it printed."""
    printed = io.StringIO()
    start = time.perf_counter()
    with contextlib.redirect_stdout(printed):
        exec(compile(code, DOC.name, "exec"), ns)
    return ns, time.perf_counter() - start, printed.getvalue()


def record(result, seconds: float) -> dict:
    """What a ``RefinementResult`` says, as plain numbers."""
    s = result.summary
    health, metrics = s["health"], s["metrics"]

    def listed(v):
        return v if isinstance(v, list) else [v]
    return {"seconds": seconds, "status": list(result.status),
            "estimates": {k: v.tolist() for k, v in result.estimates.items()},
            "lower": {k: v.tolist() for k, v in result.lower.items()},
            "upper": {k: v.tolist() for k, v in result.upper.items()},
            "half_width": {k: v.tolist() for k, v in result.half_width.items()},
            "residuals_white": listed(health.get("residuals_white")),
            "residual_widening": listed(health.get("residual_widening")),
            "validation_rmse": listed(metrics.get("validation_rmse")),
            "validation_rmse_initial": listed(metrics.get("validation_rmse_initial")),
            "warnings": list(s.get("warnings", []))}


BUILDING = 'known = rt.LTI.from_control(G, inputs={"w": 1, "u": 3}, outputs={"y": 3, "y0": 3}, dt=Ts, name="known")'
# The truth simulated whole: the continuous building with storey 2 at -20 % (the known model's own matrices with
# the feedback u_2 = 0.2 k d_2 closed before sampling), sampled at Ts.
PLANT = """
import control as _control
_K = np.diag([0.0, 0.2 * k, 0.0])
_n = G.noutputs - 3
plant = rt.LTI.from_control(_control.ss(G.A + G.B[:, 1:] @ _K @ G.C[_n:], G.B[:, :1], G.C[:_n], 0), inputs={"w": 1},
                            outputs={"y": _n}, dt=Ts, name="plant")
"""


VARIANTS = {                # the building's block with these settings replaced (each old text occurs once)
    "building": (),
    "p0_1e8": (("p0=1e16", "p0=1e8"),),
    "nu_30": (("nu=300", "nu=30"),),
    "nu_100": (("nu=300", "nu=100"),),
    "continuous": ((BUILDING, BUILDING + PLANT), ("truth=damage", "physical=plant")),
    "roof_continuous": ((BUILDING, BUILDING + PLANT), ("truth=damage", "physical=plant"),
                        ('measured=["velocity[1]", "velocity[2]", "velocity[3]"]', 'measured=["velocity[3]"]'),
                        ('outputs={"y": 3, "y0": 3}', 'outputs={"y": 1, "y0": 3}'),
                        ("n_z=3", "n_z=1"), ("rt.WhiteNoise(3, std=2e-4", "rt.WhiteNoise(1, std=2e-4"),
                        ("nu=300", "nu=100"), ("rt.refine(graph, 30000", "rt.refine(graph, 50000")),
}
CASES = [*VARIANTS, "hinge", "damper", "friction"]


def case(name: str) -> dict:
    """One case, in this (fresh) process: its record, the wall time of its block (imports and the compilation
    of NumPy functions included; for the hinge, after the building's block has run)."""
    if name in VARIANTS:
        ns, seconds, _ = execute(replaced(block("rt.models.shear_building"), *VARIANTS[name]), {})
        return {**record(ns["result"], seconds), "steps": 50000 if name.startswith("roof") else 30000}
    if name == "hinge":
        ns, _, _ = execute(block("rt.models.shear_building"), {})            # rt and np as the doc's first block
        ns, seconds, _ = execute(block("def truth_f"), ns)
        return record(ns["result"], seconds)
    if name == "damper":
        ns, seconds, _ = execute(block("def damper"), {})
        return record(ns["damper_result"], seconds)
    ns, seconds, printed = execute(block("def friction"), {})
    return {**record(ns["result"], seconds), "w_std": ns["w_std"], "sliding": [float(x) for x in ns["sliding"]],
            "printed": printed}


def fresh(name: str, threads: int) -> dict:
    """``case(name)`` in a fresh interpreter, in a temporary folder (the blocks' ``runs/`` go there)."""
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
        subprocess.run([sys.executable, str(Path(__file__).resolve()), "--case", name, "--threads", str(threads),
                        "--out", str(Path(tmp) / "case.json")], cwd=tmp, env=env, check=True)
        return json.loads((Path(tmp) / "case.json").read_text())


# ---------------------------------------------------------------------------------------------------------------
# The docs' numbers, from the results on record. Each claim is (doc, text): the text stands in that doc (line
# breaks read as spaces), every number in it rounded as here: a doc that says otherwise, or results that round
# otherwise, fail tests/test_docs_numbers.py.

def rng(values, fmt: str, sep: str = " .. ") -> str:
    """min .. max of ``values`` as ``fmt`` prints them (one value where both print alike)."""
    lo, hi = format(min(values), fmt), format(max(values), fmt)
    return lo if lo == hi else f"{lo}{sep}{hi}"


def span(values) -> str:
    """min .. max with as many decimals as the spread needs (2 to 4)."""
    width = max(values) - min(values)
    return rng(values, ".4f" if width < 0.01 else ".3f" if width < 0.1 else ".2f")


def erng(values) -> str:
    """[5.0e-4, 5.5e-4] -> '5.0-5.5e-4' (two digits, the larger value's exponent)."""
    e = math.floor(math.log10(max(values)))
    return rng([v / 10 ** e for v in values], ".1f", "-") + f"e{e}"


def up(x: float) -> str:
    """x rounded up to one significant digit (a bound: 'within up(x)')."""
    e = math.floor(math.log10(x))
    return format(math.ceil(x / 10 ** e) * 10 ** e, f".{max(0, -e)}f")


def sci(x: float) -> str:
    """6.17e7 -> '6.2e7'."""
    mant, exp = f"{x:.1e}".split("e")
    return f"{mant}e{int(exp)}"


def words(statuses) -> str:
    """['converged', 'converged', 'biased'] (or {status: count}) -> '2 converged, 1 biased' (most first)."""
    counts: dict[str, int] = dict(statuses) if isinstance(statuses, dict) else {}
    for s in () if isinstance(statuses, dict) else statuses:
        counts[s] = counts.get(s, 0) + 1
    return ", ".join(f"{n} {s}" for s, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def holds(rec: dict, key: str, truth: float) -> bool:
    return all(lo <= truth <= hi for lo, hi in zip(rec["lower"][key], rec["upper"][key]))


def own_problem(r: dict) -> list[str]:
    """docs/own-problem.md: the examples' numbers (docs_examples.json)."""
    b = r["building"]
    est = b["estimates"]
    off = max(abs(x) for k in ("dk1", "dk3") for x in est[k])
    dk2 = rng(est["dk2"], ".4f")
    cover = all(holds(b, k, t) for k, t in (("dk1", 0.0), ("dk2", -0.2), ("dk3", 0.0)))
    out = [f"30 000 steps = 300 s of shaking, {b['seconds']:.1f} s for the block with the intervals",
           f"dk2 {dk2}" + (" in both members" if " .. " not in dk2 else ""),
           f"dk1 and dk3 within {up(off)} of zero, both members `{b['status'][0]}`" if len(set(b["status"])) == 1
           else f"dk1 and dk3 within {up(off)} of zero, {words(b['status'])}",
           f"held-out validation rmse {erng(b['validation_rmse'])} m/s",
           f"against {rng(b['validation_rmse_initial'], '.2f', '-')} for the initial model",
           "The residuals are " + ("white" if all(b["residuals_white"]) else "not white"),
           f"widened by up to {max(b['residual_widening']):.1f} times",
           f"about ± {statistics.median(b['half_width']['dk2']):.2g} for dk2, and every member's intervals "
           + ("hold the truth" if cover else "do not all hold the truth")]
    p = r["p0_1e8"]
    suggested = re.search(r"try p0 of about ([0-9.e+-]+)", " ".join(p["warnings"]))
    out += [f"With p0 = 1e8, dk2 is {rng(p['estimates']['dk2'], '.4f', ' / ')} after 30 000 steps",
            f"try p0 of about {suggested.group(1) if suggested else '(no warning)'}, or a longer run"]
    out.append(f"30 leaves dk2 at {rng(r['nu_30']['estimates']['dk2'], '.3f', ' / ')}, 100 at "
               f"{rng(r['nu_100']['estimates']['dk2'], '.4f', ' / ')}, 300 at {rng(est['dk2'], '.4f', ' / ')}")
    roof = r["roof_continuous"]
    out.append("nu = 100, 50 000 steps: dk = " + ", ".join(
        rng(roof["estimates"][k], "+.2f", " / ").replace("+-", "-") for k in ("dk1", "dk2", "dk3")))
    c = r["continuous"]
    out.append(f"dk2 comes out {rng(c['estimates']['dk2'], '.3f', ' / ')} with dk1 "
               f"{rng(c['estimates']['dk1'], '.3f', ' / ')} ({words(c['status'])})")
    h = r["hinge"]
    out += [f"friction {rng(h['estimates']['friction'], '.4f')} "
            f"(± {statistics.median(h['half_width']['friction']):.2g}, the intervals' median half-width)",
            ("each member's interval holding it" if holds(h, "friction", 0.35) else
             "not every member's interval holding it") + f", {words(h['status'])}",
            f"held-out rmse {rng(h['validation_rmse'], '.4f', '-')} rad (the noise) against "
            f"{rng(h['validation_rmse_initial'], '.3f', '-')} for the initial model",
            "the residuals are " + ("white" if all(h["residuals_white"]) else "not white"),
            f"takes {h['seconds']:.1f} s"]
    d = r["damper"]
    out += [f"C_D {rng(d['estimates']['C_D'], '.5f')} against 0.8, "
            + ("each member's interval holding it" if holds(d, "C_D", 0.8) else
               "not every member's interval holding it")
            + f" (half-widths {rng(d['half_width']['C_D'], '.4f', '-')}), {words(d['status'])}",
            "the residuals " + ("white" if all(d["residuals_white"]) else "not white"),
            f"held-out rmse {rng(d['validation_rmse'], '.4f', '-')} m/s (the noise 0.01) against "
            f"{rng(d['validation_rmse_initial'], '.2f', '-')} for the initial model",
            f"{d['seconds']:.1f} s for the block"]
    f = r["friction"]
    out.append(f"It prints ({f['seconds']:.1f} s): sliding " + ", ".join(f"{x:.2f}" for x in f["sliding"])
               + " of the time; Fc " + ", ".join(f"{x:.3f}" for x in f["estimates"]["Fc"]) + " and c "
               + ", ".join(f"{x:.3g}" for x in f["estimates"]["c"]) + "; "
               + ", ".join(f"`{s}`" for s in f["status"]) + ".")
    return out


def friction_tables(fs: dict) -> list[str]:
    """docs/own-problem.md: the two tables of friction_study.json, row by row."""
    out = []
    groups = {(g["w_std"], g["lam"]): g for g in fs["excitation"]["by_w_std"]}
    for w in sorted({w for w, _ in groups}):
        a, b = groups[(w, 1.0)], groups[(w, 0.999)]
        out.append(f"| {w:g} | {a['sliding_fraction']:.0%} | {span([a['Fc_min'], a['Fc_max']])} | "
                   f"{span([a['c_min'], a['c_max']])} | {words(a['statuses'])} | "
                   f"{span([b['Fc_min'], b['Fc_max']])} / {span([b['c_min'], b['c_max']])} | "
                   f"{words(b['statuses'])} |".replace("%", " %"))
    groups = {(g["nu"], g["lam"]): g for g in fs["nu"]["by_nu"]}
    for nu in sorted({nu for nu, _ in groups}):
        cells = []
        for lam in (1.0, 0.999):
            g = groups[(nu, lam)]
            cells += [span([g["Fc_min"], g["Fc_max"]]), span([g["c_min"], g["c_max"]]),
                      f"{g['passed']} of {g['members']}"]
        out.append(f"| {nu} ({nu * 0.01:g} s) | " + " | ".join(cells) + " |")
    return out


def friction_text(fs: dict) -> list[str]:
    """docs/own-problem.md: the friction study's numbers in the text around its tables."""
    ex = {(m["w_std"], m["lam"], m["seed"]): m for m in fs["excitation"]["members"]}
    g20 = next(g for g in fs["excitation"]["by_w_std"] if g["w_std"] == 20.0 and g["lam"] == 1.0)
    fc_err = 100 * max(abs(g20["Fc_min"] - 2), abs(g20["Fc_max"] - 2)) / 2
    c_err = 100 * max(abs(g20["c_min"] - 0.5), abs(g20["c_max"] - 0.5)) / 0.5
    ten = [m for (w, lam, _), m in ex.items() if w == 10.0 and lam == 1.0]
    conv = [m for m in ten if m["status"] == "converged"]
    other = [m for m in ten if m["status"] != "converged"]
    off = [100 * abs(m["c"] - 0.5) / 0.5 for m in conv]
    out = [f"for Fc within {math.ceil(fc_err * 10) / 10:.1f} % and c within {math.ceil(c_err * 10) / 10:.1f} %",
           f"the run says `converged` for {len(conv)} of the {len(ten)} members while c is "
           f"{rng(off, '.0f', '-')} % off",
           "catches the rest (" + ", ".join(f"c {m['c']:.3f}, `{m['status']}`" for m in other) + ")"]
    damped = {g["nu"]: g for g in fs["nu_damped_model"]["by_nu"]}
    out.append(f"c comes out {rng([damped[300]['c_min'], damped[300]['c_max']], '.2f')} at nu = 300, "
               f"{rng([damped[3000]['c_min'], damped[3000]['c_max']], '.2f')} at nu = 3000 and "
               f"{rng([damped[20000]['c_min'], damped[20000]['c_max']], '.2f')} at nu = 20 000 (two seeds)")
    many = [m for m in fs["nu"]["members"] if m["nu"] in (1000, 3000)]
    n = {s: sum(m["status"] == s for m in many) for s in ("biased", "undetermined", "not_converged", "converged")}
    out.append(f"of the undamped model's {len(many)} runs at nu = 1000 and 3000, {n['biased'] + n['undetermined']} "
               f"are `biased` or `undetermined`, {n['not_converged']} `not_converged` and {n['converged']} still "
               f"`converged` ({sum(not m['pass'] for m in many)} of {len(many)} fail the requirements)")
    me = fs["mechanism"]

    def at(key, steps, i, fmt=".2f"):
        return " / ".join(format(m[i], fmt) for m in me[key][str(steps)])
    out += [f"the estimates stay there ({at('from_truth', 80000, 0, '.4f').split(' / ')[0]}, "
            f"{at('from_truth', 80000, 1, '.4f').split(' / ')[0]} after 80 000 steps"
            if len({at('from_truth', 80000, 0, '.4f'), at('from_truth', 80000, 1, '.4f')}) == 2 else "",
            f"gives c = {at('viscous_only', 20000, 0, '.4f')} at the same nu",
            f"(c = {at('lam_1', 20000, 1)} at 20 000 steps, {at('lam_1', 80000, 1)} at 80 000)",
            f"c = {at('lam_0.999', 20000, 1)} at 20 000 steps, {at('lam_0.999', 80000, 1, '.4f')} at 80 000"]
    t = fs["tuning"]
    fails = [m for m in t["poor_seeds"] if not m["pass"]]
    out.append(f"the scenario fails {len(fails)} of {len(t['poor_seeds'])} seeds (" + "; ".join(
        f"seed {m['seed']}: Fc {m['Fc']:.3f}, c {m['c']:.3f}, `{m['status']}`" for m in fails))
    best, check = t["best"], t["best_check"]
    out += [f"It chose p0 = {sci(best['p0'])}, nu = {best['nu']}, lam = {best['lam']:g} (held-out rmse "
            f"{t['best_score']:.3g} m/s, mean of two seeds)",
            f"passes: Fc {check['estimates']['Fc']:.4f}, c {check['estimates']['c']:.4f}, `{check['status']}`"
            if check["pass"] else "fails",
            f"Cost: {t['members']} members (one batch per value of nu), {t['seconds']:.1f} s"]
    finite = [c for c in t["ranked"] if math.isfinite(c["score"])]
    worst = finite[-3:]
    out.append(f"the three worst scores ({rng([c['score'] for c in worst], '.3f', ' to ')} m/s) are candidates far "
               f"from the truth (Fc {rng([x for c in worst for x in c['Fc']], '.2f')}, "
               f"c {rng([x for c in worst for x in c['c']], '.2f')})")
    exact = [m["validation_rmse"] for m in t["poor_seeds"]
             if f"{m['Fc']:.3f}" == "2.000" and f"{m['c']:.3f}" == "0.500"]
    out.append(f"an error of {rng(exact, '.3f', ' to ')} m/s even for a model exact to three digits")
    return [x for x in out if x]


def tuning_md(fs: dict, ts: dict, ti: dict) -> list[str]:
    """docs/tuning.md: tune_study.json's table, tune_study_impedance.json, and the friction row."""
    out = []
    for r in ts["results"]:
        b = r["best"]
        out.append(f"| `{r['scenario']}` | {'PASS' if r['poor_pass'] else 'FAIL'} | p0 {sci(b['p0'])}, nu {b['nu']}, "
                   f"lam {b['lam']:.4f} ({sci(r['best_score'])}) | {'PASS' if r['best_pass'] else '**FAIL**'}")
        if "dc_gain" in r["best_estimates"] and not r["best_pass"]:
            out.append(f"**FAIL** (DC gain {r['best_estimates']['dc_gain']:.2f} against {r['truth']['dc_gain']:g})")
        out.append(f"| {r['members']}, {r['seconds']:.0f} s |")
    r = ti["results"][0]
    b = r["best"]
    out.append(f"the search chooses p0 {sci(b['p0'])}, nu {b['nu']}, lam {b['lam']:g} (held-out rmse "
               f"{r['best_score']:.0e}) and the run with a new seed {'passes' if r['best_pass'] else 'fails'} "
               f"({r['members']} members, {r['seconds']:.0f} s)".replace("e-1", "e-1"))
    t = fs["tuning"]
    fails = sum(not m["pass"] for m in t["poor_seeds"])
    best, check = t["best"], t["best_check"]
    out += [f"lam = 0.98: fails in {fails} of {len(t['poor_seeds'])} seeds",
            f"{t['candidates']} candidates, 2 seeds: {t['members']} members, {t['seconds']:.1f} s",
            f"p0 {sci(best['p0'])}, nu {best['nu']}, lam {best['lam']:g}",
            ("PASS" if check["pass"] else "FAIL") + f": Fc {check['estimates']['Fc']:.4f}, "
            f"c {check['estimates']['c']:.4f}"]
    return out


def claims(r: dict, fs: dict, ts: dict, ti: dict) -> list[tuple[str, str]]:
    """(doc, text) for every number the docs state about these results."""
    return [("own-problem.md", x) for x in own_problem(r) + friction_tables(fs) + friction_text(fs)] + \
        [("tuning.md", x) for x in tuning_md(fs, ts, ti)]


def main(argv=None) -> dict | None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--claims", action="store_true", help="print the docs' numbers from the results on record")
    ap.add_argument("--case", choices=CASES, help="run one case here (what the script does in a fresh process)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of each case (default 1)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.claims:
        r = json.loads((Path(args.out) if args.out else RESULTS / "docs_examples.json").read_text())
        fs, ts, ti = (json.loads((RESULTS / f"{name}.json").read_text())
                      for name in ("friction_study", "tune_study", "tune_study_impedance"))
        for doc, text in claims(r, fs, ts, ti):
            print(f"{doc}\t{text}")
        return None
    import torch
    torch.set_num_threads(args.threads)
    if args.case:
        Path(args.out).write_text(json.dumps(case(args.case)))
        return None
    from common import machine, write_json
    out: dict = {"benchmark": "docs_examples", "doc": "docs/own-problem.md", "machine": machine(torch.device("cpu"))}
    for name in CASES:
        out[name] = fresh(name, args.threads)
        print(name, {k: [round(x, 5) for x in v] for k, v in out[name]["estimates"].items()}, out[name]["status"],
              f"{out[name]['seconds']:.1f} s", flush=True)
    print("->", write_json(out, "docs_examples", args.out))
    return out


if __name__ == "__main__":
    main()
