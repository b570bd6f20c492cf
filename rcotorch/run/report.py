"""What a run reports in words and JSON: ``summary.json`` (``to_json``), the health line and the result table
printed at the end (``health_line``, ``result_table``), and each member's reason for a status other than
converged (``member_reasons``, the summary's ``health.why``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import orjson
import torch

from ..verdict import intervals as ci
from ..verdict.health import STATUSES, Criteria


def to_json(obj: Any, indent: int = 0) -> str:
    """JSON with one key per line and every list on one line (readable, and fast for large batches: orjson
    writes a float in the fewest digits that read back as the same float64, in C; a value that is not finite
    becomes null)."""
    if isinstance(obj, Mapping) and obj:
        pad = " " * (indent + 2)
        items = [f"{pad}{_dumps(str(k))}: {to_json(v, indent + 2)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    return _dumps(obj)


def _dumps(obj: Any) -> str:
    return orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS).decode()


def health_line(summary: Mapping[str, Any]) -> str:
    """One line on the members' health (a member the data did not determine is never called converged)."""
    h = summary["health"]
    if summary["batch"] == 1:
        if h["status"] == "diverged":
            return f"health: diverged at step {h['diverged_at']} ({h['reason']})"
        detail = ", ".join(f"{k} {_fmt(h[k])}" for k in ("theta_change", "z_ratio"))
        note = ""
        if h.get("residuals_matter"):
            note = (f"; residuals not white: dynamics the model leaves unexplained bias the estimates or widen "
                    f"their intervals ({_fmt(h.get('residual_widening'))} times)")
        if h["status"] == "biased":
            return f"health: biased: {_bias_text(summary, None)} ({detail}){note}"
        if h["status"] == "undetermined" and h.get("biased"):
            note += f"; biased: {_bias_text(summary, None)}"
        if h["status"] == "undetermined":
            which = ", ".join(h.get("undetermined") or []) or "a direction of theta"
            return f"health: undetermined: settled, but the data did not determine {which} ({detail}){note}"
        why = f": {h['why']}" if h.get("why") else ""
        return f"health: {h['status']}{why} ({detail}){note}"
    counts = ", ".join(f"{n} {status}" for status, n in h["counts"].items()
                       if n or status not in ("undetermined", "biased"))
    line = f"health: {counts}"
    matter = h.get("residuals_matter")
    if isinstance(matter, list) and any(matter):
        widest = max(w for w, m in zip(h["residual_widening"], matter) if m and w is not None)
        line += (f"; residuals not white in {sum(matter)} members: dynamics the model leaves unexplained bias "
                 f"their estimates or widen their intervals (up to {widest:.3g} times)")
    if h["counts"].get("biased"):
        members = [b for b, st in enumerate(h["status"]) if st == "biased"]
        line += f"; biased: {_bias_text(summary, members)}"
    why = _why_text(h)
    if why:
        line += f"; {why}"
    if summary["diverged"]:
        first = summary["diverged"][:5]
        line += "; diverged: " + ", ".join(f"member {d['member']} at step {d['step']} ({d['reason']})"
                                           for d in first) + (", ..." if len(summary["diverged"]) > 5 else "")
    return line


def member_reasons(verdict: Mapping[str, torch.Tensor], criteria: Criteria, worse: torch.Tensor | None,
         found: ci.Intervals | None, white: torch.Tensor | None = None) -> list[str | None]:
    """Per member, why it is not converged, undetermined or biased, in a few words (None for a converged or
    diverged member: a diverged one has its ``reason``). A z_ratio above the tolerance with ``white`` residuals
    is not a reason (``Health.decide``)."""
    code = verdict["status"].cpu().tolist()
    ratio = verdict["z_ratio"].cpu().tolist()
    white_ = white.cpu().tolist() if white is not None else [False] * len(code)
    drifting = found.drifting.tolist() if found is not None and found.drifting is not None else [False] * len(code)
    worse_ = worse.tolist() if worse is not None else [False] * len(code)
    out: list[str | None] = []
    for b, c in enumerate(code):
        status = STATUSES[c]
        if status == "not_converged":
            if worse_[b]:
                out.append("fits worse than the initial model")
            elif drifting[b]:
                out.append("still drifting beyond its interval")
            elif not ratio[b] <= criteria.z_tol and not white_[b]:
                out.append(f"z_ratio above {criteria.z_tol:g}")
            else:
                out.append(f"theta_change above {criteria.theta_tol:g}")
        elif status == "undetermined":
            keys = found.undetermined_keys[b] if found is not None else []
            out.append(f"interval too wide: {', '.join(keys)}" if keys else "a direction of theta not excited")
        elif status == "biased":
            out.append("biased: " + ", ".join(found.biased_keys[b]) if found is not None and found.biased_keys
                       else "biased")
        else:
            out.append(None)
    return out


def _why_text(h: Mapping[str, Any]) -> str:
    """The reasons of the members not converged or undetermined, counted, with up to five members each."""
    why, status = h.get("why"), h.get("status")
    if not isinstance(why, list):
        return ""
    groups: dict[str, list[int]] = {}
    for b, (w, s) in enumerate(zip(why, status)):
        if w is not None and s in ("not_converged", "undetermined"):
            groups.setdefault(f"{s}: {w}", []).append(b)
    parts = []
    for text, members in groups.items():
        shown = ", ".join(map(str, members[:5])) + (", ..." if len(members) > 5 else "")
        parts.append(f"{len(members)} {text} (member{'s' if len(members) > 1 else ''} {shown})")
    return "; ".join(parts)


def _bias_text(summary: Mapping[str, Any], members: list[int] | None) -> str:
    """Which estimates are biased, by how much and why: for one member (``members`` None) each biased estimate
    with its bias; for a batch, per estimate the members' count and median bias, and the reasons' counts."""
    h, iv = summary["health"], summary.get("intervals") or {}
    if members is None:
        parts = [f"{k} by {_signed(iv.get(k, {}).get('bias'))}" for k in h.get("biased_keys") or []]
        return ", ".join(parts) + f" ({h.get('bias_reason')})"
    parts = []
    for k in dict.fromkeys(k for b in members for k in h["biased_keys"][b]):
        at = [b for b in members if k in h["biased_keys"][b]]
        bias = sorted(x for x in (iv.get(k, {}).get("bias") or [None] * (max(at) + 1))[:] if x is not None)
        median = bias[len(bias) // 2] if bias else None
        parts.append(f"{k} in {len(at)} (median {_signed(median)})")
    reasons = {}
    for b in members:
        reasons[h["bias_reason"][b]] = reasons.get(h["bias_reason"][b], 0) + 1
    return ", ".join(parts) + "; " + "; ".join(f"{n}: {r}" for r, n in reasons.items())


def _signed(v) -> str:
    return "nan" if v is None else f"{v:+.3g}"


def _fmt(v) -> str:
    if isinstance(v, list):
        finite = [x for x in v if x is not None]
        return f"{min(finite):.6g}..{max(finite):.6g}" if finite else "nan"
    return "nan" if v is None else f"{v:.6g}"


def _fmt_interval(v, interval: Mapping[str, Any] | None) -> str:
    """An estimate with its interval: 'value ± half-width' for one member ('value -below +above' where the
    interval is not symmetric about it, 'value [lower, upper]' where it does not hold the value: the data place
    the parameter to one side of the estimate), the values' range and the median half-width for a batch."""
    if interval is None:
        return _fmt(v)
    lo, hi = interval["lower"], interval["upper"]
    if not isinstance(v, list):
        if lo is None or hi is None or v is None:
            return _fmt(v)
        if not lo <= v <= hi:
            return _fmt(v) + f" [{lo:.4g}, {hi:.4g}]"
        if abs((hi - v) - (v - lo)) <= 0.05 * (hi - lo):
            return _fmt(v) + f" ± {(hi - lo) / 2:.2g}"
        return _fmt(v) + f" -{v - lo:.2g} +{hi - v:.2g}"
    half = sorted((b - a) / 2 for a, b in zip(lo, hi) if a is not None and b is not None)
    return _fmt(v) + (f" (± {half[len(half) // 2]:.2g} median)" if half else "")


def _check_text(chk: Mapping[str, Any]) -> str:
    per = chk.get("member_pass")
    if isinstance(per, list) and not chk["pass"]:
        return f"FAIL ({len(per) - sum(per)} of {len(per)} members)"
    return "PASS" if chk["pass"] else "FAIL"


def result_table(summary: Mapping[str, Any]) -> str:
    """A short text table of estimates (with their confidence intervals), truth and requirements, and the
    members' health."""
    intervals = summary.get("intervals") or {}
    level = next(iter(intervals.values()))["level"] if intervals else None
    head = "estimate" + (f" ({level:.0%} interval)" if level else "")
    rows = [("key", head, "truth", "requirement", "check")]
    checks = summary.get("requirements", {})
    # A batch's estimates and intervals are summarized over the members that did not diverge (a diverged
    # member's parameters are frozen where it failed), unless every member did.
    status = (summary.get("health") or {}).get("status")
    keep = [s != "diverged" for s in status] if isinstance(status, list) else None
    if keep is not None and (all(keep) or not any(keep)):
        keep = None

    def kept(values, interval):
        if keep is None or not isinstance(values, list) or len(values) != len(keep):
            return values, interval
        pick = lambda xs: [x for x, k in zip(xs, keep) if k]                    # noqa: E731
        return pick(values), None if interval is None else \
            {**interval, "lower": pick(interval["lower"]), "upper": pick(interval["upper"])}

    for group in ("estimates", "metrics"):
        for key, v in summary[group].items():
            chk = checks.get(f"{group}.{key}")
            truth = summary["truth"].get(key) if group == "estimates" else None
            if group == "estimates":
                v, interval = kept(v, intervals.get(key))
            rows.append((f"{group}.{key}", _fmt_interval(v, interval if group == "estimates" else None),
                         "" if truth is None else _fmt(truth),
                         chk["requirement"] + f" ({_fmt(chk['value'])})" if chk else "",
                         _check_text(chk) if chk else ""))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    if keep is not None:
        lines.append(f"(estimates: the {sum(keep)} members that did not diverge)")
    lines.append(health_line(summary))
    lines += [f"warning: {w}" for w in summary.get("warnings") or []]
    return "\n".join(lines)
