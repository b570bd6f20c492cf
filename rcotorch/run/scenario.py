"""Scenarios: a named, reproducible refinement with default settings, truth, estimates and acceptance bounds.

A scenario file defines ``SCENARIO``, an instance of a ``Scenario`` subclass. The runner (``rcotorch.run.runner``)
builds its graph, steps it, logs it and writes ``summary.json`` with the keys the scenario declares.

Where scenarios are found (``available``):

* the scenarios shipped with the package, the modules of ``rcotorch.scenarios`` (the repository's top-level
  ``scenarios/`` folder, installed as that package); they build on each other by relative import;
* the ``.py`` files of every folder listed in the environment variable ``RCOTORCH_SCENARIOS`` (separated by
  ``os.pathsep``), loaded by path; such a folder is put on ``sys.path``, so its files may import each other by
  module name, and they may build on the shipped ones (``from rcotorch.scenarios.sdof_stiffness import
  SdofStiffness``). A name defined twice is an error naming both files.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import math
import os
import pkgutil
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from ..errors import ConfigError, DimensionError, RcoError, SettingError

if TYPE_CHECKING:        # torch and the graph are imported where used: listing scenarios needs neither
    import torch

    from ..graph import Graph


@dataclass(frozen=True)
class Requirement:
    """``key`` (e.g. 'estimates.dK' or 'metrics.freq_rel_err_max') must satisfy the bound.

    kind 'abs_err': |value - truth| < bound; 'rel_err': |value - truth| / |truth| < bound;
    'max': value < bound (or <= when ``inclusive``); 'min': value >= bound.
    """

    key: str
    kind: str
    bound: float
    inclusive: bool = False

    def check(self, value, truth=None):
        """Return (the checked quantity, pass): floats, or tensors of every member's values (a NaN fails)."""
        if self.kind == "abs_err":
            q = abs(value - truth)
        elif self.kind == "rel_err":
            q = abs(value - truth) / abs(truth)
        else:
            q = value
        if self.kind == "min":
            return q, q >= self.bound
        return q, (q <= self.bound if self.inclusive else q < self.bound)

    def describe(self) -> str:
        op = {"abs_err": "|err| <", "rel_err": "rel err <", "max": "<=" if self.inclusive else "<",
              "min": ">="}[self.kind]
        return f"{op} {self.bound:g}"


class Setting(NamedTuple):
    """What a scenario setting means: its ``unit`` ('' for labels, counts and dimensionless numbers), a
    one-line ``meaning``, and the allowed values of a text setting (``choices``; empty: any)."""

    unit: str
    meaning: str
    choices: tuple[str, ...] = ()


#: Robustness options of the RCO estimator (``RCOEstimator``'s arguments of the same names) that every scenario
#: offers as settings, with their defaults: 0 leaves the option off, so a scenario's results do not change.
ESTIMATOR_OPTIONS: Mapping[str, float] = {"r_delta": 0.0, "normalize": 0.0, "p_max": 0.0}
ESTIMATOR_OPTIONS_ABOUT: Mapping[str, Setting] = {
    "r_delta": Setting("", "penalty r_delta |theta - theta(k)|^2 on theta's change in the retrospective cost "
                           "(smooths and slows the estimate); 0: off"),
    "normalize": Setting("", "scale s of normalized regressors: the update is divided by sqrt(1 + |Psi|^2 / s^2) "
                             "(bounds the step on large signals); 0: off"),
    "p_max": Setting("", "bound on trace(P): P is scaled down to it after an update (covariance windup); 0: off"),
}
#: What ``rcotorch show`` says of the estimator's usual settings, in a scenario that has them and does not
#: describe them itself.
ESTIMATOR_SETTINGS_ABOUT: Mapping[str, Setting] = {
    "p0": Setting("", "initial RLS covariance P(0) = p0 I"),
    "lam": Setting("", "RLS forgetting factor in (0, 1]"),
    "nu": Setting("", "number of Markov parameters of u -> z in the retrospective cost"),
}
#: How a number setting may be bounded (``Scenario.bounds``): above 0, at least 0, or in (0, 1].
POSITIVE, NON_NEGATIVE, UNIT_INTERVAL = "positive", "non-negative", "(0, 1]"
BOUNDS = (POSITIVE, NON_NEGATIVE, UNIT_INTERVAL)
#: The bounds of the estimator's usual settings and options, in a scenario that has them and declares none.
ESTIMATOR_BOUNDS: Mapping[str, str] = {"p0": POSITIVE, "lam": UNIT_INTERVAL, "nu": POSITIVE, "r_delta": NON_NEGATIVE,
                                       "normalize": NON_NEGATIVE, "p_max": NON_NEGATIVE}
#: The largest seed: the random streams (``rcotorch.engine.rng``) take a seed modulo 2**32, so a seed outside
#: 0..SEED_MAX would draw the stream of one inside it.
SEED_MAX = 2 ** 32 - 1
VALIDATION_MIN_STEPS = 200    # held-out samples a short run is validated on at least (fit_steps of them fix the state)
#: The options that may differ between the members of one batch (a zero penalty is the same as none; a
#: scale or bound cannot be off for some members only, so a sweep over them runs one batch per value).
ESTIMATOR_OPTIONS_PER_MEMBER = frozenset({"r_delta"})


class Scenario:
    """Base class. Subclasses set the class attributes and implement ``build``, ``estimates`` and ``truth``.

    ``settings`` maps each setting to its default value; ``about`` maps each setting to a ``Setting`` (or a
    tuple ``(unit, meaning[, choices])``): what ``rcotorch show NAME`` prints (``p0``, ``lam`` and ``nu`` have
    a standard meaning, ``ESTIMATOR_SETTINGS_ABOUT``, unless the subclass describes them).

    Every scenario also has the settings of ``ESTIMATOR_OPTIONS`` (added to ``settings``, ``about`` and
    ``per_member`` when the subclass is defined, unless it declares them itself): the graph that ``build``
    returns gets them on its estimator (the block of role 'estimator', ``RCOEstimator.set_options``) when they
    are nonzero. A scenario that passes these options to its estimator itself, or offers other ones, lists
    the options it leaves to the base class in ``estimator_options`` (() for none).

    ``bounds`` maps a number setting to ``POSITIVE``, ``NON_NEGATIVE`` or ``UNIT_INTERVAL``: a value outside is
    refused naming the setting, before anything is built (``p0``, ``lam``, ``nu`` and the estimator options
    have ``ESTIMATOR_BOUNDS`` unless the subclass declares theirs). An integer setting named ``seed`` takes
    0..``SEED_MAX``. A graph that ``build`` cannot make from settings changed from their defaults (a
    ``ConfigError`` or ``ValueError``) is refused naming those settings (``SettingError``).
    """

    name: str = ""
    section: str = ""
    description: str = ""
    steps: int = 10000
    settings: Mapping[str, Any] = {}
    about: Mapping[str, Setting | tuple] = {}
    # Units of estimates and metrics that are not settings themselves, and of the measured output ('y').
    units: Mapping[str, str] = {}
    requirements: tuple[Requirement, ...] = ()
    # Settings that may differ between the members of one batched run (physical parameters, tuning such as
    # p0 and lambda, seeds). The others fix the graph's structure (sample time, orders, nu); a sweep over
    # them runs one batch per distinct value.
    per_member: frozenset[str] = frozenset()
    # The estimator options that the base class offers as settings and applies after ``build`` (see above).
    estimator_options: tuple[str, ...] = tuple(ESTIMATOR_OPTIONS)
    # Whether runs compute confidence intervals (``rcotorch.verdict.intervals``): False for estimates that are not
    # functions of the estimator's parameters alone (e.g. instantaneous values of u, which depend on the state).
    intervals: bool = True
    # Samples of held-out validation at the end of a run (``validation``; 0: none).
    validation_steps: int = 2000
    # The number settings' bounds (see above): setting -> POSITIVE, NON_NEGATIVE or UNIT_INTERVAL.
    bounds: Mapping[str, str] = {}
    # The search space of ``rcotorch tune NAME`` (the [space] of a tuning config, rcotorch.run.tune), e.g.
    # ``estimator_space(nu=15)``; {} where the scenario declares none (a tuning then needs a config file).
    tuning_space: Mapping[str, Any] = {}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        options = tuple(cls.estimator_options)
        unknown = set(options) - set(ESTIMATOR_OPTIONS)
        if unknown:
            raise ConfigError(f"scenario class {cls.__name__}: estimator_options {sorted(unknown)} are not among "
                              f"{list(ESTIMATOR_OPTIONS)}")
        cls.settings = {**cls.settings, **{k: ESTIMATOR_OPTIONS[k] for k in options if k not in cls.settings}}
        common = {k: v for k, v in ESTIMATOR_SETTINGS_ABOUT.items() if k in cls.settings and k not in cls.about}
        cls.about = {**cls.about, **common,
                     **{k: ESTIMATOR_OPTIONS_ABOUT[k] for k in options if k not in cls.about}}
        cls.per_member = frozenset(cls.per_member) | (ESTIMATOR_OPTIONS_PER_MEMBER & set(options))
        cls.bounds = {**{k: v for k, v in ESTIMATOR_BOUNDS.items() if k in cls.settings}, **cls.bounds}
        _check_bounds_declared(cls)
        build = cls.__dict__.get("build")
        if build is not None and not getattr(build, "_sets_estimator_options", False):
            @functools.wraps(build)
            def build_with_options(self, settings, batch, dtype, device):
                try:
                    graph = build(self, settings, batch, dtype, device)
                    apply_estimator_options(graph, settings, self.estimator_options)
                except (ConfigError, DimensionError, ValueError) as e:
                    refused = self.refused_with(settings, e)
                    if refused is None:
                        raise
                    raise refused from e
                return graph
            build_with_options._sets_estimator_options = True
            cls.build = build_with_options

    def refused_with(self, settings: Mapping[str, Any], e: BaseException) -> SettingError | None:
        """``e``, raised building the graph of ``settings``, as a ``SettingError`` that names the settings
        changed from their defaults; None where it is one already, is another kind of rcotorch error (a data
        file's, say, which names the file), or no setting was changed."""
        if isinstance(e, SettingError) or (isinstance(e, RcoError) and not isinstance(e, (ConfigError,
                                                                                           DimensionError))):
            return None
        changed = [k for k, v in settings.items() if k in self.settings and _differs(v, self.settings[k])]
        if not changed:
            return None
        given = ", ".join(f"{k} = {_shown(settings[k])}" for k in changed)
        return SettingError(f"scenario '{self.name}' with {given}: {e}", settings=tuple(changed),
                            detail=f"scenario '{self.name}': {e}")

    def setting(self, key: str) -> Setting:
        """Unit, meaning and choices of one setting (meaning '' where the scenario does not document it)."""
        if key not in self.settings:
            raise ConfigError(f"scenario '{self.name}': unknown setting {key!r}; settings are {sorted(self.settings)}")
        info = self.about.get(key, ("", ""))
        return info if isinstance(info, Setting) else Setting(*info)

    def resolve(self, overrides: Mapping[str, Any] | None = None, seed: int | None = None) -> dict[str, Any]:
        """Default settings with overrides applied (unknown names and wrong types rejected)."""
        out = dict(self.settings)
        for key, value in dict(overrides or {}).items():
            if key not in out:
                raise ConfigError(f"scenario '{self.name}': unknown setting {key!r}; settings are {sorted(out)}")
            out[key] = self._value(key, value)
        if seed is not None:
            out["seed"] = self._seed(seed)
        return out

    def resolve_members(self, common: Mapping[str, Any], members: list[Mapping[str, Any]]) -> dict[str, Any]:
        """Settings for a batch whose members differ: ``common`` overrides for all, ``members[b]`` for member b.
        A setting that differs between members becomes a list of per-member values."""
        out = self.resolve(common)
        keys = sorted({k for m in members for k in m})
        for key in keys:
            if key not in out:
                raise ConfigError(f"scenario '{self.name}': unknown setting {key!r}; settings are {sorted(out)}")
            values = [self._value(key, m.get(key, out[key])) for m in members]
            if key in self.per_member:
                out[key] = values  # kept per member even when equal: a member's seed picks its own stream
                continue
            if any(v != values[0] for v in values):
                raise ConfigError(f"scenario '{self.name}': setting {key!r} fixes the graph's structure and cannot "
                                  f"differ within one batch (per-member settings: {sorted(self.per_member)})")
            out[key] = values[0]
        return out

    def unit(self, key: str, settings: dict | None = None) -> str:
        """The unit of an estimate, metric or setting ('' where none is declared); ``settings``, where given, lets
        a scenario whose units depend on its settings (a sensor's kind) say which."""
        if key in self.units:
            return self.units[key]
        return self.setting(key).unit if key in self.settings else ""

    def _value(self, key: str, value):
        """An override converted to the default's type and checked against the setting's choices and bounds
        (``SettingError`` naming the setting)."""
        try:
            value = _coerce(self.name, key, value, self.settings[key])
        except ConfigError as e:
            raise SettingError(str(e), settings=(key,)) from None
        choices = self.setting(key).choices
        if choices and value not in choices:
            raise SettingError(f"scenario '{self.name}': setting {key} must be one of {list(choices)}, got {value!r}",
                               settings=(key,))
        if key == "seed" and isinstance(self.settings[key], int):
            return self._seed(value)
        bound = self.bounds.get(key)
        if bound is not None and not _within(bound, value):
            what = f"lie in {bound}" if bound == UNIT_INTERVAL else f"be {bound}"
            raise SettingError(f"scenario '{self.name}': setting {key} must {what}, got {_shown(value)}",
                               settings=(key,))
        return value

    def _seed(self, value) -> int:
        """A seed checked to lie in 0..SEED_MAX."""
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= SEED_MAX:
            raise SettingError(f"scenario '{self.name}': setting seed must be an integer in 0..{SEED_MAX}, got "
                               f"{_shown(value)}: the random streams take a seed modulo 2**32, so another one would "
                               "draw the stream of one in that range", settings=("seed",))
        return value

    def build(self, settings: Mapping[str, Any], batch: int, dtype: torch.dtype, device) -> Graph:
        """The graph for ``batch`` members; a per-member setting is a list of length ``batch``
        (``member_values`` turns it into a tensor)."""
        raise NotImplementedError

    def default_steps(self, settings: Mapping[str, Any]) -> int:
        """The steps of a run of these settings when the run names none: ``steps`` (a scenario of recorded
        data may give the length of the rows its settings choose)."""
        return self.steps

    def truth(self, settings: Mapping[str, Any]) -> dict[str, float]:
        """The true values of the estimates where they are known (one value, or one per member), at the end of
        a run: what the requirements are checked against."""
        return {}

    def truth_history(self, settings: Mapping[str, Any]) -> dict[str, list[tuple[float, float]]]:
        """The truths that change during a run: key -> [(time, value from that time on), ...] in time order
        (time in seconds where the graph has a sample time, else in steps), the last value the one ``truth``
        gives. TensorBoard and the figures draw such a truth as it was at each time and mark its changes; the
        summary and the requirements take its value at the run's end. By default nothing changes."""
        return {}

    def estimates(self, graph: Graph, settings: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """Current estimates, each a (B,) tensor (physical units)."""
        raise NotImplementedError

    def physics(self, settings: Mapping[str, Any], estimates: Mapping[str, torch.Tensor], batch: int,
                dtype: torch.dtype, device) -> Graph | None:
        """The physical system with its parameters at the run's estimates, for the verdict to measure how far the
        refined model's estimates are from the physics' (``rcotorch.verdict.intervals.replay``'s ``physics``):
        a graph like ``build``'s whose physical blocks (the physical system and the truth it holds) take each
        member's estimate in place of the setting of the same name. By default every estimate that is also a
        per-member setting (``per_member``) is substituted; None where there is none."""
        keys = [k for k in estimates if k in self.settings and k in self.per_member]
        if not keys:
            return None
        values = dict(settings)
        for k in keys:
            values[k] = estimates[k].detach().double().reshape(-1).tolist()
        return self.build(values, batch, dtype, device)

    def scales(self, settings: Mapping[str, Any]) -> dict[str, float]:
        """A size for each estimate that may be near zero (e.g. the nominal value a change is relative to): an
        estimate is determined when its interval's half-width is at most ``rcotorch.verdict.intervals.REL_TOL`` times
        max(|estimate|, scale). Estimates without one are judged against their own size."""
        return {}

    def metrics(self, graph: Graph, settings: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """Final metrics, each a (B,) tensor."""
        return {}

    def validation(self, graph: Graph, settings: Mapping[str, Any]) -> dict[str, Any] | None:
        """How a run's refined model is validated on held-out data: the keyword arguments of
        ``rcotorch.validate`` (``steps``, ``rows`` or ``data``), or None for no validation. By default
        ``validation_steps`` samples of a fresh excitation where the graph simulates its physical system (no
        more than the run's own steps, and at least ``VALIDATION_MIN_STEPS``: a short run is not validated on
        data hundreds of times longer than itself), and none for recorded data (a scenario of recorded data
        names its held-out rows)."""
        if not self.validation_steps or "excitation" not in graph.roles:
            return None
        return {"steps": min(self.validation_steps, max(int(graph.k), VALIDATION_MIN_STEPS))}

    def figures(self, graph: Graph, settings: Mapping[str, Any]) -> dict:
        """Scenario-specific matplotlib figures {name: Figure} (the runner adds estimate-vs-time and z)."""
        return {}

    def output_names(self, settings: Mapping[str, Any]) -> list[str]:
        """The names of the measured outputs, in the order of the graph's measured port, e.g. ['floor 2',
        'floor 3']: the figures label each output and its residual z with them. [] where the scenario names none
        (the figures then say 'y', or 'y[0]', 'y[1]', ... for several)."""
        return []


def estimator_space(nu: int, p0: tuple[float, float] = (1e-2, 1e10)) -> dict[str, Any]:
    """The usual search space of a refinement's tuning (``Scenario.tuning_space``): p0 log-uniform over ``p0``;
    lam among 0.98, 0.995, 0.999 and 1, the values a user tries by hand (a continuous draw rarely lands near 1,
    where a long run's best lam often lies); nu among a third of ``nu``, ``nu`` and three times it."""
    return {"p0": {"loguniform": [float(p0[0]), float(p0[1])]}, "lam": [0.98, 0.995, 0.999, 1.0],
            "nu": sorted({max(1, nu // 3), nu, 3 * nu})}


def describe(sc: Scenario) -> str:
    """A scenario's card: name, section, description, steps, requirements, and a table of its settings with
    defaults, units and meanings (``*`` marks the settings that may differ between the members of a batch)."""
    lines = [f"{sc.name}" + (f"  [{sc.section}]" if sc.section else ""), f"  {sc.description}", "",
             f"steps: {sc.steps} (change with --steps)"]
    if sc.requirements:
        lines.append("requirements: " + "; ".join(f"{r.key} {r.describe()}" for r in sc.requirements))
    rows = [("setting", "default", "unit", "meaning")]
    for key, default in sc.settings.items():
        info = sc.setting(key)
        meaning = info.meaning or "(not documented)"
        if info.choices:
            meaning += f" [one of: {', '.join(info.choices)}]"
        rows.append((key + ("*" if key in sc.per_member else ""), _fmt_default(default), info.unit, meaning))
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    lines.append("")
    lines += ["  ".join(c.ljust(w) for c, w in zip(r[:3], widths)) + "  " + r[3] for r in rows]
    lines.append("")
    lines.append(f"Override with --set KEY=VALUE (rcotorch run {sc.name} --set KEY=VALUE ...)"
                 + ("; * may differ between the members of one batch (sweeps)." if sc.per_member else "."))
    return "\n".join(line.rstrip() for line in lines)


def _check_bounds_declared(cls) -> None:
    """Refuse, when a scenario class is defined, bounds of unknown kinds, of settings it does not have or that are
    not numbers, and defaults outside their bounds."""
    for key, bound in cls.bounds.items():
        default = cls.settings.get(key)
        if bound not in BOUNDS or isinstance(default, bool) or not isinstance(default, (int, float)):
            raise ConfigError(f"scenario class {cls.__name__}: bounds[{key!r}] = {bound!r} needs a number setting "
                              f"{key!r} and one of {list(BOUNDS)}")
        if not _within(bound, default):
            raise ConfigError(f"scenario class {cls.__name__}: the default {key} = {default!r} is not {bound}")


def _within(bound: str, value) -> bool:
    if bound == POSITIVE:
        return value > 0
    if bound == NON_NEGATIVE:
        return value >= 0
    return 0 < value <= 1


def _differs(value, default) -> bool:
    """Whether a resolved setting (one value, or a list of per-member values) differs from its default."""
    return any(v != default for v in value) if isinstance(value, list) else value != default


def _shown(value) -> str:
    """A setting's value as a message shows it: numbers without a trailing '.0'."""
    if isinstance(value, float) and math.isfinite(value):
        text = repr(value)
        return text[:-2] if text.endswith(".0") else text
    if isinstance(value, list):
        return "[" + ", ".join(_shown(v) for v in value) + "]"
    return str(value)


def _fmt_default(value) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def check_truth_history(history: Mapping[str, Any], truth: Mapping[str, Any], where: str) -> dict:
    """``history`` (see ``Scenario.truth_history``) as {key: [(time, value), ...]} of floats, checked.

    Parameters
    ----------
    history : Mapping[str, Sequence[tuple[float, float]]]
        Key -> (time, value) pairs.
    truth : Mapping[str, Any]
        The final truths; a key of ``history`` must have a shared (single) truth equal to its last value.
    where : str
        What to name in an error (the scenario).

    Returns
    -------
    dict[str, list[tuple[float, float]]]

    Raises
    ------
    ConfigError
        If a key's history is empty, not (time, value) pairs of numbers, not in time order, or ends on another
        value than its truth.
    """
    out = {}
    for key, pairs in history.items():
        try:
            pairs = [(float(t), float(v)) for t, v in pairs]
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: truth history of {key!r} must be (time, value) pairs of numbers, got "
                              f"{pairs!r}") from None
        if not pairs or any(b[0] < a[0] for a, b in zip(pairs, pairs[1:])):
            raise ConfigError(f"{where}: truth history of {key!r} must be a non-empty list of (time, value) pairs "
                              f"in time order, got {pairs!r}")
        final = truth.get(key)
        if not isinstance(final, (int, float)) or float(final) != pairs[-1][1]:
            raise ConfigError(f"{where}: the truth history of {key!r} ends at {pairs[-1][1]!r}, but its truth is "
                              f"{final!r}; give one truth for it, equal to the history's last value")
        out[key] = pairs
    return out


def truth_at(pairs: Sequence[tuple[float, float]], time: float) -> float:
    """The value of a truth history (``check_truth_history``) at ``time``: the last one whose time is at or
    before it (the first before them all)."""
    value = pairs[0][1]
    for t, v in pairs:
        if t <= time:
            value = v
    return value


def member_values(settings: Mapping[str, Any], key: str, dtype: torch.dtype | None = None) -> torch.Tensor:
    """A setting as a tensor (``dtype``, default float64): shape () when shared by the batch, (B,) when it is per
    member."""
    import torch
    return torch.as_tensor(settings[key], dtype=torch.float64 if dtype is None else dtype)


def apply_estimator_options(graph: Graph, settings: Mapping[str, Any], options=tuple(ESTIMATOR_OPTIONS)) -> None:
    """Switch on the robustness options among ``options`` that ``settings`` sets (nonzero for some member) on
    the graph's estimator (role 'estimator'); options at 0 leave the estimator as the scenario built it."""
    given = {}
    for key in options:
        if key not in settings:
            continue
        values = member_values(settings, key)
        if bool((values != 0).any()):
            given[key] = values
    if not given:
        return
    if "estimator" not in graph.roles:
        raise ConfigError(f"settings {sorted(given)} need the graph's estimator (role 'estimator'); this graph "
                          f"declares roles {sorted(graph.roles)}")
    graph.role("estimator").set_options(**given)


def _coerce(scenario: str, key: str, value, default):
    """Convert an override (often a command-line string) to the type of the default value; numbers must be
    finite (NaN and infinities are refused)."""
    where = f"scenario '{scenario}': setting {key}"
    if isinstance(default, bool):
        if isinstance(value, str) and value.lower() in ("1", "0", "true", "false", "yes", "no"):
            return value.lower() in ("1", "true", "yes")
        if isinstance(value, (bool, int)) and value in (0, 1):
            return bool(value)
        raise ConfigError(f"{where} must be true or false, got {value!r}")
    if isinstance(default, (int, float)):
        if isinstance(value, bool) or not isinstance(value, (str, int, float)):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        try:
            number = float(value)
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{where} must be a number, got {value!r}") from None
        if not math.isfinite(number):
            raise ConfigError(f"{where} must be a finite number, got {value!r}")
        if isinstance(default, int):
            if isinstance(value, int):
                return value
            if number != int(number):
                raise ConfigError(f"{where} must be an integer, got {value!r}")
            return int(number)
        return number
    if default is not None and not isinstance(value, type(default)):
        raise ConfigError(f"{where} must be a {type(default).__name__}, got {value!r}")
    return value


def scenario_dirs() -> list[Path]:
    """The folders named in ``RCOTORCH_SCENARIOS``; one that is not a folder is an error."""
    dirs = [Path(p).expanduser() for p in os.environ.get("RCOTORCH_SCENARIOS", "").split(os.pathsep) if p]
    for d in dirs:
        if not d.is_dir():
            raise ConfigError(f"RCOTORCH_SCENARIOS names {d}, which is not a folder; set it to folders of scenario "
                              f"files (separated by '{os.pathsep}') or unset it")
    return dirs


def _shipped_modules():
    """The modules of ``rcotorch.scenarios`` (the scenarios installed with the package)."""
    package = importlib.import_module("rcotorch.scenarios")
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            yield importlib.import_module(f"rcotorch.scenarios.{info.name}")


def _folder_modules(folder: Path):
    """The ``.py`` files of a user's scenario folder, loaded by path (the folder joins ``sys.path``)."""
    if str(folder) not in sys.path:  # scenario files may build on their siblings
        sys.path.append(str(folder))
    for path in sorted(folder.glob("*.py")):
        if path.name.startswith("_"):
            continue
        name = f"rcotorch_user_scenario_{path.stem}"
        module = sys.modules.get(name)
        stamp = path.stat().st_mtime_ns
        if module is None or getattr(module, "__file__", None) != str(path) or module.__dict__.get(
                "_rcotorch_mtime") != stamp:                     # loaded once, again when the file changes
            spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules[name] = module
            try:
                spec.loader.exec_module(module)
            except Exception as e:
                del sys.modules[name]
                raise ConfigError(f"scenario file {path} (from RCOTORCH_SCENARIOS) fails to load: "
                                  f"{type(e).__name__}: {e}") from e
            module._rcotorch_mtime = stamp
        yield module


def available() -> dict[str, Scenario]:
    """All scenarios, by name: the shipped ones, then those of the ``RCOTORCH_SCENARIOS`` folders."""
    found: dict[str, Scenario] = {}
    where: dict[str, str] = {}
    modules = list(_shipped_modules())
    for folder in scenario_dirs():
        modules += list(_folder_modules(folder))
    for module in modules:
        sc = getattr(module, "SCENARIO", None)
        if not isinstance(sc, Scenario):
            continue
        if sc.name in found and found[sc.name] is not sc:
            raise ConfigError(f"two scenarios are named {sc.name!r}: {where[sc.name]} and {module.__file__}")
        found[sc.name], where[sc.name] = sc, module.__file__
    return found


def get(name: str | Scenario) -> Scenario:
    """The scenario registered under ``name`` (a ``Scenario`` object is returned as it is: a scenario of one's
    own, declared in a script, runs, sweeps and tunes without being registered)."""
    if isinstance(name, Scenario):
        return name
    found = available()
    if name not in found:
        import difflib
        close = difflib.get_close_matches(name, list(found), n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise ConfigError(f"no scenario named {name!r}{hint}; available: {sorted(found)}")
    return found[name]
