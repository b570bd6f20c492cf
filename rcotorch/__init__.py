"""rcotorch: data-based model refinement with retrospective cost optimization (RCMR), batched in PyTorch."""

from . import circuits, identification, models, rng
from .blocks import Block, Gain, StaticMap, Sum
from .data import Recording, load
from .errors import AlgebraicLoopError, ConfigError, DataError, DimensionError, PortError, RcoError
from .estimator import RCOEstimator
from .graph import Graph, derive_markov, refinement
from .lti import LTI, zoh
from .nonlinear import MarkovRefresh, Nonlinear
from .rls import rls_update
from .sources import Recorded, WhiteNoise

__all__ = [
    "AlgebraicLoopError", "Block", "circuits", "ConfigError", "DataError", "derive_markov", "DimensionError",
    "Gain", "Graph", "identification", "load", "LTI", "MarkovRefresh", "models", "Nonlinear", "PortError",
    "RcoError", "RCOEstimator", "Recorded", "Recording", "refinement", "rls_update", "rng", "StaticMap",
    "Sum", "WhiteNoise", "zoh",
]
__version__ = "0.1.0"
