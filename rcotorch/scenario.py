"""Where ``Scenario`` and ``Requirement`` were imported from before: ``from rcotorch.scenario import Scenario,
Requirement`` keeps working and gives the module ``rcotorch.run.scenario`` itself, with a DeprecationWarning
that names the paths to use now: ``rcotorch.Scenario`` and ``rcotorch.Requirement`` (or
``rcotorch.run.scenario``)."""

import sys
import warnings

from .run import scenario as _scenario

warnings.warn("rcotorch.scenario is now rcotorch.run.scenario; import Scenario and Requirement as rcotorch.Scenario "
              "and rcotorch.Requirement", DeprecationWarning, stacklevel=2)
sys.modules[__name__] = _scenario
