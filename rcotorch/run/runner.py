"""Running a scenario: ``Run`` steps a batched graph, checks its members' health, logs to TensorBoard and the
figures' history, saves checkpoints and writes ``summary.json`` and the figures at the end.

Its parts live beside it, by concern: ``limits`` (what a run may ask for: device, steps, memory), ``cadence``
(when it logs, and the sums of the model error between checks and logs), ``resume`` (checkpoints and what a
resume checks), ``end_checks`` (the checks and warnings of the end beyond the members' health), ``report``
(``summary.json``, the health line and the result table), ``monitor`` (TensorBoard). The names other modules
import from here are kept here too.

Cadences, fixed when a run is created and kept by a resume:

* health checks (``Health.is_check``): every ``health.check_every(steps)`` steps (2% of the run) in the
  convergence window, every second such step before it (about 30 per run, the same for any batch size);
* logs (TensorBoard and the figures' history) every ``log_every`` steps: about 1000 per run, fewer for large
  batches (``rcotorch.run.cadence.default_log_every``), since a log costs about as much as a few steps of the
  whole batch; on check steps where the interval is longer than the checks';
* checkpoints every ``checkpoint_every`` steps when asked, at the end, and when a stop is requested (Ctrl-C,
  SIGTERM, SIGHUP).

What a run keeps grows with the batch, not with the steps: the per-member statistics of the health checks,
and a history of the logged values of the traced members (``rcotorch.run.monitor.traced_members``, at most
``HISTORY_MEMBERS``), the ones the figures draw (at most ``2 * HISTORY_MAX`` points, thinned by two when full),
so a checkpoint's size does not depend on how long the run is.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from ..errors import CheckpointError, ConfigError, RcoError
from ..estimator.tracking import ChangeDetector, change_report
from ..verdict import intervals as ci
from ..verdict.health import STATUSES, Criteria, Health, finite_list
from . import scenario as scenarios
from .cadence import (
    LOG_BUDGET,
    MAX_LOGS,
    MIN_LOGS,
    MIN_LOGS_CHANGE,
    ErrorSums,
    default_log_every,
    is_log,
    next_log,
    next_multiple,
)
from .end_checks import FIT_WORSE, fit_warnings, fits_worse, loop_settle, residual_metrics, settle_note, tuning_warnings
from .limits import (
    DTYPES,
    MAX_STEPS,
    bounded_steps,
    check_memory,
    memory_needed,
    positive_int,
    run_device,
    steps_bound_reason,
)
from .monitor import Monitor, traced_members
from .outputs import OutputFolder, save_checkpoint, write_text
from .report import health_line, member_reasons, result_table, to_json
from .resume import (
    CHECKPOINT,
    CHECKPOINT_FORMAT,
    RESUME_CHANGEABLE,
    check_resume,
    member_settings,
    read_checkpoint,
    same_layout,
    what_failed,
)

# Names that users, tests and the other modules of rcotorch.run import from here; each is defined in the module
# named above.
__all__ = ["CHECKPOINT", "CHECKPOINT_FORMAT", "DTYPES", "FIT_WORSE", "HISTORY_MAX", "HISTORY_MEMBERS", "LOG_BUDGET",
           "MAX_LOGS", "MAX_STEPS", "MIN_LOGS", "MIN_LOGS_CHANGE", "RESUME_CHANGEABLE", "Interrupted", "Run",
           "check_memory", "default_log_every", "default_out", "fit_warnings", "fits_worse", "health_line",
           "loop_settle", "member_truth", "memory_needed", "prefetch", "residual_metrics", "result_table",
           "steps_bound_reason", "to_json", "tuning_warnings"]

HISTORY_MAX = 1000
HISTORY_MEMBERS = 8      # members kept in the history (the traced ones, which the figures draw)


class Interrupted(Exception):
    """A run stopped on request (Ctrl-C, SIGTERM, SIGHUP) after saving a checkpoint."""

    def __init__(self, step: int | None, checkpoint: Path | None):
        super().__init__("stopped" if step is None else f"stopped at step {step}, checkpoint {checkpoint}")
        self.step, self.checkpoint = step, checkpoint


def default_out(name: str) -> Path:
    """``runs/NAME``, or the first of ``runs/NAME-2``, ``runs/NAME-3``, ... that holds no run when it does."""
    base = Path("runs") / name
    path, n = base, 1
    while path.exists() and (not path.is_dir() or any(p.name != ".rcotorch.lock" for p in path.iterdir())):
        n += 1
        path = base.with_name(f"{name}-{n}")
    return path


class Run:
    """One scenario run: a batched graph stepped to ``steps``, with health checks and logs on the way.

    Args:
        name: the scenario.
        steps, batch, seed, device, dtype: the run's size and settings (``seed`` overrides the scenario's).
        out: output folder (default ``runs/NAME``, or ``runs/NAME-2``, ... when that holds a run). It is
            opened (locked) when the run first writes, or by ``open_output``; a folder that holds another run
            is refused unless ``overwrite``.
        overrides: scenario settings, e.g. ``{'p0': 1e4}``.
        members: per-member settings (one dict each, e.g. {'dK': 0.3, 'seed': 7}); the batch is then
            ``len(members)`` and member b equals a batch-of-one run with ``members[b]`` as overrides.
        log_every: steps between logs (default ``default_log_every``).
        trace: members logged individually in TensorBoard and drawn in the figures (at most 8; default the
            first 8).
        health: thresholds of the member health checks (``rcotorch.verdict.health.Criteria``).
        overwrite: replace the run that ``out`` holds (only the files its manifest lists).
        intervals: compute confidence intervals of the estimates at the end (``rcotorch.verdict.intervals``: a replay
            of the convergence window, up to ``intervals.REPLAY_STEPS`` steps, once per parameter and once
            more, on the PyTorch engine) and judge whether the data determined them.
        level: the intervals' confidence level.
        validation: validate the refined model on held-out data at the end (``Scenario.validation``,
            ``rcotorch.validate``): ``validation_*`` metrics and the ``validation`` entry of the summary.

    ``hparams_session`` (default True): the run writes its HParams session, the sibling run ``verdict/`` of its
    TensorBoard run (a sweep sets it False and writes one session per member instead).
    """

    def __init__(self, name: str, steps: int | None = None, batch: int = 1, seed: int | None = None,
                 device: str = "cpu", dtype: str = "float64", out: str | Path | None = None,
                 overrides: Mapping[str, Any] | None = None, log_every: int | None = None,
                 members: list[Mapping[str, Any]] | None = None, trace: list[int] | None = None,
                 health: Criteria | None = None, overwrite: bool = False, intervals: bool = True,
                 level: float = ci.LEVEL, validation: bool = True):
        self.scenario = scenarios.get(name) if isinstance(name, str) else name
        if not isinstance(self.scenario, scenarios.Scenario):
            raise ConfigError(f"a run takes a scenario or its name, got {type(name).__name__}")
        self.intervals_on, self.level = bool(intervals) and self.scenario.intervals, float(level)
        self.validation_on = bool(validation)
        self._validation: tuple[int, Any, str | None] | None = None
        ci.quantile(self.level)                                    # checks the level
        self.trace = trace
        if members is not None:
            if not members:
                raise ConfigError("members is empty")
            batch = len(members)
        if dtype not in DTYPES:
            raise ConfigError(f"dtype must be one of {sorted(DTYPES)}, got {dtype!r}")
        self.batch = positive_int(batch, "batch")
        self.dtype_name, self.device = dtype, run_device(device)
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise ConfigError(f"seed must be an integer, got {seed!r}")
        if members is not None:
            self.settings = self.scenario.resolve_members(dict(overrides or {}, **({} if seed is None else
                                                                                  {"seed": seed})), members)
        else:
            self.settings = self.scenario.resolve(overrides, seed)
        self.steps = bounded_steps(steps if steps is not None else self.scenario.default_steps(self.settings),
                                   "steps")
        self.out = Path(out) if out else default_out(self.scenario.name)
        self.folder = OutputFolder(self.out, "run")
        self._mode = "overwrite" if overwrite else "new"
        if log_every is not None:
            positive_int(log_every, "log_every")
        check_memory(self.scenario, self.settings, self.batch, dtype)
        self.graph = self.scenario.build(self.settings, self.batch, DTYPES[dtype], self.device)
        self.graph.check_steps(self.steps)
        self.truth = self.scenario.truth(self.settings)
        self.truth_history = scenarios.check_truth_history(self.scenario.truth_history(self.settings), self.truth,
                                                 f"scenario '{self.scenario.name}'")
        follows = any(len(pairs) > 1 for pairs in (self.truth_history or {}).values()) or \
            any(isinstance(blk, ChangeDetector) for blk in self.graph.blocks.values())
        self.log_every = log_every if log_every is not None else \
            default_log_every(self.steps, self.batch, follows)
        self.health = Health(self.graph, self.steps, health)
        self.z_sig = self.graph.role_signal("error")
        self.y_sig = self.graph.role_signal("measured") if "measured" in self.graph.roles else None
        self.sums = ErrorSums.zeros(self.batch, self.device)   # z^2 and y^2 between health checks and logs
        self.history: dict[str, list] = {"step": [], "z_rms": []}
        # the history members' RLS covariance at each logged step (``_remember``), for the band over time
        self.p_history: list[torch.Tensor] = []
        self._band: tuple[int, Any] | None = None        # band_over_time at a step, made once
        self._physics_note: str | None = None             # why the physics at the estimates was not simulated
        self.history_members = traced_members(trace, self.batch)[:HISTORY_MEMBERS]
        self.snapshot: dict[str, torch.Tensor] | None = None     # the graph at the window's start
        self._intervals: tuple[int, ci.Intervals | None, ci.Residuals | None] | None = None
        self._replay_progress = None           # told the replay's steps done and in all, while a bar shows the end
        self._settle: tuple[int, int | None, str] = (0, None, "")   # settling steps, what the loop needs, why less
        self.monitor: Monitor | None = None
        self.hparams_session = True
        self.tb_origin: float | None = None    # TensorBoard's wall time at step 0 (``Monitor.wall``)
        self.figures_expected = True           # whether ``finish`` will draw figures (their imports start early)
        self.drawing = None                    # a process that draws the run's figures (``DrawingProcess``)
        self.timings: dict[str, float] = {}    # seconds of each part of the end of the run (``finish``)

    def header(self) -> str:
        """One line on what runs and where its results go: scenario, steps, batch, dtype, device, engine and
        output folder (the engine the graph will run on before it ran, the one it ran on after)."""
        engine = self.graph.ran_engine or ("torch" if self.graph.native_status() else "native")
        return (f"{self.scenario.name}: {self.steps} steps, batch {self.batch}, {self.dtype_name}, {self.device.type}, "
                f"{engine} engine -> {self.out}")

    @property
    def k(self) -> int:
        return int(self.graph.k)

    # --- the output folder ---------------------------------------------------------------------------------
    def open_output(self) -> None:
        """Open (lock) the output folder, if not yet: refuses a folder that holds another run unless the run
        was made with ``overwrite``, or is a resume into its own folder. An open folder is checked to be still
        the one opened (``OutputFolder.check``)."""
        if not self.folder.is_open:
            self.folder.open(self._mode, info={"scenario": self.scenario.name})
            self._mode = "resume"           # a later reopening continues this run
        else:
            self.folder.check()

    def close(self) -> None:
        """Release the output folder (its manifest lists every file the run wrote), also when flushing the
        TensorBoard writer fails."""
        try:
            if self.monitor is not None:
                self.monitor.flush()
        finally:
            self.folder.close()

    def __enter__(self) -> Run:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- stepping ------------------------------------------------------------------------------------------
    def advance(self, until: int | None = None, progress: bool | None = None,
                checkpoint_every: int | None = None, stop: Callable[[], bool] | None = None,
                desc: str | None = None) -> None:
        """Step to ``until`` (default: the run's ``steps``), checking health, logging and checkpointing on the
        way. ``stop()`` is asked after each stretch of steps; when it says True the run saves a checkpoint and
        raises ``Interrupted``. Each stretch ends with a check that the output folder was not deleted or replaced
        (``OutputError``)."""
        until = self.steps if until is None else bounded_steps(until, "until")
        if checkpoint_every is not None:
            positive_int(checkpoint_every, "--checkpoint-every")
        self.graph.check_steps(until - self.k)
        self._start_monitor()
        if self.batch * (until - self.k) >= PREFETCH_MEMBER_STEPS:
            prefetch(figures=self.figures_expected and (self.drawing is None or self._own_figures()))
        bar = None
        if progress or (progress is None and until - self.k >= 5000):
            from tqdm import tqdm
            bar = tqdm(total=until, initial=self.k, desc=desc or self.scenario.name, unit="step",
                       mininterval=0.5, disable=None, file=sys.stderr)
        acc = {self.z_sig: self.sums.z}
        if self.y_sig is not None and self.y_sig != self.z_sig:
            acc[self.y_sig] = self.sums.y
        try:
            self._take_snapshot()
            while self.k < until:
                k = self.k
                end = min(until, next_log(k, self.log_every), self.health.next_check(k),
                          next_multiple(k, checkpoint_every) if checkpoint_every else until)
                self.graph.advance(end - k, accumulate=acc)
                self.sums.add(end - k)
                if self.health.is_check(end):
                    self._check()
                self._take_snapshot()
                self.folder.check()
                if is_log(end, self.log_every):
                    self._log()
                if checkpoint_every and end % checkpoint_every == 0:
                    self.save()
                if bar is not None:
                    bar.update(end - k)
                if stop is not None and stop():
                    raise Interrupted(self.k, self.save())
        finally:
            if bar is not None:
                bar.close()

    def _take_snapshot(self) -> None:
        """Keep the graph's state at the convergence window's start (the intervals replay from it)."""
        if self.intervals_on and self.snapshot is None and self.k == self.health.window_start:
            self.snapshot = ci.snapshot(self.graph)

    def _start_monitor(self) -> None:
        self.open_output()
        if self.monitor is None:
            self.monitor = Monitor(self.out, self)
            self.folder.register()

    def _check(self) -> None:
        """A health check: the sums since the last check go to the health statistics (and, where no log took
        them, to the next log's sums)."""
        s = self.sums
        self.health.check(s.z, s.y if self.y_sig is not None else None, s.check_steps)
        s.checked()

    def _log(self) -> None:
        """A log: the rms of z since the last log and the estimates, to the history and TensorBoard."""
        z_rms = self.sums.take_log()
        est = {k: v.detach().to(torch.float64).cpu() for k, v in
               self.scenario.estimates(self.graph, self.settings).items()}
        z_cpu = z_rms.cpu()
        self._remember(z_cpu, est, self._covariance_now())
        self.monitor.log(self.k, z_cpu, est)

    def _covariance_now(self) -> torch.Tensor | None:
        """The history members' RLS covariance P now, (members, n, n) on the CPU, where the run computes
        intervals (the band over time, ``band_over_time``)."""
        est = self.graph.role("estimator")
        if not self.intervals_on or getattr(est, "P", None) is None or est.P.shape[0] == 0:
            return None
        return est.P.detach()[self.history_members].to(torch.float64).cpu()

    def _remember(self, z_rms: torch.Tensor, est: dict[str, torch.Tensor], P: torch.Tensor | None = None) -> None:
        """Append the first members' values to the history (thinned by two when it is full)."""
        h, members = self.history, self.history_members
        h["step"].append(self.k)
        h["z_rms"].append(z_rms[members].clone())
        for key, v in est.items():
            h.setdefault(key, []).append(v[members].clone())
        if P is not None:
            self.p_history.append(P)
        if len(h["step"]) >= 2 * HISTORY_MAX:
            for key in h:
                h[key] = h[key][1::2]
            self.p_history = self.p_history[1::2]

    def band_over_time(self) -> tuple[list[int], dict[str, torch.Tensor]] | None:
        """The confidence band of the history's members at each logged step: the final interval's half-width
        times sqrt(g^T P(k) g / g^T P(N) g) max(1, z_rms(k) / z_rms(N)), g the estimate's gradient in the
        parameters, P(k) the RLS covariance at step k (``_covariance_now``) and z_rms the model error's rms over the
        log interval: wide where P is (the start, a restart of P, forgetting) and where the model error is larger
        than at the end (a change the estimate has not yet followed), as narrow as the final interval at the end.
        It is calibrated at the end only (by the replay of the convergence window).
        Returns (steps, {key: (T, members) half-widths}), or None without final intervals or a band history.
        Where the final interval is not finite (an undetermined estimate), that member's band is NaN."""
        found = self.intervals()
        steps = self.history["step"]
        if found is None or len(self.p_history) != len(steps) or not steps:
            return None
        if self._band is not None and self._band[0] == self.k:
            return self._band[1]
        members = self.history_members
        now = self._covariance_now()
        widths = ci.rls_half_widths(self.graph, lambda g: self.scenario.estimates(g, self.settings),
                                    torch.stack([*self.p_history, now]), members, level=self.level)
        z = torch.stack(self.history["z_rms"]).to(torch.float64)                       # (T, members)
        excess = (z / z[-1]).clamp_min(1.0)
        excess = torch.where(torch.isfinite(excess), excess, torch.ones_like(excess))
        out = {}
        for key, hw in widths.items():
            if key not in found.half_width:
                continue
            final = found.half_width[key].detach().to(torch.float64).cpu()[members]
            factor = final / hw[-1]
            factor = torch.where(torch.isfinite(factor) & (factor > 0), factor, torch.full_like(factor, math.nan))
            out[key] = hw[:-1] * factor * excess
        self._band = (self.k, (list(steps), out) if out else None)
        return self._band[1]

    # --- checkpoints ---------------------------------------------------------------------------------------
    def save(self, path: str | Path | None = None) -> Path:
        """Write a checkpoint (atomically; the previous one is replaced only once this one is complete)."""
        self.open_output()
        path = Path(path) if path else self.out / CHECKPOINT
        sums, counters = self.sums.state()
        state = {
            "format": CHECKPOINT_FORMAT, "scenario": self.scenario.name, "steps": self.steps, "batch": self.batch,
            "dtype": self.dtype_name, "settings": self.settings, "log_every": self.log_every,
            "trace": self.trace, "graph": self.graph.state_dict(),
            "history": {k: torch.stack(v) if k != "step" and v else v for k, v in self.history.items()},
            "history_members": self.history_members, "counters": counters,
            "p_history": torch.stack(self.p_history) if self.p_history else None,
            "sums": sums, "health": self.health.state_dict(),
            "snapshot": None if self.snapshot is None else {k: v.cpu() for k, v in self.snapshot.items()},
            "intervals": self.intervals_on, "level": self.level, "validation": self.validation_on,
            "tb_origin": self.tb_origin,
        }
        save_checkpoint(path, state)
        self.folder.register()
        return path

    @classmethod
    def resume(cls, directory: str | Path, steps: int | None = None, device: str | None = None,
               out: str | Path | None = None, overwrite: bool = False,
               expect: Mapping[str, Any] | None = None, scenario: scenarios.Scenario | None = None) -> Run:
        """Rebuild a run from ``directory/checkpoint.pt``; ``steps`` may extend its target. ``expect``: what
        the caller asked for besides (``name``, ``batch``, ``seed``, ``dtype``, ``overrides``); anything
        that differs from the checkpoint is refused. ``out``: continue into another folder (new, or replaced
        with ``overwrite``) instead of ``directory``. ``scenario``: the scenario object of a run that was not
        made from a registered name (a graph run from Python, ``rcotorch.run.refine``). A checkpoint whose contents
        do not fit a run of its scenario (a missing entry, a tensor of another shape) raises ``CheckpointError``
        naming it."""
        directory = Path(directory)
        path, state = read_checkpoint(directory)
        try:
            run = cls._from_state(path, state, steps, device, out or directory, expect or {}, scenario)
        except RcoError:
            raise
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, RuntimeError) as e:
            # A checkpoint that hashes right but whose contents do not fit a run of its scenario.
            raise CheckpointError(f"{path}: the checkpoint does not hold a run this version can continue "
                                  f"({what_failed(e)}); start the run again") from e
        if out is None or Path(out).resolve() == directory.resolve():
            run._mode = "resume"
        elif overwrite:
            run._mode = "overwrite"
        return run

    @classmethod
    def _from_state(cls, path: Path, state: dict[str, Any], steps: int | None, device: str | None,
                    out: str | Path, expect: Mapping[str, Any], scenario: scenarios.Scenario | None) -> Run:
        """The run a checkpoint's ``state`` holds. Raises KeyError, TypeError, ValueError, ... where a part of
        ``state`` is missing, or its layout (entries, tensor shapes) differs from a fresh run of its scenario."""
        check_resume(path, state, expect)
        if scenario is not None and scenario.name != state["scenario"]:
            raise CheckpointError(f"--resume {path.parent}: the checkpoint is a run of {state['scenario']!r}, not "
                                  f"{scenario.name!r}")
        run = cls(scenario or state["scenario"], steps=steps or state["steps"], batch=state["batch"],
                  device=device or "cpu", dtype=state["dtype"], out=out,
                  overrides={k: v for k, v in state["settings"].items() if not isinstance(v, list)},
                  members=member_settings(state["settings"], state["batch"]), log_every=state["log_every"],
                  trace=state["trace"], health=Criteria(**state["health"]["criteria"]),
                  intervals=state["intervals"], level=state["level"], validation=state.get("validation", True))
        graph = run.graph.state_dict()      # its blocks check their tensors' shapes as they load them
        same_layout("graph", state["graph"], graph, shapes=False)
        if state["snapshot"] is not None:
            same_layout("snapshot", state["snapshot"], graph, shapes=False)
        sums, counters = run.sums.state()
        same_layout("sums", state["sums"], sums)
        same_layout("counters", state["counters"], counters)
        same_layout("health", state["health"], run.health.state_dict())
        run.graph.load_state_dict(state["graph"])
        run.history = {k: list(v.unbind(0)) if isinstance(v, torch.Tensor) else list(v)
                       for k, v in state["history"].items()}
        run.history_members = list(state["history_members"])
        run.p_history = [] if state.get("p_history") is None else list(state["p_history"].unbind(0))
        run.tb_origin = state.get("tb_origin")
        run.sums = ErrorSums.from_state(state["sums"], state["counters"], run.device)
        run.health.load_state_dict(state["health"])
        if run.k > run.steps:
            raise ConfigError(f"--resume: the checkpoint is at step {run.k}, past the requested {run.steps}")
        run.health.set_target(run.steps)
        snap = state["snapshot"]
        run.snapshot = None if snap is None or run.k < run.health.window_start else \
            {k: v.to(run.device) for k, v in snap.items()}
        return run

    # --- results -------------------------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """The run's results: estimates, truth, metrics, requirement checks and every member's health."""
        sc, g = self.scenario, self.graph
        est = {k: v.detach().to(torch.float64).cpu() for k, v in sc.estimates(g, self.settings).items()}
        met = {k: v.detach().to(torch.float64).cpu() for k, v in sc.metrics(g, self.settings).items()}
        verdict = self.health.status(self.sums.z, self.sums.y if self.y_sig is not None else None,
                                     self.sums.check_steps)
        met.setdefault("z_rms_final", verdict["z_rms"].cpu())
        found, res = self._replayed()
        if res is not None:
            met.update(residual_metrics(res))
        held_out = self.validation()
        if held_out is not None:
            met.update({"validation_rmse": held_out.rmse, "validation_rmse_initial": held_out.rmse_initial,
                        "validation_fit_percent": held_out.fit_percent,
                        "validation_fit_percent_initial": held_out.fit_percent_initial})
        explained = determined = worse = None
        if found is not None:
            ident = self.graph.role("estimator")
            explained = ci.change_explained(ident, self.health.state["theta_ref"], self.health.state["k_ref"],
                                            ident.covariance).to(verdict["status"].device)
            determined = found.determined.to(verdict["status"].device)
        worse = fits_worse(met)
        dev = verdict["status"].device
        z_tol = self.health.criteria.z_tol
        white = None if res is None else (res.whiteness_p >= ci.WHITE_P).to(dev)     # NaN: not tested, not white
        theta_ok = verdict["theta_change"] <= self.health.criteria.theta_tol
        settled = Health.decide(verdict["status"], verdict["z_ratio"], z_tol, explained=explained, white=white,
                                theta_ok=theta_ok)
        verdict["status"] = Health.decide(
            settled, verdict["z_ratio"], z_tol, determined=determined,
            biased=None if found is None or found.biased is None else found.biased.to(dev),
            drifting=None if found is None or found.drifting is None else found.drifting.to(dev),
            worse=None if worse is None else worse.to(dev))
        health = self.health.report(verdict)
        health["why"] = self._plain(member_reasons(verdict, self.health.criteria, worse, found, white))
        if worse is not None:
            health["fits_worse"] = self._plain(worse.tolist())
        if found is not None:
            health["determined"] = self._plain((determined & (settled == STATUSES.index("converged"))).tolist())
            health["change_explained"] = self._plain(explained.tolist())
        if res is not None:
            health["residuals_white"] = self._plain([None if p != p else p >= ci.WHITE_P    # NaN: not tested
                                                     for p in res.whiteness_p.tolist()])
            matter, widening = ci.residuals_matter(self.graph.role("estimator").covariance, found)
            health["residuals_matter"] = self._plain(matter.tolist())
            health["residual_widening"] = self._plain(finite_list(widening))
            health["undetermined"] = self._plain(found.undetermined_keys)
            if found.biased is not None:
                health["biased"] = self._plain(found.biased.tolist())
                health["biased_keys"] = self._plain(found.biased_keys)
                health["bias_reason"] = self._plain(found.bias_reason)
            if found.drifting is not None:
                health["drifting"] = self._plain(found.drifting.tolist())
        members = (verdict["status"] == STATUSES.index("diverged")).nonzero().flatten().tolist()
        diverged = [{"member": b, "step": int(verdict["diverged_at"][b]),
                     "reason": (health["reason"] if self.batch == 1 else health["reason"][b])} for b in members]
        return {
            "scenario": sc.name, "steps": self.k, "batch": self.batch, "dtype": self.dtype_name,
            "device": str(self.device.type), "engine": self.graph.ran_engine or
            ("torch" if self.graph.native_status() else "native"),
            "engine_reason": self.graph.engine_reason if self.graph.ran_engine else self.graph.native_status(),
            "estimates": {k: self._values(v) for k, v in est.items()},
            "truth": self.truth_now(), "metrics": {k: self._values(v) for k, v in met.items()},
            "settings": dict(self.settings), "health": health, "status": health["status"], "diverged": diverged,
            "requirements": self._requirements(est, met),
            "warnings": tuning_warnings(self.graph) + fit_warnings(met) + self._settle_warnings(),
            "changes": {name: {k: self._values(v.detach().to(torch.float64).cpu()) for k, v in found_.items()}
                        for name, found_ in change_report(self.graph).items()},
            "validation": None if held_out is None else {
                k: v for k, v in held_out.summary().items() if k in ("source", "steps", "fit_steps", "state_fitted")},
            "intervals": {} if found is None else {
                k: {"level": found.level, "lower": self._values(found.lower(k)), "upper": self._values(found.upper(k)),
                    **({"bias": self._values(found.bias[k])} if found.bias and bool(found.biased.any()) else {}),
                    **self._no_interval(found, k)}
                for k in found.estimate},
        }

    def _no_interval(self, found: ci.Intervals, key: str) -> dict[str, Any]:
        """{'reason': ...}: why a member has no interval for ``key`` (None where it has one), or {} where every
        member has one."""
        missing = ~torch.isfinite(found.half_width[key])
        if not bool(missing.any()):
            return {}
        est = self.graph.role("estimator")
        pc = est.covariance
        alive = est.alive.cpu().tolist()
        settles = pc.settles.cpu().tolist()
        reasons = [None if not m else "diverged: the member was frozen" if not a else
                   "a direction of theta was not excited by the data (an eigenvalue of A below "
                   f"{ci.EXCITED})" if not s else "the parameters' covariance is not finite"
                   for m, a, s in zip(missing.tolist(), alive, settles)]
        return {"reason": self._plain(reasons)}

    def intervals(self) -> ci.Intervals | None:
        """The estimates' confidence intervals at the current step, or None when the run computes none or has
        not reached its convergence window (``_replayed``)."""
        return self._replayed()[0]

    def residuals(self) -> ci.Residuals | None:
        """The refined model's residual checks and fit on the replayed window (None as for ``intervals``)."""
        return self._replayed()[1]

    def _replayed(self) -> tuple[ci.Intervals | None, ci.Residuals | None]:
        """The replay of the convergence window (``rcotorch.verdict.intervals.replay``), done once per step."""
        if not self.intervals_on or self.snapshot is None:
            return None, None
        if self._intervals is None or self._intervals[0] != self.k:
            window = min(self.k - self.health.window_start, ci.REPLAY_STEPS)
            found = (None, None)
            if window >= 2:
                started = time.perf_counter()
                steps, settle = self._replay_span(window)
                physics, self._physics_note = None, None
                if ci.physical_blocks(self.graph):     # a simulated physical system to rebuild
                    with torch.no_grad():
                        now = self.scenario.estimates(self.graph, self.settings)
                    try:
                        physics = self.scenario.physics(self.settings, now, self.batch, DTYPES[self.dtype_name],
                                                        self.device)
                    except Exception as e:        # e.g. an estimate outside its setting's bounds
                        self._physics_note = (f"the physics at the estimates could not be built ({e}); the "
                                              "estimates' bias against it is not measured")
                rep = ci.replay(self.graph, self.snapshot, steps, settle, physics=physics,
                                progress=self._replay_progress)
                ident = self.graph.role("estimator")
                ident.record_covariance(rep.covariance)        # for the verdict and the scenario's figures
                transient = ci.remaining_transient(ident, self.health.state["theta_mid"], self.health.state["k_mid"],
                                                   rep.covariance)
                found = (ci.estimate_intervals(self.graph, lambda g: self.scenario.estimates(g, self.settings),
                                               rep.covariance, level=self.level,
                                               scales=self.scenario.scales(self.settings), transient=transient),
                         rep.residuals)
                self.timings["intervals"] = time.perf_counter() - started
            self._intervals = (self.k, *found)
        return self._intervals[1:]

    def _settle_warnings(self) -> list[str]:
        self._replayed()
        note = self._physics_note
        return settle_note(*self._settle, self.graph.known_sample_time()) + ([note] if note else [])

    def _replay_span(self, window: int) -> tuple[int, int | torch.Tensor]:
        """Steps to replay from the window's start, and how many of them only settle, per member: the window with
        its first quarter settling, or, where a member's frozen loop needs longer to forget the start
        (``loop_settle``), that long and then the window's last three quarters, running on past the run's end
        (simulated sources give the same streams there) or as far as recorded data reaches. Where that falls
        short of what a loop needs, the summary warns (``_settle_warnings``)."""
        quarter = int(ci.SETTLE * window)
        need = loop_settle(self.graph)
        if need is None:
            self._settle = (quarter, None, "")
            return window, quarter
        # A member whose loop barely decays would make the whole batch replay for that long: no member settles
        # for longer than the run has run.
        settle = need.clamp_min(quarter).clamp_max(max(quarter, self.k))
        why = "the replay settles for at most as long as the run ran"
        limit = self.graph.max_steps
        if limit is not None:
            reach = max(quarter, limit - self.health.window_start - (window - quarter))
            if bool((settle > reach).any()):
                why = "the recorded data end sooner"
            settle = settle.clamp_max(reach)
        short = settle < need
        self._settle = (int(settle[short].min()) if bool(short.any()) else quarter,
                        int(need[short].max()) if bool(short.any()) else None, why)
        return int(settle.max()) + window - quarter, settle

    def validation(self):
        """The refined model on held-out data (``rcotorch.verdict.validation.Validation``) at the current step, or None
        when the run or its scenario validates nothing or the validation failed (``validation_reason``)."""
        if not self.validation_on:
            return None
        if self._validation is None or self._validation[0] != self.k:
            from ..verdict.validation import validate
            started = time.perf_counter()
            found, reason = None, None
            plan = self.scenario.validation(self.graph, self.settings)
            if plan is None:
                reason = "the scenario has no held-out data"
            else:
                try:
                    found = validate(self.graph, **{"keep": ci.KEEP_MEMBERS, **plan})
                except RcoError as e:
                    reason = str(e)
                    logging.getLogger("rcotorch").warning("validation skipped: %s", reason)
            self._validation = (self.k, found, reason)
            self.timings["validation"] = time.perf_counter() - started
        return self._validation[1]

    @property
    def validation_reason(self) -> str | None:
        return None if self._validation is None else self._validation[2]

    def _plain(self, values: list):
        return values[0] if self.batch == 1 else values

    def _values(self, t: torch.Tensor):
        return self._plain(finite_list(t.reshape(self.batch)))

    def truth_now(self) -> dict[str, Any]:
        """The truths at the run's current step: a truth that changes during the run (``truth_history``) at its
        value then (a run that ends before a change is judged against the truth before it), the others as
        given. The history's times are in the known model's sample time (seconds), else in steps."""
        if not self.truth_history:
            return dict(self.truth)
        dt = self.graph.known_sample_time() or 1.0
        return {k: scenarios.truth_at(self.truth_history[k], self.k * dt) if k in self.truth_history else v
                for k, v in self.truth.items()}

    def _requirements(self, est: dict[str, torch.Tensor], met: dict[str, torch.Tensor]) -> dict[str, Any]:
        checks = {}
        truths = self.truth_now()
        for req in self.scenario.requirements:
            group, key = req.key.split(".", 1)
            t = (est if group == "estimates" else met).get(key)
            if t is None:
                continue
            truth = truths.get(key)
            q, ok = req.check(t.reshape(-1).to(torch.float64),
                              None if truth is None else torch.tensor(member_truth(truth, self.batch),
                                                                      dtype=torch.float64))
            checks[req.key] = {"requirement": req.describe(), "value": self._values(q),
                               "pass": bool(ok.all()), "member_pass": self._plain(ok.reshape(-1).tolist())}
        return checks

    def finish(self, figures: bool = True, close: bool = True, progress: bool | None = None) -> dict[str, Any]:
        """Write summary.json, the figures (PNG and TensorBoard) and a final checkpoint; release the folder
        (unless ``close`` is False). The run's own figures (from its history) are drawn by the drawing process
        handed to the run (``drawing``, as ``rcotorch run`` does) while this process makes the summary, draws the
        scenario's figures and writes summary.json and the checkpoint; else on a second thread while the files are
        written, after the scenario's figures (which may read the graph and use pyplot), drawn in this thread.
        ``progress``: show the parts of the end as a progress
        bar (None: where the steps showed one). ``timings`` then holds the seconds of each part: ``intervals``
        (the replay of the window and the intervals), ``validation``, ``summary`` (the rest of it), ``figures``,
        ``files`` (summary.json, the checkpoint, TensorBoard's last records) and ``end`` (all of it)."""
        started = time.perf_counter()
        parts = [("intervals and residual checks", self._replayed), ("validation", self.validation)]
        bar = None
        if progress or (progress is None and self.steps >= 5000):
            from tqdm import tqdm
            bar = tqdm(total=len(parts) + 2, desc="verdict", unit="part", mininterval=0, disable=None,
                       file=sys.stderr, bar_format="{desc}: {n_fmt}/{total_fmt} parts, {elapsed}{postfix}")
        waits, sent = [], 0.0                  # the drawing process's jobs, and the seconds taken to send them
        try:
            self._start_monitor()
            if self.sums.pending_log():
                self._log()
            for what, part in parts:             # each computed once, then kept for the summary
                if bar is not None:
                    bar.set_postfix_str(what)
                    self._replay_progress = functools.partial(_say_share, bar, what)
                part()
                self._replay_progress = None
                if figures and part == self._replayed:
                    sent += self._send_figures(waits, held_out=False)
                if bar is not None:
                    bar.update(1)
            if figures and self.validation_on:
                sent += self._send_figures(waits, held_out=True)
            run_pngs = None
            if waits:
                run_pngs = lambda: {name: png for wait in waits for name, png in wait().items()}   # noqa: E731
            t = time.perf_counter()
            summary = self.summary()
            self.timings["summary"] = time.perf_counter() - t
            if bar is not None:
                bar.set_postfix_str("figures" if figures else "files")
                bar.update(1)
            t = time.perf_counter() - sent
            if figures:
                scenario_pngs = {}
                if self._own_figures():
                    from .figures import pngs
                    scenario_pngs = pngs(self.scenario.figures(self.graph, self.settings))
                if run_pngs is None:
                    from .figures import draw_meanwhile, run_figures
                    run_pngs = draw_meanwhile(lambda: run_figures(self))
            t_files = time.perf_counter()
            write_text(self.out / "summary.json", to_json(summary) + "\n")
            self.save()
            self.timings["files"] = time.perf_counter() - t_files
            if figures:
                self.monitor.figures({**run_pngs(), **scenario_pngs}, self.out)
            self.monitor.final_intervals(self.intervals(), sorted({*self.history["step"], self.k}),
                                         self.band_over_time())
            self.monitor.close(summary)
            self.folder.register()
            self.timings["figures"] = time.perf_counter() - t - self.timings["files"] if figures else 0.0
            if bar is not None:
                bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        self.timings["end"] = time.perf_counter() - started
        with contextlib.suppress(OSError, RcoError):
            self.folder.log("the end of the run: " + ", ".join(f"{k} {v:.2f} s" for k, v in self.timings.items()))
        if close:
            self.close()
        return summary

    def _send_figures(self, waits: list, held_out: bool) -> float:
        """Send the run's figures to the drawing process (where one was handed to the run), which draws them while
        this one goes on: after the intervals, those that do not show validation (drawn while the run validates),
        after validation the rest (drawn while the run makes its summary and the scenario's own figures); neither
        reads the summary. Adds the job's wait to ``waits``; returns the seconds taken."""
        if self.drawing is None or not self.drawing.started:
            return 0.0
        from .figure_data import HELD_OUT_FIGURES, RUN_FIGURES, run_figure_data
        t = time.perf_counter()
        if not self.validation_on:         # one job: every figure
            only, more = None, False
        elif held_out:
            only, more = HELD_OUT_FIGURES, False
        else:
            only, more = [n for n in RUN_FIGURES if n not in HELD_OUT_FIGURES], True
        waits.append(self.drawing.draw(run_figure_data(self, held_out=held_out, only=only), more=more))
        return time.perf_counter() - t

    def _own_figures(self) -> bool:
        """Whether the scenario draws figures of its own (``Scenario.figures``; drawn in this process)."""
        return type(self.scenario).figures is not scenarios.Scenario.figures


def _say_share(bar, what: str, done: int, total: int) -> None:
    """Show on the end's progress bar how far ``what`` has come."""
    bar.set_postfix_str(f"{what} {100 * done // max(1, total)}%")


# A stretch of at least this many member-steps starts the imports of the end of the run beside it (a shorter one
# would only slow its own steps: the imports hold Python between the engine's calls).
PREFETCH_MEMBER_STEPS = 1 << 24
_PREFETCHED: set[str] = set()


def prefetch(figures: bool) -> None:
    """Import what the end of a run needs (matplotlib and the figures) on a background thread, once per process:
    the engine and the verdict's kernels release Python while they work, so the imports run beside them instead of
    after them."""
    wanted = [m for m, on in (("rcotorch.run.figures", figures),)
              if on and m not in _PREFETCHED and m not in sys.modules]
    if not wanted:
        return
    _PREFETCHED.update(wanted)

    def load() -> None:
        for module in wanted:
            with contextlib.suppress(Exception):       # an import that fails is reported where it is used
                importlib.import_module(module)
    threading.Thread(target=load, name="rcotorch-imports", daemon=True).start()


# What a run without figures imports as it steps and ends (its TensorBoard records, validation), in ``preload``.
RUN_MODULES = ("rcotorch.verdict.validation", "torch.utils.tensorboard.summary", "tensorboard.compat.proto.event_pb2",
               "tensorboard.compat.proto.summary_pb2", "tensorboard.plugins.hparams.api_pb2",
               "tensorboard.plugins.hparams.metadata", "google_crc32c", "torch.utils.serialization")


def preload() -> None:
    """Import at once what a run without figures imports as it steps and ends (``RUN_MODULES``): a process that
    forks the runs of a sweep's shards loads them once, before it forks, instead of in every forked process."""
    for module in RUN_MODULES:
        importlib.import_module(module)


def member_truth(truth, batch: int) -> list:
    """A truth value (shared or per member) as one value per member."""
    return list(truth) if isinstance(truth, (list, tuple)) else [truth] * batch
