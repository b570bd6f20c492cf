"""Coverage of the confidence intervals over seeds: the share of members whose nominal interval holds the truth.

Each case is one batched run of a scenario in which every member has its own excitation and measurement-noise
streams (seed = 1 .. B); an estimate's coverage is the fraction of members whose interval contains the
truth. Calibrated intervals cover about their level (95%); intervals that are too narrow cover less. The cases
and the measurement of one (``coverage``) are ``tests/coverage_cases.py``, where the tests run some of them.

    python benchmarks/interval_coverage.py                 # every case, 1000 members each (about 10 minutes)
    python benchmarks/interval_coverage.py --table         # the table of the cases last run (docs/intervals.md)
    python benchmarks/interval_coverage.py --members 50 --case sdof-discrete

Writes benchmarks/results/interval_coverage.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))   # the cases, shared with the tests that run them
from coverage_cases import CASES, coverage  # noqa: E402


def table(results: dict) -> str:
    """The cases as a Markdown table: status shares and the coverage among converged members, with the exact
    (Clopper-Pearson) 95% interval of that share from the converged members' count."""
    lines = ["| case | members | steps | converged | biased | undetermined | other | estimate "
             "| coverage among converged | its 95% interval | all members | residual warning |", "|" + "---|" * 12]
    for name, r in results.items():
        sh = r["shares"]
        other = sh["not_converged"] + sh["diverged"]
        for i, (key, row) in enumerate(r["estimates"].items()):
            cov = "-" if row["coverage"] is None else f"{row['coverage']:.3f}"
            band = row.get("coverage_95")
            band = "-" if band is None else f"{band[0]:.3f}-{band[1]:.3f}"
            head = (f"| {name} | {r['members']} | {r['steps']} | {sh['converged']:.2f} | {sh['biased']:.2f} | "
                    f"{sh['undetermined']:.2f} | {other:.2f} |") if i == 0 else "| | | | | | | |"
            warn = f"{r['residual_warning']:.2f}" if i == 0 else ""
            lines.append(f"{head} {key} | {cov} | {band} | {row['coverage_all']:.3f} | {warn} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--members", type=int, default=1000)
    p.add_argument("--case", action="append", choices=sorted(CASES))
    p.add_argument("--out", default="runs/coverage")
    p.add_argument("--table", action="store_true", help="print the table of the results on record and stop")
    args = p.parse_args()
    path = Path(__file__).parent / "results" / "interval_coverage.json"
    if args.table:
        print(table({k: v for k, v in json.loads(path.read_text()).items() if k in CASES}))
        return
    results = {name: coverage(name, args.members, Path(args.out)) for name in args.case or CASES}
    print(table(results))
    path.parent.mkdir(exist_ok=True)
    kept = json.loads(path.read_text()) if path.is_file() else {}      # the cases not run this time stay
    path.write_text(json.dumps({**kept, **results}, indent=1) + "\n")
    print(f"-> {path}")


if __name__ == "__main__":
    main()
