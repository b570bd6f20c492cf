"""The interval rule, studied offline: every member's inputs to its interval recorded once, rules scored on them.

An interval is built from a handful of numbers per member and estimate (``estimate_intervals``): the estimate, its
standard deviation sd_r, the output error's step d with its standard deviations sd_d (of the step) and sd_o (of
the output error's optimum), the model class's bias against the physics g b, the drift t with its standard
deviation sd_t, and per member whether the residuals are white and how much their correlation widens the
parameters' standard deviations. ``--capture`` runs coverage cases (``tests/coverage_cases.py``) with those
numbers recorded; every rule below is then scored on the records in a second, without running anything again:

* ``shipped``: the rule of ``rcotorch.verdict.intervals`` written again in NumPy, with its constants read from
  that module; the score checks that it gives the run's own intervals and statuses, so that a change of the rule
  that is not made here too is seen;
* ``reaching``: the rule before the one shipped, whose optimum's interval was extended to hold the estimate
  and was held beside the widened one wherever the drift stood out;
* ``output-error-first``: the interval about the output error's optimum less the model class's bias,
  est + d - g b +- q sd_o w (w the correlated residuals' widening where the whiteness test rejects), extended to
  hold the estimate, wherever the step stands out from its noise (|d| > ``hold`` sd_d) or the optimum is the more
  precise (sd_o <= sd_r); where the residuals are correlated or the estimate still drifts (|t| > 3 sd_t), the hull
  with the shipped interval; a member is biased where the estimate lies more than two of the optimum's
  half-widths and ``BIAS_TOL`` of its size from it.

    python benchmarks/interval_rules.py --capture                      # every case, 1000 members (about 3 minutes)
    python benchmarks/interval_rules.py --capture --case drag --members 200
    python benchmarks/interval_rules.py                                # score the rules on the records

Records go to benchmarks/runs/interval_rules/ (not kept in the repository); the scores to
benchmarks/results/interval_rules.json.
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))   # the coverage cases, shared with the tests
import coverage_cases  # noqa: E402
from coverage_cases import CASES, coverage  # noqa: E402

RECORDS = Path(__file__).parent / "runs" / "interval_rules"


def static_lam1(members: int, out: Path, steps: int = 5000) -> dict:
    """The exact static regression of tests/test_intervals.py under lam = 1 (the refinement's estimate is the whole
    run's least-squares one, the output error's optimum that of the window alone, several times less precise)."""
    from test_intervals import _regression_graph

    import rcotorch as rt
    theta = [0.7, -1.3, 0.2]
    g = _regression_graph(theta, 0.1, seed=list(range(1, members + 1)))
    names = [f"theta[{n}]" for n in g.role("estimator").theta_names]
    return rt.refine(g, steps, out=out, overwrite=True, figures=False, validation=False, progress=False,
                     truth=dict(zip(names, theta))).summary


STUDY = {**CASES, "static-lam1": (static_lam1, {}, 5000)}     # the coverage cases and this one
STATUSES = ("converged", "not_converged", "diverged", "undetermined", "biased")


def capture(name: str, members: int, out: Path) -> dict:
    """Run coverage case ``name`` with ``members`` members, recording every member's interval inputs, the statuses
    before and after the intervals, and the truth."""
    import torch

    import rcotorch.verdict.intervals as ci
    from rcotorch.verdict.health import Health
    got: dict = {}
    intervals, decide = ci.estimate_intervals, Health.decide

    def recorded_intervals(graph, estimates, pc, level=ci.LEVEL, scales=None, rel_tol=ci.REL_TOL, transient=None):
        found = intervals(graph, estimates, pc, level=level, scales=scales, rel_tol=rel_tol, transient=transient)
        grads = ci.estimate_gradients(graph, estimates, pc.std)
        keys = {}
        for key, v in found.estimate.items():
            g = grads[key].cpu()
            row = {"v": v.numpy(), "sd_r": ci._sd(g, pc.cov).numpy(), "scale": float((scales or {}).get(key, 0.0)),
                   "below": found.below[key].numpy(), "above": found.above[key].numpy()}
            if pc.offset is not None:
                row["d"] = torch.einsum("bi,bi->b", g, pc.offset.cpu()).numpy()
            if pc.offset_cov is not None:
                row["sd_d"] = ci._sd(g, pc.offset_cov).numpy()
                row["sd_o"] = ci._sd(g, pc.offset_cov if pc.optimum_cov is None else pc.optimum_cov).numpy()
            if pc.sampling is not None:
                row["model"] = torch.einsum("bi,bi->b", g, pc.sampling.cpu()).numpy()
            if transient is not None:
                row["t"] = torch.einsum("bi,bi->b", g, transient[0].cpu()).numpy()
                row["sd_t"] = ci._sd(g, transient[1].cpu()).numpy()
            keys[key] = row
        got["intervals"] = {"keys": keys, "settles": pc.settles.cpu().numpy(),
                            "correlated": None if pc.correlated is None else pc.correlated.cpu().numpy(),
                            "widening": None if pc.widening is None else pc.widening.cpu().numpy(),
                            "offset": None if pc.offset is None else pc.offset.cpu().numpy(),
                            "offset_cov": None if pc.offset_cov is None else pc.offset_cov.cpu().numpy()}
        return found

    def recorded_decide(status, z_ratio, z_tol, determined=None, worse=None, **rest):
        final = decide(status, z_ratio, z_tol, determined=determined, worse=worse, **rest)
        if determined is not None:            # the second call: the intervals' part of the verdict
            got.update(settled=status.cpu().numpy(), final=final.cpu().numpy(),
                       worse=None if worse is None else worse.cpu().numpy())
        return final

    ci.estimate_intervals, Health.decide = recorded_intervals, staticmethod(recorded_decide)
    extra = name not in CASES              # a case of this study only, lent to coverage() for the run
    if extra:
        coverage_cases.CASES[name] = STUDY[name]
    try:
        result = coverage(name, members, out)
    finally:
        ci.estimate_intervals, Health.decide = intervals, staticmethod(decide)
        if extra:
            del coverage_cases.CASES[name]
    summary = json.loads((out / name / "summary.json").read_text())
    got["truth"] = {k: np.asarray(v, dtype=float) for k, v in summary["truth"].items()}
    got["coverage"] = result
    return got


def widened(rec: dict, parts: dict | None = None) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    """The refinement's own interval with the widenings of ``estimate_intervals`` (the output error's step and its
    interval, the physics, the drift) and no more (the library's rule until the window's optimum came in):
    {key: (below, above)}, determined, biased, drifting. ``parts`` (where given) receives per estimate its flags
    and bias: {key: (off, sampled, bias)} (off: biased by the output error's step, sampled: by the model class)."""
    import rcotorch.verdict.intervals as ci
    q = ci.quantile(ci.LEVEL)
    rows, corr = rec["intervals"]["keys"], rec["intervals"]["correlated"]
    det = rec["intervals"]["settles"].copy()
    B = det.size
    biased, drifting, sides = np.zeros(B, bool), np.zeros(B, bool), {}
    factor = np.full(B, ci.OFFSET_FACTOR) if corr is None else np.where(corr, ci.OFFSET_FACTOR_CORRELATED,
                                                                        ci.OFFSET_FACTOR)
    fin = np.isfinite
    with np.errstate(invalid="ignore"):
        for key, r in rows.items():
            v, hw = r["v"], q * r["sd_r"]
            size = np.maximum(np.abs(v), r["scale"])
            low, high, off, moved = np.zeros(B), np.zeros(B), np.zeros(B, bool), np.zeros(B)
            bias = np.full(B, np.nan)
            model = r.get("model")
            if "d" in r:
                d = r["d"]
                beyond = fin(d) & fin(hw) & (np.abs(d) > factor * hw)
                widen = beyond if corr is None else beyond | (corr & fin(d))
                off = beyond & (np.abs(d) > ci.BIAS_TOL * size)
                bias = np.where(off, -d, bias)
                if "sd_d" in r:
                    hold = fin(d) & fin(hw) & (np.abs(d) > ci.OFFSET_HOLD_Z * r["sd_d"]) & ~widen
                    centre = d if model is None else d - np.where(fin(model), model, 0.0)
                    low = np.where(hold, np.clip(q * r["sd_o"] - centre - hw, 0, None), 0.0)
                    high = np.where(hold, np.clip(q * r["sd_o"] + centre - hw, 0, None), 0.0)
                moved = np.where(widen, d, 0.0)
            sampled = np.zeros(B, bool)
            if model is not None:
                total = model - moved
                known = fin(total) & fin(hw)
                flag = known & (np.abs(total) > hw) & (np.abs(total) > ci.NEGLIGIBLE * size)
                reach = np.abs(total) - np.abs(moved)
                low = np.where(known & ~flag, np.maximum(low, reach), low)
                high = np.where(known & ~flag, np.maximum(high, reach), high)
                sampled = flag & (np.abs(model) >= np.abs(moved))
                off = off | (flag & ~sampled)
                bias = np.where(flag, total, bias)
            lo, hi = hw + np.abs(moved) + low, hw + np.abs(moved) + high
            if "t" in r:
                t, sd_t = r["t"], r["sd_t"]
                found = fin(t) & fin(lo)
                moving = found & (np.abs(t) > ci.DRIFT_Z * sd_t)
                far = moving & (np.abs(t) > ci.DRIFT_FAR * np.maximum(lo, hi)) & (np.abs(t) > ci.NEGLIGIBLE * size)
                drifting |= far
                reach = np.where(found & (np.abs(t) > ci.DRIFT_HOLD_Z * sd_t) & ~far, np.abs(t) + ci.DRIFT_NOISE * sd_t,
                                 0.0)
                lo, hi = np.where(t > 0, lo + reach, lo), np.where(t < 0, hi + reach, hi)
            lo, hi = np.where(fin(r["sd_r"]), lo, np.nan), np.where(fin(r["sd_r"]), hi, np.nan)
            det &= fin(lo + hi) & (np.maximum(lo, hi) <= ci.REL_TOL * size)
            biased |= off | sampled
            sides[key] = (lo, hi)
            if parts is not None:
                parts[key] = (off, sampled, bias)
    return sides, det, biased, drifting


def shipped(rec: dict, reaching: bool = False) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    """``estimate_intervals``'s rule on the records: ``widened``'s, its sides replaced by the window's
    output-error optimum's where the joint test rejects or the optimum is the more precise, held beside them where
    the residuals are correlated or the drift stands out (and, about the optimum, disagrees with it): {key: (below,
    above)}, determined, biased, drifting. ``reaching``: the rule before, whose optimum's interval reached the
    estimate and held the widened one wherever the drift stood out."""
    from scipy.stats import chi2

    import rcotorch.verdict.intervals as ci
    q = ci.quantile(ci.LEVEL)
    parts: dict = {}
    base, _, biased, drifting = widened(rec, parts)
    I = rec["intervals"]
    det = I["settles"].copy()
    B = det.size
    if I["offset"] is None or I["offset_cov"] is None:
        return base, _, biased, drifting
    corr = np.zeros(B, bool) if I["correlated"] is None else I["correlated"]
    widening = np.where(corr, I["widening"], 1.0) if I["widening"] is not None else np.ones(B)
    D, S = I["offset"], I["offset_cov"]
    n = D.shape[1]
    ok = np.isfinite(D).all(1) & np.isfinite(S).reshape(B, -1).all(1)
    D0 = np.where(ok[:, None], D, 0.0)
    stat = np.einsum("bi,bij,bj->b", D0, np.linalg.pinv(np.where(ok[:, None, None], S, np.eye(n))), D0)
    p = np.where(ok, chi2.sf(np.maximum(stat, 0), n), np.nan)
    sides, flagged = {}, np.zeros(B, bool)
    with np.errstate(invalid="ignore"):
        for key, r in I["keys"].items():
            v, sd_r = r["v"], r["sd_r"]
            hw, size = q * sd_r, np.maximum(np.abs(v), r["scale"])
            model = np.where(np.isfinite(r["model"]), r["model"], 0.0) if "model" in r else np.zeros(B)
            centre, sd_o = r["d"] - model, r["sd_o"] * widening
            use = np.isfinite(centre) & np.isfinite(sd_o) & np.isfinite(hw) & ((p < ci.OPTIMUM_P) | (sd_o <= sd_r))
            lo, hi = np.where(use, q * sd_o - centre, hw), np.where(use, q * sd_o + centre, hw)
            if reaching:
                lo, hi = np.where(use, np.clip(lo, 0, None), hw), np.where(use, np.clip(hi, 0, None), hw)
            hold = corr.copy()
            if "t" in r:
                drifts = np.isfinite(r["t"]) & np.isfinite(hw) & (np.abs(r["t"]) > ci.OPTIMUM_DRIFT_Z * r["sd_t"])
                apart = drifts & (np.abs(r["t"] + centre) > ci.OPTIMUM_AGREE * q * sd_o)
                hold |= drifts if reaching else np.where(use, apart, drifts)
            lo, hi = np.where(hold, np.maximum(lo, base[key][0]), lo), np.where(hold, np.maximum(hi, base[key][1]), hi)
            lo, hi = np.where(np.isfinite(sd_r), lo, np.nan), np.where(np.isfinite(sd_r), hi, np.nan)
            det &= np.isfinite(lo + hi) & (np.maximum(lo, hi) <= ci.REL_TOL * size)
            off, sampled, bias = parts[key]
            shift = np.where(np.isfinite(bias), bias, 0.0)
            held_bias = off & ~sampled & (shift <= lo) & (-shift <= hi)    # a closed-loop bias the interval holds
            flagged |= (off & ~held_bias) | sampled
            sides[key] = (lo, hi)
    return sides, det, flagged, drifting


def output_error_first(rec: dict, hold: float = 1.0) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    """The candidate rule of the module's docstring on the records."""
    import rcotorch.verdict.intervals as ci
    q = ci.quantile(ci.LEVEL)
    base, det, _, drifting = widened(rec)
    I = rec["intervals"]
    B = det.size
    corr = np.zeros(B, bool) if I["correlated"] is None else I["correlated"]
    widening = np.where(corr, I["widening"], 1.0) if I["widening"] is not None else np.ones(B)
    det, biased, sides = I["settles"].copy(), np.zeros(B, bool), {}
    fin = np.isfinite
    with np.errstate(invalid="ignore"):
        for key, r in I["keys"].items():
            v, sd_r = r["v"], r["sd_r"]
            hw, size = q * sd_r, np.maximum(np.abs(v), r["scale"])
            model = np.where(fin(r["model"]), r["model"], 0.0) if "model" in r else np.zeros(B)
            centre, sd_o = r["d"] - model, r["sd_o"] * widening        # the physics' value less the estimate
            have = fin(centre) & fin(sd_o)
            use = have & ((np.abs(r["d"]) > hold * r["sd_d"]) | (sd_o <= sd_r))
            lo = np.where(use, np.clip(q * sd_o - centre, 0, None), hw)
            hi = np.where(use, np.clip(q * sd_o + centre, 0, None), hw)
            biased |= have & (np.abs(centre) > 2 * np.where(use, q * sd_o, hw)) & (np.abs(centre) > ci.BIAS_TOL * size)
            with_shipped = corr | (np.abs(r.get("t", np.zeros(B))) > 3 * r.get("sd_t", np.ones(B)))
            lo = np.where(with_shipped, np.maximum(lo, base[key][0]), lo)
            hi = np.where(with_shipped, np.maximum(hi, base[key][1]), hi)
            lo, hi = np.where(fin(sd_r), lo, np.nan), np.where(fin(sd_r), hi, np.nan)
            det &= fin(lo + hi) & (np.maximum(lo, hi) <= ci.REL_TOL * size)
            sides[key] = (lo, hi)
    return sides, det, biased, drifting


def verdict(rec: dict, det: np.ndarray, biased: np.ndarray, drifting: np.ndarray) -> np.ndarray:
    """Every member's status (index into ``STATUSES``) from the checks' status and a rule's findings, as
    ``Health.decide`` makes it."""
    s = np.where((rec["settled"] == 0) & drifting, 1, rec["settled"])
    s = np.where((s == 0) & ~det, 3, s)
    s = np.where((s == 0) & biased, 4, s)
    if rec["worse"] is not None:
        s = np.where(rec["worse"] & np.isin(s, (0, 3, 4)), 1, s)
    return s


def score(rec: dict, rule) -> dict:
    """Shares of the statuses, and per estimate the coverage among converged members and the median half-width
    over the estimate's own 1.96 sd_r."""
    import rcotorch.verdict.intervals as ci
    sides, det, biased, drifting = rule(rec)
    status = verdict(rec, det, biased, drifting)
    conv = status == 0
    out = {"shares": {s: round(float(np.mean(status == i)), 3) for i, s in enumerate(STATUSES)}, "estimates": {}}
    for key, (lo, hi) in sides.items():
        r, t = rec["intervals"]["keys"][key], rec["truth"][key]
        inside = (r["v"] - lo <= t) & (t <= r["v"] + hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            width = (lo + hi) / 2 / (ci.quantile(ci.LEVEL) * r["sd_r"])
        out["estimates"][key] = {"coverage": round(float(inside[conv].mean()), 3) if conv.any() else None,
                                 "width": round(float(np.nanmedian(width[conv])), 2) if conv.any() else None}
    return out


def reproduces(rec: dict) -> bool:
    """Whether ``shipped`` gives the run's own intervals and statuses."""
    sides, det, biased, drifting = shipped(rec)
    same = all(np.allclose(sides[k][0], r["below"], equal_nan=True) and np.allclose(sides[k][1], r["above"],
                                                                                     equal_nan=True)
               for k, r in rec["intervals"]["keys"].items())
    return same and bool((verdict(rec, det, biased, drifting) == rec["final"]).all())


RULES = {"shipped": shipped, "reaching": lambda rec: shipped(rec, reaching=True), "widened": widened,
         "output-error-first": output_error_first}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--capture", action="store_true", help="run the cases and record their members' inputs")
    p.add_argument("--case", action="append", choices=sorted(STUDY))
    p.add_argument("--members", type=int, default=1000)
    args = p.parse_args()
    names = args.case or list(STUDY)
    RECORDS.mkdir(parents=True, exist_ok=True)
    if args.capture:
        for name in names:
            rec = capture(name, args.members, RECORDS / "runs")
            (RECORDS / f"{name}.pkl").write_bytes(pickle.dumps(rec))
            print(f"{name}: recorded {args.members} members", flush=True)
    results = {}
    for name in names:
        path = RECORDS / f"{name}.pkl"
        if not path.is_file():
            continue
        rec = pickle.loads(path.read_bytes())
        if not reproduces(rec):
            raise SystemExit(f"{name}: the NumPy copy of the rule no longer gives the run's intervals: update "
                             "shipped() to rcotorch.verdict.intervals.estimate_intervals")
        results[name] = {rule: score(rec, fn) for rule, fn in RULES.items()}
        for rule, r in results[name].items():
            cov = ", ".join(f"{k} {e['coverage']} (x{e['width']})" for k, e in r["estimates"].items())
            print(f"{name:24s} {rule:19s} converged {r['shares']['converged']:.2f} biased {r['shares']['biased']:.2f}"
                  f" | {cov}")
    out = Path(__file__).parent / "results" / "interval_rules.json"
    if results:
        kept = json.loads(out.read_text()) if out.is_file() else {}
        out.write_text(json.dumps({**kept, **results}, indent=1) + "\n")
        print(f"-> {out}")


if __name__ == "__main__":
    main()
