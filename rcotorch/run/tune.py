"""Tuning from held-out data: a search over a refinement's tuning settings, every candidate scored on held-out
validation only (``rcotorch.verdict.validation``: the refined model, theta frozen, simulated on data the refinement did
not use), never on the truth.

A tuning is a sweep (``rcotorch.run.sweep``): every candidate is a member of batched runs (one batch per graph
structure: candidates that differ only in per-member settings such as p0 and lam share a batch; nu and nc
change the graph), run on the same backends (local or Ray), resumable the same way. Method ``tpe`` (optuna's
tree-structured Parzen estimator, ``pip install 'rcotorch[tune]'``) runs ``rounds`` such sweeps: each round
asks for a batch of candidates given the scores of the rounds before it, runs them as one sweep and tells their
scores; the first round is a random draw. Each candidate runs with
``seeds`` seeds; its score is the mean over them of the held-out RMS error (``metrics.validation_rmse``, the
first output's units), a seed that diverged or could not be validated scoring infinity.

A scenario may declare its search space (``Scenario.tuning_space``): ``rcotorch tune NAME`` searches it
(``Tuning.declared``), ``--set`` holding settings for every candidate (``Tuning.fixing``: a held setting is no
longer searched). Otherwise a config file declares the search.

Config file (TOML or JSON)::

    scenario = "sdof-stiffness-damping"
    steps = 5000
    method = "random"          # or "grid": the full factorial of the lists in [space]; or "tpe"
    samples = 64               # random or tpe candidates
    rounds = 4                 # tpe: samples are asked for in this many batches, each one sweep
    seeds = 2
    [fixed]                    # settings held for every candidate (e.g. a deliberately poor start)
    dK = -0.3
    [space]                    # what is searched: a list (grid, or choice) or a distribution (random)
    p0 = {loguniform = [1.0, 1e6]}
    nu = [10, 30, 100]
    lam = {uniform = [0.98, 1.0]}

Results in the output folder: ``tune.csv`` (one row per candidate, ranked: score, its spread over seeds, the
held-out fit in percent against the initial model's, how many seeds diverged), ``best.toml`` (the best
candidate's settings and the fixed ones, which ``rcotorch run NAME --config best.toml`` accepts; its comment
says how to run them, from the script that declares a scenario that is not registered),
``sensitivity.csv`` (for each searched setting, the best and median score at each of its values, or in
quantile bins of a continuous one) and the sweep's own ``sweep.csv`` under ``runs/`` (tpe: one sweep per round,
``runs/round_000``, ...).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import math
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigError, OutputError, RcoError
from . import scenario as scenarios
from .sweep import _TYPES as SWEEP_TYPES
from .sweep import DISTRIBUTIONS, Sweep, _check_types, _is_int, run_sweep

if TYPE_CHECKING:
    from .control import RunControl

METHODS = ("grid", "random", "tpe")
CONFIG_KEYS = {"scenario", "steps", "method", "samples", "rounds", "seeds", "seed", "fixed", "space", "shard_size",
               "dtype"}
TPE_DISTRIBUTIONS = ("uniform", "loguniform", "choice")
SCORE = "validation_rmse"
BINS = 4                     # quantile bins of a continuous setting in the sensitivity table
# The type of each top-level config value: (test, what it must be); the keys a sweep has too are checked as its.
_TYPES = {**{k: v for k, v in SWEEP_TYPES.items() if k in CONFIG_KEYS},
          "method": (lambda v: v in METHODS, f"one of {METHODS}"),
          "rounds": (_is_int, "an integer"),
          "space": (lambda v: isinstance(v, Mapping) and bool(v), "a non-empty table of settings")}


@dataclass
class Tuning:
    """A declared search; ``sweep()`` is the sweep that runs it."""

    scenario: str | scenarios.Scenario       # a registered name, or a scenario object of one's own
    space: Mapping[str, Any]
    method: str = "random"
    samples: int = 32
    rounds: int = 4                           # tpe: the samples are asked for in this many batches
    seeds: int | Sequence[int] = 2
    seed: int = 0
    steps: int | None = None
    fixed: Mapping[str, Any] = field(default_factory=dict)
    shard_size: int = 4096
    dtype: str = "float64"

    @classmethod
    def from_dict(cls, spec: Mapping[str, Any], source: str = "tune") -> Tuning:
        unknown = set(spec) - CONFIG_KEYS
        if unknown:
            raise ConfigError(f"{source}: unknown key(s) {sorted(unknown)}; allowed: {sorted(CONFIG_KEYS)}")
        for key in ("scenario", "space"):
            if key not in spec:
                raise ConfigError(f"{source}: '{key}' is missing")
        _check_types(spec, source, _TYPES)
        return cls(**spec)

    @classmethod
    def from_file(cls, path: str | Path) -> Tuning:
        from .sweep import read_config
        return cls.from_dict(read_config(path, "tuning"), str(path))

    @classmethod
    def declared(cls, scenario: str | scenarios.Scenario, **options) -> Tuning:
        """The search a scenario declares (``Scenario.tuning_space``, what ``rcotorch tune NAME`` runs), with
        ``options`` (method, samples, seeds, steps, fixed, ...) as for the constructor."""
        sc = scenarios.get(scenario)
        if not sc.tuning_space:
            raise ConfigError(f"tune: scenario '{sc.name}' declares no search space; give one in a tuning config "
                              f"file (scenario = \"{sc.name}\" and a table [space], docs/tuning.md) and run "
                              "`rcotorch tune CONFIG`")
        space = {k: v if isinstance(v, Mapping) else list(v) for k, v in sc.tuning_space.items()}
        return cls(scenario=scenario, space=space, **options)

    def fixing(self, settings: Mapping[str, Any]) -> Tuning:
        """This search with ``settings`` held for every candidate: added to ``fixed``, and no longer searched
        where the space held them (``rcotorch tune ... --set lam=1`` searches the rest)."""
        if not settings:
            return self
        space = {k: v for k, v in self.space.items() if k not in settings}
        if not space:
            raise ConfigError(f"tune: {', '.join(sorted(settings))} fixed, nothing is left to search (the space is "
                              f"{sorted(self.space)})")
        return dataclasses.replace(self, space=space, fixed={**dict(self.fixed), **dict(settings)})

    def sweep(self, points: Sequence[Mapping[str, Any]] | None = None) -> Sweep:
        """The sweep of every candidate and seed. Grid: the lists' full factorial. Random: ``samples`` draws,
        a list meaning a uniform choice among its values. Tpe: the sweep of one round's candidates ``points``
        (from ``ask``). A searched setting overrides its value in ``fixed`` (the start the search leaves)."""
        sc = scenarios.get(self.scenario)
        if not sc.validation_steps and type(sc).validation is scenarios.Scenario.validation:
            raise ConfigError(f"tune: scenario '{sc.name}' has no held-out validation to score candidates on")
        fixed = {k: v for k, v in self.fixed.items() if k not in self.space}
        if self.method == "tpe":
            if points is None:
                raise ConfigError("tune: method 'tpe' runs round by round; its sweeps are of the candidates that "
                                  "Tuning.ask gives")
            self._distributions()
            return Candidates(scenario=self.scenario,
                              random={k: v if isinstance(v, Mapping) else {"choice": list(v)}
                                      for k, v in self.space.items()},
                              samples=len(points), points=[dict(p) for p in points], seeds=self.seeds,
                              seed=self.seed, steps=self.steps, fixed=fixed, shard_size=self.shard_size,
                              dtype=self.dtype)
        grid, random = {}, {}
        for name, values in self.space.items():
            if isinstance(values, Mapping):
                if self.method == "grid":
                    raise ConfigError(f"tune: method 'grid' needs a list of values for {name!r}, got {values!r}")
                random[name] = values
            elif isinstance(values, Sequence) and not isinstance(values, (str, bytes)) and values:
                if self.method == "grid":
                    grid[name] = list(values)
                else:
                    random[name] = {"choice": list(values)}
            else:
                raise ConfigError(f"tune: space {name!r} needs a list of values or one of {DISTRIBUTIONS}, "
                                  f"got {values!r}")
        return Sweep(scenario=self.scenario, grid=grid, random=random,
                     samples=self.samples if random else 0, seeds=self.seeds, seed=self.seed, steps=self.steps,
                     fixed=fixed, shard_size=self.shard_size, dtype=self.dtype)

    # --- tpe: rounds of batched candidates --------------------------------------------------------------------
    def round_sizes(self) -> list[int]:
        """How many candidates each tpe round asks for: ``samples`` split as evenly as ``rounds`` allows."""
        for key in ("samples", "rounds"):
            v = getattr(self, key)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ConfigError(f"tune: {key} must be a positive integer, got {v!r}")
        if self.rounds > self.samples:
            raise ConfigError(f"tune: rounds ({self.rounds}) cannot exceed samples ({self.samples}): every round "
                              "asks for at least one candidate")
        k, extra = divmod(self.samples, self.rounds)
        return [k + (r < extra) for r in range(self.rounds)]

    def _distributions(self) -> dict[str, Any]:
        """The searched settings as optuna distributions (a list or choice: the index of its value)."""
        _import_optuna()
        from optuna.distributions import CategoricalDistribution, FloatDistribution
        dists = {}
        for name, values in self.space.items():
            if isinstance(values, Sequence) and not isinstance(values, (str, bytes)) and values:
                values = {"choice": list(values)}
            if not isinstance(values, Mapping) or len(values) != 1 or next(iter(values)) not in TPE_DISTRIBUTIONS:
                raise ConfigError(f"tune: method 'tpe' needs, for space {name!r}, a list of values or one of "
                                  f"{TPE_DISTRIBUTIONS}, got {values!r}")
            kind, args = next(iter(values.items()))
            if not isinstance(args, Sequence) or isinstance(args, (str, bytes)):
                raise ConfigError(f"tune: space {name!r} {kind} needs a list, got {args!r}")
            args = list(args)
            if kind == "choice":
                if not args:
                    raise ConfigError(f"tune: space {name!r} choice needs a non-empty list")
                dists[name] = CategoricalDistribution(list(range(len(args))))
                continue
            if len(args) != 2 or not all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in args):
                raise ConfigError(f"tune: space {name!r} {kind} needs two numbers, got {args!r}")
            lo, hi = float(args[0]), float(args[1])
            if not lo <= hi or (kind == "loguniform" and lo <= 0):
                need = "0 < low <= high" if kind == "loguniform" else "low <= high"
                raise ConfigError(f"tune: space {name!r} {kind} needs {need}, got {args}")
            dists[name] = FloatDistribution(lo, hi, log=kind == "loguniform")
        return dists

    def _choices(self, name: str) -> list | None:
        """A listed setting's values (a choice), None for a range."""
        values = self.space[name]
        if isinstance(values, Mapping):
            return list(values["choice"]) if "choice" in values else None
        return list(values)

    def ask(self, history: Sequence[tuple[Mapping[str, Any], float]], round_index: int) -> list[dict[str, Any]]:
        """Round ``round_index``'s candidates (settings dicts) from the earlier rounds' ``history``: (candidate, score)
        pairs. A fresh TPE sampler, seeded by ``seed`` and the round, is told the history and asked for the
        round's batch (optuna's constant liar keeps the batch apart), so the candidates depend on the history
        alone: an interrupted search resumed asks for the same ones. The first round is a random draw."""
        import warnings
        optuna = _import_optuna()
        dists = self._distributions()
        sizes = self.round_sizes()
        choices = {name: self._choices(name) for name in dists}
        index = {name: None if c is None else {json.dumps(_plain(v)): i for i, v in enumerate(c)}
                 for name, c in choices.items()}
        seed = int(np.random.SeedSequence([self.seed, round_index]).generate_state(1)[0])
        verbosity = optuna.logging.get_verbosity()
        optuna.logging.set_verbosity(optuna.logging.WARNING)         # not a line per round's study
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=sizes[0], multivariate=True,
                                                     constant_liar=True)
                study = optuna.create_study(direction="minimize", sampler=sampler)
                study.add_trials([optuna.trial.create_trial(
                    params={k: c[k] if index[k] is None else index[k][json.dumps(_plain(c[k]))] for k in dists},
                    distributions=dists, value=score) for c, score in history])
                trials = [study.ask(dists) for _ in range(sizes[round_index])]
        finally:
            optuna.logging.set_verbosity(verbosity)
        return [{k: float(t.params[k]) if choices[k] is None else choices[k][t.params[k]] for k in dists}
                for t in trials]

    def check_space(self, start: Mapping[str, Any]) -> None:
        """Build the batched runs of candidate ``start`` with each listed value and each end of each range in
        turn: a tpe search fails on a bad value before any work, not in a later round."""
        from .sweep import make_run
        edges = []
        for name, values in self.space.items():
            ends = self._choices(name)
            edges += [{**start, name: v} for v in (list(next(iter(values.values()))) if ends is None else ends)]
        sweep = self.sweep(edges)
        try:
            for shard in sweep.shards():                 # the members' settings are checked here first
                make_run(self.scenario, shard, self.steps, self.dtype, "cpu", None)
        except ConfigError as e:
            raise ConfigError(f"tune space (each listed value and each end of a range): {e}") from None


@dataclass
class Candidates(Sweep):
    """A sweep of given candidates (one tpe round): ``points`` in place of random draws."""

    points: Sequence[Mapping[str, Any]] = field(default_factory=list)

    def _draws(self) -> list[dict[str, Any]]:
        return [dict(p) for p in self.points]


def _import_optuna():
    try:
        import optuna
    except ImportError:
        raise ConfigError("tune: method 'tpe' needs optuna: pip install 'rcotorch[tune]' (or pip install optuna)"
                          ) from None
    return optuna


@dataclass
class TuneResult:
    """The ranked candidates (best first) and the search's folder."""

    candidates: list[dict[str, Any]]
    sensitivity: list[dict[str, Any]]
    best: dict[str, Any]
    out: Path
    members: int

    def table(self, top: int = 10) -> str:
        keys = [k for k in self.candidates[0]["settings"]] if self.candidates else []
        head = ["rank", *keys, "score", "spread", "fit %", "fit % initial", "diverged"]
        lines = [head]
        for c in self.candidates[:top]:
            lines.append([str(c["rank"]), *(_fmt(c["settings"][k]) for k in keys), _fmt(c["score"]),
                          _fmt(c["spread"]), _fmt(c["fit_percent"]), _fmt(c["fit_percent_initial"]),
                          f"{c['diverged']}/{c['seeds']}"])
        widths = [max(len(r[i]) for r in lines) for i in range(len(head))]
        return "\n".join("  ".join(v.ljust(w) for v, w in zip(r, widths)) for r in lines)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def run_tune(tuning: Tuning, out: str | Path | None = None, backend: str = "local", device: str = "cpu",
             ray_address: str | None = None, progress: bool = True, overwrite: bool = False, resume: bool = False,
             stop=None, folder=None, control: RunControl | None = None) -> TuneResult:
    """Run every candidate (as a sweep in ``out/runs``; tpe: a sweep per round in ``out/runs/round_NNN``) and
    write ``tune.csv``, ``best.toml`` and ``sensitivity.csv`` into ``out`` (default ``runs/tune-SCENARIO``).
    ``stop()`` is asked between steps (``rcotorch.run.runner.Interrupted`` is raised after the running shard saved
    its checkpoint); ``resume`` continues an interrupted tuning (a tpe search re-reads its finished rounds from
    their folders and tells their scores again); ``folder``: an ``OutputFolder`` for ``out`` made by the caller,
    who closes it. ``control``: these five (``progress``, ``overwrite``, ``resume``, ``stop``, ``folder``) as one
    ``rcotorch.run.control.RunControl``, given instead of them; each sweep of the tuning runs with a copy of it.

    A folder that holds a tuning is refused unless ``resume`` or ``overwrite`` is given (``OutputError``, naming
    both), as ``rcotorch tune`` refuses it without ``--resume`` or ``--overwrite``. A tuning stopped before any
    candidate ran (an error, Ctrl-C) leaves the folder as it found it, so that the next one starts there afresh;
    one stopped later is continued with ``resume``."""
    from .control import RunControl
    control = RunControl.given(control, progress=progress, overwrite=overwrite, resume=resume, stop=stop,
                               folder=folder)
    if control.folder is not None:
        return _run_tune(tuning, out, backend, device, ray_address, control)
    try:
        return _run_tune(tuning, out, backend, device, ray_address, control)
    except OutputError as e:                    # said in this function's arguments, not the command line's
        raise type(e)(_in_arguments(str(e))) from e.__cause__


def _in_arguments(message: str) -> str:
    """An output folder's error as a caller of ``run_tune`` acts on it: its arguments, not the command's
    options."""
    for option, argument in (("use --resume to continue it, --overwrite to replace it, or choose another --out",
                              "pass resume=True to continue it, overwrite=True to replace it, or choose another out"),
                             ("--resume", "resume=True"), ("--overwrite", "overwrite=True"),
                             ("another --out", "another out"), ("--out", "out")):
        message = message.replace(option, argument)
    return message


def _run_tune(tuning: Tuning, out, backend, device, ray_address, control: RunControl) -> TuneResult:
    """``run_tune``, its output folder's messages in the words of the command line. Each sweep runs with a copy
    of ``control`` that opens its own folder and resumes only where that folder holds a sweep."""
    from .outputs import OutputFolder, write_text
    tpe = tuning.method == "tpe"
    if tpe:
        first = tuning.ask([], 0)
        tuning.check_space(first[0])
        sweep = tuning.sweep(first)
    else:
        sweep = tuning.sweep()
    sweep.shards()                           # every candidate checked before the folder is touched
    name = sweep.scenario_name
    out = Path(out or Path("runs") / f"tune-{name}")
    own = control.folder is None
    folder = control.folder or OutputFolder(out, "tune")
    config = {**_plain(tuning.__dict__), "scenario": name}
    folder.open(control.mode, info=None if control.resume else {"scenario": name, "config": config})
    searched = list(tuning.space)
    try:
        if not tpe:
            folder.add_child("runs")
            folder.register()
            rows = run_sweep(sweep, backend=backend, device=device, out=out / "runs", ray_address=ray_address,
                             control=_sweep_control(control, out / "runs"))
        else:
            rows, history = [], []
            sizes = tuning.round_sizes()
            with _ray_session(backend, ray_address):
                for r in range(len(sizes)):
                    points = first if r == 0 else tuning.ask(history, r)
                    where = out / "runs" / f"round_{r:03d}"
                    folder.add_child(str(where.relative_to(out)))
                    folder.register()
                    if control.progress:
                        print(f"round {r + 1}/{len(sizes)}: {len(points)} candidates", flush=True)
                    part = run_sweep(tuning.sweep(points), backend=backend, device=device, out=where,
                                     ray_address=ray_address, control=_sweep_control(control, where))
                    seeds = len(part) // len(points)            # members: candidate-major, then seed
                    history += [(p, _candidate_score(part[i * seeds:(i + 1) * seeds]))
                                for i, p in enumerate(points)]
                    rows += part
        candidates = rank(rows, searched)
        if not candidates:
            raise ConfigError("tune: no candidate ran")
        if not any(r.get(SCORE) is not None for r in rows):
            raise ConfigError(f"tune: no candidate of scenario '{name}' was validated on held-out data: the "
                              f"scenario gives none for these settings (see `rcotorch show {name}`)")
        best = {**_plain(dict(tuning.fixed)), **candidates[0]["settings"]}
        write_text(out / "tune.csv", _csv(candidates, searched))
        write_text(out / "best.toml", best_toml(name, best, candidates[0], path=out / "best.toml",
                                                script=_script_class(tuning.scenario), steps=tuning.steps))
        sensitivity = sensitivity_table(candidates, searched)
        write_text(out / "sensitivity.csv", _csv_rows(sensitivity))
        folder.register()                    # tune.csv, best.toml and sensitivity.csv are the tuning's files
    except BaseException:
        folder.discard()                     # stopped before anything ran: the folder as it was found
        raise
    finally:
        if own:
            folder.close()
    return TuneResult(candidates=candidates, sensitivity=sensitivity, best=best, out=out, members=len(rows))


def _sweep_control(control: RunControl, where: Path) -> RunControl:
    """How a sweep of a tuning into ``where`` runs: as the tuning, in a folder of its own, resumed only where
    ``where`` holds a sweep (one never started there starts afresh)."""
    from .outputs import MANIFEST
    return dataclasses.replace(control, folder=None, resume=control.resume and (where / MANIFEST).is_file())


@contextlib.contextmanager
def _ray_session(backend: str, address: str | None):
    """One Ray instance for all the rounds of a search (each sweep would otherwise start and stop its own)."""
    if backend != "ray":
        yield
        return
    from .sweep import _check_ray_address, _import_ray
    ray = _import_ray()
    if ray.is_initialized():
        yield
        return
    if address:
        _check_ray_address(address)
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    except (ConnectionError, RuntimeError, ValueError) as e:
        where = f"--ray-address {address}: cannot connect to Ray" if address else "cannot start Ray here"
        raise ConfigError(f"{where}: {e}") from None
    try:
        yield
    finally:
        ray.shutdown()


def rank(rows: Sequence[Mapping[str, Any]], searched: Sequence[str]) -> list[dict[str, Any]]:
    """Candidates (the searched settings' values) with their scores over seeds, best first."""
    groups: dict[str, list[Mapping[str, Any]]] = {}
    for r in rows:
        key = json.dumps([r.get(k) for k in searched])
        groups.setdefault(key, []).append(r)
    out = []
    for members in groups.values():
        scores = np.array([_score(r) for r in members])
        finite = scores[np.isfinite(scores)]
        out.append({"settings": {k: members[0].get(k) for k in searched}, "score": _candidate_score(members),
                    "spread": float(finite.std()) if len(finite) > 1 else 0.0,
                    "fit_percent": _mean(members, "validation_fit_percent"),
                    "fit_percent_initial": _mean(members, "validation_fit_percent_initial"),
                    "diverged": int(sum(bool(r.get("diverged")) for r in members)), "seeds": len(members)})
    out.sort(key=lambda c: (c["score"], c["spread"]))
    for i, c in enumerate(out):
        c["rank"] = i + 1
    return out


def _candidate_score(members: Sequence[Mapping[str, Any]]) -> float:
    """A candidate's score: the mean over its seeds of the held-out RMS error; infinity if a seed has none."""
    scores = np.array([_score(r) for r in members])
    return float(scores.mean()) if np.isfinite(scores).all() else math.inf


def _score(row: Mapping[str, Any]) -> float:
    v = row.get(SCORE)
    if row.get("diverged") or v is None or not isinstance(v, (int, float)) or not math.isfinite(v):
        return math.inf
    return float(v)


def _mean(rows, key) -> float:
    vals = [r.get(key) for r in rows if isinstance(r.get(key), (int, float)) and math.isfinite(r.get(key))]
    return float(np.mean(vals)) if vals else math.nan


def sensitivity_table(candidates: Sequence[Mapping[str, Any]], searched: Sequence[str]) -> list[dict[str, Any]]:
    """For each searched setting: the best and median score of the candidates at each of its values (a
    setting with more than ``BINS`` numeric values: at each quantile bin of them)."""
    table = []
    for name in searched:
        values = [c["settings"][name] for c in candidates]
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
        if numeric and len(set(values)) > BINS:
            edges = np.quantile(np.asarray(values, dtype=float), np.linspace(0, 1, BINS + 1))
            labels = [f"{edges[i]:.4g}..{edges[i + 1]:.4g}" for i in range(BINS)]
            which = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, BINS - 1)
            groups = {labels[i]: [c for c, w in zip(candidates, which) if w == i] for i in range(BINS)}
        else:
            groups = {}
            for c in candidates:
                groups.setdefault(_fmt(c["settings"][name]), []).append(c)
        for label, part in groups.items():
            if not part:
                continue
            scores = np.array([c["score"] for c in part])
            table.append({"setting": name, "value": label, "candidates": len(part), "best": float(scores.min()),
                          "median": float(np.median(scores))})
    return table


def best_toml(scenario: str, settings: Mapping[str, Any], best: Mapping[str, Any], path: str | Path = "best.toml",
              script: str | None = None, steps: int | None = None) -> str:
    """The chosen settings as a ``--config`` file of ``rcotorch run`` (at ``path``), its comment saying how to
    run them (for ``steps``, the candidates' steps, where the search gave them): ``rcotorch run`` for a
    registered scenario; for one declared in a script (``script``: the name of its class), from that script."""
    lines = [f"# the best candidate of a tuning of scenario '{scenario}' (rank 1 of the search), score "
             f"{best['score']:.6g} (held-out RMS error, mean over {best['seeds']} seeds)"]
    where = shlex.quote(str(path)) + (f" --steps {steps}" if steps is not None else "")
    if script is None:
        lines.append(f"# run it: rcotorch run {scenario} --config {where}")
    else:
        lines += [f"# '{scenario}' is declared in a script, not registered, so `rcotorch run` does not know it; "
                  "run these settings",
                  "# from that script:",
                  "#     import tomllib",
                  "#     from rcotorch.run.runner import Run, result_table",
                  f"#     settings = tomllib.load(open({str(path)!r}, 'rb'))['settings']",
                  f"#     run = Run({script}(), {'' if steps is None else f'steps={steps}, '}overrides=settings)",
                  "#     run.advance()",
                  "#     print(result_table(run.finish()))",
                  "# (or define SCENARIO = " + f"{script}() in a file of a folder listed in RCOTORCH_SCENARIOS; "
                  f"then: rcotorch run {scenario} --config {where})"]
    lines += [f'scenario = "{scenario}"', "", "[settings]"]
    for k, v in settings.items():
        lines.append(f"{k} = {_toml_value(v)}")
    return "\n".join(lines) + "\n"


def _script_class(scenario: str | scenarios.Scenario) -> str | None:
    """The class name of a scenario declared in a script (not registered under its name: ``rcotorch run`` does
    not know it); None for a registered one."""
    if isinstance(scenario, str):
        return None
    try:
        if type(scenarios.get(scenario.name)) is type(scenario):
            return None
    except RcoError:
        pass
    return type(scenario).__name__


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ConfigError(f"tune: cannot write setting value {v!r} to TOML")


def _csv(candidates: Sequence[Mapping[str, Any]], searched: Sequence[str]) -> str:
    rows = [{"rank": c["rank"], **c["settings"], **{k: c[k] for k in ("score", "spread", "fit_percent",
                                                                        "fit_percent_initial", "diverged",
                                                                        "seeds")}} for c in candidates]
    return _csv_rows(rows)


def _csv_rows(rows: Sequence[Mapping[str, Any]]) -> str:
    text = io.StringIO(newline="")
    if rows:
        w = csv.DictWriter(text, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow(r)
    return text.getvalue()


def _plain(value):
    return json.loads(json.dumps(value, default=str))
