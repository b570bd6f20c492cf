"""TensorBoard monitoring of a run: its own run and sibling runs in TensorBoard's run list (the band's edges, the
truth, the HParams session), a few chosen member traces, histograms, figures and a Custom Scalars layout.

Runs: the run's folder is its run (named "." when TensorBoard is opened on that folder); its siblings are the
subfolders ``lower/``, ``truth/`` and ``upper/``, which draw their role under the estimate's own tag, and
``verdict/``, its HParams session. TensorBoard colours each run by its place in its run list; the names and
start times keep these in this order (``ROLES``), so each role has the same colour in every run.

Tags, grouped so that TensorBoard's Time Series tab opens on what matters (it sorts groups by name, capitals
first, and expands the first two):

* ``Estimates/<key> [<unit>]``: the estimate (a batch: its mean) in the run, and under the same tag the band's
  edges in ``lower/`` and ``upper/`` (a batch: the 10% and 90% quantiles across the members; one member: truth
  -+ the requirement's tolerance, else its confidence band over time, written at the end) and the truth in
  ``truth/``, so that one chart draws estimate, band and truth in their own colours; ``Estimates/<key> |error|
  [<unit>]`` beside it (|estimate - truth|, batch mean);
* ``Model error/z rms [dB re 1 <unit of y>]`` (``[dB re 1 unit of y]`` where y has no unit given; 20 log10 of
  the rms of z over the batch and the log interval; its quantiles in ``lower/`` and ``upper/``) and
  ``Model error/<detector> alarmed members [%]``;
* ``members/<key> m<b> [<unit>]`` and ``members/z rms m<b>`` (the traced members of a batch: the ones the
  figures draw), ``bands/<key> [<unit>]`` with ``bands/<key> low|high`` (the estimate and truth -+ tolerance,
  for a margin chart), ``intervals/<key> [<unit>]`` with ``intervals/<key> lower|upper`` (the confidence band
  over time about the history members' mean estimate, written at the end), ``theta/<entry>`` (batch mean),
  ``health/diverged`` and at the end ``health/<status>`` (members, batches), histograms ``spread/<key>
  [<unit>]`` (batches from 16 members), images ``figures/<name>``, the settings as text;
* in ``verdict/``: ``final/``, ``metrics/`` and ``verdict/`` (``final_values``), written at the end.

Estimates are shown in engineering notation: ``<unit>`` carries the SI prefix that puts the scenario's size of
the estimate (``Scenario.scales``, else its default truth, else this run's truth) in [1, 1000), e.g.
``Estimates/C [uF]`` for 23.5e-6 F; the logged value is the estimate divided by ``Scaled.scale``. A unit that
takes no prefix gets a power of ten instead (``[1e-3 1/s^2]``, ``[-]`` without unit or scaling).

The x axis: the step is the sample index (the settings card gives dt). Where the graph has a sample time dt,
each scalar event's wall time is the run's origin plus the simulated time, ``origin + k dt`` (the origin is kept
in the checkpoint, so a resumed run continues the same axis), and a fresh run logs the initial model's
estimates at step 0: TensorBoard's "Relative" x axis then reads simulated time.

Custom Scalars: per run (or per sweep) categories of charts of one kind (``Monitor.layout``): each estimate with
its siblings and traced members (patterns anchored, so that a chart draws only its own tags), its |error|,
margin charts of the estimate inside truth ± tolerance and inside its confidence band, the model error with
the detectors' alarms. HParams: the session is ``verdict/`` (``write_session``: the settings, named with their
units, the status, whether the members pass the requirements; the final values as its metrics). TensorBoard's
HParams table shows five hyperparameter columns until others are ticked: the first five of its list, which
holds those that differ between sessions first, each part in name order (capitals before lower case). The
requirements and the status are named ``*requirements`` and ``*status`` (``REQUIREMENTS_HPARAM``,
``STATUS_HPARAM``) so that they lead both parts; the metrics sort by tag, so the table's metric columns open
on each estimate, its truth and its error.
"""

from __future__ import annotations

import math
import re
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..estimator.tracking import ChangeDetector, change_report
from .event_file import EventFile
from .event_file import crc32c as crc32c  # re-exported from its home, event_file
from .event_file import masked_crc32c as masked_crc32c  # likewise
from .scenario import truth_at

TRACED_DEFAULT = 8     # members traced individually when the run does not choose them (the figures draw them)
HISTOGRAM_MIN = 16     # histograms across the batch from this batch size
# The sibling runs (subfolders of the run's folder), each drawing one role under the estimate's own tag: the band's
# lower edge, the truth and the band's upper edge; and the run's HParams session with its final values.
LOW, TRUTH, HIGH, SESSION = "lower", "truth", "upper", "verdict"
BAND = {LOW: 0.1, HIGH: 0.9}     # in a batch the band's edges are these quantiles across the members
# TensorBoard lists runs by start time (the wall time of their first event), then by name, and colours each by its
# place in that list. Its default loader holds start times coarsely (runs started even 1000 s apart are listed by
# name), so a run and its siblings, started together, are listed by name: the names above sort in this order, and
# each writer starts at the run's origin plus its place here (milliseconds apart, for the loader that keeps start
# times exactly). So the estimate, lower, truth and upper take the same places, and colours, in every run.
ROLES = ("", LOW, TRUTH, HIGH, SESSION)
ESTIMATES, MODEL_ERROR = "Estimates", "Model error"
DB_FLOOR = -400.0      # the model error in dB where it is exactly zero
STATUS_HPARAM = "*status"   # '*' sorts before letters and digits: among the first columns of the HParams table
REQUIREMENTS_HPARAM = "*requirements"    # whether the requirements pass, beside the status
SI_PREFIXES = {-24: "y", -21: "z", -18: "a", -15: "f", -12: "p", -9: "n", -6: "u", -3: "m", 3: "k", 6: "M",
               9: "G", 12: "T", 15: "P", 18: "E", 21: "Z", 24: "Y"}
# Units that take an SI prefix when they lead a unit ('N' in 'N s/m', 'm' in 'm/(N s)').
PREFIXABLE = frozenset({"N", "m", "s", "V", "A", "F", "H", "W", "J", "Pa", "Hz", "ohm", "C", "T", "Wb", "S", "g",
                        "K", "rad", "mol", "cd", "lm", "lx", "Bq", "Gy", "Sv", "kat", "eV"})


# --- engineering notation ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Scaled:
    """How a quantity is shown: its value divided by ``scale`` (a power of 1000), in ``unit``."""

    scale: float
    unit: str

    @property
    def label(self) -> str:
        """The unit as a tag shows it: ``[uF]``; ``[-]`` for a plain number."""
        return f"[{self.unit or '-'}]"


def engineering(size: float | None, unit: str) -> Scaled:
    """The SI prefix (or power of ten) that puts a quantity of ``size`` (in ``unit``) in [1, 1000): 23.5e-6 in
    F gives ``Scaled(1e-6, 'uF')``; a unit that takes no prefix gets the power of ten written before it
    (``Scaled(1e-3, '1e-3 1/s^2')``). No size (None, zero, not finite) leaves the unit as it is."""
    if size is None or not math.isfinite(size) or size == 0:
        return Scaled(1.0, unit)
    exponent = 3 * math.floor(math.log10(abs(size)) / 3 + 1e-12)
    if exponent == 0:
        return Scaled(1.0, unit)
    head = re.match(r"[A-Za-z]+(?=$|[ /*(])", unit)
    if head and head.group() in PREFIXABLE and exponent in SI_PREFIXES:
        return Scaled(10.0 ** exponent, SI_PREFIXES[exponent] + unit)
    return Scaled(10.0 ** exponent, f"1e{exponent} {unit}".strip())


def _size(value) -> float | None:
    """The mean magnitude of a number or a list of numbers (None where there is no finite, nonzero one)."""
    values = np.abs(np.asarray(value if isinstance(value, (list, tuple)) else [value], dtype=np.float64))
    values = values[np.isfinite(values) & (values > 0)]
    return float(values.mean()) if values.size else None


def estimate_scales(scenario, keys: Iterable[str], truth: Mapping[str, Any] | None = None) -> dict[str, Scaled]:
    """How each estimate is shown (``engineering``): sized by the scenario's ``scales`` at its default settings,
    else by its truth at its default settings (so every run and sweep of a scenario writes the same tags), else
    by ``truth`` (this run's)."""
    try:
        defaults = dict(scenario.settings)
        sizes, truths = scenario.scales(defaults), scenario.truth(defaults)
    except (ArithmeticError, LookupError, TypeError, ValueError, RuntimeError):
        sizes, truths = {}, {}
    out = {}
    for key in keys:
        size = next((s for s in (_size(sizes.get(key)), _size(truths.get(key)), _size((truth or {}).get(key)))
                     if s is not None), None)
        out[key] = engineering(size, scenario.unit(key))
    return out


def _regex(tag: str) -> str:
    """A Custom Scalars pattern that matches ``tag`` and nothing else."""
    return f"^{re.escape(tag)}$"


def traced_members(trace, batch: int) -> list[int]:
    """The members traced individually (and drawn in the figures): the chosen ones that exist, at most
    ``TRACED_DEFAULT``, else the first ``TRACED_DEFAULT``."""
    chosen = sorted({int(b) for b in trace if 0 <= int(b) < batch}) if trace else []
    return chosen[:TRACED_DEFAULT] if chosen else list(range(min(TRACED_DEFAULT, batch)))


@dataclass(frozen=True)
class _KeyTags:
    """The tags of one estimate."""

    scaled: Scaled
    estimate: str
    error: str
    members: dict[int, str]
    band: str           # the estimate again, beside low and high (a Custom Scalars margin chart reads one run)
    low: str
    high: str
    centre: str         # the centre of the confidence band over time, beside lower and upper (likewise)
    lower: str
    upper: str
    tolerance: float | None


class Monitor:
    """The TensorBoard writers of one run (see the module docstring for the tags)."""

    def __init__(self, out: Path, run):
        self.run, self.batch, self.out = run, run.batch, Path(out)
        self.traced = traced_members(run.trace, run.batch) if run.batch > 1 else []
        self.shared_truth = {k: float(v) for k, v in run.truth.items() if isinstance(v, (int, float))}
        self.truth = {k: np.asarray(v if isinstance(v, (list, tuple)) else [v] * run.batch, dtype=np.float64)
                      for k, v in run.truth.items() if v is not None}
        self.history = dict(getattr(run, "truth_history", None) or {})     # truths that change during the run
        # The initial model's estimates (theta at its start), drawn in the figures; unknown for a resumed run.
        self.initial = None if run.k else {k: v.detach().to(torch.float64).cpu() for k, v in
                                           run.scenario.estimates(run.graph, run.settings).items()}
        keys = list(dict.fromkeys([*run.truth, *(self.initial or {})]))
        self.scales = estimate_scales(run.scenario, keys, run.truth)
        self._tags: dict[str, _KeyTags] = {}
        y_unit = run.scenario.unit("y", run.settings)
        # The model error in dB (20 log10 of its rms in the unit of y): it falls by decades during a run, and
        # TensorBoard's data tables show four decimals, which would read 0 for the small values at the end.
        self.z_unit = f"[dB re 1 {y_unit}]" if y_unit else "[dB re 1 unit of y]"
        self.z_tag = f"{MODEL_ERROR}/z rms {self.z_unit}"
        self.z_members = {b: f"members/z rms m{b} {self.z_unit}" for b in self.traced}
        self.ident = run.graph.role("estimator")
        self.theta_tags = [f"theta/{name}" for name in self.ident.theta_names]
        self.detectors = [name for name, blk in run.graph.blocks.items() if isinstance(blk, ChangeDetector)]
        self.dt = run.graph.known_sample_time()
        if getattr(run, "tb_origin", None) is None:
            run.tb_origin = time.time() - run.k * (self.dt or 0.0)
        self.origin = float(run.tb_origin)
        out.mkdir(parents=True, exist_ok=True)
        # A resumed run continues from its checkpoint at step k, saved after the log at k: TensorBoard drops what
        # the earlier writers wrote after it (a run stopped between its checkpoint and its end).
        self.purge = run.k + 1 if run.k > 0 else None
        self.writer = EventFile(out, self.purge, start=self.start(""))
        self.siblings: dict[str, EventFile] = {}    # made by their first event (``sibling``)
        self.n_logs = 0
        self.logged: list[int] = []     # the steps logged by this writer
        if run.k == 0:
            settings = "\n".join(f"| {k} | {setting_text(v)} |" for k, v in run.settings.items())
            table = (f"| setting | value |\n|---|---|\n{settings}" if settings else
                     "No settings: the graph was built in Python, with its values in its blocks.")
            axis = "\n\nThe x axis: the step is the sample index k"
            axis += (f"; the simulated time is k dt, dt = {self.dt:g} s (step 1000 = {1000 * self.dt:g} s)."
                     if self.dt else ".")
            self.writer.add_text("settings", table + axis, 0, walltime=self.origin)
            self.writer.add_custom_scalars(self.layout(keys))
            if self.initial:
                self._log_estimates(0, self.initial)

    def start(self, role: str) -> float:
        """The wall time of the first event of the writer of ``role`` (``ROLES``; "" the run itself), which orders
        the run and its siblings in TensorBoard's run list."""
        return self.origin + 1e-3 * ROLES.index(role)

    def sibling(self, role: str) -> EventFile:
        """The writer of the sibling run ``role`` (made at its first use: a run without a truth has no truth
        run)."""
        found = self.siblings.get(role)
        if found is None:
            found = self.siblings[role] = EventFile(self.out / role, self.purge, start=self.start(role))
        return found

    # --- tags ------------------------------------------------------------------------------------------------
    def tags(self, key: str) -> _KeyTags:
        """The tags of estimate ``key`` (in its scaled unit)."""
        found = self._tags.get(key)
        if found is None:
            scaled = self.scales.get(key) or estimate_scales(self.run.scenario, [key], self.run.truth)[key]
            self.scales[key] = scaled
            u = scaled.label
            found = _KeyTags(scaled, f"{ESTIMATES}/{key} {u}", f"{ESTIMATES}/{key} |error| {u}",
                             {b: f"members/{key} m{b} {u}" for b in self.traced}, f"bands/{key} {u}",
                             f"bands/{key} low {u}", f"bands/{key} high {u}", f"intervals/{key} {u}",
                             f"intervals/{key} lower {u}", f"intervals/{key} upper {u}", self.tolerance(key))
            self._tags[key] = found
        return found

    def label(self) -> str:
        """The run's name in chart titles: its folder, or for the shards of a sweep the sweep's folder (their
        charts are the same, and each draws every shard)."""
        if not getattr(self.run, "hparams_session", True):
            return f"{self.out.parent.name} (shards)"
        return self.out.name

    def layout(self, keys: list[str]) -> dict:
        """The Custom Scalars layout, its categories titled with the run's name (``label``): the estimates (each
        drawn in the run and its siblings, with the traced members), their |error|, the margin charts of the
        estimate inside truth ± tolerance and inside its confidence band over time, and the model error with the
        change detectors' alarms. A category holds charts of one kind, in the order of ``keys``. Each pattern is
        anchored and matches one tag, or the traced members' tags; each margin chart's three tags are in the run
        only (its siblings hold none of them)."""
        what = "estimate" if self.batch == 1 else "mean"
        estimates: dict[str, list] = {}
        errors: dict[str, list] = {}
        tolerances: dict[str, list] = {}
        bands: dict[str, list] = {}
        for key in keys:
            t = self.tags(key)
            series = [_regex(t.estimate)]
            if self.traced:
                series.append(f"^members/{re.escape(key)} m[0-9]+ {re.escape(t.scaled.label)}$")
            estimates[f"{key} {t.scaled.label}"] = ["Multiline", series]
            if key in self.truth:
                errors[f"{key}: {'' if self.batch == 1 else 'mean '}|estimate - truth| {t.scaled.label}"] = [
                    "Multiline", [_regex(t.error)]]
            tol = t.tolerance
            if tol:
                tolerances[f"{key}: {what} within truth ± {tol / t.scaled.scale:.3g} {t.scaled.unit}".rstrip()] = [
                    "Margin", [t.band, t.low, t.high]]
            if getattr(self.run, "intervals_on", False):
                centre = "estimate" if self.batch == 1 else "traced members' mean"
                bands[f"{key}: {centre} within its {self.run.level:.0%} band over time {t.scaled.label}"] = [
                    "Margin", [t.centre, t.lower, t.upper]]
        z = [_regex(self.z_tag)] + ([f"^members/z rms m[0-9]+ {re.escape(self.z_unit)}$"] if self.traced else [])
        model_error = {f"z rms {self.z_unit}": ["Multiline", z]}
        for name in self.detectors:
            model_error[f"{name}: alarmed members [%]"] = ["Multiline", [_regex(self.detection_tag(name))]]
        label = self.label()
        # The Custom Scalars dashboard lays a category's margin charts out in the reverse of the layout's order:
        # they are listed backwards, so that it shows them in the order of ``keys``.
        categories = {f"{label}: estimates": estimates, f"{label}: |estimate - truth|": errors,
                      f"{label}: {what} within truth ± tolerance": dict(reversed(tolerances.items())),
                      f"{label}: {what} within its confidence band": dict(reversed(bands.items())),
                      f"{label}: model error z = y - y_hat": model_error}
        return {title: charts for title, charts in categories.items() if charts}

    def detection_tag(self, name: str) -> str:
        """The tag of change detector ``name``'s share of alarmed members, beside the model error it watches."""
        return f"{MODEL_ERROR}/{name} alarmed members [%]"

    def tolerance(self, key: str) -> float | None:
        """Half-width of the band around a shared truth: the scenario's requirement on the estimate where it has
        one, else 1% of the truth (None without a shared, nonzero-band truth)."""
        truth = self.shared_truth.get(key)
        if truth is None:
            return None
        for req in self.run.scenario.requirements:
            if req.key == f"estimates.{key}" and req.kind in ("abs_err", "rel_err"):
                return req.bound if req.kind == "abs_err" else req.bound * abs(truth)
        return 0.01 * abs(truth) or None

    def wall(self, step: int) -> float:
        """The wall time of an event at ``step``: the run's origin plus the simulated time (real time where the
        graph has no sample time)."""
        return self.origin + step * self.dt if self.dt else time.time()

    # --- logging ---------------------------------------------------------------------------------------------
    def log(self, step: int, z_rms: torch.Tensor, estimates: dict[str, torch.Tensor]) -> None:
        """Log the batch at ``step``: z rms (B,) over the last interval and the estimates, each (B,) (CPU)."""
        z = z_rms.numpy()
        z_ok = z if self.batch == 1 else z[np.isfinite(z)]
        main = [(self.z_tag, float(db(np.sqrt((z_ok ** 2).mean()))) if z_ok.size else math.nan)]
        band = {name: [] for name in BAND}
        if self.batch > 1:
            self._spread(z_ok, z, self.z_members, db, self.z_tag, main, band)
        ident = self.ident
        theta = ident.theta_free().detach().to(torch.float64).cpu().numpy()
        main += zip(self.theta_tags, (theta[0] if self.batch == 1 else _column_means(theta)).tolist())
        if self.batch > 1:
            main.append(("health/diverged", float((~ident.alive).sum())))
        for name, found in change_report(self.run.graph).items():
            alarmed = found["first_alarm_step"] >= 0
            main.append((self.detection_tag(name), 100.0 * float(alarmed.double().mean())))
        self._log_estimates(step, estimates, main, band)
        self.logged.append(step)
        if self.batch >= HISTOGRAM_MIN and self.n_logs % 10 == 0:
            self._histograms(step, {"z rms": z_ok, **{k: v.numpy() for k, v in estimates.items()}})
        self.n_logs += 1

    def _log_estimates(self, step: int, estimates: Mapping[str, torch.Tensor], main: list | None = None,
                       band: dict | None = None) -> None:
        """Write one event per writer at ``step``: ``main`` (tag, value) pairs and the estimates' values in the
        run; under each estimate's tag its truth in ``truth/`` and the band's edges in ``lower/`` and ``upper/`` (a
        batch: the 10% and 90% quantiles across the members; one member: truth -+ tolerance)."""
        main = [] if main is None else main
        band = {name: [] for name in BAND} if band is None else band
        truth_run = []
        now = step * self.dt if self.dt else float(step)
        for key, v in estimates.items():
            t = self.tags(key)
            scale = t.scaled.scale
            a = v.numpy()
            ok = a if self.batch == 1 else a[np.isfinite(a)]
            mean = float(ok.mean()) / scale if ok.size else math.nan
            main.append((t.estimate, mean))
            truth, shared = self.truth.get(key), self.shared_truth.get(key)
            if key in self.history:                   # a truth that changes: its value at this step
                shared = truth_at(self.history[key], now)
                truth = np.full(self.batch, shared)
            if truth is not None:
                err = np.abs(a - truth)
                err = err if self.batch == 1 else err[np.isfinite(err)]
                main.append((t.error, float(err.mean()) / scale if err.size else math.nan))
            if shared is not None:
                truth_run.append((t.estimate, shared / scale))
                tol = t.tolerance
                if tol:
                    low, high = (shared - tol) / scale, (shared + tol) / scale
                    main += [(t.band, mean), (t.low, low), (t.high, high)]
                    if self.batch == 1:
                        band[LOW].append((t.estimate, low))
                        band[HIGH].append((t.estimate, high))
            if self.batch > 1:
                self._spread(ok, a, t.members, lambda x, scale=scale: x / scale, t.estimate, main, band)
        wall = self.wall(step)
        self.writer.scalars(step, wall, main)
        for role, values in ((LOW, band[LOW]), (TRUTH, truth_run), (HIGH, band[HIGH])):
            if values:
                self.sibling(role).scalars(step, wall, values)

    def _spread(self, ok: np.ndarray, values: np.ndarray, members: Mapping[int, str], shown, tag: str,
                main: list, band: dict) -> None:
        """The traced members' values (into ``main``) and the band's quantiles over the finite values ``ok``
        (into ``band``, under ``tag``), each as ``shown`` (a function of the value) shows it."""
        main += [(name, float(shown(float(values[b])))) for b, name in members.items()]
        if ok.size:
            for name, q in zip(BAND, quantiles(ok, BAND.values())):
                band[name].append((tag, float(shown(q))))

    def _histograms(self, step: int, values: Mapping[str, np.ndarray]) -> None:
        from torch.utils.tensorboard.summary import histogram
        for key, v in values.items():
            v = v[np.isfinite(v)]
            if v.size:
                if key == "z rms":
                    tag, shown = f"spread/z rms {self.z_unit}", db(v)
                else:
                    scaled = self.tags(key).scaled
                    tag, shown = f"spread/{key} {scaled.label}", v / scaled.scale
                bins = self.writer.default_bins
                # a value beyond the outermost bins (a member far off, say z = 1e136) is counted in the last bin
                summary = histogram(tag, np.clip(shown, bins[0], bins[-1]), bins)
                self.writer.add_summary(summary, step, self.wall(step))

    def final_intervals(self, found, steps: list[int], band=None) -> None:
        """The confidence band over time, written at the end at each of ``steps`` that the run's history holds:
        ``intervals/<key> lower|upper`` about ``intervals/<key>``, the history members' mean estimate at that step
        (one member: the estimate), for the Custom Scalars margin chart; in a run of one member, where the
        estimate has no tolerance band (no truth), also its edges under the estimate's tag in ``lower/`` and
        ``upper/``. ``found``: the final intervals (``rcotorch.verdict.intervals.Intervals``, or None; batch means
        of their bounds). ``band``: the band over time of the history's members (``Run.band_over_time``: (steps,
        {key: (T, members) half-widths})), where it is finite; the final bounds elsewhere."""
        history = self.run.history
        if found is None or not history["step"]:
            return
        at = {s: i for i, s in enumerate(history["step"])}
        steps = [s for s in sorted(set(steps)) if s in at]
        band_at, widths = ({s: i for i, s in enumerate(band[0])}, band[1]) if band is not None else ({}, {})
        main: dict[int, list] = {s: [] for s in steps}
        edges: dict[int, dict[str, list]] = {s: {LOW: [], HIGH: []} for s in steps}
        rows = [at[s] for s in steps]
        for key in found.estimate:
            lo, hi = _finite(found.lower(key).cpu().numpy()), _finite(found.upper(key).cpu().numpy())
            if not (lo.size and hi.size) or not history.get(key):
                continue
            t = self.tags(key)
            scale = t.scaled.scale
            # every step at once: the history members' values (steps, members), their mean where finite
            v = torch.stack(history[key]).to(torch.float64).cpu().numpy()[rows]
            ok = np.isfinite(v)
            mid = _row_means(v, ok)
            lower, upper = np.full(len(steps), float(lo.mean())), np.full(len(steps), float(hi.mean()))
            hw = widths.get(key)
            banded = [i for i, s in enumerate(steps) if s in band_at]
            if hw is not None and banded:
                below, above = (r.to(torch.float64).cpu().numpy()[self.run.history_members]
                                for r in found.side_ratios(key))
                w = np.asarray(hw)[[band_at[steps[i]] for i in banded]]                  # (steps, m)
                m = w.shape[1]
                inside = ok[banded, :m] & np.isfinite(w)
                has = inside.any(1)          # each side as far as the final interval's, in half-widths
                centre = _row_means(v[banded, :m], inside)
                sel = np.asarray(banded, dtype=np.int64)[has]
                mid[sel] = centre[has]
                lower[sel] = centre[has] - _row_means(w * below[:m], inside)[has]
                upper[sel] = centre[has] + _row_means(w * above[:m], inside)[has]
            own = self.batch == 1 and not t.tolerance
            for i in np.flatnonzero(ok.any(1)).tolist():
                step, low, high = steps[i], float(lower[i]) / scale, float(upper[i]) / scale
                main[step] += [(t.centre, float(mid[i]) / scale), (t.lower, low), (t.upper, high)]
                if own:
                    edges[step][LOW].append((t.estimate, low))
                    edges[step][HIGH].append((t.estimate, high))
        for step in steps:
            if main[step]:
                self.writer.scalars(step, self.wall(step), main[step])
            for role, values in edges[step].items():
                if values:
                    self.sibling(role).scalars(step, self.wall(step), values)

    def figures(self, pngs: dict[str, bytes], out: Path) -> None:
        """Save the figures (PNG bytes, ``rcotorch.run.figures.png``) in ``out`` and as images under ``figures/``
        (TensorBoard gets the PNG file's bytes)."""
        from .outputs import atomic_write
        for name, data in pngs.items():
            atomic_write(out / f"{name}.png", lambda f, data=data: f.write(data))
        write_images(self.writer, pngs, self.run.k, self.wall(self.run.k))

    def flush(self) -> None:
        for w in (self.writer, *self.siblings.values()):
            w.flush()

    def close(self, summary: dict) -> None:
        """The batch's final health counts in the run; the run's HParams session in the sibling run ``verdict/``
        (``write_session``: its settings, status and requirements; ``final_values`` as its metrics); then the
        writers are closed. TensorBoard's HParams looks a session's metrics up in its own run and the runs below
        it, and finds none for a session at the top of its logdir (a run opened on its own folder, named "."):
        so the session is a run of its own, below the run's folder."""
        k, wall = self.run.k, self.wall(self.run.k)
        if self.batch > 1:
            counts = [(f"health/{status}", float(count)) for status, count in summary["health"]["counts"].items()
                      if count or status not in ("undetermined", "biased")]
            self.writer.scalars(k, wall, counts)
        if getattr(self.run, "hparams_session", True):      # a sweep writes its own sessions (rcotorch.run.sweep)
            hparams = {k: v for k, v in summary["settings"].items() if isinstance(v, (int, float, str, bool))}
            # a graph built in Python shows the name its figures and charts carry (the one given, or its folder's)
            shown = getattr(self.run.scenario, "figure_name", None) or summary["scenario"]
            hparams.update(scenario=shown, batch=summary["batch"])
            session = self.sibling(SESSION)
            write_session(session, hparams, summary, scenario=self.run.scenario)
            session.scalars(k, wall, list(final_values(summary, scenario=self.run.scenario).items()))
        for w in (self.writer, *self.siblings.values()):
            w.close()


def quantiles(values: np.ndarray, qs: Iterable[float]) -> list[float]:
    """Quantiles of a non-empty 1-d array, interpolated linearly between the order statistics around each
    (numpy's and torch's default method), which a partial sort (``np.partition``) finds without sorting the
    rest."""
    n = values.size
    places = []
    for q in qs:
        pos = q * (n - 1)
        i = min(int(pos), n - 1)
        places.append((i, min(i + 1, n - 1), pos - i))
    v = np.partition(values, sorted({k for i, j, _ in places for k in (i, j)}))
    return [float(v[i] + (v[j] - v[i]) * f) for i, j, f in places]


def _column_means(a: np.ndarray) -> np.ndarray:
    """The mean of each column over its finite entries (NaN for none), without numpy's warning."""
    return _means(a, np.isfinite(a), 0)


def _row_means(a: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """The mean of each row of ``a`` over the entries ``ok`` (NaN for none)."""
    return _means(a, ok, 1)


def _means(a: np.ndarray, ok: np.ndarray, axis: int) -> np.ndarray:
    """The means of ``a`` along ``axis`` over the entries ``ok`` (NaN where there is none), without numpy's
    warning."""
    n = ok.sum(axis)
    return np.where(n > 0, np.where(ok, a, 0.0).sum(axis) / np.maximum(n, 1), math.nan)


def _finite(v: np.ndarray) -> np.ndarray:
    return v[np.isfinite(v)]


def db(rms):
    """20 log10 of an rms (a number or an array): ``DB_FLOOR`` where it is zero, NaN where it is NaN."""
    if isinstance(rms, float):                      # one number (a float or a NumPy float64)
        return 20.0 * math.log10(rms) if rms > 0 else DB_FLOOR if rms == 0 else math.nan
    x = np.asarray(rms, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(x > 0, 20.0 * np.log10(np.where(x > 0, x, 1.0)), np.where(x == 0, DB_FLOOR, math.nan))
    return out if out.ndim else float(out)


def write_images(writer: EventFile, pngs: Mapping[str, bytes], step: int, wall: float | None = None) -> None:
    """PNG bytes as images ``figures/<name>`` (TensorBoard gets the PNG file's bytes)."""
    import io

    from PIL import Image
    from tensorboard.compat.proto.summary_pb2 import Summary
    for name, data in pngs.items():
        im = Image.open(io.BytesIO(data))
        image = Summary.Image(height=im.height, width=im.width, colorspace=len(im.getbands()),
                              encoded_image_string=data)
        writer.add_summary(Summary(value=[Summary.Value(tag=f"figures/{name}", image=image)]), step,
                                       wall)


def write_sweep_figures(out: str | Path, rows: list[Mapping[str, Any]], swept: list[str], scenario=None,
                        run: str | Path | None = None, drawn: Callable[[], dict[str, bytes]] | None = None
                        ) -> list[Path]:
    """The figures of a finished sweep (``rcotorch.run.figures.sweep_figures``: each estimate and its |error| against
    each swept setting) as PNG files ``out/sweep_<setting>.png`` and as images ``figures/sweep_<setting>`` of
    the TensorBoard run in ``run`` (a sweep: its first shard's folder, so that the sweep's folder is no run of
    its own and the sweep adds no run to TensorBoard's list; default ``out``). ``drawn``: where the figures are
    being drawn already (``draw_sweep_figures``), the function that waits for their PNG bytes. Returns the files
    written."""
    from .outputs import MANIFEST, atomic_write, list_in_manifest
    out = Path(out)
    drawn = (drawn or draw_sweep_figures(rows, swept, scenario))()
    paths = []
    for name, data in drawn.items():
        atomic_write(out / f"{name}.png", lambda f, data=data: f.write(data))
        paths.append(out / f"{name}.png")
    if drawn:
        with EventFile(Path(run) if run is not None else out) as w:
            write_images(w, drawn, 0)
        if run is not None and (Path(run) / MANIFEST).exists():      # a finished shard lists what it holds
            list_in_manifest(run, [w.path])
    return paths


def draw_sweep_figures(rows: list[Mapping[str, Any]], swept: list[str], scenario=None, drawing=None
                       ) -> Callable[[], dict[str, bytes]]:
    """Start drawing a finished sweep's figures: in ``drawing`` (a ``rcotorch.run.drawing.DrawingProcess``), which
    draws them while the caller goes on, else here when the returned function is called; that function returns
    their PNG bytes {name: bytes}. ``scenario``: a name or object (the units and the name in the titles)."""
    from .figure_data import sweep_figure_data
    data = sweep_figure_data(rows, swept, _scenario(scenario) if isinstance(scenario, str) else scenario)
    if drawing is not None and drawing.started:
        return drawing.draw(data)

    def here() -> dict[str, bytes]:
        from .figures import pngs, sweep_figures
        return pngs(sweep_figures(data))
    return here


def final_values(summary: Mapping[str, Any], scenario=None) -> dict[str, float]:
    """The metrics of an HParams session, batch means where there are several members: each estimate and its
    |estimate - truth| (``final/<key> [<unit>]``, ``final/<key> |error| [<unit>]``; scaled as the run's tags,
    ``estimate_scales``; ``scenario``: the scenario object, else the one named in the summary); the scenario's
    metrics (``metrics/<metric>``); each estimate's truth, interval and the mean bias of the members biased in it
    (``verdict/<key> truth|lower|upper|bias [<unit>]``), the members diverged, biased and passing the
    requirements (``verdict/diverged``, ``verdict/biased``, ``verdict/requirements passed``) and the first alarm
    of each change detector (``verdict/<detector> first alarm [s]``, the mean over the members that alarmed).
    HParams sorts its metric columns by tag and shows the first five until others are ticked: these open on
    the estimates and their errors. Runs and sweep members write the same tags, so they share the columns; and
    none of them is a tag of the charts along the run."""
    out: dict[str, float] = {}
    batch = int(summary.get("batch", 1))

    def per_member(v) -> np.ndarray:     # one value per member, NaN for None
        return np.array(v if isinstance(v, list) else [v] * batch, dtype=np.float64)

    scales = _summary_scales(summary, scenario)
    intervals = summary.get("intervals") or {}
    for key, v in summary["estimates"].items():
        scaled = scales[key]
        u, est = scaled.label, per_member(v)
        out[f"final/{key} {u}"] = _mean(est, scaled.scale)
        truth = summary.get("truth", {}).get(key)
        if truth is not None:
            out[f"final/{key} |error| {u}"] = _mean(np.abs(est - per_member(truth)), scaled.scale)
            out[f"verdict/{key} truth {u}"] = _mean(per_member(truth), scaled.scale)
        iv = intervals.get(key) or {}
        if "lower" in iv and "upper" in iv:
            out[f"verdict/{key} lower {u}"] = _mean(per_member(iv["lower"]), scaled.scale)
            out[f"verdict/{key} upper {u}"] = _mean(per_member(iv["upper"]), scaled.scale)
        if iv.get("bias") is not None:                   # the mean bias of the members whose estimate is biased
            bias = np.ravel(np.array(iv["bias"], dtype=object))
            out[f"verdict/{key} bias {u}"] = _mean(per_member([np.nan if b is None else float(b) for b in bias]),
                                                   scaled.scale)
    for key, v in summary["metrics"].items():
        out[f"metrics/{key}"] = _mean(per_member(v))
    for name, found in (summary.get("changes") or {}).items():
        if "first_alarm_s" in found:
            out[f"verdict/{name} first alarm [s]"] = _mean(per_member(found["first_alarm_s"]))
    out["verdict/diverged"] = float(member_status(summary).count("diverged"))
    out["verdict/biased"] = float(member_status(summary).count("biased"))
    passed = requirements_passed(summary)
    if passed is not None:
        out["verdict/requirements passed"] = float(sum(passed))
    return {k: v for k, v in out.items() if v is not None}


def _summary_scales(summary: Mapping[str, Any], scenario=None) -> dict[str, Scaled]:
    """``estimate_scales`` for a summary's estimates (plain units where its scenario is unknown)."""
    sc = _scenario(scenario if scenario is not None else summary.get("scenario"))
    keys = list(summary["estimates"])
    if sc is None:
        return {k: engineering(_size(summary.get("truth", {}).get(k)), "") for k in keys}
    return estimate_scales(sc, keys, summary.get("truth"))


def _scenario(which):
    """The scenario object of a name or object (None where no scenario of that name is known)."""
    from ..errors import RcoError
    from . import scenario as scenarios
    if which is None:
        return None
    try:
        return scenarios.get(which)
    except (RcoError, LookupError, ImportError):
        return None


def _mean(values: np.ndarray, scale: float = 1.0) -> float | None:
    """The mean of the finite values (divided by ``scale``), None where there is none."""
    values = values[np.isfinite(values)]
    return float(values.mean()) / scale if values.size else None


def setting_text(value) -> str:
    """A setting for display: a per-member list as its range and count."""
    if isinstance(value, list) and len(value) > 4:
        numbers = [v for v in value if isinstance(v, (int, float))]
        span = f"{min(numbers):g}..{max(numbers):g}, " if len(numbers) == len(value) else ""
        return f"per member ({span}{len(value)} values)"
    return str(value)


def member_status(summary: Mapping[str, Any]) -> list[str]:
    """Each member's status: from ``summary['status']`` where the run reports one (a word, or one per member,
    or dicts with a 'status'), else 'diverged' for the members in ``summary['diverged']`` and 'finished'."""
    batch = int(summary.get("batch", 1))
    given = summary.get("status")
    if isinstance(given, str):
        return [given] * batch
    if isinstance(given, list) and len(given) == batch:
        return [g if type(g) is str else g.get("status", "finished") if isinstance(g, Mapping) else str(g)
                for g in given]
    diverged = {d["member"] for d in summary.get("diverged", [])}
    return ["diverged" if b in diverged else "finished" for b in range(batch)]


def requirements_passed(summary: Mapping[str, Any]) -> list[bool] | None:
    """Whether each member passes every requirement of the run (None when it has none)."""
    checks = summary.get("requirements") or {}
    if not checks:
        return None
    batch = int(summary.get("batch", 1))
    out = [True] * batch
    for chk in checks.values():
        per = chk.get("member_pass", chk["pass"])
        per = per if isinstance(per, list) else [per] * batch
        out = [a and bool(b) for a, b in zip(out, per)]
    return out


def status_text(summary: Mapping[str, Any]) -> str:
    """One member's status with why it is not converged, undetermined or biased (``summary['health']['why']``)
    and when each change detector first alarmed ('not_converged (theta_change above 0.02; detector alarm at
    60.02 s)', 'biased: dC'), or the count of each status in a batch ('converged 6, diverged 2')."""
    status = member_status(summary)
    if len(status) > 1:
        return ", ".join(f"{s} {n}" for s, n in sorted(Counter(status).items()))
    text, notes = status[0], []
    why = (summary.get("health") or {}).get("why")
    why = why[0] if isinstance(why, list) and why else why
    if isinstance(why, str) and why and why != text:
        if why.startswith(text):                       # 'biased: dC'
            text = why
        else:
            notes.append(why)
    for name, found in (summary.get("changes") or {}).items():
        first = found.get("first_alarm_s")
        first = first[0] if isinstance(first, list) and first else first
        if isinstance(first, (int, float)) and math.isfinite(first):
            notes.append(f"{name} alarm at {first:g} s")
    return f"{text} ({'; '.join(notes)})" if notes else text


def requirements_text(summary: Mapping[str, Any]) -> str:
    """Whether the members pass every requirement: 'pass' or 'FAIL' (one member), 'pass 7 of 8' (a batch),
    'none' where the run has no requirements."""
    passed = requirements_passed(summary)
    if passed is None:
        return "none"
    if len(passed) == 1:
        return "pass" if passed[0] else "FAIL"
    return f"pass {sum(passed)} of {len(passed)}"


def session_status(summary: Mapping[str, Any]) -> str:
    """HParams' session status: failure when a member diverged, success when every member converged."""
    status = set(member_status(summary))
    if "diverged" in status:
        return "STATUS_FAILURE"
    return "STATUS_SUCCESS" if status == {"converged"} else "STATUS_UNKNOWN"


def hparam_names(hparams: Mapping[str, Any], scenario=None) -> dict[str, Any]:
    """The hyperparameters with each setting of the scenario named with its unit (``C [F]``, ``C [N s/m]``),
    so that settings of different scenarios that share a name and not a unit are separate columns;
    ``scenario``: the scenario object, else the one named by ``hparams['scenario']``."""
    sc = _scenario(scenario if scenario is not None else hparams.get("scenario"))
    if sc is None:
        return dict(hparams)
    out = {}
    for key, value in hparams.items():
        unit = sc.unit(key) if key in sc.settings else ""
        out[f"{key} [{unit}]" if unit else key] = value
    return out


def write_session(writer: EventFile, hparams: Mapping[str, Any], summary: Mapping[str, Any],
                  scenario=None) -> None:
    """Make the writer's run an HParams session with these hyperparameters (settings named with their units,
    ``hparam_names``), the status of ``summary``'s members (``STATUS_HPARAM``, ``status_text``; the session's
    own status, ``session_status``) and whether they pass the requirements (``REQUIREMENTS_HPARAM``,
    ``requirements_text``). No experiment summary is written: TensorBoard then builds the
    table from every session under its logdir, so runs of different scenarios (with different settings) can
    share one folder."""
    from tensorboard.compat.proto.summary_pb2 import Summary, SummaryMetadata
    from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2
    from torch.utils.tensorboard.summary import hparams as hparams_summaries

    named = hparam_names(hparams, scenario)
    _, start, _ = hparams_summaries({**named, STATUS_HPARAM: status_text(summary),
                                     REQUIREMENTS_HPARAM: requirements_text(summary)}, {})
    end = plugin_data_pb2.HParamsPluginData(
        session_end_info=plugin_data_pb2.SessionEndInfo(status=api_pb2.Status.Value(session_status(summary))),
        version=metadata.PLUGIN_DATA_VERSION)
    meta = SummaryMetadata(plugin_data=SummaryMetadata.PluginData(plugin_name=metadata.PLUGIN_NAME,
                                                                  content=end.SerializeToString()))
    writer.add_summary(start)
    writer.add_summary(Summary(value=[Summary.Value(tag=metadata.SESSION_END_INFO_TAG,
                                                                metadata=meta)]))
