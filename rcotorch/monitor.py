"""TensorBoard monitoring of a run: one writer per run, batch aggregates, histograms, figures, hparams."""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch.utils.tensorboard import SummaryWriter

PER_MEMBER_MAX = 8     # individual traces up to this batch size
HISTOGRAM_MIN = 16     # histograms across the batch from this batch size


class Monitor:
    """Scalars under ``z/``, ``theta/``, ``estimate/``, ``truth/``, ``error/``; histograms under ``batch/``;
    figures under ``figures/``; settings as text and hparams. Charts pairing each estimate with its truth
    are in the Custom Scalars tab."""

    def __init__(self, out: Path, run):
        self.run, self.batch = run, run.batch
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
        if B <= PER_MEMBER_MAX and B > 1:
            for b in range(B):
                w.add_scalar(f"z/member_{b}", float(z_rms[b]), step)
        ident = self.run.graph.blocks["identified"]
        theta = ident.theta.detach().reshape(B, -1)[:, ident.free].to(torch.float64).cpu()
        for i, name in enumerate(ident.theta_names):
            w.add_scalar(f"theta/{name}", float(theta[:, i].mean()), step)
            if 1 < B <= PER_MEMBER_MAX:
                for b in range(B):
                    w.add_scalar(f"theta/{name}/member_{b}", float(theta[b, i]), step)
        for key, v in estimates.items():
            if B == 1:
                w.add_scalar(f"estimate/{key}", float(v[0]), step)
            else:
                w.add_scalar(f"estimate/{key}/mean", float(v.nanmean()), step)
                if B <= PER_MEMBER_MAX:
                    for b in range(B):
                        w.add_scalar(f"estimate/{key}/member_{b}", float(v[b]), step)
            truth = self.run.truth.get(key)
            if isinstance(truth, (int, float)):
                w.add_scalar(f"truth/{key}", float(truth), step)
            if truth is not None:
                w.add_scalar(f"error/{key}", float((v - torch.as_tensor(truth, dtype=v.dtype)).abs().nanmean()), step)
        w.add_scalar("batch/diverged", float((~ident.alive).sum()), step)
        if B >= HISTOGRAM_MIN and self.n_logs % 10 == 0:
            w.add_histogram("batch/z_rms", z_rms[finite], step)
            for key, v in estimates.items():
                ok = torch.isfinite(v)
                if ok.any():
                    w.add_histogram(f"batch/{key}", v[ok], step)
        self.n_logs += 1

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
