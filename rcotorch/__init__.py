"""rcotorch: data-based model refinement with retrospective cost optimization (RCMR), batched in PyTorch.

The public names are imported on first use (``rcotorch.Graph`` imports ``rcotorch.graph`` then), so that
``import rcotorch`` and the command line's ``list``, ``show`` and ``--version`` start without loading torch.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# Each public name and the submodule that defines it. Submodules (the public ones are datasets, features, models
# and rng) are imported on first use as well: ``rcotorch.models.sdof`` imports the subpackage then.
_DEFINED_IN = {
    "Block": "blocks", "Gain": "blocks", "StaticMap": "blocks", "Sum": "blocks",
    "Recording": "data", "load": "data",
    "AlgebraicLoopError": "errors", "ConfigError": "errors", "DataError": "errors", "DimensionError": "errors",
    "PortError": "errors", "RcoError": "errors",
    "RCOEstimator": "estimator",
    "Graph": "graph",
    "LTI": "lti", "zoh": "lti",
    "MarkovRefresh": "nonlinear", "Nonlinear": "nonlinear",
    "RefinementResult": "refine", "refine": "refine",
    "derive_markov": "refinement", "refinement": "refinement",
    "rls_update": "rls",
    "Recorded": "sources", "WhiteNoise": "sources",
    "ChangeDetector": "tracking", "ResetOnChange": "tracking", "at_step": "tracking",
    "Validation": "validation", "validate": "validation",
}

__all__ = [
    "AlgebraicLoopError", "at_step", "Block", "ChangeDetector", "ConfigError", "DataError", "datasets",
    "derive_markov", "DimensionError", "features", "Gain", "Graph", "load", "LTI", "MarkovRefresh", "models",
    "Nonlinear", "PortError", "RcoError", "RCOEstimator", "Recorded", "Recording", "refine", "RefinementResult",
    "refinement", "ResetOnChange", "rls_update", "rng", "StaticMap", "Sum", "validate", "Validation", "WhiteNoise",
    "zoh",
]


def __getattr__(name: str):
    if name in _DEFINED_IN:
        value = getattr(importlib.import_module(f"{__name__}.{_DEFINED_IN[name]}"), name)
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


class _Package(types.ModuleType):
    """The package's module type. Python binds a submodule, once imported, as an attribute of its package; the
    functions ``refine`` and ``refinement`` share their names with the submodules that define them, and keep
    those names: binding such a submodule binds its function instead."""

    def __setattr__(self, name: str, value) -> None:
        if isinstance(value, types.ModuleType) and _DEFINED_IN.get(name) == name:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package

if TYPE_CHECKING:
    from . import datasets, features, models, rng
    from .blocks import Block, Gain, StaticMap, Sum
    from .data import Recording, load
    from .errors import AlgebraicLoopError, ConfigError, DataError, DimensionError, PortError, RcoError
    from .estimator import RCOEstimator
    from .graph import Graph
    from .lti import LTI, zoh
    from .nonlinear import MarkovRefresh, Nonlinear
    from .refine import RefinementResult, refine
    from .refinement import derive_markov, refinement
    from .rls import rls_update
    from .sources import Recorded, WhiteNoise
    from .tracking import ChangeDetector, ResetOnChange, at_step
    from .validation import Validation, validate
