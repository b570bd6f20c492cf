"""A building that is damaged while it is watched: storey 2 of a 3-storey shear building loses 20% of its
stiffness during the run; the refinement detects the change and re-identifies the storeys.

Known: floors of m = 2e4 kg, storeys of k = 2e7 N/m, 2% Rayleigh damping in the first two modes (periods 0.4465,
0.1593 and 0.1103 s), excited at the base by white-noise ground acceleration (std ``w_std``); accelerometers on
the ``measured`` floors (2 and 3) read each floor's absolute acceleration with white noise of std ``noise``
(``sensor=velocity``: the floors' velocities relative to the ground instead). The truth is the discrete known
model with the storeys' stiffness changes as force pairs u_j = -dk_j k d_j on the storey drifts d_j, zero until
``t_change``, then ``change`` on storey ``storey``. The identified subsystem is a static gain from the drifts to
the force pairs, masked to its diagonal: dk_j = -theta_jj / k. The force pairs reach the accelerations at once
(the first Markov parameter is the model's feedthrough), which the retrospective cost weighs like any other.

Tracking: a ``ChangeDetector`` (CUSUM) on the model error z, and ``ResetOnChange``, which restarts an alarmed
member's estimator (P = ``restart_p0`` I), lets it forget at ``track_lam`` for ``track_hold`` steps and, from
``markov_after`` steps after the alarm to the end of ``track_hold``, gives it the Markov parameters of the loop
closed at its present estimate (``track_markov``), renewed every ``markov_every`` steps where the estimate has moved
by more than ``markov_tol`` of its size. The run ends 50 first-mode periods after the change, where the estimates
are judged; docs/tracking.md has the studies over 200 seeds.
"""

import math

import numpy as np

import rcotorch as rt
from rcotorch.run.scenario import NON_NEGATIVE, POSITIVE, UNIT_INTERVAL, Requirement, Scenario, member_values

from .sdof_stiffness import noise_seed


def building(s, identified=(1, 2, 3)):
    floors = [int(f) for f in str(s["measured"]).split(",")]
    return rt.models.shear_building([s["m"]] * 3, [s["k"]] * 3, damping_ratio=s["zeta"], force="base",
                                    measured=[f"{s['sensor']}[{f}]" for f in floors], identified=list(identified))


def first_period(s) -> float:
    G = building(s, identified=())
    return 2 * math.pi / float(np.sort(np.abs(np.linalg.eigvals(G.A)))[0])


class ShearBuildingDamage(Scenario):
    name = "shear-building-damage"
    section = "tracking"
    description = "3-storey shear building, storey 2 loses 20% of its stiffness mid-run: detect and re-identify"
    # t_change / Ts, then 50 periods of 0.4465 s
    steps = 6000 + 2232
    settings = dict(Ts=0.01, m=2.0e4, k=2.0e7, zeta=0.02, storey=2, change=-0.2, t_change=60.0, w_std=1.0,
                    noise=0.01, sensor="acceleration", measured="2,3", nu=100, p0=1e20, lam=1.0, threshold=30.0,
                    drift=1.0, warmup=2000, window=1000, holdoff=3000, restart_p0=1e14, track_lam=0.99, track_hold=3000,
                    restart_every=50, track_markov="closed-loop", markov_after=200, markov_every=50, markov_tol=0.01,
                    seed=1)
    about = dict(
        Ts=("s", "sample time"),
        m=("kg", "mass of each floor"),
        k=("N/m", "stiffness of each storey (known model)"),
        zeta=("", "damping ratio of the first two modes (Rayleigh)"),
        storey=("", "the storey that changes (1..3)"),
        change=("", "its stiffness change, relative to k"),
        t_change=("s", "when it changes"),
        w_std=("m/s^2", "std of the white-noise ground acceleration"),
        noise=("m/s or m/s^2", "std of the measurement noise (in the sensor's unit)"),
        sensor=("", "what is measured at each floor: its velocity relative to the ground, or its absolute "
                    "acceleration (an accelerometer; the force pairs reach it at once)",
                ("velocity", "acceleration")),
        measured=("", "the floors whose sensors are read, separated by commas"),
        threshold=("", "the change detector's alarm level (CUSUM on the normalized squared model error)"),
        drift=("", "the detector's allowance (changes below drift x the noise power are ignored)"),
        warmup=("steps", "steps before the detector's reference window"),
        window=("steps", "steps of the detector's reference window"),
        holdoff=("steps", "steps after an alarm before the detector's next reference window"),
        restart_p0=("", "P = restart_p0 I for a member whose detector alarmed (0: keep P)"),
        track_lam=("", "forgetting factor for track_hold steps after an alarm"),
        track_hold=("steps", "how long the forgetting lasts after an alarm"),
        restart_every=("steps", "the restart acts every this many steps, on the alarms since it last acted (each "
                                "time it acts, the native engine stops: a pass over every member's state)"),
        track_markov=("", "the Markov parameters while following a change: the known model's own, or those of the loop "
                          "closed at the member's present estimate, renewed every markov_every steps",
                      ("open-loop", "closed-loop")),
        markov_after=("steps", "steps after an alarm before the loop is first closed at the estimate"),
        markov_tol=("", "a member's closed-loop Markov parameters are renewed only where its estimate moved by more "
                        "than this share of its size since they were made (0: every time)"),
        markov_every=("steps", "steps between two renewals of the closed-loop Markov parameters (a multiple of "
                               "restart_every)"),
        seed=("", "excitation seed; member b of a batch draws the stream (seed, b)"),
    )
    per_member = frozenset({"p0", "lam", "seed"})
    bounds = dict(Ts=POSITIVE, m=POSITIVE, k=POSITIVE, zeta=NON_NEGATIVE, t_change=NON_NEGATIVE, w_std=NON_NEGATIVE,
                  noise=NON_NEGATIVE, drift=NON_NEGATIVE, warmup=NON_NEGATIVE, window=POSITIVE, holdoff=NON_NEGATIVE,
                  restart_p0=NON_NEGATIVE, track_lam=UNIT_INTERVAL, track_hold=NON_NEGATIVE, restart_every=POSITIVE,
                  markov_after=NON_NEGATIVE, markov_every=POSITIVE, markov_tol=NON_NEGATIVE)
    units = {"y": "m/s^2"}

    def unit(self, key: str, settings=None) -> str:
        """The measured signal's unit follows the sensor (m/s^2 for accelerometers, m/s for velocities)."""
        if key in ("y", "noise"):
            return "m/s" if settings is not None and settings.get("sensor") == "velocity" else "m/s^2"
        return super().unit(key, settings)

    def output_names(self, settings) -> list[str]:
        """Each measured floor's sensor: 'floor 2 acceleration', 'floor 3 acceleration'."""
        return [f"floor {int(f)} {settings['sensor']}" for f in str(settings["measured"]).split(",")]
    requirements = (Requirement("estimates.dk1", "abs_err", 0.016), Requirement("estimates.dk2", "abs_err", 0.016),
                    Requirement("estimates.dk3", "abs_err", 0.016),
                    Requirement("metrics.detection_delay_periods", "max", 5.0, inclusive=True),
                    Requirement("metrics.false_alarms", "max", 0.5))

    def build(self, s, batch, dtype, device):
        import torch
        G = building(s)
        n_y = G.noutputs - 3
        if not 1 <= int(s["storey"]) <= 3:
            raise rt.ConfigError(f"scenario '{self.name}': storey must be 1, 2 or 3, got {s['storey']}")
        known = rt.LTI.from_control(G, inputs={"w": 1, "u": 3}, outputs={"y": n_y, "y0": 3}, dt=s["Ts"],
                                    name="known")
        ident = rt.RCOEstimator.static_gain({"y0": 3}, n_u=3, n_z=n_y, mask=np.eye(3, dtype=bool),
                                            p0=member_values(s, "p0"), lam=member_values(s, "lam"))
        detector = rt.ChangeDetector(n_y, warmup=int(s["warmup"]), window=int(s["window"]),
                                     holdoff=int(s["holdoff"]), drift=s["drift"], threshold=s["threshold"],
                                     dt=s["Ts"])
        graph = rt.refinement(known, ident, truth=rt.Gain(np.zeros((3, 3)), name="unknown"),
                              excitation=rt.WhiteNoise(1, std=s["w_std"], seed=s["seed"]),
                              noise=rt.WhiteNoise(n_y, std=s["noise"], seed=noise_seed(s["seed"])), nu=int(s["nu"]),
                              batch_size=batch, dtype=dtype, device=device, blocks=[detector],
                              connections=[("error.out", "detector.z")])
        damage = torch.zeros(1, 3, 3, dtype=torch.float64)
        j = int(s["storey"]) - 1
        damage[0, j, j] = -s["change"] * s["k"]

        def change(g):
            g.blocks["unknown"].K.copy_(damage.to(g.blocks["unknown"].K))

        graph.add_hook(rt.at_step(self.change_step(s), change, acts_on=["unknown"]))
        graph.add_hook(rt.ResetOnChange(graph, every=int(s["restart_every"]), p0=s["restart_p0"] or None,
                                        restart=bool(s["restart_p0"]), lam=s["track_lam"],
                                        hold=int(s["track_hold"]), markov=s["track_markov"],
                                        markov_after=int(s["markov_after"]), markov_every=int(s["markov_every"]),
                                        markov_tol=float(s["markov_tol"])))
        return graph

    @staticmethod
    def change_step(s) -> int:
        return max(1, int(round(s["t_change"] / s["Ts"])))

    def truth(self, s):
        out = {"dk1": 0.0, "dk2": 0.0, "dk3": 0.0}
        out[f"dk{int(s['storey'])}"] = s["change"]
        return out

    def truth_history(self, s):
        """The changing storey's stiffness change: 0 until the change step, then ``change``."""
        return {f"dk{int(s['storey'])}": [(0.0, 0.0), (self.change_step(s) * s["Ts"], s["change"])]}

    def scales(self, s):
        return {f"dk{j}": 1.0 for j in (1, 2, 3)}

    def estimates(self, g, s):
        theta = g.role("estimator").theta
        return {f"dk{j + 1}": -theta[:, j, j] / s["k"] for j in range(3)}

    def metrics(self, g, s):
        import torch
        det = g.blocks["detector"]
        first = det.first_alarm().to(torch.float64)
        kd = self.change_step(s)
        T1 = first_period(s)
        detected = first >= kd
        delay = torch.where(detected, (first - kd) * s["Ts"] / T1, torch.full_like(first, math.nan))
        return {"detection_step": first, "detection_delay_periods": delay,
                "false_alarms": ((first >= 0) & (first < kd)).to(torch.float64),
                "alarms": det.alarms().to(torch.float64), "first_period_s": torch.full_like(first, T1)}


SCENARIO = ShearBuildingDamage()
