"""Seed Section V.A: a stiffness change on a single-degree-of-freedom structure.

Known: m x'' + C x' + K x = w + u (m=1, K=0.6, C=0.8), velocity measured. Truth: the continuous structure
with K + dK, C + dC (dK=0.5, dC=0), ZOH-discretized as a whole at Ts (so the discrete best fit differs from
the continuous parameters by O(Ts), see DESIGN.md). The unknown subsystem is the force u = -(dK x + dC x');
the identified subsystem acts on y0 = [x, x'].

Structure: nc = 0 gives the exactly proper static gain u(k) = theta [x(k), x'(k)], so dK = -theta_x,
dC = -theta_v; nc >= 1 gives a strictly proper controller of order nc and dK, dC are minus its DC gains.
"""

import rcotorch as rt
from rcotorch.scenario import Requirement, Scenario, member_values


class SdofStiffness(Scenario):
    name = "sdof-stiffness"
    section = "V.A"
    description = "SDOF stiffness change dK=0.5 from velocity data (static-gain identified subsystem)"
    steps = 20000
    settings = dict(Ts=0.01, m=1.0, K=0.6, C=0.8, dK=0.5, dC=0.0, nc=0, p0=1e3, lam=1.0, nu=15,
                    w_std=1.0, seed=1)
    requirements = (Requirement("estimates.dK", "abs_err", 0.01), Requirement("estimates.dC", "abs_err", 0.03))
    per_member = frozenset({"m", "K", "C", "dK", "dC", "p0", "lam", "w_std", "seed"})
    units = {"y": "m/s"}
    about = dict(
        Ts=("s", "sample time (known model and truth ZOH-discretized at Ts)"),
        m=("kg", "mass"),
        K=("N/m", "stiffness of the known model"),
        C=("N s/m", "damping of the known model"),
        dK=("N/m", "stiffness change in the truth (what the refinement recovers)"),
        dC=("N s/m", "damping change in the truth (what the refinement recovers)"),
        nc=("", "order of the identified subsystem; 0: exactly proper static gain on [x, x']"),
        w_std=("N", "standard deviation of the white-noise force w"),
        seed=("", "excitation seed; member b of a batch draws the stream (seed, b)"),
    )

    def build(self, s, batch, dtype, device):
        m, K, C, dK, dC = (member_values(s, key) for key in ("m", "K", "C", "dK", "dC"))
        known = rt.LTI.continuous(*rt.models.sdof_matrices(m, C, K, sees=["position", "velocity"]),
                                  inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=s["Ts"], name="known")
        physical = rt.LTI.continuous(*rt.models.sdof_matrices(m, C + dC, K + dK, sees=[], actuation=False),
                                     inputs=["w"], outputs=["y"], dt=s["Ts"], name="plant")
        if s["nc"] == 0:
            ident = rt.RCOEstimator.static_gain({"y0": 2}, p0=s["p0"], lam=s["lam"])
        else:
            ident = rt.RCOEstimator({"y0": 2}, nc=s["nc"], p0=s["p0"], lam=s["lam"])
        return rt.refinement(known, ident, physical=physical,
                             excitation=rt.WhiteNoise(1, std=s["w_std"], seed=s["seed"]), nu=s["nu"],
                             batch_size=batch, dtype=dtype, device=device)

    def truth(self, s):
        return {"dK": s["dK"], "dC": s["dC"]}

    def estimates(self, g, s):
        dc = g.role("estimator").dc_gain()[:, 0]          # (B, 2): gains on [x, x']
        return {"dK": -dc[:, 0], "dC": -dc[:, 1]}


SCENARIO = SdofStiffness()
