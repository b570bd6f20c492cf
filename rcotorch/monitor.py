"""TensorBoard monitoring of a run: one writer per run (one run in TensorBoard's run list), batch aggregates,
a few chosen member traces, histograms, figures, a Custom Scalars layout and an HParams session.

Tags, grouped so that TensorBoard's Time Series tab opens on what matters (it sorts groups by name, capitals
first, and expands the first two):

* ``Estimates/<key>`` next to ``Estimates/<key> truth`` (a batch: ``<key> mean``; with a truth per member,
  ``<key> |error| mean`` instead of the truth);
* ``Model error/z rms`` (rms of z over the batch and the log interval);
* ``errors/<key>`` (|estimate - truth|, batch mean), ``quantiles/<key> q10|q50|q90`` and ``quantiles/z rms ...``
  (batches), ``members/<key> m<b>`` and ``members/z rms m<b>`` (the traced members of a batch),
  ``intervals/<key> lower|upper`` (the final confidence interval, written at every logged step at the end),
  ``theta/<entry>`` (batch mean), ``health/diverged`` (members), ``final/<key>`` (the final values that HParams
  shows, batch means), histograms ``spread/<key>`` (batches from 16 members), images ``figures/<name>``, the
  settings as text.

Custom Scalars: per estimate one chart of estimate (or mean and quantiles), truth and traced members as
separately named series; a margin chart of the estimate (batch mean) inside the band truth ± tolerance (the
scenario's requirement, else 1% of the truth; tags ``bands/<key> low|high``); a margin chart of the estimate
inside its final confidence interval; for batches a margin chart of the mean inside its 10-90% band; the model
error likewise. HParams: the run itself is the session (its settings,
final estimates and errors, status). TensorBoard's HParams table shows five hyperparameter columns until others
are ticked: the first five of its list, which holds those that differ between sessions first, each part in
name order (capitals before lower case). The status is named ``*status`` (``STATUS_HPARAM``) so that it leads
both parts: it is shown by default whatever the settings are called.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter

TRACED_DEFAULT = 3     # members traced individually when the run does not choose them
HISTOGRAM_MIN = 16     # histograms across the batch from this batch size
QUANTILES = (0.1, 0.5, 0.9)
ESTIMATES, MODEL_ERROR = "Estimates", "Model error"
STATUS_HPARAM = "*status"   # '*' sorts before letters and digits: the first column of the HParams table


def _q(q: float) -> str:
    return f"q{round(q * 100):02d}"


class Monitor:
    """The TensorBoard writer of one run (see the module docstring for the tags)."""

    def __init__(self, out: Path, run):
        self.run, self.batch = run, run.batch
        chosen = run.trace if run.trace is not None else range(min(TRACED_DEFAULT, run.batch))
        self.traced = sorted({b for b in chosen if 0 <= b < run.batch}) if run.batch > 1 else []
        self.shared_truth = {k: float(v) for k, v in run.truth.items() if isinstance(v, (int, float))}
        # The initial model's estimates (theta at its start), drawn in the figures; unknown for a resumed run.
        self.initial = None if run.k else {k: v.detach().to(torch.float64).cpu() for k, v in
                                           run.scenario.estimates(run.graph, run.settings).items()}
        out.mkdir(parents=True, exist_ok=True)
        self.writer = SummaryWriter(log_dir=str(out), purge_step=run.k if run.k > 0 else None)
        self.n_logs = 0
        if run.k == 0:
            settings = "\n".join(f"| {k} | {setting_text(v)} |" for k, v in run.settings.items())
            self.writer.add_text("settings", f"| setting | value |\n|---|---|\n{settings}", 0)
            keys = list(dict.fromkeys([*run.truth, *(self.initial or {})]))
            self.writer.add_custom_scalars(self.layout(keys))

    # --- tags ------------------------------------------------------------------------------------------------
    def estimate_tag(self, key: str) -> str:
        return f"{ESTIMATES}/{key}" if self.batch == 1 else f"{ESTIMATES}/{key} mean"

    def layout(self, keys: list[str]) -> dict:
        """The Custom Scalars layout: one category for the estimates, one for the model error."""
        def series(key_tag: str, quantile_tag: str, member_tag: str, extra: list[str]) -> list[str]:
            if self.batch == 1:
                return [key_tag] + extra
            return ([key_tag] + [f"quantiles/{quantile_tag} {_q(q)}" for q in QUANTILES] + extra
                    + [f"members/{member_tag} m{b}" for b in self.traced])

        charts: dict[str, list] = {}
        for key in keys:
            truth = [f"{ESTIMATES}/{key} truth"] if key in self.shared_truth else []
            charts[key] = ["Multiline", series(self.estimate_tag(key), key, key, truth)]
            if getattr(self.run, "intervals_on", False):
                what = "estimate" if self.batch == 1 else "mean"
                charts[f"{key}: {what} within its final {self.run.level:.0%} interval"] = [
                    "Margin", [self.estimate_tag(key), f"intervals/{key} lower", f"intervals/{key} upper"]]
            tol = self.tolerance(key)
            if tol:
                what = "estimate" if self.batch == 1 else "mean"
                charts[f"{key}: {what} within truth ± {tol:.3g}"] = [
                    "Margin", [self.estimate_tag(key), f"bands/{key} low", f"bands/{key} high"]]
            if self.batch > 1:
                charts[f"{key}: mean within the 10-90% band"] = [
                    "Margin", [self.estimate_tag(key), f"quantiles/{key} q10", f"quantiles/{key} q90"]]
        z = {"z rms": ["Multiline", series(f"{MODEL_ERROR}/z rms", "z rms", "z rms", [])]}
        return {"Estimates vs truth": charts, "Model error z = y - y_hat": z}

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

    # --- logging ---------------------------------------------------------------------------------------------
    def log(self, step: int, z_rms: torch.Tensor, estimates: dict[str, torch.Tensor]) -> None:
        """Log the batch at ``step``: z rms (B,) over the last interval and the estimates, each (B,)."""
        w = self.writer
        finite = {key: _finite(v) for key, v in {"z rms": z_rms, **estimates}.items()}
        z_ok = finite["z rms"]
        w.add_scalar(f"{MODEL_ERROR}/z rms", float(torch.sqrt((z_ok ** 2).mean())) if z_ok.numel() else math.nan,
                     step)
        self._spread("z rms", z_rms, z_ok, step)
        for key, v in estimates.items():
            self._estimate(key, v, finite[key], step)
        ident = self.run.graph.role("estimator")
        theta = ident.theta_free().detach().to(torch.float64).cpu()
        for i, name in enumerate(ident.theta_names):
            w.add_scalar(f"theta/{name}", float(theta[:, i].nanmean()), step)
        w.add_scalar("health/diverged", float((~ident.alive).sum()), step)
        if self.batch >= HISTOGRAM_MIN and self.n_logs % 10 == 0:
            for key, ok in finite.items():
                if ok.numel():
                    w.add_histogram(f"spread/{key}", ok, step)
        self.n_logs += 1

    def _estimate(self, key: str, v: torch.Tensor, ok: torch.Tensor, step: int) -> None:
        w = self.writer
        w.add_scalar(self.estimate_tag(key), float(v.nanmean()), step)
        truth = self.run.truth.get(key)
        if key in self.shared_truth:
            w.add_scalar(f"{ESTIMATES}/{key} truth", self.shared_truth[key], step)
            tol = self.tolerance(key)
            if tol:
                w.add_scalar(f"bands/{key} low", self.shared_truth[key] - tol, step)
                w.add_scalar(f"bands/{key} high", self.shared_truth[key] + tol, step)
        if truth is not None:
            err = (v - torch.as_tensor(truth, dtype=v.dtype)).abs()
            w.add_scalar(f"errors/{key}", float(err.nanmean()), step)
            if key not in self.shared_truth:       # a truth per member: the error stands beside the estimate
                w.add_scalar(f"{ESTIMATES}/{key} |error| mean", float(err.nanmean()), step)
        self._spread(key, v, ok, step)

    def _spread(self, name: str, v: torch.Tensor, ok: torch.Tensor, step: int) -> None:
        """Quantiles over the batch (of its finite values ``ok``) and the traced members' values."""
        if self.batch == 1:
            return
        for b in self.traced:
            self.writer.add_scalar(f"members/{name} m{b}", float(v[b]), step)
        if ok.numel():      # numpy's quantiles: the same linear interpolation as torch.quantile, several times faster
            for q, value in zip(QUANTILES, np.quantile(ok.numpy(), QUANTILES)):
                self.writer.add_scalar(f"quantiles/{name} {_q(q)}", float(value), step)

    def intervals(self, found, steps: list[int]) -> None:
        """The final confidence intervals (``rcotorch.intervals.Intervals``; batch means of their bounds) as
        ``intervals/<key> lower|upper`` at each of ``steps`` (the logged steps), so that the Custom Scalars
        chart draws the estimate's path into its final band."""
        for key in found.estimate:
            lo, hi = _finite(found.lower(key)), _finite(found.upper(key))
            if not lo.numel() or not hi.numel():
                continue
            for step in steps:
                self.writer.add_scalar(f"intervals/{key} lower", float(lo.mean()), step)
                self.writer.add_scalar(f"intervals/{key} upper", float(hi.mean()), step)

    def figures(self, pngs: dict[str, bytes], out: Path) -> None:
        """Save the figures (PNG bytes, ``rcotorch.figures.png``) in ``out`` and as images under ``figures/``
        (TensorBoard gets the PNG file's bytes)."""
        import io

        from PIL import Image
        from tensorboard.compat.proto.summary_pb2 import Summary

        from .outputs import atomic_write
        for name, png in pngs.items():
            atomic_write(out / f"{name}.png", lambda f, png=png: f.write(png))
            im = Image.open(io.BytesIO(png))
            image = Summary.Image(height=im.height, width=im.width, colorspace=len(im.getbands()),
                                  encoded_image_string=png)
            self.writer.file_writer.add_summary(Summary(value=[Summary.Value(tag=f"figures/{name}", image=image)]),
                                                self.run.k)

    def close(self, summary: dict) -> None:
        """Final values (``final/``, the HParams metrics) and the run's HParams session: its settings and status."""
        if getattr(self.run, "hparams_session", True):      # a sweep writes its own sessions (rcotorch.sweep)
            for tag, value in final_values(summary).items():
                self.writer.add_scalar(tag, value, self.run.k)
            hparams = {k: v for k, v in summary["settings"].items() if isinstance(v, (int, float, str, bool))}
            hparams.update(scenario=summary["scenario"], batch=summary["batch"])
            write_session(self.writer, hparams, summary)
        self.writer.close()


def _finite(v: torch.Tensor) -> torch.Tensor:
    """The finite values of a CPU tensor, in order (the tensor itself when all are: the common case costs one
    pass of numpy's isfinite instead of a masked copy)."""
    ok = np.isfinite(v.numpy())
    return v if ok.all() else v[torch.from_numpy(ok)]


def final_values(summary: Mapping[str, Any]) -> dict[str, float]:
    """The numbers of an HParams row, batch means where there are several members: ``final/<key>`` for each
    estimate and metric, ``final/|error| <key>`` for each estimate with a truth, ``final/<key> lower`` and
    ``upper`` (its confidence interval), ``final/diverged`` and ``final/requirements passed`` (members)."""
    out: dict[str, float] = {}
    batch = int(summary.get("batch", 1))

    def per_member(v) -> np.ndarray:     # one value per member, NaN for None
        return np.array(v if isinstance(v, list) else [v] * batch, dtype=np.float64)

    for key, v in summary["estimates"].items():
        est = per_member(v)
        out[f"final/{key}"] = _mean(est)
        truth = summary.get("truth", {}).get(key)
        if truth is not None:
            out[f"final/|error| {key}"] = _mean(np.abs(est - per_member(truth)))
    for key, v in summary["metrics"].items():
        out[f"final/{key}"] = _mean(per_member(v))
    for key, iv in (summary.get("intervals") or {}).items():
        out[f"final/{key} lower"] = _mean(per_member(iv["lower"]))
        out[f"final/{key} upper"] = _mean(per_member(iv["upper"]))
    out["final/diverged"] = float(member_status(summary).count("diverged"))
    passed = requirements_passed(summary)
    if passed is not None:
        out["final/requirements passed"] = float(sum(passed))
    return {k: v for k, v in out.items() if v is not None}


def _mean(values: np.ndarray) -> float | None:
    """The mean of the finite values, None where there is none."""
    values = values[np.isfinite(values)]
    return float(values.mean()) if values.size else None


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
    """One member's status, or the count of each status in a batch ('converged 6, diverged 2'), with the
    requirements' pass or fail beside it ('converged, requirements pass'; '..., requirements pass 7 of 8')."""
    status = member_status(summary)
    text = status[0] if len(status) == 1 else ", ".join(f"{s} {n}" for s, n in sorted(Counter(status).items()))
    passed = requirements_passed(summary)
    if passed is None:
        return text
    if len(passed) == 1:
        return text + (", requirements pass" if passed[0] else ", requirements FAIL")
    return text + f"; requirements pass {sum(passed)} of {len(passed)}"


def session_status(summary: Mapping[str, Any]) -> str:
    """HParams' session status: failure when a member diverged, success when every member converged."""
    status = set(member_status(summary))
    if "diverged" in status:
        return "STATUS_FAILURE"
    return "STATUS_SUCCESS" if status == {"converged"} else "STATUS_UNKNOWN"


def write_session(writer: SummaryWriter, hparams: Mapping[str, Any], summary: Mapping[str, Any]) -> None:
    """Make the writer's run an HParams session with these hyperparameters and the status of ``summary``'s
    members (``STATUS_HPARAM``, ``status_text``; the session's own status, ``session_status``). No experiment
    summary is written: TensorBoard then builds the table from every session under its logdir, so runs of
    different scenarios (with different settings) can share one folder."""
    from tensorboard.compat.proto.summary_pb2 import Summary, SummaryMetadata
    from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2
    from torch.utils.tensorboard.summary import hparams as hparams_summaries

    _, start, _ = hparams_summaries({**hparams, STATUS_HPARAM: status_text(summary)}, {})
    end = plugin_data_pb2.HParamsPluginData(
        session_end_info=plugin_data_pb2.SessionEndInfo(status=api_pb2.Status.Value(session_status(summary))),
        version=metadata.PLUGIN_DATA_VERSION)
    meta = SummaryMetadata(plugin_data=SummaryMetadata.PluginData(plugin_name=metadata.PLUGIN_NAME,
                                                                  content=end.SerializeToString()))
    writer.file_writer.add_summary(start)
    writer.file_writer.add_summary(Summary(value=[Summary.Value(tag=metadata.SESSION_END_INFO_TAG,
                                                                metadata=meta)]))
