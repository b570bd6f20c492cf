"""The damaged building (scenario shear-building-damage) identified three ways on the same data, side by side:
rcotorch (RCMR with the change detector and restart), the unscented Kalman filter of filterpy (joint estimation of
the floors' states and the storeys' stiffness changes, one filter per member, as the field's standard code does
it), and the same unscented filter batched over the members in torch, as a performance-minded user writes it.

    python benchmarks/ukf_peer.py                   # about 3 minutes; --members, --filterpy-members, --batch
    python benchmarks/ukf_peer.py --set storey=3 --set change=-0.3 --out ukf_peer_storey3.json   # another damage

The data: the scenario's graph with the three floors' velocities measured (``sensor=velocity``, noise 2e-4 m/s, the
detector's reference window from 500 to 1,000 steps; the scenario's own accelerometers would give the filters a
measurement that the inputs reach at once) run for B members (seeds 1..B), its ground acceleration w and measured
velocities y recorded by the native engine. Both filters get w and y and know the building (the discrete model the
truth is made of): augmented state [floor displacements and velocities (6), dk1, dk2, dk3], dynamics x(k+1) = A x +
B_w w + B_u u with u_j = -dk_j k d_j(x), the parameters a random walk of variance q per step, y = C x with the
measurement noise's variance as R. Tuning: q = 1e-7 (a change of 0.2 is followed within a few hundred steps, and
the estimate's noise before the change stays near 1e-3), P0 = 1e-8 on the floors' states and 1e-2 on the
parameters, Merwe's sigma points (alpha = 0.1, beta = 2, kappa = 0). A filter's "detection" is the first step, from
the 1,000th on (where rcotorch's detector arms), where an estimate moves more than half the change (0.1) from zero;
before the change that is a false alarm. rcotorch's detection is its detector's alarm. The batched filter is
filterpy's algorithm step for step (a test checks it against filterpy to rounding). The data, both filters and the
paired comparison are ``tests/ukf_filters.py``.

Compared: detection delay, false alarms, the largest error over the storeys 50 periods after the change, and the
cost per member-step (rcotorch: the graph's steps with the detector, at --batch over the whole run to the judgement,
the change, the restart and the closed-loop Markov parameters included, and before the change alone; filterpy: its
predict and update; batched: one predict and update of all members); and, member by member against the batched
filter on the same data, how often rcotorch's error is the smaller and bootstrap intervals of the differences of the
median and largest errors (``compare``). The run goes on past the scenario's end, and the same members are judged
again ``--later`` (63, 75 and 100 periods after the change): rcotorch's estimate keeps re-converging as the known
model follows the truth again, the filters' stays at the noise level their random walk allows. Writes
benchmarks/results/ukf_peer.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from common import machine, table, write_json
from rcotorch.scenarios.shear_building_damage import first_period

from rcotorch.run import scenario as scenarios

sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))   # the filters live with the tests that check them
from ukf_filters import (  # noqa: E402
    ALPHA,
    BETA,
    KAPPA,
    NAME,
    P0_THETA,
    P0_X,
    Q_THETA,
    VELOCITY,
    batched_ukf,
    compare,
    filterpy_run,
    model,
    record,
)

MOVE = 0.1              # half the change: a filter's estimate past it counts as a detection


def judge(traj, kd, judge_step, truth, settle):
    """From parameter estimates per step (K, B, 3): detection steps (the first step from ``settle`` on past MOVE,
    -1: none) and the largest error over the storeys at ``judge_step``."""
    moved = np.abs(traj).max(2) > MOVE                              # (K, B)
    moved[:settle] = False                                         # the start, as the detector's warm-up
    first = np.where(moved.any(0), moved.argmax(0) + 1, -1)
    return first, np.abs(traj[judge_step - 1] - truth).max(1)


def summary(name, first, err, kd, T1, seconds, members):
    detected = first >= kd
    delay = (first[detected] - kd) * 0.01 / T1
    return {"method": name, "members": int(members), "us_per_member_step": seconds * 1e6,
            "false_alarms": int(((first >= 0) & (first < kd)).sum()), "detected": int(detected.sum()),
            "delay_periods_max": float(delay.max()) if len(delay) else None,
            "delay_periods_median": float(np.median(delay)) if len(delay) else None,
            "error_median": float(np.median(err)), "error_max": float(err.max()),
            "within_0.016": float((err < 0.016).mean())}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=200, help="members for the accuracy comparison")
    ap.add_argument("--filterpy-members", type=int, default=4, help="members run through filterpy (slow)")
    ap.add_argument("--batch", type=int, default=4096, help="batch of the cost comparison")
    ap.add_argument("--cost-steps", type=int, default=200,
                    help="steps of the batched filter timed at --batch (and of rcotorch before the change)")
    ap.add_argument("--nu", type=int, default=None, help="rcotorch's Markov window (default: the scenario's)")
    ap.add_argument("--later", default="63,75,100",
                    help="first-mode periods after the change at which the errors are compared again")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="another setting of the scenario (storey=3, change=-0.3, track_markov=open-loop, ...)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    sc = scenarios.get(NAME)
    settings = {**VELOCITY, **({} if args.nu is None else {"nu": args.nu}),
                **dict(item.split("=", 1) for item in args.set)}
    s = sc.resolve(settings)
    T1 = first_period(s)
    kd, judge_step = sc.change_step(s), sc.steps
    later = [float(p) for p in args.later.split(",") if p]
    marks = [judge_step] + [kd + round(p * T1 / s["Ts"]) for p in later]
    settle = int(s["warmup"] + s["window"])           # the filters' estimates count from where the detector arms
    truth = np.zeros(3)
    truth[int(s["storey"]) - 1] = s["change"]
    A, Bw, Bu, Cy, Cd = model(sc, s)
    R = np.eye(Cy.shape[0]) * s["noise"] ** 2
    w, y, dks, first_rco, cost_rco, engine = record(sc, s, args.members, marks)
    errs_rco = [np.abs(dk - truth).max(1) for dk in dks]
    err_rco = errs_rco[0]
    results = [summary(f"rcotorch ({engine})", first_rco, err_rco, kd, T1, cost_rco, args.members)]
    traj, cost_b = batched_ukf(A, Bw, Bu, Cy, Cd, s["k"], w, y, R)
    first_ukf, err_ukf = judge(traj, kd, judge_step, truth, settle)
    results.append(summary("UKF batched (torch)", first_ukf, err_ukf, kd, T1, cost_b / args.members, args.members))
    paired = compare(err_rco, err_ukf)
    m = args.filterpy_members
    trajs, costs = [], []
    for b in range(m):
        tr, c = filterpy_run(A, Bw, Bu, Cy, Cd, s["k"], w[:, b], y[:, b], R)
        trajs.append(tr)
        costs.append(c)
    traj_fp = np.stack(trajs, 1)
    results.append(summary("UKF filterpy (one member at a time)", *judge(traj_fp, kd, judge_step, truth, settle), kd,
                           T1, float(np.median(costs)), m))
    results.append(summary(f"rcotorch on filterpy's {m} members", first_rco[:m], err_rco[:m], kd, T1, cost_rco, m))
    # The same members judged again later: rcotorch's re-convergence against the filters' noise floors.
    after = []
    for mark, e_rco in zip(marks, errs_rco):
        periods = (mark - kd) * s["Ts"] / T1
        e_ukf = np.abs(traj[mark - 1] - truth).max(1)
        e_fp = np.abs(traj_fp[mark - 1] - truth).max(1)
        after.append({"periods": periods, "step": mark,
                      "error_median": {"rcotorch": float(np.median(e_rco)), "ukf_batched": float(np.median(e_ukf)),
                                       "ukf_filterpy": float(np.median(e_fp))},
                      "error_max": {"rcotorch": float(e_rco.max()), "ukf_batched": float(e_ukf.max()),
                                    "ukf_filterpy": float(e_fp.max())},
                      "error_max_on_filterpy_members": {"rcotorch": float(e_rco[:m].max()),
                                                        "ukf_filterpy": float(e_fp.max())},
                      "rcotorch_against_batched_ukf": compare(e_rco, e_ukf)})
    # The cost at a large batch: rcotorch's graph over the whole run (the change, the restart and the closed-loop
    # Markov parameters included), the batched filter over a few hundred steps (its cost per step is the same at
    # every step).
    big = sc.build(sc.resolve(settings), args.batch, torch.float64, "cpu")
    big.advance(10)
    t = time.perf_counter()
    big.advance(args.cost_steps)
    rco_steady = (time.perf_counter() - t) / (args.cost_steps * args.batch)      # before the change: no hook acts
    t = time.perf_counter()
    big.advance(judge_step - 10 - args.cost_steps)
    rco_big = (time.perf_counter() - t + rco_steady * args.cost_steps * args.batch) / ((judge_step - 10) * args.batch)
    wb = np.random.default_rng(0).standard_normal((args.cost_steps, args.batch))
    yb = np.zeros((args.cost_steps, args.batch, Cy.shape[0]))
    ukf_big = batched_ukf(A, Bw, Bu, Cy, Cd, s["k"], wb, yb, R)[1] / args.batch
    fp = results[2]["us_per_member_step"] * 1e-6                          # filterpy's
    cost = {"batch": args.batch, "rcotorch_us": rco_big * 1e6, "ukf_batched_us": ukf_big * 1e6,
            "ukf_filterpy_us": fp * 1e6, "filterpy_over_rcotorch": fp / rco_big,
            "batched_over_rcotorch": ukf_big / rco_big, "rcotorch_before_change_us": rco_steady * 1e6,
            "filterpy_over_rcotorch_before_change": fp / rco_steady,
            "batched_over_rcotorch_before_change": ukf_big / rco_steady}
    rows = [[r["method"], r["members"], r["detected"], r["false_alarms"],
             "-" if r["delay_periods_max"] is None else f"{r['delay_periods_max']:.2f}",
             f"{r['error_median']:.4f}", f"{r['error_max']:.4f}", f"{100 * r['within_0.016']:.0f}%",
             f"{r['us_per_member_step']:.3g}"] for r in results]
    print(f"{NAME}: change at step {kd}, judged at step {judge_step} (50 periods of {T1:.4f} s later)")
    print(table(rows, ["method", "members", "detected", "false alarms", "delay max [T1]", "error median",
                       "error max", "within 0.016", "us / member-step"]))
    print(f"rcotorch against the batched UKF on the same {args.members} members: smaller error in "
          f"{100 * paired['a_smaller_share']:.0f}%, median difference {paired['median_difference']:+.5f} (95%: "
          f"{paired['median_difference_95'][0]:+.5f} .. {paired['median_difference_95'][1]:+.5f}), largest "
          f"{paired['max_difference']:+.5f} ({paired['max_difference_95'][0]:+.5f} .. "
          f"{paired['max_difference_95'][1]:+.5f})")
    print(table([[f"{a['periods']:.0f}", a["step"], *(f"{a[key][who]:.5f}" for key in ("error_median", "error_max")
                                                      for who in ("rcotorch", "ukf_batched", "ukf_filterpy")),
                  f"{a['rcotorch_against_batched_ukf']['median_difference_95'][0]:+.5f} .. "
                  f"{a['rcotorch_against_batched_ukf']['median_difference_95'][1]:+.5f}",
                  f"{a['rcotorch_against_batched_ukf']['max_difference_95'][0]:+.5f} .. "
                  f"{a['rcotorch_against_batched_ukf']['max_difference_95'][1]:+.5f}"] for a in after],
                ["periods after", "step", "median: rcotorch", "UKF batched", "filterpy", "max: rcotorch", "UKF batched",
                 "filterpy", "median diff 95%", "max diff 95%"]))
    print(f"cost at B = {args.batch}: rcotorch {cost['rcotorch_us']:.3g} us, batched UKF {cost['ukf_batched_us']:.3g} "
          f"us, filterpy {cost['ukf_filterpy_us']:.3g} us per member-step: filterpy / rcotorch "
          f"{cost['filterpy_over_rcotorch']:.0f}x (goal 1000x), batched / rcotorch "
          f"{cost['batched_over_rcotorch']:.2f}x (goal 10x), over the whole run; before the change (no hook acting) "
          f"rcotorch {cost['rcotorch_before_change_us']:.3g} us: {cost['filterpy_over_rcotorch_before_change']:.0f}x "
          f"and {cost['batched_over_rcotorch_before_change']:.2f}x")
    write_json({"benchmark": "ukf_peer", "machine": machine(torch.device("cpu")), "scenario": NAME,
                "settings": {"q_theta": Q_THETA, "p0_x": P0_X, "p0_theta": P0_THETA, "alpha": ALPHA, "beta": BETA,
                             "kappa": KAPPA, "move": MOVE},
                "results": results, "rcotorch_against_batched_ukf": paired, "after": after, "cost": cost},
               "ukf_peer", args.out)


if __name__ == "__main__":
    main()
