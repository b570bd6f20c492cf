"""rcotorch: data-based model refinement with retrospective cost optimization (RCMR), batched in PyTorch.

The public names are imported on first use (``rcotorch.Graph`` imports ``rcotorch.graph`` then), so that
``import rcotorch`` and the command line's ``list``, ``show`` and ``--version`` start without loading torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# Each public name and the submodule that defines it. Submodules (the public ones are datasets, features, models
# and rng) are imported on first use as well: ``rcotorch.models.sdof`` imports the subpackage then.
_DEFINED_IN = {
    "Block": "blocks.base", "Gain": "blocks.base", "StaticMap": "blocks.base", "Sum": "blocks.base",
    "Recording": "data.recording", "load": "data.recording",
    "AlgebraicLoopError": "errors", "ConfigError": "errors", "DataError": "errors", "DimensionError": "errors",
    "OutputError": "errors", "PortError": "errors", "RcoError": "errors",
    "RCOEstimator": "estimator.rco", "UpdateOptions": "estimator.rco",
    "Graph": "graph",
    "LTI": "blocks.lti", "zoh": "blocks.lti",
    "MarkovRefresh": "blocks.nonlinear", "Nonlinear": "blocks.nonlinear",
    "RefinementResult": "run.refine", "refine": "run.refine",
    "Requirement": "run.scenario", "Scenario": "run.scenario",
    "derive_markov": "wiring", "refinement": "wiring",
    "rls_update": "engine.rls",
    "Recorded": "blocks.sources", "WhiteNoise": "blocks.sources",
    "ChangeDetector": "estimator.tracking", "ResetOnChange": "estimator.tracking", "at_step": "estimator.tracking",
    "closed_loop_markov": "estimator.tracking",
    "Validation": "verdict.validation", "validate": "verdict.validation",
}

# The public submodules that live in a subpackage: rcotorch.<name> imports rcotorch.<path>.
_SUBMODULES = {"datasets": "data.datasets", "features": "blocks.features", "rng": "engine.rng",
               "scenario": "run.scenario"}

__all__ = [
    "AlgebraicLoopError", "at_step", "Block", "ChangeDetector", "closed_loop_markov", "ConfigError", "DataError",
    "datasets", "derive_markov", "DimensionError", "features", "Gain", "Graph", "load", "LTI", "MarkovRefresh",
    "models", "Nonlinear", "OutputError", "PortError", "RcoError", "RCOEstimator", "Recorded", "Recording", "refine",
    "RefinementResult", "refinement", "ResetOnChange", "rls_update", "rng", "StaticMap", "Sum", "UpdateOptions",
    "validate", "Validation", "WhiteNoise", "zoh",
]


def __getattr__(name: str):
    if name in _DEFINED_IN:
        value = getattr(importlib.import_module(f"{__name__}.{_DEFINED_IN[name]}"), name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        value = importlib.import_module(f"{__name__}.{_SUBMODULES[name]}")
        globals()[name] = value
        return value
    if not name.startswith("__"):
        try:
            return importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"{__name__}.{name}":      # the submodule exists; something it imports does not
                raise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:
    from . import models
    from .blocks import features
    from .blocks.base import Block, Gain, StaticMap, Sum
    from .blocks.lti import LTI, zoh
    from .blocks.nonlinear import MarkovRefresh, Nonlinear
    from .blocks.sources import Recorded, WhiteNoise
    from .data import datasets
    from .data.recording import Recording, load
    from .engine import rng
    from .engine.rls import rls_update
    from .errors import AlgebraicLoopError, ConfigError, DataError, DimensionError, OutputError, PortError, RcoError
    from .estimator.rco import RCOEstimator, UpdateOptions
    from .estimator.tracking import ChangeDetector, ResetOnChange, at_step, closed_loop_markov
    from .graph import Graph
    from .run.refine import RefinementResult, refine
    from .verdict.validation import Validation, validate
    from .wiring import derive_markov, refinement
