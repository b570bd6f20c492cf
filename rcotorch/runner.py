"""Running a scenario: stepping, TensorBoard monitoring, checkpoints, figures and ``summary.json``."""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from . import scenario as scenarios
from .errors import ConfigError
from .monitor import Monitor

DTYPES = {"float64": torch.float64, "float32": torch.float32}
CHECKPOINT = "checkpoint.pt"


def _device(name: str) -> torch.device:
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda asked for, but torch sees no CUDA device on this machine")
    return dev


class Run:
    """One scenario run: a batched graph stepped to ``steps``, logged every ``log_every`` steps."""

    def __init__(self, name: str, steps: int | None = None, batch: int = 1, seed: int | None = None,
                 device: str = "cpu", dtype: str = "float64", out: str | Path | None = None,
                 overrides: Mapping[str, Any] | None = None, log_every: int | None = None,
                 members: list[Mapping[str, Any]] | None = None, trace: list[int] | None = None):
        """``members``: per-member settings (one dict each, e.g. {'dK': 0.3, 'seed': 7}); the batch is then
        ``len(members)`` and member b equals a batch-of-one run with ``members[b]`` as overrides.
        ``trace``: members logged individually in TensorBoard when the batch is larger than 8."""
        self.scenario = scenarios.get(name)
        self.trace = trace
        if members is not None:
            if not members:
                raise ConfigError("members is empty")
            batch = len(members)
        if dtype not in DTYPES:
            raise ConfigError(f"dtype must be one of {sorted(DTYPES)}, got {dtype!r}")
        if batch < 1:
            raise ConfigError(f"batch must be positive, got {batch}")
        self.steps = int(steps if steps is not None else self.scenario.steps)
        if self.steps < 1:
            raise ConfigError(f"steps must be positive, got {self.steps}")
        self.batch, self.dtype_name, self.device = batch, dtype, _device(device)
        if members is not None:
            self.settings = self.scenario.resolve_members(dict(overrides or {}, **({} if seed is None else
                                                                                  {"seed": seed})), members)
        else:
            self.settings = self.scenario.resolve(overrides, seed)
        self.out = Path(out) if out else Path("runs") / self.scenario.name
        self.log_every = int(log_every or max(1, self.steps // 1000))
        self.graph = self.scenario.build(self.settings, batch, DTYPES[dtype], self.device)
        self.graph.check_steps(self.steps)
        self.truth = self.scenario.truth(self.settings)
        self.history: dict[str, list] = {"step": [], "z_rms": []}
        self.z_sq = torch.zeros(batch, dtype=torch.float64, device=self.device)
        self.z_count = 0
        self.monitor: Monitor | None = None

    def clear_outputs(self) -> None:
        """Remove the outputs of an earlier run in the same directory (events, figures, summary, checkpoint)."""
        import shutil
        if not self.out.is_dir():
            return
        for pattern in ("events.out.tfevents.*", "*.png", "summary.json", CHECKPOINT):
            for f in self.out.glob(pattern):
                f.unlink()
        shutil.rmtree(self.out / "hparams", ignore_errors=True)

    @property
    def k(self) -> int:
        return int(self.graph.k)

    # --- stepping ----------------------------------------------------------------------------------------
    def advance(self, until: int | None = None, progress: bool | None = None,
                checkpoint_every: int | None = None) -> None:
        """Step to ``until`` (default: the run's ``steps``), logging and checkpointing on the way."""
        until = self.steps if until is None else until
        self.graph.check_steps(until - self.k)
        if self.monitor is None:
            self.monitor = Monitor(self.out, self)
        bar = None
        if progress or (progress is None and until - self.k >= 5000):
            from tqdm import tqdm
            bar = tqdm(total=until, initial=self.k, desc=self.scenario.name, unit="step", mininterval=0.5,
                       disable=None, file=sys.stderr)
        z_node = self.graph.role_signal("error")
        while self.k < until:
            # Up to the next log or checkpoint step in one call (many steps per call on the native engine).
            stop = min(until, (self.k // self.log_every + 1) * self.log_every)
            if checkpoint_every:
                stop = min(stop, (self.k // checkpoint_every + 1) * checkpoint_every)
            n = stop - self.k
            self.graph.advance(n, accumulate={z_node: self.z_sq})
            self.z_count += n
            if self.k % self.log_every == 0:
                self._log()
            if checkpoint_every and self.k % checkpoint_every == 0:
                self.save()
            if bar is not None:
                bar.update(n)
        if bar is not None:
            bar.close()

    def _log(self) -> None:
        z_rms = torch.sqrt(self.z_sq / max(self.z_count, 1))
        est = {k: v.detach().to(torch.float64).cpu() for k, v in
               self.scenario.estimates(self.graph, self.settings).items()}
        self.history["step"].append(self.k)
        self.history["z_rms"].append(z_rms.cpu())
        for key, v in est.items():
            self.history.setdefault(key, []).append(v)
        self.monitor.log(self.k, z_rms.cpu(), est)
        self.z_sq.zero_()
        self.z_count = 0

    # --- checkpoints -------------------------------------------------------------------------------------
    def save(self, path: str | Path | None = None) -> Path:
        path = Path(path) if path else self.out / CHECKPOINT
        path.parent.mkdir(parents=True, exist_ok=True)
        state = {
            "scenario": self.scenario.name, "steps": self.steps, "batch": self.batch,
            "dtype": self.dtype_name, "settings": self.settings, "log_every": self.log_every,
            "graph": self.graph.state_dict(), "history": self.history,
            "z_sq": self.z_sq, "z_count": self.z_count,
        }
        tmp = path.with_suffix(".tmp")
        torch.save(state, tmp)
        tmp.replace(path)
        return path

    @classmethod
    def resume(cls, directory: str | Path, steps: int | None = None, device: str | None = None,
               out: str | Path | None = None) -> Run:
        """Rebuild a run from ``directory/checkpoint.pt``; ``steps`` may extend its target."""
        path = Path(directory) / CHECKPOINT
        if not path.is_file():
            raise ConfigError(f"--resume {directory}: no {CHECKPOINT} there")
        state = torch.load(path, map_location="cpu", weights_only=False)
        run = cls(state["scenario"], steps=steps or state["steps"], batch=state["batch"],
                  device=device or "cpu", dtype=state["dtype"], out=out or directory,
                  overrides={k: v for k, v in state["settings"].items() if not isinstance(v, list)},
                  members=_members(state["settings"], state["batch"]), log_every=state["log_every"])
        run.graph.load_state_dict(state["graph"])
        run.history = state["history"]
        run.z_sq = state["z_sq"].to(run.device)
        run.z_count = state["z_count"]
        if run.k > run.steps:
            raise ConfigError(f"--resume: the checkpoint is at step {run.k}, past the requested {run.steps}")
        return run

    # --- results -----------------------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        sc, g = self.scenario, self.graph
        est = {k: v.detach().to(torch.float64).cpu() for k, v in sc.estimates(g, self.settings).items()}
        met = {k: v.detach().to(torch.float64).cpu() for k, v in sc.metrics(g, self.settings).items()}
        z_rms = self.history["z_rms"][-1] if self.history["z_rms"] else torch.full((self.batch,), math.nan)
        met.setdefault("z_rms_final", z_rms)
        ident = g.role("estimator")
        diverged = [{"member": int(b), "step": int(ident.diverged_at[b])}
                    for b in torch.nonzero(~ident.alive).flatten().tolist()]

        def value(t: torch.Tensor):
            vals = [None if not math.isfinite(x) else float(x) for x in t.reshape(self.batch).tolist()]
            return vals[0] if self.batch == 1 else vals

        checks = {}
        for req in sc.requirements:
            group, key = req.key.split(".", 1)
            t = (est if group == "estimates" else met).get(key)
            if t is None:
                continue
            truth = member_truth(self.truth.get(key), self.batch)
            per_member = [req.check(float(x), tv) for x, tv in zip(t.reshape(-1).tolist(), truth)]
            checks[req.key] = {"requirement": req.describe(),
                               "value": value(torch.tensor([q for q, _ in per_member])),
                               "pass": all(ok for _, ok in per_member)}
        return {
            "scenario": sc.name, "steps": self.k, "batch": self.batch, "dtype": self.dtype_name,
            "device": str(self.device.type), "engine": self.graph.ran_engine or
            ("torch" if self.graph.native_status() else "native"),
            "engine_reason": self.graph.engine_reason if self.graph.ran_engine else self.graph.native_status(),
            "estimates": {k: value(v) for k, v in est.items()},
            "truth": self.truth, "metrics": {k: value(v) for k, v in met.items()},
            "settings": dict(self.settings), "diverged": diverged, "requirements": checks,
        }

    def finish(self, figures: bool = True) -> dict[str, Any]:
        """Write summary.json, the figures (PNG and TensorBoard) and a final checkpoint."""
        if self.monitor is None:
            self.monitor = Monitor(self.out, self)
        if self.z_count:
            self._log()
        summary = self.summary()
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        if figures:
            from .figures import run_figures
            figs = run_figures(self)
            figs.update(self.scenario.figures(self.graph, self.settings))
            self.monitor.figures(figs, self.out)
        self.monitor.close(summary)
        self.save()
        return summary


def member_truth(truth, batch: int) -> list:
    """A truth value (shared or per member) as one value per member."""
    return list(truth) if isinstance(truth, (list, tuple)) else [truth] * batch


def _members(settings: Mapping[str, Any], batch: int) -> list[dict[str, Any]] | None:
    """Per-member settings of a resolved batch (the inverse of ``Scenario.resolve_members``)."""
    varying = {k: v for k, v in settings.items() if isinstance(v, list)}
    if not varying:
        return None
    return [{k: v[b] for k, v in varying.items()} for b in range(batch)]


def result_table(summary: Mapping[str, Any]) -> str:
    """A short text table of estimates, truth and requirements."""
    rows = [("key", "estimate", "truth", "requirement", "check")]
    checks = summary.get("requirements", {})

    def fmt(v):
        if isinstance(v, list):
            finite = [x for x in v if x is not None]
            return f"{min(finite):.6g}..{max(finite):.6g}" if finite else "nan"
        return "nan" if v is None else f"{v:.6g}"

    for group in ("estimates", "metrics"):
        for key, v in summary[group].items():
            chk = checks.get(f"{group}.{key}")
            truth = summary["truth"].get(key) if group == "estimates" else None
            rows.append((f"{group}.{key}", fmt(v), "" if truth is None else fmt(truth),
                         chk["requirement"] + f" ({fmt(chk['value'])})" if chk else "",
                         ("PASS" if chk["pass"] else "FAIL") if chk else ""))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    if summary.get("diverged"):
        lines.append(f"diverged members: {summary['diverged']}")
    return "\n".join(lines)
