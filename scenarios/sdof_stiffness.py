"""Seed Section V.A: a stiffness change on a single-degree-of-freedom structure.

Known: m x'' + C x' + K x = w + u (m=1, K=0.6, C=0.8), velocity measured. Truth (setting ``truth``):
``continuous`` (default), the continuous structure with K + dK, C + dC (dK=0.5, dC=0) ZOH-discretized as a
whole at Ts (so the discrete best fit differs from the continuous parameters by O(Ts), docs/scenarios.md);
``discrete``, the discrete known model in feedback with u(k) = -(dK x(k) + dC x'(k)), which the static gain
represents exactly (for calibration studies of the confidence intervals). The unknown subsystem is the
force u = -(dK x + dC x'); the identified subsystem acts on y0 = [x, x']. Setting ``noise``: white
measurement noise on y, its std a fraction of the steady-state rms of the noise-free y.

Structure: nc = 0 gives the exactly proper static gain u(k) = theta [x(k), x'(k)], so dK = -theta_x,
dC = -theta_v; nc >= 1 gives a strictly proper controller of order nc and dK, dC are minus its DC gains.
"""

import numpy as np

import rcotorch as rt
from rcotorch.run.scenario import NON_NEGATIVE, POSITIVE, Requirement, Scenario, estimator_space, member_values

NOISE_SEED = 7919       # the measurement noise of member b draws the stream (seed + NOISE_SEED, b)


def noise_std(s, truth_system) -> list[float] | float:
    """Std of the measurement noise: s['noise'] times the rms of y (w of std w_std), per member where a setting
    differs between members (``truth_system(member settings)``: the discrete python-control system w -> y)."""
    from rcotorch.estimator.analysis import white_noise_rms

    def std(member) -> float:
        return member["noise"] * float(white_noise_rms(truth_system(member), member["w_std"])[0])
    keys = [k for k, v in s.items() if isinstance(v, list)]
    if not keys:
        return std(s)
    return [std({**s, **{k: s[k][b] for k in keys}}) for b in range(len(s[keys[0]]))]


def noise_seed(seed):
    """The measurement noise's seed (or per-member seeds) for an excitation seed (or per-member seeds)."""
    return [x + NOISE_SEED for x in seed] if isinstance(seed, list) else seed + NOISE_SEED


def noise_block(s, truth_system):
    """The measurement-noise source of a scenario with a ``noise`` setting, or None when it is 0."""
    if not s["noise"]:
        return None
    return rt.WhiteNoise(1, std=noise_std(s, truth_system), seed=noise_seed(s["seed"]))


class SdofStiffness(Scenario):
    name = "sdof-stiffness"
    section = "V.A"
    description = "SDOF stiffness change dK=0.5 from velocity data (static-gain identified subsystem)"
    steps = 20000
    settings = dict(Ts=0.01, m=1.0, K=0.6, C=0.8, dK=0.5, dC=0.0, nc=0, p0=1e3, lam=1.0, nu=15,
                    w_std=1.0, truth="continuous", noise=0.0, seed=1)
    requirements = (Requirement("estimates.dK", "abs_err", 0.01), Requirement("estimates.dC", "abs_err", 0.03))
    per_member = frozenset({"m", "K", "C", "dK", "dC", "p0", "lam", "w_std", "seed"})
    bounds = dict(Ts=POSITIVE, m=POSITIVE, nc=NON_NEGATIVE, w_std=NON_NEGATIVE, noise=NON_NEGATIVE)
    tuning_space = estimator_space(nu=15)    # what `rcotorch tune sdof-stiffness` searches
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
        truth=("", "continuous structure ZOH-discretized, or the discrete interconnection (exact for the gain)",
               ("continuous", "discrete")),
        noise=("", "measurement noise on y: its std as a fraction of the rms of y (0: none)"),
        seed=("", "excitation seed; member b of a batch draws the stream (seed, b)"),
    )

    def build(self, s, batch, dtype, device):
        import torch
        m, K, C, dK, dC = (member_values(s, key) for key in ("m", "K", "C", "dK", "dC"))
        known = rt.LTI.continuous(*rt.models.sdof_matrices(m, C, K, sees=["position", "velocity"]),
                                  inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=s["Ts"], name="known")
        if s["nc"] == 0:
            ident = rt.RCOEstimator.static_gain({"y0": 2}, p0=s["p0"], lam=s["lam"])
        else:
            ident = rt.RCOEstimator({"y0": 2}, nc=s["nc"], p0=s["p0"], lam=s["lam"])
        common = dict(excitation=rt.WhiteNoise(1, std=s["w_std"], seed=s["seed"]), nu=s["nu"],
                      noise=noise_block(s, self.truth_system), batch_size=batch, dtype=dtype, device=device)
        if s["truth"] == "discrete":
            gains = torch.stack([-dK.expand(batch), -dC.expand(batch)], dim=1).reshape(batch, 1, 2)
            return rt.refinement(known, ident, truth=rt.Gain(gains), **common)
        physical = rt.LTI.continuous(*rt.models.sdof_matrices(m, C + dC, K + dK, sees=[], actuation=False),
                                     inputs=["w"], outputs=["y"], dt=s["Ts"], name="plant")
        return rt.refinement(known, ident, physical=physical, **common)

    @staticmethod
    def truth_system(s):
        """The true system w -> y of one member as a discrete python-control system (for the noise level)."""
        import control
        if s["truth"] == "discrete":
            G = control.sample_system(rt.models.sdof(s["m"], s["C"], s["K"], sees=["position", "velocity"]), s["Ts"])
            A = G.A + G.B[:, 1:2] @ np.array([[-s["dK"], -s["dC"]]]) @ G.C[1:3]      # u(k) = -(dK x + dC x')
            return control.ss(A, G.B[:, :1], G.C[:1], [[0.0]], s["Ts"])
        T = rt.models.sdof(s["m"], s["C"] + s["dC"], s["K"] + s["dK"], sees=[], actuation=False)
        return control.sample_system(T, s["Ts"])

    def scales(self, s):
        """dK and dC are changes of K and C: judged against the known model's values."""
        return {"dK": float(np.max(np.abs(s["K"]))), "dC": float(np.max(np.abs(s["C"])))}

    def truth(self, s):
        return {"dK": s["dK"], "dC": s["dC"]}

    def estimates(self, g, s):
        dc = g.role("estimator").dc_gain()[:, 0]          # (B, 2): gains on [x, x']
        return {"dK": -dc[:, 0], "dC": -dc[:, 1]}


SCENARIO = SdofStiffness()
