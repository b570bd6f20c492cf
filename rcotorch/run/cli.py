"""Command line: ``rcotorch list``, ``rcotorch show NAME``, ``rcotorch run NAME [options]``, ``rcotorch sweep
CONFIG [options]``, ``rcotorch tune NAME|CONFIG [options]``.

Exit codes: 0 the run passed its requirements (a sweep finished), 1 a requirement failed, 2 bad input or
environment (a setting, file, folder or checkpoint, a full disk, an output folder deleted during the run, a run
that needs more memory than there is or that ran out of it; one line on stderr names it and says what to do),
3 an internal error (one line on stderr, the traceback in the output folder's ``rcotorch.log``), 128 + the
signal's number when stopped by a signal after
saving a checkpoint: 130 Ctrl-C (SIGINT), 143 SIGTERM, 129 SIGHUP (the message says how to resume; a signal
while a finished run writes its summary stops that at once). See docs/cli.md.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import shlex
import signal
import sys
import tempfile
import threading
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..errors import ConfigError, OutputError, RcoError, SettingError
from .control import STOP_SIGNALS

EXIT_PASS, EXIT_FAILED, EXIT_INPUT, EXIT_INTERNAL = 0, 1, 2, 3


def _settings(pairs: list[str]) -> dict[str, str]:
    out = {}
    for item in pairs:
        if "=" not in item:
            raise ConfigError(f"--set expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def _positive(value: int | None, flag: str) -> None:
    if value is not None and value < 1:
        raise ConfigError(f"{flag} must be a positive integer, got {value}")


def _steps(value: int | None) -> None:
    """--steps: a positive integer, at most the bound of ``runner.MAX_STEPS``."""
    from .runner import MAX_STEPS, steps_bound_reason
    _positive(value, "--steps")
    if value is not None and value > MAX_STEPS:
        raise ConfigError(f"--steps {value}: a run takes at most {MAX_STEPS} steps: {steps_bound_reason()}; "
                          "choose fewer")


def _seed(value: int | None) -> None:
    """--seed: an integer in 0..SEED_MAX, the seeds whose random streams differ."""
    from .scenario import SEED_MAX
    if value is not None and not 0 <= value <= SEED_MAX:
        raise ConfigError(f"--seed {value}: a seed must be an integer in 0..{SEED_MAX}: the random streams take a "
                          "seed modulo 2**32, so another one would draw the stream of one in that range")


def _named(e: SettingError, given: dict[str, str]) -> RcoError:
    """``e`` with the options that gave its settings in front (``--set m=0: ...``), where the user gave them."""
    flags = [given[k] for k in e.settings if k in given]
    return SettingError(f"{', '.join(flags)}: {e.detail}", e.settings) if flags else e


def sweep_report(rows: list[dict], out: str | Path) -> str:
    """Members, their health and error quantiles of a finished sweep."""
    import numpy as np

    from ..verdict.health import STATUSES
    lines = [f"{len(rows)} members -> {out}/sweep.csv, sweep.json"]
    counts = {s: sum(r.get("status") == s for r in rows) for s in STATUSES}
    lines.append("health: " + ", ".join(f"{n} {s}" for s, n in counts.items()))
    for key in [k for k in rows[0] if k.startswith("err_")] if rows else []:
        v = np.array([abs(r[key]) for r in rows if r[key] is not None])
        if len(v):
            q = np.quantile(v, [0.5, 0.9, 1.0])
            lines.append(f"|{key}|: median {q[0]:.3g}, 90% {q[1]:.3g}, max {q[2]:.3g}")
    return "\n".join(lines)


# --- the parser (one function per command; add a command with its own ``_add_*`` and an entry in COMMANDS) ---
def _add_list(sub) -> None:
    sub.add_parser("list", help="list the scenarios")


def _add_show(sub) -> None:
    sub.add_parser("show", help="print a scenario's settings: defaults, units and meanings").add_argument(
        "name", help="scenario name (see `rcotorch list`)")


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", help="cpu (default), cuda or cuda:N")
    p.add_argument("--threads", type=int, help="CPU threads for torch (default: 1 below batch 1024, where "
                   "threading costs more than it gives, else torch's default)")
    p.add_argument("--engine", choices=["auto", "native", "torch"],
                   help="how graphs step: native (lowered to C, CPU float64), torch, or auto (default: native "
                        "where it applies; also $RCOTORCH_ENGINE)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the results in --out (only the files the earlier run wrote)")


def _add_run(sub) -> None:
    run = sub.add_parser("run", help="run a scenario and write runs/NAME/")
    run.add_argument("name", nargs="?", help="scenario name (see `rcotorch list`)")
    run.add_argument("--steps", type=int, help="number of steps (default: the scenario's)")
    run.add_argument("--batch", type=int, help="parallel refinements B (default 1)")
    run.add_argument("--seed", type=int, help="excitation seed (default: the scenario's)")
    run.add_argument("--dtype", choices=["float64", "float32"], help="float64 (default) or float32")
    run.add_argument("--out", help="output folder (default runs/NAME, or runs/NAME-2, ... when that holds a run)")
    run.add_argument("--config", metavar="FILE", help="settings from a TOML/JSON file: a table [settings] (and "
                     "optionally scenario = NAME), e.g. the best.toml of `rcotorch tune`; --set overrides it")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override a scenario setting (repeatable)")
    run.add_argument("--checkpoint-every", type=int, metavar="N", help="save a checkpoint every N steps")
    run.add_argument("--resume", metavar="DIR", help="continue the run in DIR from its checkpoint.pt "
                     "(--steps may extend it)")
    run.add_argument("--no-figures", action="store_true", help="skip the PNG/TensorBoard figures")
    run.add_argument("--no-validation", action="store_true",
                     help="skip the held-out validation of the refined model at the end")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_common(run)


def _add_shards(p, what: str, kind: str) -> None:
    """The options of a command that runs shards (sweep, tune): backend, Ray cluster, output folder, resume."""
    p.add_argument("--backend", default="local", choices=["local", "ray"])
    p.add_argument("--ray-address", help="address of an existing Ray cluster, HOST:PORT (default: start a "
                   "local one)")
    p.add_argument("--out", help=f"output folder (default runs/{kind}-SCENARIO)")
    p.add_argument("--resume", action="store_true", help=f"continue an interrupted {what} in --out")
    p.add_argument("--workers", type=int, metavar="N", help="shards run at once by the local backend, each in a "
                   "process of its own on one thread (default: one per CPU core; 1: one after another in this "
                   "process, on --threads threads)")
    _add_common(p)


def _add_sweep(sub) -> None:
    sw = sub.add_parser("sweep", help="run a parameter sweep (TOML/JSON config) as batched shards")
    sw.add_argument("config", help="sweep config file (.toml or .json)")
    _add_shards(sw, "sweep", "sweep")


def _add_tune(sub) -> None:
    tu = sub.add_parser("tune", help="choose a scenario's tuning (p0, nu, lam, ...) from held-out data")
    tu.add_argument("config", metavar="NAME|CONFIG",
                    help="a scenario's name (the search space it declares), or a tuning config file (.toml or "
                         ".json): scenario, method, samples, seeds, [fixed], [space]; see docs/tuning.md")
    tu.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="hold a scenario setting for every candidate (repeatable); a searched setting so held is "
                         "no longer searched")
    tu.add_argument("--trials", type=int, metavar="N", help="candidates to draw (random or tpe; config: samples; "
                    "default 32)")
    tu.add_argument("--seeds", type=int, metavar="N", help="seeds each candidate runs with; its score is their "
                    "mean (default 2)")
    tu.add_argument("--steps", type=int, help="steps of each run (default: the scenario's)")
    tu.add_argument("--method", choices=["random", "grid", "tpe"], help="random (default), grid or tpe")
    tu.add_argument("--seed", type=int, help="seed of the search's draws (default 0)")
    _add_shards(tu, "tuning", "tune")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    parser = argparse.ArgumentParser(prog="rcotorch", description="Model refinement by retrospective cost "
                                     "optimization, batched in PyTorch.")
    parser.add_argument("--version", action="version", version=f"rcotorch {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in ADD_COMMANDS:
        add(sub)
    return parser


ADD_COMMANDS: list[Callable] = [_add_list, _add_show, _add_run, _add_sweep, _add_tune]


def _say(text: str) -> None:
    """A message on stderr (lost, not raised, when stderr is gone: a closed terminal after SIGHUP)."""
    with contextlib.suppress(OSError, ValueError):
        print(text, file=sys.stderr, flush=True)


# --- running a command --------------------------------------------------------------------------------------
class StopSummary(KeyboardInterrupt):
    """A stop signal while a finished run writes its summary: the summary's replays can take minutes, so it is
    abandoned at once and the run's final state saved instead (its resume writes the summary)."""


class Session:
    """What a command has open (its run and output folder, for the log and to release them), the stop request
    (a signal) and the command that resumes the work."""

    def __init__(self, argv: list[str]):
        self.argv, self.folder, self.run = argv, None, None
        self.resume: str | None = None          # the command that continues the work, once it has one
        self.stop = threading.Event()
        self.stop_signal = signal.SIGINT        # the last stop signal received
        self.summarizing = False                # a stop signal abandons the summary at once (StopSummary)
        # what the work's memory grows with, for the line of a run that ran out of it (None: the batch)
        self.memory_drivers: Callable[[], str] | None = None
        self.drawing = None                     # the process that draws a run's figures (``DrawingProcess``)

    def command(self) -> str:
        return "rcotorch " + " ".join(shlex.quote(a) for a in self.argv)

    @property
    def stopped_by(self) -> str:
        return STOP_SIGNALS[self.stop_signal]

    def exit_stopped(self) -> int:
        """The exit code of work stopped by a signal: 128 + its number (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP)."""
        return 128 + int(self.stop_signal)

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[threading.Event]:
        """The first Ctrl-C, SIGTERM or SIGHUP asks the work to stop at the next step boundary (it then saves a
        checkpoint); a second one stops at once. A signal the process ignores stays ignored (SIGHUP under
        ``nohup``)."""
        if threading.current_thread() is not threading.main_thread():
            yield self.stop
            return

        def handler(signum, frame):
            self.stop_signal = signal.Signals(signum)
            if self.stop.is_set():
                raise KeyboardInterrupt
            self.stop.set()
            start, again = ("\nrcotorch:", "Ctrl-C again") if signum == signal.SIGINT else \
                (f"rcotorch: {self.stopped_by} received:", "the signal again")
            if self.summarizing:
                raise StopSummary
            _say(f"{start} stopping after the current steps to save a checkpoint ({again} to quit at once)")
        previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS if signal.getsignal(s) is not signal.SIG_IGN}
        try:
            yield self.stop
        finally:
            for s, h in previous.items():
                signal.signal(s, h)

    @contextlib.contextmanager
    def thread_errors_logged(self) -> Iterator[None]:
        """While the command runs, the traceback of an exception in a background thread (the figures' drawing
        thread, whose error the main thread meets again when it waits for it) goes to the output folder's log
        instead of stderr. One that cannot be logged goes to stderr as usual, unless it is an OSError (a full disk, say,
        which the main thread reports)."""
        previous = threading.excepthook

        def hook(args) -> None:
            text = "".join(traceback.format_exception(args.exc_type, args.exc_value, args.exc_traceback))
            with contextlib.suppress(OSError):
                if self.folder is not None and self.folder.is_open:
                    self.folder.log(f"exception in thread {args.thread.name if args.thread else '?'}:\n{text}")
                    return
            if not issubclass(args.exc_type, OSError):
                previous(args)
        threading.excepthook = hook
        try:
            yield
        finally:
            threading.excepthook = previous

    def log(self, line: str) -> None:
        if self.folder is not None:
            with contextlib.suppress(OSError):
                self.folder.log(line)

    def close(self) -> None:
        """Release the run (its TensorBoard writer is flushed), the output folder and the drawing process."""
        if self.drawing is not None:
            self.drawing.close()
        if self.run is not None:
            with contextlib.suppress(OSError):
                self.run.close()
        if self.folder is not None:
            self.folder.close()

    def keep_traceback(self, e: BaseException, headline: str) -> str | None:
        """Write ``headline`` and ``e``'s traceback to the output folder's log, or else to a temporary file;
        returns where (None when neither could be written)."""
        text = "".join(traceback.format_exception(e))
        if self.folder is not None and self.folder.is_open:
            with contextlib.suppress(OSError):
                self.folder.log(f"{headline}:\n{text}")
                return str(self.folder.path / "rcotorch.log")
        with contextlib.suppress(OSError):
            fd, name = tempfile.mkstemp(prefix="rcotorch-error-", suffix=".log")
            with os.fdopen(fd, "w") as f:
                f.write(f"{self.command()}\n{text}")
            return name
        return None

    def error(self, e: RcoError) -> int:
        """Bad input, or a fault of the file system (an ``OutputError`` raised from an OSError, whose traceback
        goes to the log): one line on stderr that names the file or folder and says what to do."""
        line = str(e)
        if isinstance(e, OutputError) and isinstance(e.__cause__, OSError):
            line += self._resume_hint()
            where = self.keep_traceback(e.__cause__, f"error: {line}")
            line += f" (traceback in {where})" if where else ""
        else:
            self.log(f"error: {line}")
        _say(f"rcotorch: error: {line}")
        return EXIT_INPUT

    def _resume_hint(self) -> str:
        """'; then resume with: ...' where the work can be resumed from the output folder."""
        from .runner import CHECKPOINT
        if self.resume is None or self.folder is None or not self.folder.is_open:
            return ""
        try:
            self.folder.check()
        except OutputError:
            return ""
        if self.folder.kind == "run" and not (self.folder.path / CHECKPOINT).is_file():
            return ""
        return f"; then resume with: {self.resume}"

    def folder_fault(self, e: OSError) -> OutputError | None:
        """``e`` as an ``OutputError`` when it comes from the output folder: the folder deleted or replaced, a
        file in it that cannot be written, or a write fault without a file name (a full disk, met by a buffered
        write of an event file); None when it does not (an internal error)."""
        from .outputs import WRITE_FAULTS, write_error
        if self.folder is None:
            return None
        fault = None
        try:
            self.folder.check()
        except OutputError as gone:
            fault = gone
        names = [Path(os.path.abspath(os.fsdecode(n))) for n in (e.filename, e.filename2)
                 if isinstance(n, (str, bytes, os.PathLike))]
        root = Path(os.path.abspath(self.folder.path))
        inside = [n for n in names if n == root or n.is_relative_to(root)]
        if fault is None and inside:
            fault = write_error(e, f"cannot write {inside[0]}")
        elif fault is None and not names and e.errno in WRITE_FAULTS:
            fault = write_error(e, f"cannot write to the output folder {self.folder.path}")
        if fault is not None:
            fault.__cause__ = e
        return fault

    def internal_error(self, e: BaseException) -> int:
        """One line on stderr; the traceback in the output folder's log (or a temporary file). Memory that ran
        out is no internal error: ``out_of_memory``."""
        if _out_of_memory(e):
            return self.out_of_memory(e)
        where = self.keep_traceback(e, f"internal error in `{self.command()}`")
        message = str(e).strip().splitlines()[0] if str(e).strip() else ""
        _say(f"rcotorch: internal error: {type(e).__name__}: {message}" + (f" (traceback in {where})" if where else ""))
        return EXIT_INTERNAL

    def out_of_memory(self, e: BaseException) -> int:
        """Exit 2 with one line: memory ran out, and the settings the work's memory grows with (their values);
        the traceback in the output folder's log (or a temporary file)."""
        message = str(e).strip().splitlines()[0] if str(e).strip() else ""
        drivers = None
        if self.memory_drivers is not None:
            with contextlib.suppress(Exception):         # the line is written whatever the drivers' lookup meets
                drivers = self.memory_drivers()
        line = f"out of memory{f' ({message})' if message else ''}: " + \
            (f"{drivers}; choose smaller ones" if drivers else "try a smaller --batch")
        where = self.keep_traceback(e, f"error: {line}")
        _say(f"rcotorch: error: {line}" + (f" (traceback in {where})" if where else ""))
        return EXIT_INPUT


def _out_of_memory(e: BaseException) -> bool:
    """Whether ``e`` says memory ran out: a MemoryError, or torch's RuntimeError for a failed allocation (a
    C++ std::bad_alloc, CPU or CUDA memory exhausted)."""
    text = str(e).lower()
    return isinstance(e, MemoryError) or (isinstance(e, RuntimeError) and (
        "out of memory" in text or "can't allocate memory" in text or "not enough memory" in text
        or "bad_alloc" in text))


def _import_lasting() -> None:
    """Import torch and the run's modules with the garbage collector paused, then take every object they made out
    of its reach (``gc.freeze``): they last as long as the process, and each full collection would walk them
    again (a tenth of a second or more of a run)."""
    import gc
    gc.disable()
    try:
        import torch  # noqa: F401

        from . import runner  # noqa: F401
    finally:
        gc.freeze()
        gc.enable()


def _threads(args) -> None:
    _positive(args.threads, "--threads")
    batch = getattr(args, "batch", None) or 1
    if args.threads or (args.command == "run" and not args.resume and batch < 1024):
        import torch
        torch.set_num_threads(args.threads or 1)


def cmd_list(args, session: Session) -> int:
    from . import scenario as scenarios
    for name, sc in sorted(scenarios.available().items()):
        print(f"{name:<28} {('[' + sc.section + '] ') if sc.section else ''}{sc.description}")
    return EXIT_PASS


def cmd_show(args, session: Session) -> int:
    from . import scenario as scenarios
    print(scenarios.describe(scenarios.get(args.name)))
    return EXIT_PASS


def cmd_run(args, session: Session) -> int:
    from .runner import Interrupted, Run, result_table
    _positive(args.checkpoint_every, "--checkpoint-every")
    _positive(args.batch, "--batch")
    _steps(args.steps)
    _seed(args.seed)
    overrides = _settings(args.overrides)
    given = {k: f"--set {k}={v}" for k, v in overrides.items()}       # the options that gave each setting
    if args.config:
        name, settings = _config_settings(args.config)
        if name and args.name and name != args.name:
            raise ConfigError(f"--config {args.config}: it is for scenario {name!r}, not {args.name!r}")
        args.name = args.name or name
        given = {**{k: f"--config {args.config}: {k} = {v!r}" for k, v in settings.items()}, **given}
        overrides = {**settings, **overrides}
    given.update({k: f"--{k} {v}" for k, v in (("batch", args.batch), ("seed", args.seed)) if v is not None})
    session.memory_drivers = lambda: _run_memory_drivers(session.run, args, overrides, given)
    try:
        if args.resume:
            r = Run.resume(args.resume, steps=args.steps, device=args.device, out=args.out,
                           overwrite=args.overwrite, expect=dict(name=args.name, batch=args.batch, seed=args.seed,
                                                                 dtype=args.dtype, overrides=overrides))
        else:
            if not args.name:
                raise ConfigError("run needs a scenario NAME (or --resume DIR); see `rcotorch list`")
            r = Run(args.name, steps=args.steps, batch=args.batch or 1, seed=args.seed,
                    device=args.device or "cpu", dtype=args.dtype or "float64", out=args.out, overrides=overrides,
                    overwrite=args.overwrite, validation=not args.no_validation)
    except SettingError as e:
        raise _named(e, given) from None
    session.folder, session.run = r.folder, r
    r.figures_expected = not args.no_figures
    r.drawing = session.drawing
    session.resume = f"rcotorch run --resume {shlex.quote(str(r.out))}"
    if args.checkpoint_every:
        session.resume += f" --checkpoint-every {args.checkpoint_every}"
    with session.interruptible() as stop:
        r.open_output()
        print(r.header(), flush=True)
        session.log(f"`{session.command()}` at step {r.k} of {r.steps}")
        try:
            r.advance(progress=False if args.quiet else None, checkpoint_every=args.checkpoint_every,
                      stop=stop.is_set)
        except Interrupted as e:
            session.log(f"stopped by {session.stopped_by} at step {e.step}; resume with: {session.resume}")
            _say(f"rcotorch: stopped at step {e.step} of {r.steps}; checkpoint saved to {e.checkpoint}\n"
                 f"resume with: {session.resume}")
            return session.exit_stopped()
        session.summarizing = True
        try:
            summary = r.finish(figures=not args.no_figures, close=False, progress=False if args.quiet else None)
        except StopSummary:
            path = r.save()
            session.log(f"stopped by {session.stopped_by} while writing the summary at step {r.k}; "
                        f"resume with: {session.resume}")
            _say(f"rcotorch: {session.stopped_by}: stopped while writing the summary (all {r.k} steps are done); "
                 f"checkpoint saved to {path}\nresume with: {session.resume} (it writes the summary)")
            return session.exit_stopped()
        finally:
            session.summarizing = False
    print(result_table(summary))
    passed = all(c["pass"] for c in summary["requirements"].values())
    session.log(f"finished at step {summary['steps']}: " + ("every requirement passes" if passed else
                                                            "a requirement failed"))
    return EXIT_PASS if passed else EXIT_FAILED


def _run_memory_drivers(run, args, overrides: dict[str, Any], given: dict[str, str]) -> str:
    """What a run's memory grows with, as the user gave it or else with the run's values: the batch, and nu where
    the scenario has it ('the run's memory grows with the batch and nu (here --batch 3, --set nu=40)')."""
    from . import scenario as scenarios
    batch = run.batch if run is not None else args.batch or 1
    here = [given.get("batch", f"batch {batch}")]
    if run is not None:
        nu = run.settings.get("nu")
    else:
        sc = scenarios.get(args.name)
        nu = sc.resolve({k: v for k, v in overrides.items() if k == "nu"}).get("nu")
    if nu is not None:
        here.append(given.get("nu", f"nu = {nu}"))
    return f"the run's memory grows with the batch{' and nu' if nu is not None else ''} (here {', '.join(here)})"


def _in_shards(session: Session, what: str, job: Callable):
    """``job(stop)`` (a sweep or a tuning, run as shards) with Ctrl-C, SIGTERM and SIGHUP asking it to stop;
    its result, or None when it stopped (the running shard saved its checkpoint)."""
    from .runner import Interrupted
    with session.interruptible() as stop:
        try:
            return job(stop.is_set)
        except Interrupted as e:
            session.log(f"stopped by {session.stopped_by}; resume with: {session.resume}")
            _say(f"rcotorch: {what} stopped ({e}); finished shards are kept\nresume with: {session.resume}")
            return None


def _shards_control(args, session: Session):
    """How ``rcotorch sweep`` and ``rcotorch tune`` drive their shards: ``--overwrite``, ``--resume`` and the
    output folder the session opened (the stop request is added once the signals are caught, ``_in_shards``)."""
    from .control import RunControl
    _positive(args.workers, "--workers")
    return RunControl(overwrite=args.overwrite, resume=args.resume, folder=session.folder, workers=args.workers)


def cmd_sweep(args, session: Session) -> int:
    from .limits import run_device
    from .outputs import OutputFolder
    from .sweep import Sweep, run_sweep
    sweep = Sweep.from_file(args.config)
    run_device(args.device or "cpu")
    session.memory_drivers = lambda: _shards_memory_drivers(sweep)
    session.folder = OutputFolder(args.out or Path("runs") / f"sweep-{sweep.scenario_name}", "sweep")
    control = _shards_control(args, session)
    session.resume = (f"rcotorch sweep {shlex.quote(args.config)} --out {shlex.quote(str(session.folder.path))} "
                      "--resume")
    session.log(f"`{session.command()}`")            # written once run_sweep opens the folder
    rows = _in_shards(session, "sweep", lambda stop: run_sweep(
        sweep, backend=args.backend, device=args.device or "cpu", ray_address=args.ray_address,
        control=dataclasses.replace(control, stop=stop), drawing=session.drawing))
    if rows is None:
        return session.exit_stopped()
    session.log(f"finished: {len(rows)} members")
    print(sweep_report(rows, session.folder.path))
    return EXIT_PASS


def _shards_memory_drivers(spec) -> str:
    """What the memory of a sweep or tuning (``spec``) grows with: the members of a shard, and nu."""
    nu = spec.fixed.get("nu") if isinstance(spec.fixed, dict) else None
    return ("the memory grows with the members of a shard and nu (here shard_size = "
            f"{spec.shard_size}{'' if nu is None else f', nu = {nu}'})")


def _config_settings(path: str) -> tuple[str | None, dict[str, Any]]:
    """The scenario name and settings of a ``--config`` file."""
    from .sweep import read_config
    spec = read_config(path, "run")
    unknown = set(spec) - {"scenario", "settings"}
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {sorted(unknown)}; a run config has scenario = NAME and a "
                          "table [settings]")
    settings = spec.get("settings", {})
    if not isinstance(settings, dict) or any(isinstance(v, dict) for v in settings.values()):
        raise ConfigError(f"{path}: [settings] must be a table of setting = value")
    name = spec.get("scenario")
    if name is not None and not isinstance(name, str):
        raise ConfigError(f"{path}: scenario must be a name, got {name!r}")
    return name, dict(settings)


def _tuning(args):
    """The search of ``rcotorch tune NAME|CONFIG``: a config file's, or the one scenario NAME declares, with the
    options given (``--set`` holds settings for every candidate; the others replace the config's values)."""
    from . import scenario as scenarios
    from .tune import Tuning
    _positive(args.trials, "--trials")
    _positive(args.seeds, "--seeds")
    _steps(args.steps)
    _seed(args.seed)
    options = {k: v for k, v in (("samples", args.trials), ("seeds", args.seeds), ("steps", args.steps),
                                 ("method", args.method), ("seed", args.seed)) if v is not None}
    if Path(args.config).suffix.lower() in (".toml", ".json") or Path(args.config).is_file():
        tuning = dataclasses.replace(Tuning.from_file(args.config), **options)
    else:
        try:
            scenarios.get(args.config)
        except ConfigError as e:
            raise ConfigError(f"tune {args.config}: not a tuning config file (.toml or .json), and {e}") from None
        tuning = Tuning.declared(args.config, **options)
    if tuning.method == "grid" and args.trials is not None:
        raise ConfigError("--trials is the number of candidates of a random or tpe search; a grid search runs every "
                          "combination of its lists")
    sets = _settings(args.overrides)
    if sets:
        sc = scenarios.get(tuning.scenario)
        try:
            resolved = sc.resolve(sets)
        except SettingError as e:
            raise _named(e, {k: f"--set {k}={v}" for k, v in sets.items()}) from None
        tuning = tuning.fixing({k: resolved[k] for k in sets})
    return tuning


def _tune_resume(argv: list[str], out: Path) -> str:
    """The command that continues the tuning of ``argv`` in ``out``: the same options, --out OUT --resume."""
    kept, skip = [], False
    for a in argv[1:]:
        if skip:
            skip = False
            continue
        if a == "--out":
            skip = True
            continue
        if a.startswith("--out=") or a in ("--resume", "--overwrite"):
            continue
        kept.append(a)
    return " ".join(["rcotorch tune", *map(shlex.quote, kept), "--out", shlex.quote(str(out)), "--resume"])


def cmd_tune(args, session: Session) -> int:
    from .limits import run_device
    from .outputs import OutputFolder
    from .tune import run_tune
    tuning = _tuning(args)
    run_device(args.device or "cpu")
    session.memory_drivers = lambda: _shards_memory_drivers(tuning)
    name = getattr(tuning.scenario, "name", tuning.scenario)
    out = Path(args.out or Path("runs") / f"tune-{name}")
    session.folder = OutputFolder(out, "tune")
    control = _shards_control(args, session)
    session.resume = _tune_resume(session.argv, out)
    session.log(f"`{session.command()}`")            # written once run_tune opens the folder
    result = _in_shards(session, "tuning", lambda stop: run_tune(
        tuning, out=out, backend=args.backend, device=args.device or "cpu", ray_address=args.ray_address,
        control=dataclasses.replace(control, stop=stop)))
    if result is None:
        return session.exit_stopped()
    session.log(f"finished: {len(result.candidates)} candidates, {result.members} members")
    print(f"{name}: {len(result.candidates)} candidates x seeds = {result.members} members, scored on "
          f"held-out data (validation_rmse) -> {out}")
    print(result.table())
    print(f"best: {out / 'best.toml'}  (rcotorch run {name} --config {shlex.quote(str(out / 'best.toml'))})")
    print(f"sensitivity of the score to each setting: {out / 'sensitivity.csv'}")
    return EXIT_PASS


COMMANDS: dict[str, Callable] = {"list": cmd_list, "show": cmd_show, "run": cmd_run, "sweep": cmd_sweep,
                                 "tune": cmd_tune}


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default: ``sys.argv[1:]``); returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:   # --help, --version (0) and usage errors (2, with argparse's message)
        return e.code if isinstance(e.code, int) else EXIT_INPUT
    session = Session(argv)
    with session.thread_errors_logged():
        try:
            if getattr(args, "engine", None):
                os.environ["RCOTORCH_ENGINE"] = args.engine
            if (args.command == "run" and not args.no_figures) or args.command == "sweep":
                from .drawing import DrawingProcess
                session.drawing = DrawingProcess()     # first: it imports matplotlib while this imports torch
            if args.command not in ("list", "show"):
                _import_lasting()
                _threads(args)
            code = COMMANDS[args.command](args, session)
            sys.stdout.flush()        # here, so that a closed stdout is met inside this handler
            return code
        except RcoError as e:
            return session.error(e)
        except BrokenPipeError:       # the reader of stdout stopped reading (`rcotorch list | head`)
            with contextlib.suppress(OSError, ValueError):
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return EXIT_PASS
        except KeyboardInterrupt:
            session.log(f"stopped by a second {session.stopped_by}, without a checkpoint")
            _say("\nrcotorch: stopped (no checkpoint saved since the last one)")
            return session.exit_stopped()
        except OSError as e:          # from the output folder (exit 2), or else an internal error
            fault = session.folder_fault(e)
            return session.error(fault) if fault is not None else session.internal_error(e)
        except Exception as e:
            return session.internal_error(e)
        finally:
            session.close()


if __name__ == "__main__":
    sys.exit(main())
