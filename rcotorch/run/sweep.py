"""Parameter sweeps: many refinements that differ in truth or tuning, run as batched shards.

A sweep names a scenario, a grid and/or random draws over its settings, and seeds. Members that share the
settings fixing the graph's structure (sample time, orders, nu) form a group; each group is cut into shards
of at most ``shard_size`` members, and each shard is one batched run. The ``local`` backend runs the shards
on this machine, several at once in forked processes (``workers``) or one after another in this process, the
``ray`` backend as Ray tasks (on a local instance or an existing cluster); both run the
same shards, so their tables are identical. Member b of a shard equals a batch-of-one run with its settings.

Config file (TOML or JSON)::

    scenario = "sdof-stiffness-damping"
    steps = 20000
    seeds = 2               # seeds per parameter point: seed, seed+1 (or a list)
    seed = 0                # base seed, also for the random draws
    shard_size = 4096
    trace = [0, 17]         # members traced individually in TensorBoard (default: the first 3 of each shard)
    [fixed]                 # overrides for every member
    nu = 15
    [grid]                  # full factorial
    dK = [-0.4, -0.2, 0.2]
    p0 = [1e3, 1e6]
    [random]                # 'samples' draws, crossed with the grid
    dC = {uniform = [0.0, 1.0]}
    lam = {loguniform = [0.99, 1.0]}
"""

from __future__ import annotations

import contextlib
import csv
import io
import itertools
import json
import math
import os
import signal
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, RcoError
from . import scenario as scenarios
from .control import STOP_SIGNALS, RunControl
from .pipes import read_frame, write_frame

DISTRIBUTIONS = ("uniform", "loguniform", "normal", "choice")
CONFIG_KEYS = {"scenario", "steps", "seeds", "seed", "shard_size", "fixed", "grid", "random", "samples",
               "dtype", "trace"}


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


# The type of each top-level config value: (test, what it must be).
_TYPES = {
    "scenario": (lambda v: isinstance(v, str), "a scenario name"),
    "steps": (lambda v: v is None or _is_int(v), "an integer"),
    "seeds": (lambda v: _is_int(v) or (isinstance(v, list) and all(_is_int(x) for x in v)),
              "an integer count or a list of integers"),
    "seed": (_is_int, "an integer"),
    "shard_size": (_is_int, "an integer"),
    "samples": (_is_int, "an integer"),
    "dtype": (lambda v: v in ("float64", "float32"), "'float64' or 'float32'"),
    "trace": (lambda v: isinstance(v, list) and all(_is_int(x) for x in v), "a list of member indices"),
    "fixed": (lambda v: isinstance(v, Mapping), "a table of settings"),
    "grid": (lambda v: isinstance(v, Mapping), "a table of lists"),
    "random": (lambda v: isinstance(v, Mapping), "a table of distributions"),
}


def _check_types(spec: Mapping[str, Any], source: str, types: Mapping[str, tuple] = _TYPES) -> None:
    """Raise ``ConfigError`` naming ``source`` and the key where a config's value is not of its type."""
    for key, value in spec.items():
        ok, what = types[key]
        if not ok(value):
            raise ConfigError(f"{source}: {key} must be {what}, got {value!r}")


@dataclass
class Sweep:
    """A declared sweep; ``members()`` lists each member's settings (validated before any work)."""

    scenario: str | scenarios.Scenario        # a registered name, or a scenario object of one's own
    grid: Mapping[str, Sequence] = field(default_factory=dict)
    random: Mapping[str, Mapping[str, Sequence]] = field(default_factory=dict)
    samples: int = 0
    seeds: int | Sequence[int] = 1
    seed: int = 0
    steps: int | None = None
    fixed: Mapping[str, Any] = field(default_factory=dict)
    shard_size: int = 4096
    dtype: str = "float64"
    trace: Sequence[int] = ()   # member indices logged individually in TensorBoard (default: 3 per shard)

    def __post_init__(self):
        self.scenario = scenarios.get(self.scenario)       # looked up once; the members carry the object

    @classmethod
    def from_dict(cls, spec: Mapping[str, Any], source: str = "sweep") -> Sweep:
        unknown = set(spec) - CONFIG_KEYS
        if unknown:
            raise ConfigError(f"{source}: unknown key(s) {sorted(unknown)}; allowed: {sorted(CONFIG_KEYS)}")
        if "scenario" not in spec:
            raise ConfigError(f"{source}: 'scenario' is missing")
        _check_types(spec, source)
        return cls(**spec)

    @property
    def scenario_name(self) -> str:
        return self.scenario.name

    def scenario_ref(self) -> str | scenarios.Scenario:
        """What a worker process is given to find the scenario: its registered name (the worker imports it),
        or the object itself for a scenario of one's own."""
        registered = scenarios.available().get(self.scenario.name)
        return self.scenario.name if registered is self.scenario else self.scenario

    def config(self) -> dict[str, Any]:
        """The sweep as plain data (the scenario by name), as its folder records it."""
        spec = {f: getattr(self, f) for f in self.__dataclass_fields__}
        spec["scenario"] = self.scenario_name
        return json.loads(json.dumps(spec, default=list))

    @classmethod
    def from_file(cls, path: str | Path) -> Sweep:
        return cls.from_dict(read_config(path, "sweep"), str(path))

    # --- members -----------------------------------------------------------------------------------------
    def seed_list(self) -> list[int]:
        if not 0 <= self.seed <= scenarios.SEED_MAX:
            raise ConfigError(f"sweep: seed must be an integer in 0..{scenarios.SEED_MAX}, got {self.seed}: the "
                              "random streams take a seed modulo 2**32")
        if isinstance(self.seeds, int):
            if self.seeds < 1:
                raise ConfigError(f"sweep: seeds must be at least 1, got {self.seeds}")
            return [self.seed + i for i in range(self.seeds)]
        seeds = list(self.seeds)
        if not seeds or not all(isinstance(s, int) for s in seeds):
            raise ConfigError(f"sweep: seeds must be a positive count or a non-empty list of integers, got {seeds}")
        return seeds

    def members(self) -> list[dict[str, Any]]:
        """One settings dict per member (swept names plus 'seed'), after checking names and values."""
        sc = self.scenario
        known = set(sc.settings)
        for what, names in (("grid", self.grid), ("random", self.random), ("fixed", self.fixed)):
            for name in names:
                if name not in known:
                    import difflib
                    close = difflib.get_close_matches(name, known, n=1)
                    hint = f" (did you mean '{close[0]}'?)" if close else ""
                    raise ConfigError(f"sweep {what}: scenario '{sc.name}' has no setting {name!r}{hint}; "
                                      f"settings are {sorted(known)}")
                if name == "seed":
                    raise ConfigError(f"sweep {what}: set seeds with 'seeds' and 'seed', not as a setting")
        overlap = (set(self.grid) & set(self.random)) | ((set(self.grid) | set(self.random)) & set(self.fixed))
        if overlap:
            raise ConfigError(f"sweep: {sorted(overlap)} appear in more than one of grid, random and fixed")
        for name, values in self.grid.items():
            if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) or len(values) == 0:
                raise ConfigError(f"sweep grid: {name!r} needs a non-empty list of values, got {values!r}")
        if self.random and self.samples < 1:
            raise ConfigError("sweep: random draws need samples >= 1")
        if self.steps is not None and self.steps < 1:
            raise ConfigError(f"sweep: steps must be positive, got {self.steps}")
        if self.steps is not None:
            from .limits import bounded_steps
            bounded_steps(self.steps, "sweep: steps")
        if self.shard_size < 1:
            raise ConfigError(f"sweep: shard_size must be positive, got {self.shard_size}")
        draws = self._draws()
        points = [dict(zip(self.grid, combo)) for combo in itertools.product(*self.grid.values())] or [{}]
        seeds = self.seed_list()
        if "seed" in known:
            members = [dict(point, **draw, seed=seed) for point in points for draw in draws for seed in seeds]
        elif len(seeds) > 1:
            raise ConfigError(f"sweep: scenario '{sc.name}' has no setting 'seed' (its runs do not draw random "
                              f"numbers), so more than one seed repeats the same run; set seeds = 1")
        else:
            members = [dict(point, **draw) for point in points for draw in draws]
        for i, m in enumerate(members):  # every member's values go through the scenario's own checks
            try:
                sc.resolve(dict(self.fixed, **m))
            except ConfigError as e:
                raise ConfigError(f"sweep member {i} ({m}): {e}") from None
        return members

    def _draws(self) -> list[dict[str, Any]]:
        if not self.random:
            return [{}]
        rng = np.random.default_rng(self.seed)
        cols = {}
        for name, dist in self.random.items():
            if not isinstance(dist, Mapping) or len(dist) != 1 or next(iter(dist)) not in DISTRIBUTIONS:
                raise ConfigError(f"sweep random: {name!r} needs one of {DISTRIBUTIONS}, e.g. "
                                  f"{{uniform = [0.0, 1.0]}}; got {dist!r}")
            kind, args = next(iter(dist.items()))
            args = list(args)
            if kind == "choice":
                if not args:
                    raise ConfigError(f"sweep random: {name!r} choice needs a non-empty list")
                cols[name] = [args[i] for i in rng.integers(0, len(args), self.samples)]
                continue
            if len(args) != 2 or not all(isinstance(a, (int, float)) for a in args):
                raise ConfigError(f"sweep random: {name!r} {kind} needs two numbers, got {args!r}")
            lo, hi = args
            if kind == "uniform":
                if not lo <= hi:
                    raise ConfigError(f"sweep random: {name!r} uniform needs low <= high, got {args}")
                cols[name] = rng.uniform(lo, hi, self.samples).tolist()
            elif kind == "loguniform":
                if not 0 < lo <= hi:
                    raise ConfigError(f"sweep random: {name!r} loguniform needs 0 < low <= high, got {args}")
                cols[name] = np.exp(rng.uniform(math.log(lo), math.log(hi), self.samples)).tolist()
            else:
                if hi < 0:
                    raise ConfigError(f"sweep random: {name!r} normal needs [mean, std >= 0], got {args}")
                cols[name] = rng.normal(lo, hi, self.samples).tolist()
        return [{k: v[i] for k, v in cols.items()} for i in range(self.samples)]

    def shards(self) -> list[dict[str, Any]]:
        """Shard specs: {'index', 'members' (member indices), 'settings' (per-member dicts), 'common'}."""
        sc = self.scenario
        members = self.members()
        groups: dict[tuple, list[int]] = {}
        for i, m in enumerate(members):
            key = tuple(sorted((k, repr(v)) for k, v in m.items() if k not in sc.per_member))
            groups.setdefault(key, []).append(i)
        shards = []
        for idx in groups.values():
            for start in range(0, len(idx), self.shard_size):
                part = idx[start:start + self.shard_size]
                first = members[part[0]]
                common = dict(self.fixed, **{k: v for k, v in first.items() if k not in sc.per_member})
                shards.append({"index": len(shards), "members": part, "common": common, "trace": list(self.trace),
                               "settings": [{k: v for k, v in members[i].items() if k in sc.per_member}
                                            for i in part]})
        return shards


def read_config(path: str | Path, what: str) -> dict[str, Any]:
    """A config file's table: TOML (``.toml``) or JSON (``.json``), UTF-8; ``what`` names it in errors."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such {what} config")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text (byte {e.object[e.start]:#04x} at offset {e.start}); save "
                          "the config as UTF-8") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the {what} config: {e.strerror or e}") from None
    if path.suffix == ".toml":
        import tomllib
        try:
            spec = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"{path}: not valid TOML: {e}") from None
    elif path.suffix == ".json":
        try:
            spec = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(f"{path}: not valid JSON: {e}") from None
        if not isinstance(spec, dict):
            raise ConfigError(f"{path}: a {what} config is a JSON object")
    else:
        raise ConfigError(f"{path}: a {what} config is a .toml or .json file")
    return spec


def make_run(scenario: str | scenarios.Scenario, shard: Mapping[str, Any], steps: int | None, dtype: str, device: str,
             out: str | None, overwrite: bool = False):
    """The batched run of one shard (building it checks every member's settings)."""
    from .runner import Run
    local = [b for b, m in enumerate(shard["members"]) if m in set(shard.get("trace", ()))]
    try:
        run = Run(scenario, steps=steps, device=device, dtype=dtype, out=out, overrides=shard["common"],
                  members=shard["settings"], trace=local or None, overwrite=overwrite)
    except ConfigError as e:
        raise ConfigError(f"sweep shard {shard['index']} (members {shard['members'][0]}..{shard['members'][-1]}): "
                          f"{e}") from None
    run.hparams_session = False          # the sweep writes the HParams sessions (write_hparams)
    run.figures_expected = False         # shards draw no figures
    return run


def run_shard(scenario: str | scenarios.Scenario, shard: Mapping[str, Any], steps: int | None, dtype: str, device: str,
              out: str | None, threads: int | None = None, run=None, stop=None, desc: str | None = None
              ) -> list[dict[str, Any]]:
    """Run one shard as a batched run; return one table row per member. A shard folder left by an
    interrupted sweep is taken up where it stopped: finished (its summary.json), resumed from its
    checkpoint, or started again."""
    import torch

    from .outputs import MANIFEST
    from .runner import CHECKPOINT, Run
    if threads:
        torch.set_num_threads(threads)
    folder = Path(out) if out else None
    if run is None and folder is not None and (folder / MANIFEST).is_file():
        done = folder / "summary.json"
        if done.is_file():
            summary, damage = _shard_summary(done, len(shard["members"]))
            if summary is not None:
                sc = scenarios.get(scenario)
                expected = steps or sc.default_steps(sc.resolve(shard["common"]))
                if summary["steps"] == expected:
                    return shard_rows(shard, summary)
            else:                         # the shard runs again, which writes its summary anew
                start = "from its checkpoint" if (folder / CHECKPOINT).is_file() else "from its start"
                print(f"rcotorch: {done}: not a complete summary ({damage}); the sweep runs the shard again {start}",
                      file=sys.stderr, flush=True)
        if (folder / CHECKPOINT).is_file():
            run = Run.resume(folder, scenario=None if isinstance(scenario, str) else scenario)
            run.hparams_session = False
            run.figures_expected = False
        else:
            run = make_run(scenario, shard, steps, dtype, device, out, overwrite=True)
    run = run or make_run(scenario, shard, steps, dtype, device, out)
    try:
        run.advance(progress=desc is not None, stop=stop, desc=desc)
        summary = run.finish(figures=False) if out else run.summary()
    except BaseException:
        with contextlib.suppress(OSError):
            run.close()                  # releases the shard's folder (its checkpoint is kept)
        raise
    return shard_rows(shard, summary)


SUMMARY_KEYS = ("steps", "batch", "estimates", "truth", "metrics", "health")   # what ``shard_rows`` reads


def _shard_summary(path: Path, members: int) -> tuple[dict[str, Any] | None, str | None]:
    """A finished shard's ``summary.json``, or None and what is wrong with it where it cannot be read as one (cut
    short by a full disk or a killed copy, edited, or of another batch)."""
    try:
        summary = json.loads(path.read_bytes())
    except (OSError, ValueError) as e:            # JSONDecodeError and UnicodeDecodeError are ValueErrors
        return None, " ".join(str(e).split()) or type(e).__name__
    if not isinstance(summary, dict):
        return None, f"a JSON {type(summary).__name__}, not an object"
    missing = [k for k in SUMMARY_KEYS if k not in summary]
    if missing:
        return None, f"no {', '.join(missing)}"
    if summary["batch"] != members:
        return None, f"a batch of {summary['batch']!r}, not the shard's {members} members"
    return summary, None


def shard_rows(shard: Mapping[str, Any], summary: Mapping[str, Any]) -> list[dict[str, Any]]:
    """One table row per member of a shard from its run's summary: settings, estimates with truth and error,
    metrics, health."""
    from .runner import member_truth
    B = summary["batch"]
    health = {k: member_truth(summary["health"][k], B) for k in ("status", "reason", "diverged_at", "theta_change",
                                                                  "z_ratio", "determined", "residuals_white",
                                                                  "bias_reason")
              if k in summary["health"]}
    intervals = summary.get("intervals") or {}
    checks = summary.get("requirements") or {}
    rows = []
    for b, member in enumerate(shard["members"]):
        row: dict[str, Any] = {"member": member, "shard": shard["index"]}
        row.update({k: v for k, v in shard["common"].items()})
        row.update(shard["settings"][b])
        for key, v in summary["estimates"].items():
            est = member_truth(v, B)[b]
            row[f"est_{key}"] = est
            truth = summary["truth"].get(key)
            if truth is not None:
                tv = member_truth(truth, B)[b]
                row[f"truth_{key}"] = tv
                row[f"err_{key}"] = None if est is None else est - tv
            if key in intervals:
                row[f"lower_{key}"] = member_truth(intervals[key]["lower"], B)[b]
                row[f"upper_{key}"] = member_truth(intervals[key]["upper"], B)[b]
                if "bias" in intervals[key]:
                    row[f"bias_{key}"] = member_truth(intervals[key]["bias"], B)[b]
        for key, v in summary["metrics"].items():
            row[key] = member_truth(v, B)[b]
        row["status"] = health["status"][b]
        for key, chk in checks.items():
            row[f"pass_{key.split('.', 1)[1]}"] = member_truth(chk.get("member_pass", chk["pass"]), B)[b]
        for key in ("determined", "residuals_white", "theta_change", "z_ratio"):
            if key in health:
                row[key] = health[key][b]
        row["reason"] = health["reason"][b]
        if "bias_reason" in health:
            row["bias_reason"] = health["bias_reason"][b]
        row["diverged"] = health["status"][b] == "diverged"
        row["diverged_at"] = health["diverged_at"][b]
        rows.append(row)
    return rows


def run_sweep(sweep: Sweep, backend: str = "local", device: str = "cpu", out: str | Path | None = None,
              ray_address: str | None = None, progress: bool = True, overwrite: bool = False,
              resume: bool = False, stop=None, folder=None, control: RunControl | None = None, drawing=None,
              workers: int | None = None) -> list[dict[str, Any]]:
    """Run every shard and return the merged table (sorted by member); writes sweep.csv/json under ``out``.

    ``out`` (default ``runs/sweep-SCENARIO``) must not hold results unless ``overwrite`` (replace the sweep
    there) or ``resume`` (continue the interrupted sweep there, with the same config). ``stop()`` is asked
    between steps (Ctrl-C, SIGTERM, SIGHUP): the running shard saves a checkpoint and ``Interrupted`` is raised.
    ``folder``: an ``OutputFolder`` for ``out`` made by the caller, who closes it (and may log into it
    meanwhile). ``workers``: how many shards the local backend runs at once, each in a forked process
    (``RunControl.workers``; None: one per usable core, 1: one after another in this process). ``control``:
    these six (``progress``, ``overwrite``, ``resume``, ``stop``, ``folder``, ``workers``) as one
    ``rcotorch.run.control.RunControl``, given instead of them. ``drawing``: a ``rcotorch.run.drawing.DrawingProcess``
    that draws the sweep's figures while the sweep writes its table (``rcotorch sweep`` starts one before it
    imports torch); without it they are drawn here. A sweep refused (an ``RcoError``) before its first shard wrote
    anything leaves the folder as it found it."""
    from .outputs import OutputFolder
    if backend not in ("local", "ray"):
        raise ConfigError(f"backend must be 'local' or 'ray', got {backend!r}")
    control = RunControl.given(control, progress=progress, overwrite=overwrite, resume=resume, stop=stop,
                               folder=folder, workers=workers)
    shards = sweep.shards()  # validates everything before any work
    sc = sweep.scenario
    steps = sweep.steps                  # None: each shard's scenario default for its settings
    own = control.folder is None
    folder = control.folder or OutputFolder(out or Path("runs") / f"sweep-{sweep.scenario_name}", "sweep")
    shard_out = [str(folder.path / f"shard_{s['index']:04d}") for s in shards]
    # Build every shard before running any, so a bad value fails before work starts.
    runs = [make_run(sweep.scenario, s, steps, sweep.dtype, device, o) for s, o in zip(shards, shard_out)]
    if backend == "ray":
        ray = _import_ray()
        if ray_address and not ray.is_initialized():
            _check_ray_address(ray_address)
    config = sweep.config()
    folder.open(control.mode, info=None if control.resume else {"scenario": sweep.scenario_name, "config": config})
    try:
        if control.resume and folder.info.get("config") != config:
            raise ConfigError(f"--resume: the sweep in {folder.path} was run with another config")
        out = folder.path
        for name in [Path(o).name for o in shard_out] + ["members"]:
            folder.add_child(name)
        folder.register()
        if backend == "local":
            n = local_workers(control.workers, len(shards), device)
            rows = (_run_local(sweep, shards, steps, device, shard_out, runs, control) if n == 1 else
                    _run_forked(sweep, shards, steps, device, shard_out, runs, control, n))
        else:
            del runs
            rows = _run_ray(sweep, shards, steps, device, shard_out, ray_address, control)
        rows.sort(key=lambda r: r["member"])
        folder.check()
        from .monitor import draw_sweep_figures, write_sweep_figures
        swept = list(sweep.grid) + list(sweep.random) or ["seed"]
        drawn = draw_sweep_figures(rows, swept, sc, drawing)       # in the drawing process meanwhile, where given
        write_table(rows, out)
        write_hparams(rows, sweep, out, [Path(o) for o in shard_out])
        write_sweep_figures(out, rows, swept, sc, run=shard_out[0], drawn=drawn)
        folder.register()
    except RcoError:
        folder.discard()
        raise
    finally:
        if own:
            folder.close()
    return rows


def _run_local(sweep, shards, steps, device, shard_out, runs, control: RunControl) -> list[dict[str, Any]]:
    """The shards run one after another in this process, each asking ``control.stop`` between its steps."""
    import time
    rows = []
    for s, o, r in zip(shards, shard_out, runs):
        label = f"shard {s['index'] + 1}/{len(shards)}"
        if control.progress:
            print(f"{label}: {_members(len(s['members']))}", flush=True)
        start = time.perf_counter()
        part = run_shard(sweep.scenario, s, steps, sweep.dtype, device, o, run=None if Path(o).exists() else r,
                         stop=control.stop, desc=label if control.progress else None)
        if control.progress:
            print(f"{label}: done in {time.perf_counter() - start:.1f} s; {_health_counts(part)}", flush=True)
        rows += part
    return rows


def local_workers(asked: int | None, shards: int, device: str) -> int:
    """How many shards the local backend runs at once: ``asked`` (at most one per shard), or where None one per
    core this process may use; 1 off Linux (no fork) and on a GPU (one device, and CUDA does not survive a
    fork)."""
    if not sys.platform.startswith("linux") or not hasattr(os, "fork") or not str(device).startswith("cpu"):
        return 1
    if asked is None:
        asked = len(os.sched_getaffinity(0))
    return max(1, min(asked, shards))


def _run_forked(sweep, shards, steps, device, shard_out, runs, control: RunControl, workers: int
                ) -> list[dict[str, Any]]:
    """The shards run ``workers`` at a time in as many worker processes forked from this one (``_Worker``), each
    taking shard after shard from this process, running it on one thread and sending back its rows: a worker
    keeps what its first shard loaded and touched, where a process forked for every shard would copy it again.
    ``control.stop`` is asked while waiting: when it says True, the running shards are sent SIGTERM (each saves
    its checkpoint, as a shard run here would) and no more start; a shard that fails stops the others likewise,
    and its error is raised here once they ended."""
    import select
    import time

    from .runner import preload
    preload()                                  # imported once here, not in every worker
    todo = list(range(len(shards)))
    pool: dict[int, _Worker] = {}              # read end of a worker's results -> the worker
    parts: dict[int, list] = {}
    stopped = failure = None
    told = left = False
    try:
        if not (control.stop is not None and control.stop()):
            for _ in range(min(workers, len(todo))):
                worker = _Worker(sweep, shards, steps, device, shard_out, runs)
                pool[worker.results] = worker
        while pool or todo:
            if not told and (failure is not None or not pool or (control.stop is not None and control.stop())):
                told, left = True, bool(todo)  # stop what runs, start nothing more
                todo.clear()
                for worker in pool.values():
                    worker.stop()
            for worker in pool.values():
                if worker.shard is None and todo:
                    i = todo.pop(0)
                    if control.progress:
                        print(f"shard {i + 1}/{len(shards)}: {_members(len(shards[i]['members']))}", flush=True)
                    worker.send(i, fresh=not Path(shard_out[i]).exists(), start=time.perf_counter())
                elif worker.shard is None:
                    worker.stop()              # nothing more to do: it ends
            ready = select.select(list(pool), [], [], 0.1)[0] if pool else []
            for fd in ready:
                worker = pool[fd]
                data = worker.read()
                if data is not None:
                    s = shards[worker.shard]
                    kind, value = _shard_outcome(data, 0, s)
                    if kind == "rows":
                        parts[s["index"]] = value
                        if control.progress:
                            print(f"shard {s['index'] + 1}/{len(shards)}: done in "
                                  f"{time.perf_counter() - worker.start:.1f} s; {_health_counts(value)}", flush=True)
                    elif kind == "stopped":
                        stopped = stopped or value
                    else:
                        failure = failure or value
                    worker.shard = None
                if worker.ended:
                    status = worker.close()
                    del pool[fd]
                    if worker.shard is not None:    # it died within a shard, without a word
                        failure = failure or _shard_outcome(b"", status, shards[worker.shard])[1]
    except BaseException:
        for worker in pool.values():           # a second signal, or an error here: end them at once
            worker.kill()
        raise
    if failure is not None:
        raise failure
    if stopped is not None:
        raise stopped
    if left:              # stopped before every shard started, where no running shard was still stopping
        from .runner import Interrupted
        raise Interrupted(None, None)
    return [row for i in sorted(parts) for row in parts[i]]


class _Worker:
    """One process forked from the sweep's (``_worker``) that runs the shards it is sent, one at a time. Jobs go
    down one pipe (a shard's index, and whether its run built here is to be used), outcomes come back up another
    (``_worker``'s pickled outcome), each a message of ``rcotorch.run.pipes``."""

    def __init__(self, sweep, shards, steps, device, shard_out, runs) -> None:
        import warnings
        jobs_r, self.jobs = os.pipe()
        self.results, results_w = os.pipe()
        self.shard: int | None = None          # the shard it runs, None while it waits for one
        self.start = 0.0
        self.ended = False
        # the stop signals wait until the forked process has its own handlers (a signal meanwhile would reach this
        # process's handlers in it, and the shard would not hear of it)
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
        try:
            with warnings.catch_warnings():  # Python 3.12+ warns of forking with threads: the child uses none
                warnings.simplefilter("ignore", DeprecationWarning)
                self.pid = os.fork()
            if self.pid == 0:                # pragma: no cover - the child ends in os._exit
                os.close(self.jobs)
                os.close(self.results)
                _worker(jobs_r, results_w, sweep, shards, steps, device, shard_out, runs, blocked)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        os.close(jobs_r)
        os.close(results_w)

    def send(self, shard: int, fresh: bool, start: float) -> None:
        """Hand it shard ``shard``. A worker that died since its last shard is found at the end of its results
        (``read``), and the shard named as the one it did not finish."""
        self.shard, self.start = shard, start
        with contextlib.suppress(BrokenPipeError):
            write_frame(self.jobs, shard.to_bytes(4, "little") + bytes([fresh]))

    def read(self) -> bytes | None:
        """The outcome the worker sent (a worker writes each whole, so that it is read at once where the pipe has
        data), or None, and ``ended``, where the worker closed its end."""
        frame = read_frame(self.results)
        self.ended = frame is None
        return frame

    def stop(self) -> None:
        """No more shards: a running one is sent SIGTERM (it saves its checkpoint), a waiting worker ends."""
        if self.shard is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGTERM)
        if self.jobs >= 0:
            os.close(self.jobs)
            self.jobs = -1

    def close(self) -> int:
        """Wait for the ended process; its wait status."""
        if self.jobs >= 0:
            os.close(self.jobs)
            self.jobs = -1
        os.close(self.results)
        return os.waitpid(self.pid, 0)[1]

    def kill(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self.pid, 0)
        for fd in (self.jobs, self.results):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)


def _worker(jobs: int, results: int, sweep, shards, steps, device, shard_out, runs, mask) -> None:
    """In a forked worker: with its own stop request (Ctrl-C, SIGTERM or SIGHUP, which the sweep forwards), run
    each shard sent on ``jobs`` on one thread and write its outcome to ``results`` (its length, then the pickled
    outcome: ('rows', rows), ('stopped', (step, checkpoint)) or ('error', (exception or None, traceback)), then
    what the shard printed on stdout and on stderr, which the sweep prints where its own output goes: a
    notebook's cell, a test's capture); end at the end of the jobs, at a stop, or after a shard that failed."""
    import gc
    import pickle
    import threading
    import traceback
    status = 3
    try:
        # what the sweep made before the fork (its imports, every shard's run) is out of the collector's reach here:
        # a collection would walk it again and again, and copy every page it touches
        gc.freeze()
        stop = threading.Event()
        for sig in STOP_SIGNALS:
            if signal.getsignal(sig) is not signal.SIG_IGN:
                signal.signal(sig, lambda *_: stop.set())
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)      # a signal held back since the fork arrives now
        import torch
        torch.set_num_threads(1)
        from .runner import Interrupted
        while not stop.is_set():
            job = read_frame(jobs)
            if job is None:
                break
            i, fresh = int.from_bytes(job[:4], "little"), bool(job[4])
            run, runs[i] = runs[i] if fresh else None, None     # a finished run is not kept
            printed = sys.stdout, sys.stderr = io.StringIO(), io.StringIO()
            try:
                outcome: tuple = ("rows", run_shard(sweep.scenario, shards[i], steps, sweep.dtype, device,
                                                    shard_out[i], run=run, stop=stop.is_set))
            except Interrupted as e:
                outcome = ("stopped", (e.step, None if e.checkpoint is None else str(e.checkpoint)))
            except BaseException as e:
                outcome = ("error", (e, traceback.format_exc()))
            del run
            texts = tuple(p.getvalue() for p in printed)
            try:
                data = pickle.dumps(outcome + texts)
                pickle.loads(data)              # an exception that does not come back whole comes as its text
            except Exception:
                text = outcome[1][1] if outcome[0] == "error" else traceback.format_exc()
                data = pickle.dumps(("error", (None, text)) + texts)
            write_frame(results, data)
            if outcome[0] != "rows":
                break
        status = 0
    finally:
        os._exit(status)


def _shard_outcome(data: bytes, status: int, shard) -> tuple[str, Any]:
    """What a worker sent for a shard (``_worker``), after printing what the shard printed: ('rows', rows),
    ('stopped', Interrupted) or ('error', the exception to raise here)."""
    import pickle

    from .runner import Interrupted
    where = f"sweep shard {shard['index']} (members {shard['members'][0]}..{shard['members'][-1]})"
    try:
        kind, value, printed, said = pickle.loads(data)
    except Exception:
        how = (f"was killed by signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status)
               else f"exited with status {os.WEXITSTATUS(status)}")
        return "error", RuntimeError(f"{where}: its process {how} before it sent its result")
    for text, stream in ((printed, sys.stdout), (said, sys.stderr)):
        if text:
            stream.write(text)
            stream.flush()
    if kind == "stopped":
        step, checkpoint = value
        return kind, Interrupted(step, None if checkpoint is None else Path(checkpoint))
    if kind == "error":
        error, text = value
        if error is None:
            error = RuntimeError(f"{where} failed in its process:\n{text}")
        elif not isinstance(error, RcoError):
            error.add_note(f"{where}, in its process:\n{text}")
        return kind, error
    return kind, value


def _members(n: int) -> str:
    return f"{n} member" if n == 1 else f"{n} members"


def _health_counts(rows: list[dict[str, Any]]) -> str:
    from ..verdict.health import STATUSES
    return ", ".join(f"{sum(r['status'] == st for r in rows)} {st}" for st in STATUSES)


RAY_TIMEOUT = 20.0   # seconds to wait for an existing Ray cluster to answer


def _check_ray_address(address: str, timeout: float | None = None) -> None:
    """Fail fast when nothing answers at a Ray cluster's address (Ray itself retries for minutes): within
    ``timeout`` seconds, by default ``RAY_TIMEOUT`` (read when called)."""
    if address in ("auto", "local"):
        return
    timeout = RAY_TIMEOUT if timeout is None else timeout
    hostport = address.removeprefix("ray://")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"--ray-address {address!r}: expected HOST:PORT (the cluster's GCS address, as printed "
                          "by `ray start --head`), ray://HOST:PORT or auto")
    import grpc
    channel = grpc.insecure_channel(hostport)
    try:
        grpc.channel_ready_future(channel).result(timeout=timeout)
    except grpc.FutureTimeoutError:
        raise ConfigError(f"--ray-address {address}: no Ray cluster answered within {timeout:.0f} s; start one "
                          "with `ray start --head` and pass the address it prints, or leave --ray-address out "
                          "to start a local one") from None
    finally:
        channel.close()


def _import_ray():
    try:
        import ray
    except ImportError:
        raise ConfigError("the ray backend needs Ray: pip install 'rcotorch[ray]' (or pip install ray)") from None
    return ray


def _run_ray(sweep, shards, steps, device, shard_out, address, control: RunControl) -> list[dict[str, Any]]:
    """The shards run as Ray tasks (a local instance, or the cluster at ``address``); ``control.stop`` is asked
    while waiting for them, and cancels those still running."""
    ray = _import_ray()
    started = not ray.is_initialized()
    if started:
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
        except (ConnectionError, RuntimeError, ValueError) as e:
            where = f"--ray-address {address}: cannot connect to Ray" if address else "cannot start Ray here"
            raise ConfigError(f"{where}: {e}") from None
    try:
        task = ray.remote(num_cpus=1, num_gpus=1 if device == "cuda" else 0)(run_shard)
        ref = sweep.scenario_ref()
        refs = {task.remote(ref, s, steps, sweep.dtype, device, o, 1): s for s, o in zip(shards, shard_out)}
        parts, pending, done = {}, list(refs), 0
        while pending:
            ready, pending = ray.wait(pending, num_returns=1, timeout=0.5)
            if control.stop is not None and control.stop():
                from .runner import Interrupted
                for ref in pending:
                    ray.cancel(ref, force=True)
                raise Interrupted(None, None)
            for ref in ready:
                s = refs[ref]
                parts[s["index"]] = ray.get(ref)
                done += 1
                if control.progress:
                    print(f"shard {s['index'] + 1}/{len(shards)} done ({done} of {len(shards)}): "
                          f"{_health_counts(parts[s['index']])}", flush=True)
        return [row for i in sorted(parts) for row in parts[i]]
    finally:
        if started:
            ray.shutdown()


def write_table(rows: list[dict[str, Any]], out: Path) -> None:
    """``sweep.json`` (a list, one member's row per line) and ``sweep.csv`` (one row per member), each written
    atomically."""
    from .outputs import write_text
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "sweep.json", "[\n" + ",\n".join(json.dumps(r) for r in rows) + "\n]\n")
    columns = list(dict.fromkeys(c for r in rows for c in r))          # each column once, in the order met
    text = io.StringIO(newline="")
    w = csv.writer(text)
    w.writerow(columns)
    for r in rows:
        w.writerow(["" if (v := r.get(c)) is None else v for c in columns])
    write_text(out / "sweep.csv", text.getvalue())


HPARAMS_MEMBERS_MAX = 400   # one HParams session (a TensorBoard run) per member up to this sweep size


def write_hparams(rows: list[dict[str, Any]], sweep: Sweep, out: Path, shard_dirs: list[Path]) -> None:
    """HParams sessions of a sweep: one per member (``out/members/member_NNNNNN``) with its swept settings, seed,
    status and final values (``rcotorch.run.monitor.final_values``, at its shard's last step), while the sweep
    has at most ``HPARAMS_MEMBERS_MAX`` members.

    Every session is a run in TensorBoard's run list, and TensorBoard leaves every run unselected (empty
    charts) once a logdir holds more than 500 runs; so a larger sweep makes each shard's session (in the shard's
    ``hparams/``: settings, ranges of the per-member ones, counts of each status, batch means) and says so in a
    text card (``sweep``): the per-member table is ``sweep.csv``.
    """
    import time

    from .monitor import SESSION, EventFile, final_values, setting_text, write_session
    from .outputs import MANIFEST, list_in_manifest
    sc = sweep.scenario
    by_shard: dict[int, list] = {}                      # each shard's rows, in the table's order
    for r in rows:
        by_shard.setdefault(r["shard"], []).append(r)
    if len(rows) <= HPARAMS_MEMBERS_MAX:
        swept = list(sweep.grid) + list(sweep.random) + ["seed"]
        settings = set(sc.settings)
        last: dict[int, int] = {}           # each shard's last step, where its members' final values are
        why: dict[int, Any] = {}            # why each member is not converged, undetermined or biased
        for index, folder in enumerate(shard_dirs):
            try:
                shard = json.loads((folder / "summary.json").read_text())
                last[index] = int(shard["steps"])
            except (OSError, ValueError, KeyError, TypeError):
                last[index] = 0
                continue
            whys = (shard.get("health") or {}).get("why")
            part = sorted(r["member"] for r in by_shard.get(index, ()))   # the shard's members, in its order
            if isinstance(whys, list) and len(whys) == len(part):
                why.update(zip(part, whys))
        for r in rows:
            summary = _member_summary(r, settings)
            summary["health"] = {"why": why.get(r["member"])}
            hp = {k: r[k] for k in swept if isinstance(r.get(k), (int, float, str, bool))}
            hp.update(scenario=sweep.scenario_name, shard=r["shard"], member=r["member"])
            with EventFile(out / "members" / f"member_{r['member']:06d}") as w:
                write_session(w, hp, summary, scenario=sc)
                w.scalars(last.get(r["shard"], 0), time.time(), list(final_values(summary, scenario=sc).items()))
        return
    note = (f"This sweep has {len(rows)} members. TensorBoard leaves every run unselected once a logdir holds "
            f"more than 500 runs, and each HParams row is a run, so HParams shows one row per shard (sweeps up to "
            f"{HPARAMS_MEMBERS_MAX} members get one row per member). The table of every member (settings, seed, "
            f"estimates, errors, status) is {out / 'sweep.csv'} (and sweep.json).")
    for index, folder in enumerate(shard_dirs):
        part = by_shard.get(index)
        if not part:
            continue
        summary = json.loads((folder / "summary.json").read_text())
        summary["status"] = [r.get("status") or ("diverged" if r["diverged"] else "finished") for r in part]
        hp = {k: v if isinstance(v, (int, float, str, bool)) else setting_text(v)
              for k, v in summary["settings"].items()}
        hp.update(scenario=sweep.scenario_name, members=f"{part[0]['member']}..{part[-1]['member']}")
        with EventFile(folder / SESSION) as w:
            write_session(w, hp, summary, scenario=sc)
            w.scalars(summary["steps"], time.time(), list(final_values(summary, scenario=sc).items()))
        with EventFile(folder) as n:
            n.add_text("sweep", note, 0)
        if (folder / MANIFEST).is_file():        # the shard lists them, so that --overwrite may replace them
            list_in_manifest(folder, [w.path, n.path])


def _member_summary(row: Mapping[str, Any], settings: set[str]) -> dict[str, Any]:
    """A member's row of the sweep table in the shape of a batch-of-one summary (``settings``: the scenario's
    setting names, which the row holds beside the results)."""
    est = {k[4:]: v for k, v in row.items() if k.startswith("est_")}
    truth = {k[6:]: v for k, v in row.items() if k.startswith("truth_")}
    skip = settings | {"member", "shard", "diverged", "diverged_at", "status"}
    metrics = {k: v for k, v in row.items() if k not in skip and not k.startswith(("est_", "truth_", "err_", "lower_",
                                                                                   "upper_", "bias_"))
               and isinstance(v, (int, float)) and not isinstance(v, bool)}
    intervals = {k[6:]: {"lower": v, "upper": row.get(f"upper_{k[6:]}"), "bias": row.get(f"bias_{k[6:]}")}
                 for k, v in row.items() if k.startswith("lower_")}
    requirements = {k[5:]: {"pass": bool(v)} for k, v in row.items() if k.startswith("pass_")}
    return {"batch": 1, "estimates": est, "truth": truth, "metrics": metrics, "status": row.get("status"),
            "intervals": intervals, "requirements": requirements,
            "diverged": [{"member": 0, "step": row["diverged_at"]}] if row["diverged"] else []}
