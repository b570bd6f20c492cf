"""Physical models that serve as known subsystems (or as truths in tests and scenarios).

They are kept apart from the library core: the core (blocks, estimator, graph) never imports them.

* ``structures``: mass-spring-damper structures with named signals (``sdof``, ``structure``,
  ``shear_building``).
* ``circuits``: a series RLC circuit with named signals.
* ``ports``: any python-control plant as a known model, its signals picked and named w, u, y, y0
  (``label_ports``, ``known_model``).
* ``identification``: an initial linear model fitted to measured data (``MassSpringDamper``).
* ``thermosphere``: a batched 1-D thermosphere column (imported on use: ``rcotorch.models.thermosphere``).
"""

from . import circuits, identification, ports
from .circuits import series_rlc
from .identification import MassSpringDamper
from .ports import known_model, label_ports
from .structures import SIGNALS, sdof, sdof_matrices, shear_building, structure

__all__ = ["circuits", "identification", "known_model", "label_ports", "MassSpringDamper", "ports", "sdof",
           "sdof_matrices", "series_rlc", "shear_building", "SIGNALS", "structure"]
