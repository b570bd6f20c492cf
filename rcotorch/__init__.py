"""rcotorch: data-based model refinement with retrospective cost optimization (RCMR), batched in PyTorch."""

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

__all__ = [
    "AlgebraicLoopError", "at_step", "Block", "ChangeDetector", "ConfigError", "DataError", "datasets",
    "derive_markov", "DimensionError", "features", "Gain", "Graph", "load", "LTI", "MarkovRefresh", "models",
    "Nonlinear", "PortError", "RcoError", "RCOEstimator", "Recorded", "Recording", "refine", "RefinementResult",
    "refinement", "ResetOnChange", "rls_update", "rng", "StaticMap", "Sum", "validate", "Validation", "WhiteNoise",
    "zoh",
]
__version__ = "0.1.0"
