"""Physical models that serve as known subsystems (or as truths in tests and scenarios).

They are kept apart from the library core: the core (blocks, estimator, graph) never imports them.

* ``structures``: mass-spring-damper structures with named signals (``sdof``, ``structure``).
* ``circuits``: a series RLC circuit with named signals.
* ``identification``: an initial linear model fitted to measured data (``MassSpringDamper``).
* ``thermosphere``: a batched 1-D thermosphere column (imported on use: ``rcotorch.models.thermosphere``).
"""

from . import circuits, identification
from .circuits import series_rlc
from .identification import MassSpringDamper
from .structures import SIGNALS, sdof, sdof_matrices, structure

__all__ = ["circuits", "identification", "MassSpringDamper", "sdof", "sdof_matrices", "series_rlc", "SIGNALS",
           "structure"]
