"""Seed Section V.A: simultaneous stiffness and damping changes on a single-degree-of-freedom structure.

As ``sdof-stiffness`` with K=0.7, dK=-0.4, C=0.4, dC=0.5 and the seed's tuning: a strictly proper identified
subsystem of order nc = 1 on [x, x'], p0 = 1e6, 15 Markov parameters; dK and dC are minus its DC gains.
"""

from rcotorch.run.scenario import Requirement

from .sdof_stiffness import SdofStiffness


class SdofStiffnessDamping(SdofStiffness):
    name = "sdof-stiffness-damping"
    description = "SDOF stiffness dK=-0.4 and damping dC=0.5 changes (order-1 identified subsystem, DC gains)"
    settings = dict(SdofStiffness.settings, K=0.7, dK=-0.4, C=0.4, dC=0.5, nc=1, p0=1e6, nu=15)
    requirements = (Requirement("estimates.dK", "abs_err", 0.01), Requirement("estimates.dC", "abs_err", 0.01))


SCENARIO = SdofStiffnessDamping()
