"""TensorBoard monitoring of a run: its own run and sibling runs in TensorBoard's run list (the truth and, for a
batch, the 10% and 90% quantiles), a few chosen member traces, histograms, figures, a Custom Scalars layout and
an HParams session.

Tags, grouped so that TensorBoard's Time Series tab opens on what matters (it sorts groups by name, capitals
first, and expands the first two):

* ``Estimates/<key> [<unit>]``: the estimate (a batch: its mean) in the run's folder, the truth under the same
  tag in the sibling run ``truth/`` and the batch's 10% and 90% quantiles in ``q10/`` and ``q90/``, so that one
  chart draws estimate, truth and band in their own colours; ``Estimates/<key> |error| [<unit>]`` beside it
  (|estimate - truth|, batch mean);
* ``Model error/z rms [<unit of y>]`` (rms of z over the batch and the log interval; its quantiles in ``q10/``
  and ``q90/``);
* ``members/<key> m<b> [<unit>]`` and ``members/z rms m<b>`` (the traced members of a batch: the ones the
  figures draw), ``bands/<key> low|high [<unit>]`` (truth ± the requirement's tolerance), ``intervals/<key>
  lower|upper [<unit>]`` (the final confidence interval, written at every logged step at the end),
  ``theta/<entry>`` (batch mean), ``health/diverged`` and at the end ``health/<status>`` (members, batches),
  ``final/`` (the scenario's metrics, diverged members, requirements passed), histograms ``spread/<key>
  [<unit>]`` (batches from 16 members), images ``figures/<name>``, the settings as text.

Estimates are shown in engineering notation: ``<unit>`` carries the SI prefix that puts the scenario's size of
the estimate (``Scenario.scales``, else its default truth, else this run's truth) in [1, 1000), e.g.
``Estimates/C [uF]`` for 23.5e-6 F; the logged value is the estimate divided by ``Scaled.scale``. A unit that
takes no prefix gets a power of ten instead (``[1e-3 1/s^2]``, ``[-]`` without unit or scaling).

The x axis: the step is the sample index. Where the graph has a sample time dt, each scalar event's wall time is
the run's origin plus the simulated time, ``origin + k dt`` (the origin is kept in the checkpoint, so a resumed
run continues the same axis), and a fresh run logs the initial model's estimates at step 0: TensorBoard's
"Relative" x axis then reads simulated seconds.

Custom Scalars: per run (or per sweep) a category of charts: each estimate with truth, band and traced members
(patterns anchored, so that a chart draws only its own tags), its |error|, margin charts of the estimate inside
truth ± tolerance and inside its final confidence interval; the model error likewise. HParams: the run itself
is the session (its settings, named with their units, its status, whether it passes the requirements, and
final values). TensorBoard's HParams table shows five hyperparameter columns until others are ticked: the first
five of its list, which holds those that differ between sessions first, each part in name order (capitals
before lower case). The requirements and the status are named ``*requirements`` and ``*status``
(``REQUIREMENTS_HPARAM``, ``STATUS_HPARAM``) so that they lead both parts; the metrics sort by tag, so the
table's metric columns open on each estimate, its truth and its error.
"""

from __future__ import annotations

import math
import re
import time
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..estimator.tracking import change_report
from .scenario import truth_at

TRACED_DEFAULT = 8     # members traced individually when the run does not choose them (the figures draw them)
HISTOGRAM_MIN = 16     # histograms across the batch from this batch size
BAND = {"q10": 0.1, "q90": 0.9}     # sibling runs of a batch: the quantiles that bound the band
TRUTH = "truth"        # sibling run of the truth
ESTIMATES, MODEL_ERROR = "Estimates", "Model error"
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
    low: str
    high: str
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
        self.z_tag = f"{MODEL_ERROR}/z rms [{y_unit or '-'}]"
        self.z_members = {b: f"members/z rms m{b} [{y_unit or '-'}]" for b in self.traced}
        self.ident = run.graph.role("estimator")
        self.theta_tags = [f"theta/{name}" for name in self.ident.theta_names]
        self.dt = run.graph.known_sample_time()
        if getattr(run, "tb_origin", None) is None:
            run.tb_origin = time.time() - run.k * (self.dt or 0.0)
        self.origin = float(run.tb_origin)
        out.mkdir(parents=True, exist_ok=True)
        # A resumed run continues from its checkpoint at step k, saved after the log at k: TensorBoard drops what
        # the earlier writers wrote after it (a run stopped between its checkpoint and its end).
        purge = run.k + 1 if run.k > 0 else None
        self.writer = EventFile(out, purge)
        names = ([TRUTH] if self.shared_truth else []) + (list(BAND) if self.batch > 1 else [])
        self.siblings = {name: EventFile(out / name, purge) for name in names}
        self.n_logs = 0
        self.logged: list[int] = []     # the steps logged by this writer
        if run.k == 0:
            settings = "\n".join(f"| {k} | {setting_text(v)} |" for k, v in run.settings.items())
            self.writer.add_text("settings", f"| setting | value |\n|---|---|\n{settings}", 0, walltime=self.origin)
            self.writer.add_custom_scalars(self.layout(keys))
            if self.initial:
                self._log_estimates(0, self.initial)

    # --- tags ------------------------------------------------------------------------------------------------
    def tags(self, key: str) -> _KeyTags:
        """The tags of estimate ``key`` (in its scaled unit)."""
        found = self._tags.get(key)
        if found is None:
            scaled = self.scales.get(key) or estimate_scales(self.run.scenario, [key], self.run.truth)[key]
            self.scales[key] = scaled
            u = scaled.label
            found = _KeyTags(scaled, f"{ESTIMATES}/{key} {u}", f"{ESTIMATES}/{key} |error| {u}",
                             {b: f"members/{key} m{b} {u}" for b in self.traced}, f"bands/{key} low {u}",
                             f"bands/{key} high {u}", f"intervals/{key} lower {u}", f"intervals/{key} upper {u}",
                             self.tolerance(key))
            self._tags[key] = found
        return found

    def label(self) -> str:
        """The run's name in chart titles: its folder, or for the shards of a sweep the sweep's folder (their
        charts are the same, and each draws every shard)."""
        if not getattr(self.run, "hparams_session", True):
            return f"{self.out.parent.name} (shards)"
        return self.out.name

    def layout(self, keys: list[str]) -> dict:
        """The Custom Scalars layout: one category for the estimates, one for the model error, titled with the
        run's name (``label``). Each pattern is anchored and matches one tag, or the traced members' tags."""
        charts: dict[str, list] = {}
        what = "estimate" if self.batch == 1 else "mean"
        for key in keys:
            t = self.tags(key)
            series = [_regex(t.estimate)]
            if self.traced:
                series.append(f"^members/{re.escape(key)} m[0-9]+ {re.escape(t.scaled.label)}$")
            charts[f"{key} {t.scaled.label}"] = ["Multiline", series]
            if key in self.truth:
                charts[f"{key}: {'' if self.batch == 1 else 'mean '}|estimate - truth|"] = [
                    "Multiline", [_regex(t.error)]]
            if getattr(self.run, "intervals_on", False):
                charts[f"{key}: {what} within its {self.run.level:.0%} band (the final interval at the end)"] = [
                    "Margin", [t.estimate, t.lower, t.upper]]
            tol = t.tolerance
            if tol:
                charts[f"{key}: {what} within truth ± {tol / t.scaled.scale:.3g} {t.scaled.unit}".rstrip()] = [
                    "Margin", [t.estimate, t.low, t.high]]
        z = [_regex(self.z_tag)] + ([f"^members/z rms m[0-9]+ {re.escape(self.z_tag.rsplit(' ', 1)[1])}$"]
                                    if self.traced else [])
        label = self.label()
        return {f"{label}: estimates vs truth": charts,
                f"{label}: model error z = y - y_hat": {self.z_tag.split("/", 1)[1]: ["Multiline", z]}}

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
        main = [(self.z_tag, float(np.sqrt((z_ok ** 2).mean())) if z_ok.size else math.nan)]
        band = {name: [] for name in BAND} if self.batch > 1 else None
        if band is not None:
            self._spread(z_ok, z, self.z_members, 1.0, self.z_tag, main, band)
        ident = self.ident
        theta = ident.theta_free().detach().to(torch.float64).cpu().numpy()
        main += zip(self.theta_tags, (theta[0] if self.batch == 1 else _column_means(theta)).tolist())
        if self.batch > 1:
            main.append(("health/diverged", float((~ident.alive).sum())))
        for name, found in change_report(self.run.graph).items():
            alarmed = found["first_alarm_step"] >= 0
            main.append((f"detection/{name} alarmed members [%]", 100.0 * float(alarmed.double().mean())))
        self._log_estimates(step, estimates, main, band)
        self.logged.append(step)
        if self.batch >= HISTOGRAM_MIN and self.n_logs % 10 == 0:
            self._histograms(step, {"z rms": z_ok, **{k: v.numpy() for k, v in estimates.items()}})
        self.n_logs += 1

    def _log_estimates(self, step: int, estimates: Mapping[str, torch.Tensor], main: list | None = None,
                       band: dict | None = None) -> None:
        """Write one event per writer at ``step``: ``main`` (tag, value) pairs and the estimates' values in the
        run, their truths in ``truth/``, their quantiles in ``q10/``, ``q90/``."""
        main = [] if main is None else main
        if band is None and self.batch > 1:
            band = {name: [] for name in BAND}
        truth_run = []
        now = step * self.dt if self.dt else float(step)
        for key, v in estimates.items():
            t = self.tags(key)
            scale = t.scaled.scale
            a = v.numpy()
            ok = a if self.batch == 1 else a[np.isfinite(a)]
            main.append((t.estimate, float(ok.mean()) / scale if ok.size else math.nan))
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
                    main += [(t.low, (shared - tol) / scale), (t.high, (shared + tol) / scale)]
            if band is not None:
                self._spread(ok, a, t.members, scale, t.estimate, main, band)
        wall = self.wall(step)
        self.writer.scalars(step, wall, main)
        if truth_run:
            self.siblings[TRUTH].scalars(step, wall, truth_run)
        for name, values in (band or {}).items():
            self.siblings[name].scalars(step, wall, values)

    def _spread(self, ok: np.ndarray, values: np.ndarray, members: Mapping[int, str], scale: float, tag: str,
                main: list, band: dict) -> None:
        """The traced members' values (into ``main``) and the band's quantiles over the finite values ``ok``
        (into ``band``, under ``tag``)."""
        main += [(name, float(values[b]) / scale) for b, name in members.items()]
        if ok.size:
            for name, q in zip(BAND, quantiles(ok, BAND.values())):
                band[name].append((tag, q / scale))

    def _histograms(self, step: int, values: Mapping[str, np.ndarray]) -> None:
        from torch.utils.tensorboard.summary import histogram
        for key, v in values.items():
            v = v[np.isfinite(v)]
            if v.size:
                scaled = Scaled(1.0, self.z_tag.rsplit(" [", 1)[1][:-1]) if key == "z rms" else self.tags(key).scaled
                bins = self.writer.default_bins
                # a value beyond the outermost bins (a member far off, say z = 1e136) is counted in the last bin
                shown = np.clip(v / scaled.scale, bins[0], bins[-1])
                summary = histogram(f"spread/{key} {scaled.label}", shown, bins)
                self.writer.add_summary(summary, step, self.wall(step))

    def final_intervals(self, found, steps: list[int], band=None) -> None:
        """The confidence band as ``intervals/<key> lower|upper`` at each of ``steps`` (the logged steps), so that
        the Custom Scalars chart draws the estimate's path inside it. ``found``: the final intervals
        (``rcotorch.verdict.intervals.Intervals``, or None; batch means of their bounds). ``band``: the band over
        time of the history's members (``Run.band_over_time``: (steps, {key: (T, members) half-widths})), drawn
        about their mean estimate at each of its steps, where it is finite; the final bounds elsewhere."""
        if found is None:
            return
        steps = sorted({0, *steps, *self.logged})    # every step the estimates have: the margin chart needs them
        bounds = []
        for key in found.estimate:
            lo, hi = _finite(found.lower(key).cpu().numpy()), _finite(found.upper(key).cpu().numpy())
            if lo.size and hi.size:
                t = self.tags(key)
                bounds += [(t.lower, float(lo.mean()) / t.scaled.scale), (t.upper, float(hi.mean()) / t.scaled.scale)]
        over_time: dict[int, dict[str, float]] = {}
        if band is not None:
            band_steps, widths = band
            for key, hw in widths.items():
                t = self.tags(key)
                values = torch.stack(self.run.history[key]).to(torch.float64)[:, :hw.shape[1]]
                for i, step in enumerate(band_steps):
                    ok = torch.isfinite(hw[i]) & torch.isfinite(values[i])
                    if bool(ok.any()):
                        mid, half = float(values[i][ok].mean()), float(hw[i][ok].mean())
                        over_time.setdefault(step, {})[t.lower] = (mid - half) / t.scaled.scale
                        over_time[step][t.upper] = (mid + half) / t.scaled.scale
        if bounds:
            for step in steps:
                values = dict(bounds) | over_time.get(step, {})
                self.writer.scalars(step, self.wall(step), list(values.items()))

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
        """The batch's final health counts, the final values (``final/``) and the run's HParams session: its
        settings and status; then the writers are closed."""
        k, wall = self.run.k, self.wall(self.run.k)
        values = []
        if self.batch > 1:
            values += [(f"health/{status}", float(count)) for status, count in summary["health"]["counts"].items()
                       if count or status not in ("undetermined", "biased")]
        if getattr(self.run, "hparams_session", True):      # a sweep writes its own sessions (rcotorch.run.sweep)
            values += final_values(summary, logged=True).items()
        if values:
            self.writer.scalars(k, wall, values)
        if getattr(self.run, "hparams_session", True):
            hparams = {k: v for k, v in summary["settings"].items() if isinstance(v, (int, float, str, bool))}
            hparams.update(scenario=summary["scenario"], batch=summary["batch"])
            write_session(self.writer, hparams, summary, scenario=self.run.scenario)
        for w in (self.writer, *self.siblings.values()):
            w.close()


def _scalar_event(values: Iterable[tuple[str, float]]):
    from tensorboard.compat.proto.event_pb2 import Event
    from tensorboard.compat.proto.summary_pb2 import Summary
    return Event(summary=Summary(value=[Summary.Value(tag=tag, simple_value=value) for tag, value in values]))


def _growing_edges(start: float = 1e-12, stop: float = 1e20, factor: float = 1.1) -> list[float]:
    """start, start * factor, ... below stop."""
    edges, v = [], start
    while v < stop:
        edges.append(v)
        v *= factor
    return edges


class EventFile:
    """A TensorBoard event file written in the calling thread: each event framed as a record (its length, the
    masked CRC-32C of the length, the serialized event, the masked CRC-32C of the event) into a buffered file,
    flushed every ``FLUSH_S`` seconds and by ``flush`` and ``close``. Every run's events are written so (the run,
    its siblings, a sweep's sessions): an event costs its serialization and checksum, with no writer thread to
    hand it to. Summaries are made by TensorBoard's and PyTorch's summary functions (``add_summary``).

    Args:
        folder: the run's folder (made if missing).
        purge_step: where a resumed run continues: TensorBoard drops this run's earlier events from that step.
    """

    FLUSH_S = 5.0
    _count = 0

    def __init__(self, folder: Path, purge_step: int | None = None):
        import os
        import socket

        from tensorboard.compat.proto.event_pb2 import Event, SessionLog
        folder.mkdir(parents=True, exist_ok=True)
        EventFile._count += 1
        self.path = folder / (f"events.out.tfevents.{int(time.time()):010d}.{socket.gethostname()}.{os.getpid()}."
                              f"{EventFile._count:04d}")
        self._file = open(self.path, "wb")      # open until close
        self._flushed = time.monotonic()
        self._write(Event(wall_time=time.time(), file_version="brain.Event:2"))
        if purge_step is not None:
            self._write(Event(wall_time=time.time(), step=purge_step, session_log=SessionLog(status=SessionLog.START)))
        self.flush()

    # The histograms' bin edges: TensorBoard's convention, +-1e-12 growing by 10% a bin up to 1e20, and 0.
    default_bins = [-e for e in reversed(_growing_edges())] + [0.0] + _growing_edges()

    def scalars(self, step: int, wall: float, values: Iterable[tuple[str, float]]) -> None:
        """One event holding every (tag, value) pair at ``step`` and wall time ``wall``."""
        event = _scalar_event(values)
        event.step, event.wall_time = step, wall
        self._write(event)

    def add_event(self, event, step: int | None = None, wall: float | None = None) -> None:
        """An event at ``step`` (none: the event's own) and wall time ``wall`` (none: now)."""
        event.wall_time = time.time() if wall is None else wall
        if step is not None:
            event.step = int(step)
        self._write(event)

    def add_summary(self, summary, step: int | None = None, wall: float | None = None) -> None:
        """A ``Summary`` protocol buffer as an event (``add_event``)."""
        from tensorboard.compat.proto.event_pb2 import Event
        self.add_event(Event(summary=summary), step, wall)

    def add_scalar(self, tag: str, value: float, step: int, wall: float | None = None) -> None:
        self.scalars(step, time.time() if wall is None else wall, [(tag, float(value))])

    def add_text(self, tag: str, text: str, step: int, walltime: float | None = None) -> None:
        """Markdown text under ``tag`` (TensorBoard's Text tab)."""
        from torch.utils.tensorboard.summary import text as text_summary
        self.add_summary(text_summary(tag, text), step, walltime)

    def add_custom_scalars(self, layout: Mapping[str, Any]) -> None:
        """The Custom Scalars layout ({section: {title: ['Multiline' or 'Margin', tags]}})."""
        from torch.utils.tensorboard.summary import custom_scalars
        self.add_summary(custom_scalars(layout))

    def __enter__(self) -> EventFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _write(self, event) -> None:
        import struct
        data = event.SerializeToString()
        head = struct.pack("<Q", len(data))
        self._file.write(head + struct.pack("<I", masked_crc32c(head)) + data + struct.pack("<I", masked_crc32c(data)))
        if time.monotonic() - self._flushed > self.FLUSH_S:
            self.flush()

    def flush(self) -> None:
        if not self._file.closed:
            self._file.flush()
            self._flushed = time.monotonic()

    def close(self) -> None:
        if not self._file.closed:
            try:
                self._file.flush()
            finally:
                self._file.close()


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
    ok = np.isfinite(a)
    n = ok.sum(0)
    return np.where(n > 0, np.where(ok, a, 0.0).sum(0) / np.maximum(n, 1), math.nan)


def _finite(v: np.ndarray) -> np.ndarray:
    return v[np.isfinite(v)]


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


def write_sweep_figures(out: str | Path, rows: list[Mapping[str, Any]], swept: list[str], scenario=None) -> list[Path]:
    """The figures of a finished sweep (``rcotorch.run.figures.sweep_figures``: each estimate and its |error| against
    each swept setting) as PNG files ``out/sweep_<setting>.png`` and as images ``figures/sweep_<setting>`` of
    the TensorBoard run in ``out`` (the sweep's folder). Returns the files written."""
    from .figures import pngs, sweep_figures
    from .outputs import atomic_write
    out = Path(out)
    drawn = pngs(sweep_figures(rows, swept, scenario))
    paths = []
    for name, data in drawn.items():
        atomic_write(out / f"{name}.png", lambda f, data=data: f.write(data))
        paths.append(out / f"{name}.png")
    if drawn:
        with EventFile(out) as w:
            write_images(w, drawn, 0)
    return paths


def final_values(summary: Mapping[str, Any], logged: bool = False, scenario=None) -> dict[str, float]:
    """The numbers of an HParams row, batch means where there are several members: ``final/<key>`` for each
    metric, ``final/diverged`` and ``final/requirements passed`` (members). Unless the run ``logged`` its
    estimates (a sweep's member), also what a run's last log holds: ``Estimates/<key> [<unit>]`` and
    ``Estimates/<key> |error| [<unit>]`` (scaled as the run's, ``estimate_scales``; ``scenario``: the scenario
    object, else the one named in the summary) and ``intervals/<key> lower|upper [<unit>]``; so that runs and
    sweep members share the HParams columns."""
    out: dict[str, float] = {}
    batch = int(summary.get("batch", 1))

    def per_member(v) -> np.ndarray:     # one value per member, NaN for None
        return np.array(v if isinstance(v, list) else [v] * batch, dtype=np.float64)

    if not logged:
        scales = _summary_scales(summary, scenario)
        intervals = summary.get("intervals") or {}
        for key, v in summary["estimates"].items():
            scaled = scales[key]
            est = per_member(v)
            out[f"{ESTIMATES}/{key} {scaled.label}"] = _mean(est, scaled.scale)
            truth = summary.get("truth", {}).get(key)
            if truth is not None:
                out[f"{ESTIMATES}/{key} |error| {scaled.label}"] = _mean(np.abs(est - per_member(truth)), scaled.scale)
            if key in intervals:
                out[f"intervals/{key} lower {scaled.label}"] = _mean(per_member(intervals[key]["lower"]), scaled.scale)
                out[f"intervals/{key} upper {scaled.label}"] = _mean(per_member(intervals[key]["upper"]), scaled.scale)
    for key, v in summary["metrics"].items():
        out[f"final/{key}"] = _mean(per_member(v))
    for key, iv in (summary.get("intervals") or {}).items():
        if iv.get("bias") is not None:                   # the mean bias of the members whose estimate is biased
            bias = np.ravel(np.array(iv["bias"], dtype=object))
            out[f"final/{key} bias"] = _mean(per_member([np.nan if b is None else float(b) for b in bias]))
    out["final/diverged"] = float(member_status(summary).count("diverged"))
    out["final/biased"] = float(member_status(summary).count("biased"))
    passed = requirements_passed(summary)
    if passed is not None:
        out["final/requirements passed"] = float(sum(passed))
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
    """One member's status, or the count of each status in a batch ('converged 6, diverged 2')."""
    status = member_status(summary)
    return status[0] if len(status) == 1 else ", ".join(f"{s} {n}" for s, n in sorted(Counter(status).items()))


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


# --- the event files' checksum ---------------------------------------------------------------------------------
# TensorBoard's event records are checksummed (their length and their bytes) with CRC-32C; google-crc32c computes it
# in C.
def crc32c(data: bytes) -> int:
    """The CRC-32C (Castagnoli) of ``data``."""
    import google_crc32c
    return google_crc32c.value(data)


def masked_crc32c(data: bytes) -> int:
    """The masked CRC-32C of TensorBoard's record format."""
    x = crc32c(data)
    return (((x >> 15) | (x << 17)) + 0xA282EAD8) & 0xFFFFFFFF
