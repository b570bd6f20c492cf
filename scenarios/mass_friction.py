"""A mass on a spring with Coulomb and viscous friction that nobody modelled, identified with a basis regressor.

Known: m x'' + C x' + K x = w + u (m = 1, K = 4, C = 0: no friction at all), the velocity measured (with white
measurement noise of std ``noise``), ZOH-discretized at Ts. Truth: the same discrete model in feedback with
the friction force u(k) = -(Fc sign(v(k)) + c v(k)) (Fc = 2 N, c = 0.5 N s/m), a NumPy function
(``rt.StaticMap``, compiled into the native engine). The identified subsystem is the static basis regressor
u(k) = theta_1 sign(y0(k)) + theta_2 y0(k) on the model's velocity y0, which represents the truth exactly, so
Fc = -theta_1 and c = -theta_2.

The excitation decides whether the friction can be told apart at all: a white-noise force of std ``w_std``
too weak to break the mass loose leaves it stuck most of the time, and a stuck mass's sampled velocity only
chatters about zero (it reverses almost every sample), where sign(v) carries no information on Fc. The metric
``sliding_fraction`` is the fraction of samples at which the true velocity keeps its sign from the previous
sample (the mass slides); docs/own-problem.md ("Friction, and the excitation it needs") measures the
estimates against it and against nu.
"""

from __future__ import annotations

import numpy as np

import rcotorch as rt
from rcotorch.run.scenario import NON_NEGATIVE, POSITIVE, Requirement, Scenario, estimator_space, member_values

from .sdof_stiffness import noise_seed


def friction_law(Fc: float, c: float):
    """The friction force -(Fc sign(v) + c v) as a NumPy function of a (B, 1) velocity (compiled natively)."""
    Fc, c = float(Fc), float(c)

    def friction(v):
        return -(Fc * np.sign(v) + c * v)
    return friction


class MassFriction(Scenario):
    name = "mass-friction"
    section = "nonlinear"
    description = "Coulomb and viscous friction Fc=2, c=0.5 on a mass-spring model without friction (basis sign(v), v)"
    steps = 20000
    settings = dict(Ts=0.01, m=1.0, K=4.0, C=0.0, Fc=2.0, c=0.5, w_std=20.0, noise=0.0, p0=1e3, lam=1.0,
                    nu=30, seed=1)
    requirements = (Requirement("estimates.Fc", "rel_err", 0.02), Requirement("estimates.c", "rel_err", 0.05))
    per_member = frozenset({"m", "K", "C", "w_std", "noise", "p0", "lam", "seed"})
    bounds = dict(Ts=POSITIVE, m=POSITIVE, K=NON_NEGATIVE, C=NON_NEGATIVE, Fc=NON_NEGATIVE, c=NON_NEGATIVE,
                  w_std=NON_NEGATIVE, noise=NON_NEGATIVE)
    tuning_space = estimator_space(nu=30)    # what `rcotorch tune mass-friction` searches
    units = {"Fc": "N", "c": "N s/m", "y": "m/s", "sliding_fraction": ""}
    about = dict(
        Ts=("s", "sample time (known model ZOH-discretized at Ts; the friction force is held over a sample)"),
        m=("kg", "mass"),
        K=("N/m", "spring stiffness (0: a free mass)"),
        C=("N s/m", "damping of the known model (0: the known model has no friction at all)"),
        Fc=("N", "Coulomb friction force in the truth (what the refinement recovers)"),
        c=("N s/m", "viscous friction coefficient in the truth (what the refinement recovers)"),
        w_std=("N", "standard deviation of the white-noise force w: too small and the mass sticks"),
        noise=("m/s", "standard deviation of white measurement noise on the velocity (0: none)"),
        seed=("", "excitation seed; member b of a batch draws the stream (seed, b)"),
    )

    def known(self, s, dtype=None):
        """The known model: the mass on its spring without the friction, velocity measured and seen."""
        import torch
        m, K, C = (member_values(s, key) for key in ("m", "K", "C"))
        return rt.LTI.continuous(*rt.models.sdof_matrices(m, C, K, measured=["velocity"], sees=["velocity"]),
                                 inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=s["Ts"], name="known",
                                 dtype=torch.float64 if dtype is None else dtype)

    def build(self, s, batch, dtype, device):
        ident = rt.RCOEstimator.static_gain({"y0": 1}, features=[rt.features.sign("y0"), rt.features.port("y0")],
                                            p0=s["p0"], lam=s["lam"], dtype=dtype)
        noise = None
        if bool((member_values(s, "noise") != 0).any()):
            noise = rt.WhiteNoise(1, std=s["noise"], seed=noise_seed(s["seed"]), dtype=dtype)
        return rt.refinement(self.known(s, dtype), ident,
                             truth=rt.StaticMap(friction_law(s["Fc"], s["c"]), 1, name="unknown", dtype=dtype),
                             excitation=rt.WhiteNoise(1, std=s["w_std"], seed=s["seed"], dtype=dtype),
                             noise=noise, nu=s["nu"], batch_size=batch, dtype=dtype, device=device)

    def truth(self, s):
        return {"Fc": s["Fc"], "c": s["c"]}

    def estimates(self, g, s):
        theta = g.role("estimator").theta[:, 0]          # (B, 2): gains on [sign(y0), y0]
        return {"Fc": -theta[:, 0], "c": -theta[:, 1]}

    def metrics(self, g, s):
        return {"sliding_fraction": sliding_fraction(s, g.batch_size, int(g.k), g.role("estimator").theta.dtype)}


def sliding_fraction(s, batch: int, steps: int, dtype=None):
    """The fraction of the first ``steps`` samples at which the true velocity keeps its sign from the previous
    sample, per member ((B,) float64): the truth's loop (the excitation of settings ``s`` through the known
    model with the friction law in feedback) simulated again on its own."""
    import torch
    if steps < 2:
        return torch.full((batch,), float("nan"), dtype=torch.float64)
    sc = MassFriction()
    blocks = [rt.WhiteNoise(1, std=s["w_std"], seed=s["seed"], name="w", dtype=dtype),
              sc.known(s, dtype), rt.StaticMap(friction_law(s["Fc"], s["c"]), 1, name="friction", dtype=dtype)]
    g = rt.Graph(blocks, ["w.out -> known.w", "known.y0 -> friction.in", "friction.out -> known.u"],
                 batch_size=batch, dtype=dtype)
    keeps, last, done = torch.zeros(batch, dtype=torch.float64), None, 0
    while done < steps:                      # in stretches, so that a large batch's record stays small
        n = min(CHUNK, steps - done)
        v = g.run(n, record={"v": "known.y0"})["v"][:, :, 0].to(torch.float64)        # (n, B)
        if last is not None:
            v = torch.cat([last, v])
        keeps += ((v[1:] * v[:-1]) > 0).sum(0)
        last, done = v[-1:], done + n
    return keeps / (steps - 1)


CHUNK = 2000           # steps of the sliding fraction's simulation recorded at once


SCENARIO = MassFriction()
