"""Running a scenario: stepping, member health, TensorBoard monitoring, checkpoints, figures, ``summary.json``.

Cadences, fixed when a run is created and kept by a resume:

* health checks (``Health.is_check``): every ``health.check_every(steps)`` steps (2% of the run) in the
  convergence window, every second such step before it (about 30 per run, the same for any batch size);
* logs (TensorBoard and the figures' history) every ``log_every`` steps: about 1000 per run, fewer for large
  batches (``default_log_every``), since a log costs about as much as a few steps of the whole batch; on
  check steps where the interval is longer than the checks';
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
import re
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import orjson
import torch

from ..errors import CheckpointError, ConfigError, RcoError, SettingError
from ..estimator.tracking import ChangeDetector, _closed_loop, change_report
from ..system import available_memory
from ..verdict import intervals as ci
from ..verdict.health import STATUSES, Criteria, Health, check_every, finite_list
from . import scenario as scenarios
from .monitor import Monitor, traced_members
from .outputs import OutputFolder, load_checkpoint, save_checkpoint, write_text

DTYPES = {"float64": torch.float64, "float32": torch.float32}
CHECKPOINT = "checkpoint.pt"
CHECKPOINT_FORMAT = 4   # the layout of checkpoint.pt (4: the graph's state at the window's start, for intervals)
LOG_BUDGET = 2 ** 21     # member-values logged per run, at most (but at least MIN_LOGS logs)
MIN_LOGS, MAX_LOGS = 20, 1000
MIN_LOGS_CHANGE = 250    # at least, in a run that follows a change (a truth that changes, or a change detector)
# The logs of a run may take about LOG_SHARE of the engine's time, or LOG_FREE_S seconds where that is more: a
# log (with the stop of the engine before it) costs about LOG_US + LOG_US_PER_MEMBER * batch microseconds, a
# member-step of the native engine at least ENGINE_NS nanoseconds (docs/cli.md).
LOG_SHARE, LOG_FREE_S, LOG_US, LOG_US_PER_MEMBER, ENGINE_NS = 0.1, 0.01, 250.0, 0.7, 30.0
# The most steps a run may take: its step counters are 64-bit integers, but the bound is time: at the engine's
# fastest (ENGINE_NS a member-step) 10^12 steps of one member already take more than 8 hours.
MAX_STEPS = 10 ** 12
# The least memory a run holds while it steps (``memory_needed``), measured on sdof-stiffness: the known model's
# Markov parameters are made one small tensor a sample, about MARKOV_SAMPLE_BYTES each until they are stacked
# (``derive_markov`` examines max(4 nu, 64) + nu samples); the estimator's window and Markov filter hold about
# STATE_NUMBERS numbers per member and Markov parameter; every member about MEMBER_BYTES more (its RLS state,
# sums and health statistics). The intervals' and validation's replays at the end of a run need more.
MARKOV_SAMPLE_BYTES, STATE_NUMBERS, MEMBER_BYTES = 600, 5, 1500
HISTORY_MAX = 1000
HISTORY_MEMBERS = 8      # members kept in the history (the traced ones, which the figures draw)
# What ``--resume`` accepts besides the checkpoint's own settings (anything else must match the checkpoint).
RESUME_CHANGEABLE = ("--steps", "--device", "--out", "--overwrite", "--checkpoint-every", "--threads", "--engine",
                     "--quiet", "--no-figures")


class Interrupted(Exception):
    """A run stopped on request (Ctrl-C, SIGTERM, SIGHUP) after saving a checkpoint."""

    def __init__(self, step: int | None, checkpoint: Path | None):
        super().__init__("stopped" if step is None else f"stopped at step {step}, checkpoint {checkpoint}")
        self.step, self.checkpoint = step, checkpoint


def _device(name: str) -> torch.device:
    hint = "valid devices: cpu, cuda, cuda:N"
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise ConfigError(f"--device {name!r} is not a device; {hint}") from None
    if dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"--device {name!r}: rcotorch runs on cpu or cuda; {hint}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"--device {name} asked for, but torch sees no CUDA device on this machine")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return dev


def _positive_int(value, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{what} must be a positive integer, got {value!r}")
    return value


def steps_bound_reason() -> str:
    """Why a run takes at most MAX_STEPS steps."""
    hours = MAX_STEPS * ENGINE_NS * 1e-9 / 3600
    return f"at the engine's fastest, about {ENGINE_NS:g} ns a member-step, that many take more than {int(hours)} hours"


def _steps(value, what: str) -> int:
    """A number of steps: a positive integer, at most MAX_STEPS."""
    _positive_int(value, what)
    if value > MAX_STEPS:
        raise ConfigError(f"{what} must be at most {MAX_STEPS}, got {value}: {steps_bound_reason()}")
    return value


def memory_needed(scenario: scenarios.Scenario, settings: Mapping[str, Any], batch: int, dtype: str
                  ) -> list[tuple[str, int]]:
    """What a run of ``settings`` holds at least while it steps, in bytes, part by part (its constants above):
    the known model's Markov parameters and the estimator's window where the scenario has the setting ``nu``,
    and the members' state."""
    parts = []
    nu = _nu(scenario, settings)
    if nu is not None:
        samples = max(4 * nu, 64) + nu
        parts.append((f"the known model's {samples} Markov parameters", samples * MARKOV_SAMPLE_BYTES))
        parts.append((f"the estimator's window of {nu} steps", batch * nu * STATE_NUMBERS * DTYPES[dtype].itemsize))
    parts.append((f"{batch} member{'s' * (batch != 1)}' state", batch * MEMBER_BYTES))
    return parts


def _nu(scenario: scenarios.Scenario, settings: Mapping[str, Any]) -> int | None:
    """The run's number of Markov parameters (the setting ``nu``, the largest of per-member ones), or None."""
    nu = settings.get("nu") if "nu" in scenario.settings else None
    nu = max(nu) if isinstance(nu, list) and nu else nu
    return nu if isinstance(nu, int) and not isinstance(nu, bool) and nu > 0 else None


def _size(n: float) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e8 else f"{n / 1e6:.0f} MB"


def check_memory(scenario: scenarios.Scenario, settings: Mapping[str, Any], batch: int, dtype: str) -> None:
    """Refuse (``SettingError`` naming nu and the batch) a run whose ``memory_needed`` exceeds the
    ``available_memory``, before anything is allocated."""
    parts = memory_needed(scenario, settings, batch, dtype)
    needed = sum(n for _, n in parts)
    found = available_memory()
    if found is None or needed <= found[0]:
        return
    nu = _nu(scenario, settings)
    drivers, smaller = (f"batch {batch}", "batch") if nu is None else (f"nu = {nu} and batch {batch}", "nu or batch")
    what = "; ".join(f"{name} {_size(n)}" for name, n in parts if n >= needed / 100)
    raise SettingError(f"scenario '{scenario.name}' with {drivers} needs at least {_size(needed)} of memory while "
                       f"it steps ({what}), but {_size(found[0])} is available ({found[1]}); choose a smaller "
                       f"{smaller}", settings=("batch",) if nu is None else ("nu", "batch"))


def default_log_every(steps: int, batch: int, follows_change: bool = False) -> int:
    """Steps between logs: as many logs as take about LOG_SHARE of the engine's time (or LOG_FREE_S), at most
    MAX_LOGS and LOG_BUDGET member-values in all (since a log reads every member), but at least MIN_LOGS, or
    MIN_LOGS_CHANGE in a run that follows a change (its figures draw the change and the estimates' path after
    it, which a few dozen points would join by straight lines across the change). An interval
    longer than the health checks' (in the convergence window) is the nearest multiple of twice theirs (their
    spacing before the window), a shorter one a divisor of theirs near it, so that logs fall on check steps or
    checks on log steps: every stop of the engine costs a pass over the whole batch's state."""
    budget_us = max(LOG_SHARE * steps * batch * ENGINE_NS * 1e-3, LOG_FREE_S * 1e6)
    affordable = budget_us / (LOG_US + LOG_US_PER_MEMBER * batch)
    least = MIN_LOGS_CHANGE if follows_change else MIN_LOGS
    logs = min(MAX_LOGS, max(MIN_LOGS, min(max(int(affordable), least), LOG_BUDGET // batch)))
    every, check = max(1, math.ceil(steps / logs)), check_every(steps)
    if every > check:
        return 2 * check * max(1, round(every / (2 * check)))
    n = max(1, check // every)                  # a divisor of the checks' spacing, no shorter: checks fall on logs
    while check % n:
        n -= 1
    return check // n


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
        self.batch = _positive_int(batch, "batch")
        self.dtype_name, self.device = dtype, _device(device)
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise ConfigError(f"seed must be an integer, got {seed!r}")
        if members is not None:
            self.settings = self.scenario.resolve_members(dict(overrides or {}, **({} if seed is None else
                                                                                  {"seed": seed})), members)
        else:
            self.settings = self.scenario.resolve(overrides, seed)
        self.steps = _steps(steps if steps is not None else self.scenario.default_steps(self.settings), "steps")
        self.out = Path(out) if out else default_out(self.scenario.name)
        self.folder = OutputFolder(self.out, "run")
        self._mode = "overwrite" if overwrite else "new"
        if log_every is not None:
            _positive_int(log_every, "log_every")
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
        self.counters = {"acc": 0, "log": 0, "mark": 0}   # steps summed in acc, log_z, mark_z
        self.sums = {k: torch.zeros(self.batch, dtype=torch.float64, device=self.device)
                     for k in ("z", "y", "log_z", "mark_z", "z_rms_last")}
        self.sums["z_rms_last"].fill_(math.nan)
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
        until = self.steps if until is None else _steps(until, "until")
        if checkpoint_every is not None:
            _positive_int(checkpoint_every, "--checkpoint-every")
        self.graph.check_steps(until - self.k)
        self._start_monitor()
        if self.batch * (until - self.k) >= PREFETCH_MEMBER_STEPS:
            prefetch(figures=self.figures_expected)
        bar = None
        if progress or (progress is None and until - self.k >= 5000):
            from tqdm import tqdm
            bar = tqdm(total=until, initial=self.k, desc=desc or self.scenario.name, unit="step",
                       mininterval=0.5, disable=None, file=sys.stderr)
        acc = {self.z_sig: self.sums["z"]}
        if self.y_sig is not None and self.y_sig != self.z_sig:
            acc[self.y_sig] = self.sums["y"]
        try:
            self._take_snapshot()
            while self.k < until:
                k = self.k
                end = min(until, _next_log(k, self.log_every), self.health.next_check(k),
                          _next(k, checkpoint_every) if checkpoint_every else until)
                self.graph.advance(end - k, accumulate=acc)
                self.counters["acc"] += end - k
                if self.health.is_check(end):
                    self._check()
                self._take_snapshot()
                self.folder.check()
                if _is_log(end, self.log_every):
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
        """A health check: the sums since the last check go to the health statistics and the log's sums."""
        s, c = self.sums, self.counters
        s["log_z"] += s["z"] - s["mark_z"]
        c["log"] += c["acc"] - c["mark"]
        self.health.check(s["z"], s["y"] if self.y_sig is not None else None, c["acc"])
        for key in ("z", "y", "mark_z"):
            s[key].zero_()
        c["acc"] = c["mark"] = 0

    def _log(self) -> None:
        s, c = self.sums, self.counters
        n = c["log"] + c["acc"] - c["mark"]
        z_rms = torch.sqrt((s["log_z"] + s["z"] - s["mark_z"]) / max(n, 1))
        s["log_z"].zero_()
        s["mark_z"].copy_(s["z"])
        c["log"], c["mark"] = 0, c["acc"]
        s["z_rms_last"].copy_(z_rms)
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

    def _pending_log(self) -> int:
        c = self.counters
        return c["log"] + c["acc"] - c["mark"]

    # --- checkpoints ---------------------------------------------------------------------------------------
    def save(self, path: str | Path | None = None) -> Path:
        """Write a checkpoint (atomically; the previous one is replaced only once this one is complete)."""
        self.open_output()
        path = Path(path) if path else self.out / CHECKPOINT
        state = {
            "format": CHECKPOINT_FORMAT, "scenario": self.scenario.name, "steps": self.steps, "batch": self.batch,
            "dtype": self.dtype_name, "settings": self.settings, "log_every": self.log_every,
            "trace": self.trace, "graph": self.graph.state_dict(),
            "history": {k: torch.stack(v) if k != "step" and v else v for k, v in self.history.items()},
            "history_members": self.history_members, "counters": dict(self.counters),
            "p_history": torch.stack(self.p_history) if self.p_history else None,
            "sums": {k: v.cpu() for k, v in self.sums.items()}, "health": self.health.state_dict(),
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
        if not directory.is_dir():
            raise CheckpointError(f"--resume {directory}: no such folder")
        OutputFolder(directory, "run").check_free()      # not while another process writes the run
        path = directory / CHECKPOINT
        if not path.is_file():
            raise CheckpointError(f"--resume {directory}: no {CHECKPOINT} there")
        state = load_checkpoint(path)
        version = state.get("format") if isinstance(state, dict) else None
        if version != CHECKPOINT_FORMAT:
            raise CheckpointError(f"{path}: written by another version of rcotorch (format {version})")
        try:
            run = cls._from_state(path, state, steps, device, out or directory, expect or {}, scenario)
        except RcoError:
            raise
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, RuntimeError) as e:
            # A checkpoint that hashes right but whose contents do not fit a run of its scenario.
            raise CheckpointError(f"{path}: the checkpoint does not hold a run this version can continue "
                                  f"({_what_failed(e)}); start the run again") from e
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
        _check_resume(path, state, expect)
        if scenario is not None and scenario.name != state["scenario"]:
            raise CheckpointError(f"--resume {path.parent}: the checkpoint is a run of {state['scenario']!r}, not "
                                  f"{scenario.name!r}")
        run = cls(scenario or state["scenario"], steps=steps or state["steps"], batch=state["batch"],
                  device=device or "cpu", dtype=state["dtype"], out=out,
                  overrides={k: v for k, v in state["settings"].items() if not isinstance(v, list)},
                  members=_members(state["settings"], state["batch"]), log_every=state["log_every"],
                  trace=state["trace"], health=Criteria(**state["health"]["criteria"]),
                  intervals=state["intervals"], level=state["level"], validation=state.get("validation", True))
        graph = run.graph.state_dict()      # its blocks check their tensors' shapes as they load them
        _same_layout("graph", state["graph"], graph, shapes=False)
        if state["snapshot"] is not None:
            _same_layout("snapshot", state["snapshot"], graph, shapes=False)
        _same_layout("sums", state["sums"], run.sums)
        _same_layout("counters", state["counters"], run.counters)
        _same_layout("health", state["health"], run.health.state_dict())
        run.graph.load_state_dict(state["graph"])
        run.history = {k: list(v.unbind(0)) if isinstance(v, torch.Tensor) else list(v)
                       for k, v in state["history"].items()}
        run.history_members = list(state["history_members"])
        run.p_history = [] if state.get("p_history") is None else list(state["p_history"].unbind(0))
        run.tb_origin = state.get("tb_origin")
        run.counters = {k: int(v) for k, v in state["counters"].items()}
        run.sums = {k: v.to(run.device) for k, v in state["sums"].items()}
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
        verdict = self.health.status(self.sums["z"], self.sums["y"] if self.y_sig is not None else None,
                                     self.counters["acc"])
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
        settled = Health.decide(verdict["status"], verdict["z_ratio"], z_tol, explained=explained)
        verdict["status"] = Health.decide(
            settled, verdict["z_ratio"], z_tol, determined=determined,
            biased=None if found is None or found.biased is None else found.biased.to(dev),
            drifting=None if found is None or found.drifting is None else found.drifting.to(dev),
            worse=None if worse is None else worse.to(dev))
        health = self.health.report(verdict)
        health["why"] = self._plain(_why(verdict, self.health.criteria, worse, found))
        if worse is not None:
            health["fits_worse"] = self._plain(worse.tolist())
        if found is not None:
            health["determined"] = self._plain((determined & (settled == STATUSES.index("converged"))).tolist())
            health["change_explained"] = self._plain(explained.tolist())
        if res is not None:
            health["residuals_white"] = self._plain((res.whiteness_p >= ci.WHITE_P).tolist())
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
        return _settle_note(*self._settle, self.graph.known_sample_time()) + ([note] if note else [])

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
        (unless ``close`` is False). The run's own figures (from its history) are drawn on a second thread
        while summary.json and the checkpoint are written; the scenario's figures (which may read the graph
        and use pyplot) are drawn before, in this thread. ``progress``: show the parts of the end as a progress
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
        try:
            self._start_monitor()
            if self._pending_log():
                self._log()
            for what, part in parts:             # each computed once, then kept for the summary
                if bar is not None:
                    bar.set_postfix_str(what)
                    self._replay_progress = functools.partial(_say_share, bar, what)
                part()
                self._replay_progress = None
                if bar is not None:
                    bar.update(1)
            t = time.perf_counter()
            summary = self.summary()
            self.timings["summary"] = time.perf_counter() - t
            if bar is not None:
                bar.set_postfix_str("figures" if figures else "files")
                bar.update(1)
            t = time.perf_counter()
            if figures:
                from .figures import draw_meanwhile, pngs, run_figures
                scenario_pngs = pngs(self.scenario.figures(self.graph, self.settings))
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


PRIOR_SHARE = 0.5     # P_ii / p0 above this at the end: the data did less than the prior to fix parameter i


def loop_settle(graph) -> torch.Tensor | None:
    """Steps each member's frozen loop needs to forget its start, (B,): ``ci.SETTLE_TAUS`` time constants of the
    slowest decaying mode (|eigenvalue| < 1) of the known model with the estimator's loop closed at its present
    theta (the loop of ``rcotorch.estimator.tracking.closed_loop_markov``), at most ``ci.SETTLE_MAX``; None where
    that loop cannot be formed (a known model that is not an ``LTI``, features, a regressor fed through another
    block)."""
    est = graph.role("estimator")
    try:
        A = _closed_loop(graph, est.theta.detach(), None, None, "u", "y", None)[0]
    except (ConfigError, KeyError, AttributeError, TypeError, ValueError, RuntimeError):
        return None
    A = A.detach().to("cpu", torch.float64)
    A = torch.where(torch.isfinite(A).flatten(1).all(1).reshape(-1, 1, 1), A, 0.0)   # a diverged member: none
    mag = torch.linalg.eigvals(A).abs()
    rho = torch.where(mag < 1.0 - 1e-12, mag, 0.0).amax(-1) if mag.shape[-1] else torch.zeros(mag.shape[0])
    taus = torch.where(rho > 0, ci.SETTLE_TAUS / -torch.log(rho.clamp_min(1e-300)), 0.0)
    return taus.clamp_max(ci.SETTLE_MAX).ceil().to(torch.int64).to(est.theta.device)


def _settle_note(settle: int, need: int | None, why: str, dt: float | None) -> list[str]:
    if need is None or settle >= need:
        return []
    unit = (lambda n: f"{n * dt:.4g} s") if dt else (lambda n: f"{n} steps")
    return [f"the intervals' replay settled for {unit(settle)} where the refined loop's slowest mode needs "
            f"{unit(need)} ({ci.SETTLE_TAUS:g} time constants) to forget the window's start: {why}; the "
            "intervals and residual checks may carry that transient"]


def tuning_warnings(graph) -> list[str]:
    """Settings far off for the data, judged at the end of a run: a p0 so small against the regressors that
    the data barely moved P from p0 I (P_ii / p0 > ``PRIOR_SHARE``; with P^-1 = I / p0 + sum Psi Psi^T that
    means p0 sum psi_i^2 < 1, so theta stays near its initial value). Members that forget (lam < 1) are not
    judged: their P is renewed from the data, and p0 matters little."""
    est = graph.role("estimator") if "estimator" in graph.roles else None
    if est is None or not hasattr(est, "P") or est.P.shape[0] == 0:
        return []
    B = est.P.shape[0]
    p0 = est.p0.to(torch.float64).reshape(-1, 1).expand(B, 1)
    lam = torch.as_tensor(est.lam, dtype=torch.float64).reshape(-1, 1).expand(B, 1).to(p0.device)
    share = torch.diagonal(est.P.to(torch.float64), dim1=1, dim2=2) / p0              # (B, n_eta)
    stuck = (share > PRIOR_SHARE) & (lam >= 1.0)
    if not bool(stuck.any()):
        return []
    members = stuck.any(1).nonzero().flatten().tolist()
    names = getattr(est, "theta_names", None) or [f"theta[{i}]" for i in range(share.shape[1])]
    which = sorted({names[i] for i in stuck.any(0).nonzero().flatten().tolist() if i < len(names)})
    info = (p0 / share.clamp_min(1e-300) - p0).clamp_min(0) / p0.square()             # sum psi_i^2
    suggest = float((1e3 / info[stuck].clamp_min(1e-300)).median())
    where = f"member {members[0]}" if len(members) == 1 else f"{len(members)} members"
    return [f"p0 = {float(p0[members[0], 0]):.3g} is small for the regressors ({where}): the data moved P by less "
            f"than half from p0 I for {', '.join(which)}, so theta stays near its initial value; "
            f"try p0 of about {suggest:.2g}"]


FIT_WORSE = 5.0        # percentage points: a refined model this much below the initial model's fit went astray
_FITS = (("over the run's last window", "fit_percent", "fit_percent_initial"),
         ("on the held-out data", "validation_fit_percent", "validation_fit_percent_initial"))


def _fit_pairs(met: Mapping[str, torch.Tensor]):
    """For each fit the run computed: what it is over, the refined and the initial model's fits (B,) and where
    the refined one is more than ``FIT_WORSE`` points below."""
    for what, refined, initial in _FITS:
        if refined in met and initial in met:
            r, i = (met[key].detach().to(torch.float64).cpu().reshape(-1) for key in (refined, initial))
            yield what, r, i, r < i - FIT_WORSE


def fits_worse(met: Mapping[str, torch.Tensor]) -> torch.Tensor | None:
    """(B,) bool: the members whose refined model fits the data worse than the initial (known) model did, on the
    run's last window (``fit_percent`` against ``fit_percent_initial``) or on held-out data
    (``validation_fit_percent``), by more than ``FIT_WORSE`` points; None where no fit was computed. A
    refinement exists to explain the data better; one that explains it worse went astray (an unstable
    adaptation, a Markov window much shorter than the known model's response), whatever its estimates'
    intervals say, so such a member is not ``converged``."""
    out = None
    for _, _, _, worse in _fit_pairs(met):
        out = worse if out is None else out | worse
    return out


def fit_warnings(met: Mapping[str, torch.Tensor]) -> list[str]:
    """The warnings for ``fits_worse``: for each fit, the members below the initial model's and both fits."""
    out = []
    for what, r, i, worse in _fit_pairs(met):
        if not bool(worse.any()):
            continue
        members = worse.nonzero().flatten().tolist()
        where = f"member {members[0]}" if len(members) == 1 else f"{len(members)} of {len(r)} members"
        out.append(f"the refined model fits the data worse than the initial model {what} in {where} (fit "
                   f"{_span(r[worse])} % against {_span(i[worse])} %): the refinement went astray there; a longer "
                   f"Markov window (nu), forgetting nearer 1 or a smaller p0 may help")
    return out


def _span(t: torch.Tensor) -> str:
    """A value, or the range of several, in percent with one decimal."""
    return f"{float(t.min()):.1f}" if len(t) == 1 else f"{float(t.min()):.1f}..{float(t.max()):.1f}"


def residual_metrics(res: ci.Residuals) -> dict[str, torch.Tensor]:
    """The residual checks as per-member metrics: the fit in percent of the refined and the initial model, the
    largest |autocorrelation| of z over lags 1..L and |cross-correlation| of z with w over lags 0..L (to be read
    against ``residual_bound``, 1.96 / sqrt(N)), and the Ljung-Box p-value that z is white."""
    B = res.fit.shape[0]
    out = {"fit_percent": res.fit, "fit_percent_initial": res.fit_initial,
           "z_autocorr_max": res.autocorr[:, 1:].abs().flatten(1).amax(1),
           "z_whiteness_p": res.whiteness_p}
    if res.xcorr is not None:
        out["z_w_xcorr_max"] = res.xcorr.abs().flatten(1).amax(1)
    out["residual_bound"] = torch.full((B,), res.bound, dtype=torch.float64)
    return out


def _next(k: int, every: int) -> int:
    """The first multiple of ``every`` after ``k``."""
    return (k // every + 1) * every


EARLY_LOGS = 4          # logs before the first interval: at its halves every / 2, every / 4, ...


def _early(every: int) -> list[int]:
    """The steps of the logs before the first interval, in order (integer halves, at least step 1)."""
    return sorted({every >> j for j in range(1, EARLY_LOGS + 1)} - {0})


def _is_log(k: int, every: int) -> bool:
    """Whether a run logs after step k: every ``every`` steps, and before the first of those at every / 2,
    every / 4, ... (``EARLY_LOGS`` of them), so that the start of a run, where estimates move most, is seen on
    a log time axis too, while the logs at the regular interval stay the most."""
    return k % every == 0 or (0 < k < every and k in _early(every))


def _next_log(k: int, every: int) -> int:
    """The first log step after step k (``_is_log``)."""
    return next((step for step in _early(every) if step > k), None) or _next(k, every)


def _check_resume(path: Path, state: Mapping[str, Any], expect: Mapping[str, Any]) -> None:
    """Refuse a resume that asks for another scenario, batch, seed, dtype or setting than the checkpoint's."""
    changeable = f"a resume keeps the run's settings; it accepts {', '.join(RESUME_CHANGEABLE)}"
    given = {"name": state["scenario"], "batch": state["batch"], "dtype": state["dtype"],
             "seed": state["settings"].get("seed")}
    for key, have in given.items():
        want = expect.get(key)
        if want is not None and want != have:
            flag = "scenario" if key == "name" else f"--{key}"
            raise CheckpointError(f"--resume {path.parent}: the checkpoint's run has {flag} {have!r}, not "
                                  f"{want!r}; {changeable}")
    overrides = dict(expect.get("overrides") or {})
    if overrides:
        resolved = scenarios.get(state["scenario"]).resolve(overrides)
        for key in overrides:
            if resolved[key] != state["settings"].get(key):
                raise CheckpointError(f"--resume {path.parent}: --set {key}={overrides[key]} differs from the "
                                      f"checkpoint's {key} = {state['settings'].get(key)!r}; {changeable}")


def _same_layout(what: str, got: Any, want: Mapping[str, Any], shapes: bool = True) -> None:
    """Raise ValueError unless a checkpoint's ``got`` has the entries of ``want`` (a fresh run's) and, with
    ``shapes``, each tensor of ``want``'s shape."""
    if not isinstance(got, Mapping):
        raise ValueError(f"{what}: a {type(got).__name__}, not a table")
    missing, unknown = sorted(map(str, set(want) - set(got))), sorted(map(str, set(got) - set(want)))
    if missing or unknown:
        raise ValueError(f"{what}: " + "; ".join([f"missing {', '.join(missing[:3])}"] * bool(missing)
                                                  + [f"unknown {', '.join(unknown[:3])}"] * bool(unknown)))
    for key, v in want.items() if shapes else ():
        if isinstance(v, torch.Tensor) and (not isinstance(got[key], torch.Tensor) or got[key].shape != v.shape):
            shape = tuple(got[key].shape) if isinstance(got[key], torch.Tensor) else type(got[key]).__name__
            raise ValueError(f"{what}: {key} has shape {shape}, not {tuple(v.shape)}")


def _what_failed(e: BaseException) -> str:
    """A short, one-line account of an error met reading a checkpoint's contents."""
    if isinstance(e, KeyError):
        return f"missing {e.args[0]!r}" if e.args else "an entry is missing"
    text = " ".join(str(e).split()).rstrip(".") or type(e).__name__
    text = re.sub(r"^Error\(s\) in loading state_dict for \w+: ", "graph: ", text)    # torch's load_state_dict
    return text if len(text) <= 200 else text[:197] + "..."


def member_truth(truth, batch: int) -> list:
    """A truth value (shared or per member) as one value per member."""
    return list(truth) if isinstance(truth, (list, tuple)) else [truth] * batch


def _members(settings: Mapping[str, Any], batch: int) -> list[dict[str, Any]] | None:
    """Per-member settings of a resolved batch (the inverse of ``Scenario.resolve_members``)."""
    varying = {k: v for k, v in settings.items() if isinstance(v, list)}
    if not varying:
        return None
    return [{k: v[b] for k, v in varying.items()} for b in range(batch)]


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


def _why(verdict: Mapping[str, torch.Tensor], criteria: Criteria, worse: torch.Tensor | None,
         found: ci.Intervals | None) -> list[str | None]:
    """Per member, why it is not converged, undetermined or biased, in a few words (None for a converged or
    diverged member: a diverged one has its ``reason``)."""
    code = verdict["status"].cpu().tolist()
    ratio = verdict["z_ratio"].cpu().tolist()
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
            elif not ratio[b] <= criteria.z_tol:
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
    """An estimate with its interval: 'value ± half-width' for one member, the values' range and the median
    half-width for a batch."""
    if interval is None:
        return _fmt(v)
    lo, hi = interval["lower"], interval["upper"]
    if not isinstance(v, list):
        return _fmt(v) + ("" if lo is None or hi is None else f" ± {(hi - lo) / 2:.2g}")
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
