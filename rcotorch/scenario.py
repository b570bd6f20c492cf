"""Scenarios: a named, reproducible refinement with default settings, truth, estimates and acceptance bounds.

A scenario file in ``scenarios/`` defines ``SCENARIO``, an instance of a ``Scenario`` subclass. The runner
(``rcotorch.runner``) builds its graph, steps it, logs it and writes ``summary.json`` with the keys the
scenario declares.
"""

from __future__ import annotations

import importlib.util
import math
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .errors import ConfigError
from .graph import Graph


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

    def check(self, value: float, truth: float | None = None) -> tuple[float, bool]:
        """Return (the checked quantity, pass)."""
        if self.kind == "abs_err":
            q = abs(value - truth)
        elif self.kind == "rel_err":
            q = abs(value - truth) / abs(truth)
        else:
            q = value
        if q != q:  # NaN
            return q, False
        if self.kind == "min":
            return q, q >= self.bound
        return q, (q <= self.bound if self.inclusive else q < self.bound)

    def describe(self) -> str:
        op = {"abs_err": "|err| <", "rel_err": "rel err <", "max": "<=" if self.inclusive else "<",
              "min": ">="}[self.kind]
        return f"{op} {self.bound:g}"


class Scenario:
    """Base class. Subclasses set the class attributes and implement ``build``, ``estimates`` and ``truth``."""

    name: str = ""
    section: str = ""
    description: str = ""
    steps: int = 10000
    settings: Mapping[str, Any] = {}
    requirements: tuple[Requirement, ...] = ()
    # Settings that may differ between the members of one batched run (physical parameters, tuning such as
    # p0 and lambda, seeds). The others fix the graph's structure (sample time, orders, nu); a sweep over
    # them runs one batch per distinct value.
    per_member: frozenset[str] = frozenset()

    def resolve(self, overrides: Mapping[str, Any] | None = None, seed: int | None = None) -> dict[str, Any]:
        """Default settings with overrides applied (unknown names and wrong types rejected)."""
        out = dict(self.settings)
        for key, value in dict(overrides or {}).items():
            if key not in out:
                raise ConfigError(f"scenario '{self.name}': unknown setting {key!r}; settings are {sorted(out)}")
            out[key] = _coerce(self.name, key, value, out[key])
        if seed is not None:
            out["seed"] = int(seed)
        return out

    def resolve_members(self, common: Mapping[str, Any], members: list[Mapping[str, Any]]) -> dict[str, Any]:
        """Settings for a batch whose members differ: ``common`` overrides for all, ``members[b]`` for member b.
        A setting that differs between members becomes a list of per-member values."""
        out = self.resolve(common)
        keys = sorted({k for m in members for k in m})
        for key in keys:
            if key not in out:
                raise ConfigError(f"scenario '{self.name}': unknown setting {key!r}; settings are {sorted(out)}")
            values = [_coerce(self.name, key, m.get(key, out[key]), self.settings[key]) for m in members]
            if key in self.per_member:
                out[key] = values  # kept per member even when equal: a member's seed picks its own stream
                continue
            if any(v != values[0] for v in values):
                raise ConfigError(f"scenario '{self.name}': setting {key!r} fixes the graph's structure and cannot "
                                  f"differ within one batch (per-member settings: {sorted(self.per_member)})")
            out[key] = values[0]
        return out

    def build(self, settings: Mapping[str, Any], batch: int, dtype: torch.dtype, device) -> Graph:
        """The graph for ``batch`` members; a per-member setting is a list of length ``batch``
        (``member_values`` turns it into a tensor)."""
        raise NotImplementedError

    def truth(self, settings: Mapping[str, Any]) -> dict[str, float]:
        return {}

    def estimates(self, graph: Graph, settings: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """Current estimates, each a (B,) tensor (physical units)."""
        raise NotImplementedError

    def metrics(self, graph: Graph, settings: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """Final metrics, each a (B,) tensor."""
        return {}

    def figures(self, graph: Graph, settings: Mapping[str, Any]) -> dict:
        """Scenario-specific matplotlib figures {name: Figure} (the runner adds estimate-vs-time and z)."""
        return {}


def member_values(settings: Mapping[str, Any], key: str, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """A setting as a tensor: shape () when shared by the batch, (B,) when it is per member."""
    return torch.as_tensor(settings[key], dtype=dtype)


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
    dirs = [Path(p) for p in os.environ.get("RCOTORCH_SCENARIOS", "").split(os.pathsep) if p]
    dirs.append(Path(__file__).resolve().parents[1] / "scenarios")
    return [d for d in dirs if d.is_dir()]


def available() -> dict[str, Scenario]:
    """All scenarios found in the scenario directories, by name."""
    found: dict[str, Scenario] = {}
    for d in scenario_dirs():
        if str(d) not in sys.path:  # scenario files may build on their siblings
            sys.path.append(str(d))
        for path in sorted(d.glob("*.py")):
            if path.name.startswith("_"):
                continue
            name = f"rcotorch_scenario_{path.stem}"
            module = sys.modules.get(name)
            if module is None or getattr(module, "__file__", None) != str(path):
                spec = importlib.util.spec_from_file_location(name, path)
                module = importlib.util.module_from_spec(spec)
                sys.modules[name] = module
                spec.loader.exec_module(module)
            sc = getattr(module, "SCENARIO", None)
            if isinstance(sc, Scenario):
                found.setdefault(sc.name, sc)
    return found


def get(name: str) -> Scenario:
    found = available()
    if name not in found:
        import difflib
        close = difflib.get_close_matches(name, list(found), n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise ConfigError(f"no scenario named {name!r}{hint}; available: {sorted(found)}")
    return found[name]
