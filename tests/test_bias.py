"""Estimates the model class cannot make honest: a biased status with the bias's size and sign, checked against
the truth (not the code's own output); the remaining transient against its closed form; the status decided in
one place; the residual warning where it matters and not on exact, noise-free runs; coverage over seeds on
cases off the exact model (slow)."""

import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from coverage_cases import coverage

import rcotorch as rt
from rcotorch.run.report import health_line
from rcotorch.run.runner import Run
from rcotorch.verdict import intervals as ci
from rcotorch.verdict.health import STATUSES, Health


def _finish(name, tmp_path, batch=2, **overrides):
    run = Run(name, batch=batch, overrides=overrides, out=tmp_path / name, validation=False)
    run.advance(progress=False)
    return run, run.finish(figures=False)


def test_a_continuous_truth_makes_a_sampled_estimate_biased_by_the_measured_amount(tmp_path):
    """sdof-stiffness as shipped: a continuous truth (dK = 0.5, dC = 0), no noise. The sampled static gain settles
    at dC = 0.0025 (an O(Ts) bias, DESIGN: 'dK 0.4999 for 0.5'), far beyond its noise-free interval: every member is
    biased, and the bias the verdict reports is the estimate's actual error to 2%. dK's bias is below 0.1% of its
    size, so its interval is widened and holds the truth."""
    run, s = _finish("sdof-stiffness", tmp_path)
    assert s["health"]["status"] == ["biased", "biased"]
    assert s["health"]["biased_keys"] == [["dC"], ["dC"]]
    assert all(r.startswith("model:") for r in s["health"]["bias_reason"])     # the scenario's physics
    err = np.array(s["estimates"]["dC"]) - 0.0
    np.testing.assert_allclose(s["intervals"]["dC"]["bias"], err, rtol=0.02)
    lo, hi = np.array(s["intervals"]["dK"]["lower"]), np.array(s["intervals"]["dK"]["upper"])
    assert np.all((lo <= 0.5) & (0.5 <= hi))
    line = health_line(s)
    assert "2 biased" in line and "dC in 2 (median +0.0025)" in line


def test_a_discrete_truth_is_not_biased(tmp_path):
    """The same structure against its exact discrete truth with 5% noise: no member is biased, no bias is
    reported, and the intervals hold the truth."""
    run, s = _finish("sdof-stiffness", tmp_path, batch=8, truth="discrete", noise=0.05)
    assert s["health"]["counts"]["biased"] == 0
    assert all("bias" not in iv for iv in s["intervals"].values())


def test_the_rlc_circuits_inductance_is_biased_by_its_sampling(tmp_path):
    """rlc-circuit as shipped: its continuous circuit sampled at 10 us puts L 0.5% high, 30 standard deviations;
    the verdict calls the members biased in L and measures the bias within 10% of the actual error."""
    run, s = _finish("rlc-circuit", tmp_path)
    assert s["health"]["status"] == ["biased", "biased"]
    assert all("L" in keys for keys in s["health"]["biased_keys"])
    err = np.array(s["estimates"]["L"]) - s["truth"]["L"]
    assert np.all(err > 5 * (np.array(s["intervals"]["L"]["upper"]) - np.array(s["estimates"]["L"])))
    np.testing.assert_allclose(s["intervals"]["L"]["bias"], err, rtol=0.1)


def test_a_dynamic_subsystem_is_checked_against_the_physics_at_its_estimates(tmp_path):
    """sdof-stiffness-damping: an order-1 identified subsystem whose DC gains are dK and dC, against the continuous
    truth. Its structure has no continuous counterpart to simulate; the scenario's physics at the estimates
    (Scenario.physics) does, and most of the bias is the retrospective cost's own, away from the output error's
    optimum (the cause named): the reported bias, the two together, is dK's actual error within 15%. A member
    whose interval, which holds the window's output-error optimum less the model's bias, holds the physics'
    value is converged instead, and its intervals hold the truth."""
    run, s = _finish("sdof-stiffness-damping", tmp_path)
    status = s["health"]["status"]
    assert set(status) <= {"biased", "converged"} and "biased" in status, status
    err = np.array(s["estimates"]["dK"]) - s["truth"]["dK"]
    for b, st in enumerate(status):
        if st == "biased":
            assert s["health"]["bias_reason"][b].split(":")[0] in ("output error", "model")
            assert s["intervals"]["dK"]["bias"][b] == pytest.approx(err[b], rel=0.15)
        else:
            for key in ("dK", "dC"):
                iv = s["intervals"][key]
                assert iv["lower"][b] <= s["truth"][key] <= iv["upper"][b], (key, b)


def _spring(dK, dC, batch, noise=0.0):
    """A user's own graph: a continuous mass-spring-damper whose stiffness and damping changed, sampled at 20 ms."""
    Ts = 0.02
    known = rt.LTI.continuous(*rt.models.sdof_matrices(2.0, 0.3, 5.0, measured=["velocity"],
                                                       sees=["position", "velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=Ts, name="known")
    m, c, k = 2.0, 0.3 + torch.as_tensor(dC, dtype=torch.float64), 5.0 + torch.as_tensor(dK, dtype=torch.float64)
    plant = rt.LTI.continuous(*rt.models.sdof_matrices(m, c.reshape(-1), k.reshape(-1), measured=["velocity"],
                                                       sees=[], actuation=False),
                              inputs=["w"], outputs=["y"], dt=Ts, name="spring")
    ident = rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3)
    return rt.refinement(known, ident, physical=plant, nu=20, batch_size=batch,
                         excitation=rt.WhiteNoise(1, seed=list(range(3, 3 + batch))),
                         noise=rt.WhiteNoise(1, std=noise, seed=list(range(40, 40 + batch))) if noise else None)


def test_a_python_graph_is_checked_against_the_physics_its_user_gives(tmp_path):
    """A graph built in Python with physics=: the user's own builder with the estimates in place of the truth.
    The reported biases are the actual errors of dK and dC (the truth being the same continuous spring)."""
    est = {"dK": lambda g: -g.role("estimator").theta[:, 0, 0], "dC": lambda g: -g.role("estimator").theta[:, 0, 1]}
    res = rt.refine(_spring(-1.0, 0.6, 2), 8000, est, truth={"dK": -1.0, "dC": 0.6}, out=tmp_path / "spring",
                    figures=False, validation=False, progress=False,
                    physics=lambda e: _spring(e["dK"], e["dC"], 2))
    s = res.summary
    assert res.status == ["biased", "biased"]
    for key, truth in (("dK", -1.0), ("dC", 0.6)):
        err = np.array(s["estimates"][key]) - truth
        bias = np.array([np.nan if b is None else b for b in s["intervals"][key].get("bias", [None, None])])
        flagged = np.isfinite(bias)
        assert flagged.any() or np.all(np.abs(err) < 1e-3 * abs(truth)), key
        np.testing.assert_allclose(bias[flagged], err[flagged], rtol=0.05)


def test_without_physics_the_sampled_feedback_is_simulated_continuously(tmp_path):
    """The same graph without physics=: the verdict simulates the refined model with its static gain acting
    between the samples (rcotorch.verdict.sampling) and finds the same biases, within 5% of the actual errors."""
    est = {"dK": lambda g: -g.role("estimator").theta[:, 0, 0], "dC": lambda g: -g.role("estimator").theta[:, 0, 1]}
    res = rt.refine(_spring(-1.0, 0.6, 2), 8000, est, truth={"dK": -1.0, "dC": 0.6}, out=tmp_path / "spring",
                    figures=False, validation=False, progress=False)
    s = res.summary
    assert res.status == ["biased", "biased"]
    assert all(r.startswith("sampling:") for r in s["health"]["bias_reason"])
    err = np.array(s["estimates"]["dC"]) - 0.6
    np.testing.assert_allclose(s["intervals"]["dC"]["bias"], err, rtol=0.05)


def test_the_status_is_decided_in_one_place():
    """Health.decide on every combination the end of a run can bring, per member."""
    S = {s: STATUSES.index(s) for s in STATUSES}
    status = torch.tensor([S["converged"], S["not_converged"], S["converged"], S["converged"], S["converged"],
                           S["diverged"], S["converged"]])
    ratio = torch.full((7,), 0.01)
    explained = torch.tensor([True, True, True, True, True, True, True])
    determined = torch.tensor([True, True, False, True, True, True, True])
    biased = torch.tensor([False, False, True, True, False, True, False])
    drifting = torch.tensor([False, False, False, False, True, False, False])
    worse = torch.tensor([False, False, False, False, False, False, True])
    out = Health.decide(status, ratio, 0.1, explained=explained, determined=determined, biased=biased,
                        drifting=drifting, worse=worse)
    assert [STATUSES[i] for i in out] == ["converged", "converged", "undetermined", "biased", "not_converged",
                                          "diverged", "not_converged"]


def test_the_remaining_transient_has_its_closed_form(tmp_path):
    """With A = a I, lambda = 1 and the drift measured from k0 to N, tau = (1 - exp(a D))^-1 (eta(N) - eta(k0)),
    D = sum_{k0 < k <= N} 1/k (exact harmonic sums here)."""
    run, _ = _finish("sdof-stiffness", tmp_path, batch=1, truth="discrete", noise=0.05)
    est = run.graph.role("estimator")
    N, k0, a = int(est.k), 1000, 0.7
    D = float(sum(Fraction(1, k) for k in range(k0 + 1, N + 1)))
    n = est.theta_free().shape[1]
    X = 1e-6 * torch.eye(n, dtype=torch.float64).unsqueeze(0)
    pc = ci.ParameterCovariance(cov=X, gain=a * torch.eye(n, dtype=torch.float64).unsqueeze(0), noise=X[:, :1, :1],
                                settles=torch.tensor([True]), replayed=10, measured=10)
    start = est.theta.detach().clone() + 0.01
    tau, cov = ci.remaining_transient(est, start, k0, pc)
    drift = est.theta_free().detach() - start.reshape(1, -1).index_select(1, est.free_idx)
    np.testing.assert_allclose(tau.numpy(), (drift / (1 - math.exp(a * D))).numpy(), rtol=1e-9)
    assert bool((cov.diagonal(dim1=1, dim2=2) > 0).all())


def test_the_residual_warning_is_silent_on_an_exact_noise_free_run_and_speaks_on_a_continuous_truth(tmp_path):
    """The exact discrete truth without noise: z is what is left of the parameters' error (the Gauss-Newton step
    takes it back), so no warning although z fails the whiteness test. The continuous truth without noise: z is
    dynamics no parameter represents, and its correlation widens the intervals: the warning says so."""
    run, s = _finish("sdof-stiffness", tmp_path, truth="discrete")
    assert s["health"]["residuals_white"] == [False, False]
    assert s["health"]["residuals_matter"] == [False, False]
    assert "residuals not white" not in health_line(s)
    run, s = _finish("sdof-stiffness", tmp_path / "c")
    assert s["health"]["residuals_matter"] == [True, True]
    assert "residuals not white in 2 members" in health_line(s)


@pytest.mark.slow
@pytest.mark.parametrize("case, most, members", [("friction-strong", 0.985, 200), ("impedance-noise", 1.0, 200),
                                                 ("twodof-discrete", 0.98, 1000), ("duffing", 0.985, 200),
                                                 ("sdof-damping-noise", 0.98, 1000), ("drag", 0.98, 1000)])
def test_converged_means_covered_off_the_exact_model_over_200_seeds(case, most, members, tmp_path):
    """Hard cases of the interval coverage (coverage_cases.py), 200 members with their own streams: friction with
    strong excitation (a non-smooth basis whose estimates still carry their start's error), the impedance with 5%
    noise, a Duffing truth built in Python (a continuous nonlinear truth, a cubic feature); and 1000 members (a
    few seconds each) of the exact model with lam = 1 (a recursion that forgets its start slowly), of
    ``sdof-stiffness-damping`` with 5% noise (a closed-loop bias of a few of the output-error step's sd, which the
    widened intervals alone held in 88% of members: 200 cannot tell that from 90%) and of the drag truth built in
    Python, where intervals that also reached the estimate, or held the widened interval wherever the estimate
    drifted, covered 0.98-0.99. Among the members called converged the 95% intervals hold the truth in at least
    90%, and at most 98% over 1000 members, 98.5% over 200 (with about 180 converged members a coverage's
    sampling error is about 1.6%; the impedance's 100 or so converged members cannot tell 98% from all), and at
    least a third of the members are converged."""
    r = coverage(case, members, tmp_path)
    assert r["shares"]["converged"] >= 1 / 3, r["shares"]
    for key, row in r["estimates"].items():
        assert 0.90 <= row["coverage"] <= most, (key, row)


@pytest.mark.slow
def test_the_shipped_continuous_truths_are_biased_not_converged(tmp_path):
    """sdof-stiffness at 100 000 steps (the interval shrinks, the sampling bias stays): no member converged,
    every member biased."""
    r = coverage("sdof-shipped-100k", 200, tmp_path)
    assert r["shares"]["converged"] == 0.0 and r["shares"]["biased"] >= 0.99, r["shares"]


def test_a_physics_that_cannot_be_built_is_said_and_the_run_ends(tmp_path):
    """The fault reproduced: a user's physics function that raises (here for an estimate it refuses) stops no
    run; the summary says the bias was not measured, and the members keep the status the rest decides."""
    est = {"dK": lambda g: -g.role("estimator").theta[:, 0, 0], "dC": lambda g: -g.role("estimator").theta[:, 0, 1]}

    def refuse(e):
        raise ValueError("a damping below zero")
    res = rt.refine(_spring(-1.0, 0.6, 2), 2000, est, out=tmp_path / "spring", figures=False, validation=False,
                    progress=False, physics=refuse)
    assert any("the physics at the estimates could not be built (a damping below zero)" in w
               for w in res.summary["warnings"])
    assert all(s in STATUSES for s in res.status)


def test_the_health_line_says_why_members_are_not_converged_and_summary_why_an_interval_is_missing(tmp_path):
    """Faults reproduced: a batch's health line gave counts only, and an estimate without an interval had null
    bounds and no reason. Now every member not converged or undetermined has its reason (health.why), the line
    counts them with the members, and a member without an interval says why (intervals.KEY.reason)."""
    run = Run("sdof-stiffness", batch=3, steps=4000, overrides={"truth": "discrete", "noise": 0.05},
              out=tmp_path / "r", validation=False)
    run.advance(until=1999, progress=False)
    est = run.graph.role("estimator")
    theta = est.theta.clone()
    theta[1] = 1e8                                   # member 1 runs away and is frozen
    est.set_state(theta=theta)
    run.advance(progress=False)
    s = run.finish(figures=False)
    assert s["health"]["status"][1] == "diverged"
    assert s["intervals"]["dK"]["lower"][1] is None
    assert s["intervals"]["dK"]["reason"][1] == "diverged: the member was frozen"
    assert s["intervals"]["dK"]["reason"][0] is None
    why = s["health"]["why"]
    assert why[1] is None and len(why) == 3
    # a member held from converging: its reason is counted in the line with its index
    s["health"]["status"][2], s["health"]["why"][2] = "not_converged", "z_ratio above 0.1"
    assert "1 not_converged: z_ratio above 0.1 (member 2)" in health_line(s)


def _deck(noise_std, members, truth=None):
    """A footbridge deck (m = 2, c = 0.3, k = 8, velocity measured) whose unmodelled damper retrofit is a static
    gain on [position, velocity] (a graph built in Python), lam = 1; ``truth`` another block in its place."""
    seeds = list(range(1, members + 1))
    known = rt.LTI.continuous(*rt.models.sdof_matrices(2.0, 0.3, 8.0, measured=["velocity"],
                                                       sees=["position", "velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=0.02, name="deck")
    ident = rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3, lam=1.0)
    return rt.refinement(known, ident, truth=truth if truth is not None else rt.Gain(torch.tensor([[0.4, -0.9]])),
                         excitation=rt.WhiteNoise(1, std=3.0, seed=seeds), nu=25, batch_size=members,
                         noise=rt.WhiteNoise(1, std=noise_std, seed=[s + 500 for s in seeds]))


def test_noise_above_z_tol_with_white_residuals_does_not_keep_a_member_unconverged(tmp_path):
    """The fault reproduced: with 3% velocity noise the model error's share of the output (z_ratio, about 0.15) is
    the noise's, above z_tol = 0.1, and every member was not_converged ('z_ratio above 0.1') although theta had
    settled and the intervals held the truth. With residuals that pass the whiteness test the z_ratio is what the
    noise leaves: the members are converged and their intervals hold the truth (dk = -0.4, dc = 0.9)."""
    est = {"dk": lambda g: -g.role("estimator").theta[:, 0, 0], "dc": lambda g: -g.role("estimator").theta[:, 0, 1]}
    res = rt.refine(_deck(0.03, 64), 20000, est, truth={"dk": -0.4, "dc": 0.9}, out=tmp_path / "deck",
                    figures=False, validation=False, progress=False)
    h = res.summary["health"]
    assert min(h["z_ratio"]) > 0.1 and all(h["residuals_white"])
    assert h["status"].count("converged") >= 60, h["status"]
    conv = torch.tensor([s == "converged" for s in h["status"]])
    for key, t in (("dk", -0.4), ("dc", 0.9)):     # 0.96 and 0.94 over 400 members
        inside = (res.lower[key] <= t) & (t <= res.upper[key])
        assert float(inside[conv].double().mean()) >= 0.88, (key, inside.tolist())
    assert "z_ratio above" not in health_line(res.summary)


def test_a_model_error_with_dynamics_above_z_tol_keeps_the_member_unconverged(tmp_path):
    """The other side: the retrofit is a damper with its own dynamics (damping 3 behind a first-order lag of 0.4 s
    on the velocity) that a static gain cannot represent; its model error is large (z_ratio about 0.16) and not
    white: not_converged on z_ratio, as before."""
    lag = rt.LTI(np.array([[0.95]]), np.array([[0.0, 0.05]]), np.array([[-3.0]]), np.zeros((1, 2)),
                 inputs={"y0": 2}, outputs={"u": 1}, dt=0.02, name="lagged_damper")
    est = {"dk": lambda g: -g.role("estimator").theta[:, 0, 0], "dc": lambda g: -g.role("estimator").theta[:, 0, 1]}
    res = rt.refine(_deck(0.001, 4, truth=lag), 20000, est, out=tmp_path / "lag", figures=False,
                    validation=False, progress=False)
    h = res.summary["health"]
    assert not any(h["residuals_white"]), h["residuals_white"]
    assert all(z > 0.1 for z in h["z_ratio"]), h["z_ratio"]
    assert h["status"] == ["not_converged"] * 4 and set(h["why"]) == {"z_ratio above 0.1"}, (h["status"], h["why"])
