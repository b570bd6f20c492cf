"""Seed Section IV: a dynamic unknown subsystem (an impedance 10/(s+2) on velocity) in positive feedback.

Known: m x'' + c x' + k x = w + u, m=1, k=30, c=5, velocity measured and seen by the unknown subsystem.
Truth: the known model and G_Delta = 10/(s+2), each ZOH-discretized at Ts, in discrete positive feedback
(closed loop G/(1 - G G_Delta)). Identified: order nc = 5, phi = [y0(k-1..k-5), u(k-1..k-5)] (w left out:
with w in phi, G_Delta's y0 and w parts are not jointly identifiable, see docs/method.md).
Pass: the identified frequency response within 1% of ZOH(10/(s+2)) from 0.01 rad/s to Nyquist.

Estimates: the DC gain and the gain |G_Delta| at three frequencies (0.5 and 5 rad/s and 90% of Nyquist), each
with its confidence interval; near Nyquist the closed loop carries little information, and the interval says
so. Setting ``noise``: white measurement noise on y, its std a fraction of the rms of y.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from rcotorch.scenarios.sdof_stiffness import noise_block

import rcotorch as rt
from rcotorch.run.scenario import NON_NEGATIVE, POSITIVE, Requirement, Scenario, estimator_space

if TYPE_CHECKING:
    import control

FREQUENCIES = {"gain_0.5rad_s": 0.5, "gain_5rad_s": 5.0}    # rad/s; and gain_nyquist90 at 0.9 pi / Ts


class SdofDynamicImpedance(Scenario):
    name = "sdof-dynamic-impedance"
    section = "IV"
    description = "SDOF with unknown impedance 10/(s+2) on velocity; identify its transfer function"
    steps = 20000
    settings = dict(Ts=0.1, m=1.0, k=30.0, c=5.0, gain=10.0, pole=2.0, nc=5, p0=1e8, lam=1.0, nu=10,
                    w_std=1.0, noise=0.0, seed=1, n_freq=400)
    requirements = (Requirement("estimates.dc_gain", "abs_err", 0.05),
                    Requirement("metrics.freq_rel_err_max", "max", 0.01))
    per_member = frozenset({"p0", "lam", "w_std", "seed"})
    bounds = dict(Ts=POSITIVE, m=POSITIVE, nc=NON_NEGATIVE, w_std=NON_NEGATIVE, noise=NON_NEGATIVE, n_freq=POSITIVE)
    tuning_space = estimator_space(nu=10)    # what `rcotorch tune sdof-dynamic-impedance` searches
    units = {"dc_gain": "N s/m", "y": "m/s", **{k: "N s/m" for k in (*FREQUENCIES, "gain_nyquist90")}}
    about = dict(
        Ts=("s", "sample time (known model and unknown subsystem each ZOH-discretized at Ts)"),
        m=("kg", "mass"),
        k=("N/m", "stiffness"),
        c=("N s/m", "damping"),
        gain=("N/m", "numerator of the unknown impedance gain / (s + pole), velocity -> force"),
        pole=("1/s", "pole of the unknown impedance gain / (s + pole)"),
        nc=("", "order of the identified subsystem (past y0 and u in phi)"),
        w_std=("N", "standard deviation of the white-noise force w"),
        noise=("", "measurement noise on y: its std as a fraction of the rms of y (0: none)"),
        seed=("", "excitation seed; member b of a batch draws the stream (seed, b)"),
        n_freq=("", "frequencies of the log grid 0.01 rad/s .. Nyquist for freq_rel_err_max"),
    )

    def truth_tf(self, s):
        import control
        return control.sample_system(control.tf([s["gain"]], [1.0, s["pole"]]), s["Ts"], method="zoh")

    def build(self, s, batch, dtype, device):
        G = rt.models.sdof(s["m"], s["c"], s["k"], measured=["velocity"], sees=["velocity"])
        known = rt.LTI.from_control(G, inputs=["w", "u"], outputs=["y", "y0"], dt=s["Ts"], name="known")
        truth = rt.LTI.from_control(self.truth_tf(s), inputs=["in"], outputs=["out"], name="unknown")
        ident = rt.RCOEstimator({"y0": 1}, nc=s["nc"], p0=s["p0"], lam=s["lam"])
        return rt.refinement(known, ident, truth=truth, excitation=rt.WhiteNoise(1, std=s["w_std"], seed=s["seed"]),
                             nu=s["nu"], noise=noise_block(s, self.truth_system), batch_size=batch, dtype=dtype,
                             device=device)

    def truth_system(self, s) -> control.StateSpace:
        """The true closed loop w -> y, discrete (for the noise level)."""
        import control
        G = control.sample_system(rt.models.sdof(s["m"], s["c"], s["k"], measured=["velocity"], sees=["velocity"]),
                                  s["Ts"])
        D = control.tf2ss(self.truth_tf(s), inputs="y0", outputs="u")
        return control.interconnect([G, D], inputs="w", outputs="y")

    def frequencies(self, s) -> dict[str, float]:
        return {**FREQUENCIES, "gain_nyquist90": 0.9 * np.pi / s["Ts"]}

    def truth(self, s):
        tf = self.truth_tf(s)
        out = {"dc_gain": s["gain"] / s["pole"]}
        out.update({k: float(abs(tf(np.exp(1j * w * s["Ts"])))) for k, w in self.frequencies(s).items()})
        return out

    def estimates(self, g, s):
        ident = g.role("estimator")
        freqs = self.frequencies(s)
        mags = ident.frequency_response(np.array(list(freqs.values())))[:, :, 0, 0].abs()      # (B, 3)
        return {"dc_gain": ident.dc_gain()[:, 0, 0], **{k: mags[:, i] for i, k in enumerate(freqs)}}

    def omega(self, s):
        from rcotorch.estimator.analysis import log_grid
        return log_grid(s["Ts"], 1e-2, s["n_freq"])

    def metrics(self, g, s):
        from rcotorch.estimator.analysis import frequency_error
        return {"freq_rel_err_max": frequency_error(g.role("estimator"), self.truth_tf(s), self.omega(s))}

    def figures(self, g, s):
        import torch

        from rcotorch.run.figures import frequency_figure
        from rcotorch.verdict.intervals import band
        w = self.omega(s)
        est = g.role("estimator")
        ident = est.frequency_response(w)[0, :, 0, 0].cpu().numpy()
        bands = None
        cov = est.covariance                   # measured by the run's intervals
        if cov is not None and bool(torch.isfinite(cov.cov[0]).all()):
            mag, half = band(g, lambda g: g.role("estimator").frequency_response(w)[:, :, 0, 0].abs(), cov)
            lo, hi = (mag[0] - half[0]).cpu().numpy(), (mag[0] + half[0]).cpu().numpy()
            bands = {"95% confidence band (member 0)": (lo, hi)}
        return {"frequency_response": frequency_figure(
            w, {"identified (member 0)": ident, "true ZOH(10/(s+2))": self.truth_tf(s)(np.exp(1j * w * s["Ts"]))},
            "Identified vs true unknown subsystem (velocity -> force)", nyquist=np.pi / s["Ts"], unit="N s/m",
            bands=bands)}


SCENARIO = SdofDynamicImpedance()
