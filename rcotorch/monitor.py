"""TensorBoard monitoring of a run: one writer per run, batch aggregates, histograms, figures, hparams."""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch.utils.tensorboard import SummaryWriter

PER_MEMBER_MAX = 8     # individual traces of every member up to this batch size
HISTOGRAM_MIN = 16     # histograms across the batch from this batch size
QUANTILES = (0.1, 0.5, 0.9)


class Monitor:
    """Scalars under ``z/``, ``theta/``, ``estimate/``, ``truth/``, ``error/``; histograms under ``batch/``;
    figures under ``figures/``; settings as text and hparams. Charts pairing each estimate with its truth
    are in the Custom Scalars tab."""

    def __init__(self, out: Path, run):
        self.run, self.batch = run, run.batch
        # Members traced individually: all of a small batch, else the chosen ones (default: the first 3).
        chosen = run.trace if run.trace is not None else range(min(3, run.batch))
        self.traced = list(range(run.batch)) if run.batch <= PER_MEMBER_MAX else sorted(set(chosen))
        out.mkdir(parents=True, exist_ok=True)
        self.writer = SummaryWriter(log_dir=str(out), purge_step=run.k if run.k > 0 else None)
        self.n_logs = 0
        if run.k == 0:
            settings = "\n".join(f"| {k} | {v} |" for k, v in run.settings.items())
            self.writer.add_text("settings", f"| setting | value |\n|---|---|\n{settings}", 0)
            self.writer.add_custom_scalars({"estimates vs truth": {
                key: ["Multiline", [f"estimate/{key}", f"estimate/{key}/mean", f"truth/{key}"]]
                for key in run.truth}})

    def log(self, step: int, z_rms: torch.Tensor, estimates: dict[str, torch.Tensor]) -> None:
        w, B = self.writer, self.batch
        finite = torch.isfinite(z_rms)
        w.add_scalar("z/rms", float(torch.sqrt((z_rms[finite] ** 2).mean())) if finite.any() else math.nan, step)
        traced = self.traced if B > 1 else []
        for b in traced:
            w.add_scalar(f"z/member_{b}", float(z_rms[b]), step)
        if B > PER_MEMBER_MAX:
            self._quantiles("z", z_rms, step)
        ident = self.run.graph.role("estimator")
        theta = ident.theta_free().detach().to(torch.float64).cpu()
        for i, name in enumerate(ident.theta_names):
            w.add_scalar(f"theta/{name}", float(theta[:, i].mean()), step)
            for b in traced:
                w.add_scalar(f"theta/{name}/member_{b}", float(theta[b, i]), step)
        for key, v in estimates.items():
            if B == 1:
                w.add_scalar(f"estimate/{key}", float(v[0]), step)
            else:
                w.add_scalar(f"estimate/{key}/mean", float(v.nanmean()), step)
                for b in traced:
                    w.add_scalar(f"estimate/{key}/member_{b}", float(v[b]), step)
            truth = self.run.truth.get(key)
            if isinstance(truth, (int, float)):
                w.add_scalar(f"truth/{key}", float(truth), step)
            if truth is not None:
                err = (v - torch.as_tensor(truth, dtype=v.dtype)).abs()
                w.add_scalar(f"error/{key}", float(err.nanmean()), step)
                if B > PER_MEMBER_MAX:
                    self._quantiles(f"error/{key}", err, step)
        w.add_scalar("batch/diverged", float((~ident.alive).sum()), step)
        if B >= HISTOGRAM_MIN and self.n_logs % 10 == 0:
            w.add_histogram("batch/z_rms", z_rms[finite], step)
            for key, v in estimates.items():
                ok = torch.isfinite(v)
                if ok.any():
                    w.add_histogram(f"batch/{key}", v[ok], step)
        self.n_logs += 1

    def _quantiles(self, tag: str, v: torch.Tensor, step: int) -> None:
        v = v[torch.isfinite(v)]
        if v.numel():
            for q, value in zip(QUANTILES, torch.quantile(v, torch.tensor(QUANTILES, dtype=v.dtype))):
                self.writer.add_scalar(f"{tag}/q{int(q * 100):02d}", float(value), step)

    def figures(self, figs: dict, out: Path) -> None:
        import matplotlib.pyplot as plt
        for name, fig in figs.items():
            fig.savefig(out / f"{name}.png", dpi=110, bbox_inches="tight")
            self.writer.add_figure(f"figures/{name}", fig, self.run.k, close=False)
            plt.close(fig)

    def close(self, summary: dict) -> None:
        hparams = {k: v for k, v in summary["settings"].items() if isinstance(v, (int, float, str, bool))}
        metrics = {}
        for group in ("estimates", "metrics"):
            for k, v in summary[group].items():
                vals = [x for x in (v if isinstance(v, list) else [v]) if x is not None]
                if vals:
                    metrics[f"final/{k}"] = sum(vals) / len(vals)
        self.writer.add_hparams(hparams, metrics, run_name="hparams", global_step=self.run.k)
        self.writer.close()
