"""Seed Section VI: inductance and capacitance of a series RLC circuit from the voltage across its resistor.

Truth: L i' + R i + q/C = w, q' = i (R = 250 ohm, L = 55 mH, C = 23.5 uF), driven by a white-noise source
voltage w; measured y = R i, the voltage across R, plus Gaussian noise of std ``noise`` (1%) times the rms of
R i (the steady-state rms of the discrete truth driven by w, from its discrete Lyapunov equation). The truth is
the continuous circuit ZOH-discretized as a whole at Ts.

Known subsystem: the same circuit with nominal L0, C0, R0 and a second series voltage source u (the unknown
subsystem's port): L0 i' + R0 i + q/C0 = w + u (``rcotorch.models.series_rlc``), measured y = v_R = R0 i.
Default initial model: L0 = 1.3 L, C0 = 0.7 C (30% off each way), R0 = R. Unknown subsystem: the voltage u that
makes the nominal circuit reproduce the measurement. With R0 = R: solve the true equation for i' and
substitute it into the nominal one,

    u = L0 i' + R0 i + q/C0 - w = gC v_C + gR v_R + gw w,    v_C = q/C0, v_R = R0 i  (the nominal voltages)
    gC = 1 - L0 C0 / (L C),   gR = 1 - L0 / L,   gw = L0 / L - 1,

a static gain on [v_C, v_R, w], all three gains dimensionless and O(1) (the raw gains on q and i would span
nine orders of magnitude and make P badly conditioned). Identified subsystem: the exactly proper static gain
u(k) = theta [v_C(k), v_R(k), w(k)] (w is fed from the excitation). Back-out formulas (physical units: H, F, ohm):

    L = L0 / (1 + gw),   C = C0 (1 + gw) / (1 - gC),   R = R0 (1 - gR) / (1 + gw).

Identifiability: the measured map is R C s / (L C s^2 + R C s + 1) = (R/L) s / (s^2 + (R/L) s + 1/(L C)); it
depends on R/L and L C only, so (R, L, 1/C) scaled together give the same data. One of the three has to be
known: here R (R0 = R). The three gains fix the numerator gain (1 + gw) R0 / L0, the damping (1 - gR) R0 / L0
and the stiffness (1 - gC) / (L0 C0) of the refined model; the numerator gain gives L (because y = R0 i in the
model), the stiffness C, and R is damping / numerator gain times R0: a consistency check of the identified
gains, not an independent measurement of R. With R0 != R (setting ``R0_rel``) the gains that reproduce the
data are gC as above, gR = 1 - R L0 / (R0 L), gw = R L0 / (R0 L) - 1, and the back-out returns R = R0 with the
equivalent L = R0 L / R, C = R C / R0, a circuit with the true input-output map (measured with R0_rel = 0.2:
R = 299.9 ohm, L = 66.1 mH, C = 19.55 uF; predicted 300 ohm, 66.0 mH, 19.58 uF).

Measured on this machine (CPU, float64; defaults: Ts = 1e-5 s, nu = 50, p0 = 100, lam = 1, 20 000 steps = 0.2 s,
1% noise; two noise streams, batch 2):

    initial model               L [mH]          C [uF]          R [ohm]        rel. rms model error
    L0 = 1.3 L, C0 = 0.7 C      55.30 / 55.29   23.33 / 23.52   249.8 / 250.0  17.4% -> 0.11% / 0.015%
    L0 = 0.7 L, C0 = 1.3 C      54.45 / 54.48   23.68 / 23.46   250.1 / 249.9  27.5% -> 0.11% / 0.024%
    truth                       55.0            23.5            250

(rel. rms model error: ||T - G||_2 / ||T||_2 of the sampled systems, noise-free, initial -> refined.) The small
positive L bias is the O(Ts) discretization bias of "ZOH model + sampled feedback" against a continuous truth:
+1.0% at Ts = 2e-5 s, +0.54% at 1e-5 s, +0.27% at 5e-6 s. Without noise the estimates are the same to 0.2%.

From the paper's own initial guesses (``initial='paper'``: L0 = 2 uH, C0 = 1 F, R0 = R) the method does not
recover L and C. Measured (defaults otherwise, batch 2): L = 45.0 uH (1/1200 of the truth), C = 42 / 43 mF
(1800 times the truth), R = 260 / 271 ohm (4% / 8%, by coincidence); the sampled refined model does fit the data
much better than the initial one (rel. rms model error 641% -> 18.6%): it matches the true circuit above about
1 krad/s, where the white drive puts most of the output power, but not the capacitor's low-frequency roll-off.
A finer Ts = 1e-6 s with nu = 200 does not help (L = 0.42 / 0.45 mH, C = 4.8 / 4.4 mF).

Why: with L0 = 2 uH the nominal circuit's electrical time constant L0/R = 8 ns is 1250 times shorter than Ts,
and with C0 = 1 F its other one, R C0 = 250 s, is 2.5e7 samples long. Sampled, the
nominal model is a resistor (the current settles within one sample) plus an integrator that barely moves, so its
Markov parameters are [-1, 4e-8, 4e-8, ...] and the refined model is a first-order discrete filter; v_C = q/C0 is
about 1e-5 V, so gC has almost no information. The three gains then fit the fast pole of the true circuit (the
discrete model error falls, see ``metrics.freq_rel_err_max``) but the back-out formulas, which assume that the
sampled refined model is the discretization of a continuous RLC circuit, do not hold, and L = L0 / (1 + gw)
divides by 1 + gw = L0/L = 3.6e-5, so any error in gw is amplified 3e4-fold. A correction that has to cancel
99.996% of the nominal inductance is not a refinement of that model; the initial model must resolve the circuit
at the chosen sample time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

import rcotorch as rt
from rcotorch.run.scenario import NON_NEGATIVE, POSITIVE, Requirement, Scenario, estimator_space

if TYPE_CHECKING:
    import control
    import torch

PAPER_L0, PAPER_C0 = 2e-6, 1.0


def initial_values(s) -> tuple[float, float, float]:
    """Nominal (L0, C0, R0) of the known model."""
    R0 = s["R"] * (1 + s["R0_rel"])
    if s["initial"] == "paper":
        return PAPER_L0, PAPER_C0, R0
    if s["initial"] == "nominal":
        return s["L"] * (1 + s["L0_rel"]), s["C"] * (1 + s["C0_rel"]), R0
    raise rt.ConfigError(f"rlc-circuit: initial must be 'nominal' or 'paper', got {s['initial']!r}")


def back_out(theta: torch.Tensor, L0: float, C0: float, R0: float) -> dict[str, torch.Tensor]:
    """(L, C, R) from the gains theta = [gC, gR, gw] on [v_C, v_R, w], each (B,)."""
    gC, gR, gw = theta[..., 0], theta[..., 1], theta[..., 2]
    return {"L": L0 / (1 + gw), "C": C0 * (1 + gw) / (1 - gC), "R": R0 * (1 - gR) / (1 + gw)}


def true_gains(s) -> dict[str, float]:
    """The gains [gC, gR, gw] with which the nominal circuit reproduces the measured voltage exactly (in
    continuous time)."""
    L0, C0, R0 = initial_values(s)
    L, C, R = s["L"], s["C"], s["R"]
    return {"gC": 1 - L0 * C0 / (L * C), "gR": 1 - R * L0 / (R0 * L), "gw": R * L0 / (R0 * L) - 1}


def truth_discrete(s) -> control.StateSpace:
    import control

    from rcotorch.models.circuits import series_rlc
    T = series_rlc(s["R"], s["L"], s["C"], measured=["v_R"], sees=[], actuation=False)
    return control.sample_system(T, s["Ts"], method="zoh")


def h2_rel_err(model: control.StateSpace, ref: control.StateSpace) -> float:
    """||ref - model||_2 / ||ref||_2 for sampled SISO systems without feedthrough: the rms output error for white
    input relative to the rms output (inf if the model is unstable)."""
    import scipy.linalg
    if np.max(np.abs(np.linalg.eigvals(model.A))) >= 1:
        return float("inf")

    def var(A, B, C):
        X = scipy.linalg.solve_discrete_lyapunov(A, B @ B.T)
        return float((C @ X @ C.T)[0, 0])

    A = scipy.linalg.block_diag(ref.A, model.A)
    return float(np.sqrt(var(A, np.vstack([ref.B, model.B]), np.hstack([ref.C, -model.C])) /
                         var(ref.A, ref.B, ref.C)))


def output_rms(s) -> float:
    """Steady-state rms of R i for white w of std w_std (discrete Lyapunov equation of the sampled truth)."""
    import scipy.linalg
    Td = truth_discrete(s)
    X = scipy.linalg.solve_discrete_lyapunov(Td.A, Td.B @ Td.B.T)
    return float(s["w_std"] * np.sqrt((Td.C @ X @ Td.C.T)[0, 0]))


class RlcCircuit(Scenario):
    name = "rlc-circuit"
    section = "VI"
    description = "series RLC: L, C (and R as a check) from the noisy resistor voltage, 30% initial error"
    steps = 20000
    settings = dict(Ts=1e-5, R=250.0, L=55e-3, C=23.5e-6, initial="nominal", L0_rel=0.3, C0_rel=-0.3,
                    R0_rel=0.0, noise=0.01, p0=100.0, lam=1.0, nu=50, w_std=1.0, seed=1)
    requirements = (Requirement("estimates.L", "rel_err", 0.05), Requirement("estimates.C", "rel_err", 0.05),
                    Requirement("estimates.R", "rel_err", 0.05))
    units = {"y": "V", "rel_rms_err_initial": "", "rel_rms_err_refined": ""}
    per_member = frozenset({"seed"})        # one seed per member: member b draws the streams of its own seed
    bounds = dict(Ts=POSITIVE, R=POSITIVE, L=POSITIVE, C=POSITIVE, noise=NON_NEGATIVE, w_std=NON_NEGATIVE)
    tuning_space = estimator_space(nu=50)    # what `rcotorch tune rlc-circuit` searches
    about = dict(
        Ts=("s", "sample time"),
        R=("ohm", "true resistance"),
        L=("H", "true inductance"),
        C=("F", "true capacitance"),
        initial=("", "initial model: L0, C0 from the relative errors below, or the paper's L0 = 2 uH, C0 = 1 F",
                 ("nominal", "paper")),
        L0_rel=("", "relative error of the initial L0: L0 = L (1 + L0_rel)"),
        C0_rel=("", "relative error of the initial C0: C0 = C (1 + C0_rel)"),
        R0_rel=("", "relative error of the model's R0 (R is taken as known: 0)"),
        noise=("", "measurement noise std as a fraction of the rms voltage across R"),
        w_std=("V", "standard deviation of the white-noise source voltage w"),
        seed=("", "seed of the source voltage and of the measurement noise"),
    )

    def build(self, s, batch, dtype, device):
        from rcotorch.models.circuits import series_rlc
        L0, C0, R0 = initial_values(s)
        G = series_rlc(R0, L0, C0, measured=["v_R"], sees=["v_C", "v_R"])
        known = rt.LTI.from_control(G, inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=s["Ts"], name="known")
        truth = rt.LTI.from_control(truth_discrete(s), inputs=["w"], outputs=["y"], name="circuit")
        seed = s["seed"]
        noise_seed = [x + 7919 for x in seed] if isinstance(seed, list) else seed + 7919
        ident = rt.RCOEstimator.static_gain({"y0": 2, "w": 1}, p0=s["p0"], lam=s["lam"])
        return rt.refinement(known, ident, physical=truth,
                             noise=rt.WhiteNoise(1, std=s["noise"] * output_rms(s), seed=noise_seed),
                             excitation=rt.WhiteNoise(1, std=s["w_std"], seed=s["seed"]), nu=s["nu"],
                             batch_size=batch, dtype=dtype, device=device)

    def truth(self, s):
        return {"L": s["L"], "C": s["C"], "R": s["R"]}

    def estimates(self, g, s):
        return back_out(g.role("estimator").theta[:, 0], *initial_values(s))

    # --- frequency responses --------------------------------------------------------------------------
    @staticmethod
    def _refined_discrete(g, member: int) -> control.StateSpace:
        """The simulated system w -> y: the sampled known model with u(k) = theta [y0(k); w(k)]."""
        import control
        known = g.role("known")
        A, B, C = (getattr(known, k)[0].detach().cpu().double().numpy() for k in ("A", "B", "C"))
        th = g.role("estimator").theta[member, 0].detach().cpu().double().numpy()
        bw, bu = B[:, :1], B[:, 1:2]
        cy, cy0 = C[:1], C[1:3]
        return control.ss(A + bu @ th[None, :2] @ cy0, bw + bu * th[2], cy, np.zeros((1, 1)), known.dt)

    def metrics(self, g, s):
        """freq_rel_err_max: max over 10 rad/s .. Nyquist of |refined - truth| / |truth| for the sampled
        refined model (known + identified gain) against the sampled truth; freq_rel_err_initial: the same for
        the initial model; rel_rms_err_refined / rel_rms_err_initial: rms of (true - model) output for the white
        drive, noise-free, relative to the rms output (||T - G||_2 / ||T||_2 of the sampled systems); gC, gR, gw:
        the identified gains, gC_true, gR_true, gw_true: the continuous-time ones (``true_gains``); noise_std:
        the measurement noise std in volts."""
        import control
        import torch

        from rcotorch.models.circuits import series_rlc
        omega = np.logspace(1, np.log10(np.pi / s["Ts"]), 300)
        zs = np.exp(1j * omega * s["Ts"])
        true = np.asarray(truth_discrete(s)(zs)).reshape(-1)
        L0, C0, R0 = initial_values(s)
        init = control.sample_system(series_rlc(R0, L0, C0, measured=["v_R"], sees=[], actuation=False),
                                     s["Ts"], method="zoh")
        e0 = np.max(np.abs(np.asarray(init(zs)).reshape(-1) - true) / np.abs(true))
        errs = [np.max(np.abs(np.asarray(self._refined_discrete(g, b)(zs)).reshape(-1) - true) / np.abs(true))
                for b in range(g.batch_size)]
        B, Td = g.batch_size, truth_discrete(s)
        out = {"freq_rel_err_max": torch.tensor(errs), "freq_rel_err_initial": torch.full((B,), float(e0)),
               "rel_rms_err_refined": torch.tensor([h2_rel_err(self._refined_discrete(g, b), Td) for b in range(B)]),
               "rel_rms_err_initial": torch.full((B,), h2_rel_err(init, Td)),
               "noise_std": torch.full((B,), s["noise"] * output_rms(s))}
        theta = g.role("estimator").theta[:, 0]
        for i, key in enumerate(("gC", "gR", "gw")):
            out[key] = theta[:, i]
            out[key + "_true"] = torch.full((B,), true_gains(s)[key])
        return out

    def figures(self, g, s):
        from rcotorch.models.circuits import series_rlc
        from rcotorch.run.figures import frequency_figure
        from rcotorch.verdict.intervals import member_band
        omega = np.logspace(1, np.log10(np.pi / s["Ts"]), 400)
        L0, C0, R0 = initial_values(s)
        est = {k: float(v[0]) for k, v in self.estimates(g, s).items()}
        curves = {}
        for label, (R, L, C) in {"initial model": (R0, L0, C0), "true circuit": (s["R"], s["L"], s["C"]),
                                 "refined (backed-out R, L, C)": (est["R"], est["L"], est["C"])}.items():
            if min(R, L, C) > 0 and np.isfinite([R, L, C]).all():
                sys = series_rlc(R, L, C, measured=["v_R"], sees=[], actuation=False)
                curves[label] = np.asarray(sys(1j * omega)).reshape(-1)
        zs = np.exp(1j * omega * s["Ts"])
        curves["true circuit, sampled"] = np.asarray(truth_discrete(s)(zs)).reshape(-1)
        curves["refined, sampled (known model + gain)"] = np.asarray(self._refined_discrete(g, 0)(zs)).reshape(-1)
        bands = None
        cov = g.role("estimator").covariance              # measured by the run's intervals
        if cov is not None:
            found = member_band(g, lambda g: np.abs(np.asarray(self._refined_discrete(g, 0)(zs)).reshape(-1)), cov)
            if found is not None:
                mag, half = found
                bands = {"95% confidence band of the refined model (member 0)": (mag - half, mag + half)}
        fig = frequency_figure(omega, curves, "series RLC: source voltage w -> voltage across R",
                               nyquist=np.pi / s["Ts"], unit="V/V", bands=bands)
        return {"frequency_response": fig}


SCENARIO = RlcCircuit()
