"""rcotorch: data-based model refinement with retrospective cost optimization (RCMR), batched in PyTorch."""

from . import identification, models, rng
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
    "AlgebraicLoopError", "Block", "ConfigError", "DataError", "DimensionError", "Gain", "Graph", "LTI", "StaticMap",
    "PortError", "RCOEstimator", "RcoError", "Recorded", "Recording", "Sum", "WhiteNoise", "derive_markov",
    "MarkovRefresh", "Nonlinear", "identification", "load", "models", "refinement", "rls_update", "rng", "zoh",
]
__version__ = "0.1.0"
