"""Confidence intervals and the verdict: against closed-form least squares, per member, for a graph built in
Python, on an undetermined structure, and by coverage over seeds (slow)."""

import contextlib
import json
import math

import numpy as np
import pytest
import scipy.stats
import torch

import rcotorch as rt
from rcotorch.run.report import health_line
from rcotorch.run.runner import Run
from rcotorch.run.scenario import Requirement


def _regression_graph(theta_true, noise_std, seed=5, p0=1e8):
    """y(k) = theta* w(k-1) + v(k) against the known model y_hat(k) = u(k-1) with u(k) = theta w(k): the
    retrospective cost is then the least-squares cost of the static regression of y(k) on w(k-1)."""
    n = len(theta_true)
    known = rt.LTI(np.zeros((1, 1)), np.hstack([np.zeros((1, n)), np.ones((1, 1))]), np.ones((1, 1)),
                   np.zeros((1, n + 1)), inputs={"w": n, "u": 1}, outputs={"y": 1}, dt=1.0, name="known")
    physical = rt.LTI(np.zeros((n, n)), np.eye(n), np.asarray([theta_true], dtype=float), np.zeros((1, n)),
                      inputs={"w": n}, outputs={"y": 1}, dt=1.0)
    ident = rt.RCOEstimator.static_gain({"w": n}, p0=p0)
    many = isinstance(seed, list)           # one seed per member: a batch
    return rt.refinement(known, ident, physical=physical, excitation=rt.WhiteNoise(n, seed=seed),
                         noise=rt.WhiteNoise(1, std=noise_std, seed=[s + 1000 for s in seed] if many else seed + 1),
                         nu=1, batch_size=len(seed) if many else 1)


def test_intervals_of_a_static_regression_are_the_least_squares_intervals(tmp_path):
    theta_true, steps, sd = [0.7, -1.3, 0.2], 5000, 0.1
    g = _regression_graph(theta_true, sd)
    est = g.role("estimator")
    res = rt.refine(g, steps, out=tmp_path / "run", figures=False)
    # the same streams, drawn again from their seeds: w(k) and v(k) are pure functions of (seed, member, k)
    w_src, v_src = rt.WhiteNoise(3, seed=5), rt.WhiteNoise(1, std=sd, seed=6)
    w_src.reset(1)
    v_src.reset(1)
    w = np.array([w_src.step()["out"][0].numpy() for _ in range(steps)])
    v = np.array([v_src.step()["out"][0, 0].item() for _ in range(steps)])
    X, y = w[:-1], w[:-1] @ np.array(theta_true) + v[1:]
    beta, rss = np.linalg.lstsq(X, y, rcond=None)[:2]
    N, p = X.shape
    s2 = float(rss[0]) / (N - p)
    half = scipy.stats.t.ppf(0.975, N - p) * np.sqrt(s2 * np.diag(np.linalg.inv(X.T @ X)))
    names = [f"theta[{n}]" for n in est.theta_names]
    got_est = np.array([res.estimates[k].item() for k in names])
    below = np.array([(res.estimates[k] - res.lower[k]).item() for k in names])
    above = np.array([(res.upper[k] - res.estimates[k]).item() for k in names])
    np.testing.assert_allclose(got_est, beta, rtol=0, atol=1e-6)
    # sigma^2 comes from the last part of the run (the replay), s^2 from every residual: a few % apart; the side
    # towards which the drift check finds the estimate still moving reaches further (docs/intervals.md), the
    # other is the least-squares half-width
    np.testing.assert_allclose(np.minimum(below, above), half, rtol=0.08)
    assert np.all(np.maximum(below, above) >= 0.92 * half)
    # the residual checks on the replayed window (theta frozen), from the same streams: z(t) = y(t) - theta w(t-1)
    start = res.summary["health"]["criteria"]["window_start"]
    replayed = min(steps - start, 4000)
    first = start + replayed // 4
    t = np.arange(first, start + replayed)
    z = w[t - 1] @ (np.array(theta_true) - got_est) + v[t]
    yy = w[t - 1] @ np.array(theta_true) + v[t]
    r = res.run.residuals()
    assert r.steps == len(t)
    fit = 100 * (1 - np.linalg.norm(z) / np.linalg.norm(yy - yy.mean()))
    fit0 = 100 * (1 - np.linalg.norm(yy) / np.linalg.norm(yy - yy.mean()))          # theta0 = 0: y_hat = 0
    assert res.summary["metrics"]["fit_percent"] == pytest.approx(fit, abs=1e-6)
    assert res.summary["metrics"]["fit_percent_initial"] == pytest.approx(fit0, abs=1e-6)
    N, m = len(z), z.mean()
    auto = [(np.dot(z[lag:], z[:N - lag]) / (N - lag) - m * m) / (np.dot(z, z) / N - m * m) for lag in range(26)]
    np.testing.assert_allclose(r.autocorr[0, :, 0].numpy(), auto, atol=1e-9)
    q = N * (N + 2) * sum(auto[lag] ** 2 / (N - lag) for lag in range(1, 26))
    assert float(r.whiteness_p[0]) == pytest.approx(scipy.stats.chi2.sf(q, 25), rel=1e-6)
    assert float(r.whiteness_p[0]) > 0.01 and r.bound == pytest.approx(1.959964 / np.sqrt(N))
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["intervals"][names[0]]["level"] == 0.95
    assert summary["intervals"][names[0]]["lower"] < beta[0] < summary["intervals"][names[0]]["upper"]
    assert summary["health"]["determined"] is True and res.status == ["converged"]


def test_each_member_of_a_batch_has_the_intervals_of_its_batch_of_one_run(tmp_path):
    common = dict(steps=3000, overrides={"truth": "discrete", "noise": 0.05})
    batch = Run("sdof-stiffness", members=[{"seed": s} for s in (1, 2, 3)], out=tmp_path / "b", **common)
    batch.advance(progress=False)
    sb = batch.finish(figures=False)
    one = Run("sdof-stiffness", seed=2, out=tmp_path / "one", **common)
    one.advance(progress=False)
    so = one.finish(figures=False)
    for key in ("dK", "dC"):
        for side in ("lower", "upper"):
            assert sb["intervals"][key][side][1] == pytest.approx(so["intervals"][key][side], rel=1e-9, abs=1e-12)
    assert sb["health"]["determined"][1] == so["health"]["determined"]


def test_a_graph_built_in_python_gets_a_verdict_intervals_and_a_summary(tmp_path, capsys):
    Ts = 0.02
    known = rt.LTI.continuous(*rt.models.sdof_matrices(2.0, 0.3, 5.0, measured=["velocity"],
                                                       sees=["position", "velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=Ts, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3)
    g = rt.refinement(known, ident, truth=rt.Gain(torch.tensor([[1.0, -0.6]])), batch_size=2,
                      excitation=rt.WhiteNoise(1, seed=[3, 4]), noise=rt.WhiteNoise(1, std=0.002, seed=[5, 6]),
                      nu=20)
    estimates = {"dK": lambda g: -g.role("estimator").theta[:, 0, 0],
                 "dC": lambda g: -g.role("estimator").theta[:, 0, 1]}
    res = rt.refine(g, 8000, estimates, truth={"dK": -1.0, "dC": 0.6}, out=tmp_path / "mine",
                    requirements=[Requirement("estimates.dK", "abs_err", 0.05)])
    for key, truth in (("dK", -1.0), ("dC", 0.6)):
        # an interval about the estimate, or about the window's output-error optimum (which may lie to one side
        # of the estimate): within a few of its half-widths of the estimate either way
        half = (res.upper[key] - res.lower[key]) / 2
        assert bool((half > 0).all())
        assert bool(((res.estimates[key] - (res.lower[key] + half)).abs() <= 3 * half).all())
        assert float((res.estimates[key] - truth).abs().max()) < 0.05
    assert res.passed["estimates.dK"].tolist() == [True, True] and len(res.status) == 2
    assert bool(res.determined.all())
    summary = json.loads((tmp_path / "mine" / "summary.json").read_text())
    assert len(summary["intervals"]["dK"]["lower"]) == 2 and summary["health"]["determined"] == [True, True]
    assert summary["requirements"]["estimates.dK"]["member_pass"] == [True, True]
    # member 0's dC interval lies below its estimate (the optimum's): drawn as it is, not as error bars' sides
    assert float(res.upper["dC"][0]) < float(res.estimates["dC"][0])
    assert (tmp_path / "mine" / "estimates.png").is_file() and (tmp_path / "mine" / "checkpoint.pt").is_file()
    assert "±" in str(res) and "health:" in str(res)
    with pytest.raises(rt.ConfigError, match="already run"):
        rt.refine(g, 10)
    g2 = rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 2}), truth=rt.Gain(torch.tensor([[1.0, 0.0]])),
                       excitation=rt.WhiteNoise(1), nu=5)
    with pytest.raises(rt.ConfigError, match="not an estimate"):
        rt.refine(g2, 10, estimates, truth={"dX": 1.0})


def test_parameters_the_data_cannot_separate_are_undetermined_not_converged(tmp_path):
    """Two regressors that are the same signal: only their sum is determined, so the run must not be called
    converged; the same graph with distinct regressors is determined."""
    Ts = 0.02
    A, B, C, D = rt.models.sdof_matrices(1.0, 0.5, 2.0, measured=["velocity"], sees=["position", "position"])
    known = rt.LTI.continuous(A, B, C, D, inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=Ts, name="known")
    truth = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.5, 2.5, sees=[], actuation=False),
                              inputs=["w"], outputs=["y"], dt=Ts)
    g = rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3), physical=truth,
                      excitation=rt.WhiteNoise(1, seed=2), noise=rt.WhiteNoise(1, std=1e-3, seed=3), nu=30)
    res = rt.refine(g, 6000, out=tmp_path / "twin", figures=False)
    assert res.status == ["undetermined"] and not bool(res.determined.any())
    assert "converged" not in str(res).splitlines()[-1].replace("not_converged", "")
    assert res.summary["health"]["counts"]["undetermined"] == 1


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sdof-stiffness", "twodof-stiffness"])
def test_intervals_cover_the_truth_at_their_level_over_200_seeds(name, tmp_path):
    """A discrete truth and 5% measurement noise, 200 members with their own streams, the scenario's other
    defaults: the nominal 95% intervals hold the truth in 92-98% of members for each estimate."""
    run = Run(name, steps=20000, overrides={"truth": "discrete", "noise": 0.05},
              members=[{"seed": s} for s in range(1, 201)], out=tmp_path / "cov")
    run.advance(progress=False)
    s = run.finish(figures=False)
    for key in s["estimates"]:
        lo, hi = np.array(s["intervals"][key]["lower"]), np.array(s["intervals"][key]["upper"])
        truth = s["truth"][key]
        cover = np.mean((lo <= truth) & (truth <= hi))
        assert 0.92 <= cover <= 0.98, (key, cover)
    assert np.mean(s["health"]["determined"]) == 1.0


@pytest.mark.slow
def test_a_static_regression_under_lam_1_covers_at_its_level_over_200_seeds(tmp_path):
    """The least-squares case of the first test over 200 members with their own streams (lam = 1, the model
    exact): the drift check widens a side of some intervals, the nominal 95% intervals still hold the truth in
    92-98% of members for each parameter, and every member is converged."""
    theta_true, seeds = [0.7, -1.3, 0.2], list(range(1, 201))
    g = _regression_graph(theta_true, 0.1, seed=seeds)
    names = [f"theta[{n}]" for n in g.role("estimator").theta_names]
    res = rt.refine(g, 5000, out=tmp_path / "run", figures=False, validation=False, progress=False,
                    truth=dict(zip(names, theta_true)))
    assert res.status == ["converged"] * 200
    for name, truth in zip(names, theta_true):
        cover = float(((res.lower[name] <= truth) & (truth <= res.upper[name])).double().mean())
        assert 0.92 <= cover <= 0.98, (name, cover)


def test_a_graph_run_resumed_inside_its_window_gives_the_same_intervals_and_checks(tmp_path):
    """The state at the window's start travels in the checkpoint: a Python graph's run stopped inside the
    convergence window and resumed (with its scenario object) ends with the same intervals and residual checks."""
    from rcotorch.run.refine import GraphScenario

    def graph():
        known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.8, 0.6, sees=["position", "velocity"]),
                                  inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=0.01, name="known")
        return rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3),
                             truth=rt.Gain(torch.tensor([[-0.5, 0.0]])), excitation=rt.WhiteNoise(1, seed=[1, 2]),
                             noise=rt.WhiteNoise(1, std=0.004, seed=[3, 4]), nu=15, batch_size=2)

    full = Run(GraphScenario(graph(), name="mine"), steps=3000, batch=2, out=tmp_path / "full")
    full.advance(progress=False)
    part = Run(GraphScenario(graph(), name="mine"), steps=3000, batch=2, out=tmp_path / "part")
    part.advance(until=2700, progress=False)              # inside the window (it starts at 2400)
    assert part.snapshot is not None
    part.save()
    part.close()
    with pytest.raises(rt.errors.CheckpointError, match="not 'other'"):
        Run.resume(tmp_path / "part", scenario=GraphScenario(graph(), name="other"))
    resumed = Run.resume(tmp_path / "part", scenario=GraphScenario(graph(), name="mine"))
    resumed.advance(progress=False)
    a, b = full.summary(), resumed.summary()
    assert a["intervals"] == b["intervals"] and a["metrics"] == b["metrics"] and a["health"] == b["health"]


def test_residuals_that_are_not_white_are_said_beside_the_verdict(tmp_path):
    """A continuous truth without noise leaves z = the discretization's mismatch, a colored signal: the
    whiteness test fails and the verdict line says so; a discrete truth with white noise passes."""
    from rcotorch.run.report import result_table

    colored = Run("sdof-stiffness", steps=20000, out=tmp_path / "c")
    colored.advance(progress=False)
    sc = colored.finish(figures=False)
    assert sc["health"]["residuals_white"] is False and sc["metrics"]["z_whiteness_p"] < 1e-6
    assert "residuals not white" in result_table(sc).splitlines()[-1]
    white = Run("sdof-stiffness", steps=3000, overrides={"truth": "discrete", "noise": 0.05}, out=tmp_path / "w")
    white.advance(progress=False)
    sw = white.finish(figures=False)
    assert sw["health"]["residuals_white"] is True and "residuals not white" not in result_table(sw)


def test_a_window_too_short_for_a_lag_tests_no_whiteness_and_reports_no_correlation_above_one(tmp_path):
    """A 10-step run replays a window of 2 measured steps: its 25 lags had no pairs of steps, so the normalized
    correlations came out as large as 1e10, the whiteness test rejected at random and the scores' long-run
    covariance widened intervals 1e153 times. With fewer than 5 steps per lag the checks test no lag, say so, and
    widen nothing; a window of 60 steps tests 12 lags, each correlation within [-1, 1]."""
    from rcotorch.run.figure_data import residual_verdict, run_figure_data
    from rcotorch.run.figures import png, residual_figures
    from rcotorch.run.report import result_table

    short = Run("sdof-stiffness-damping", batch=64, steps=10, out=tmp_path / "s")
    short.advance(progress=False)
    s = short.finish(figures=False, close=False)
    res = short.residuals()
    assert res.steps < 5 and res.autocorr.shape[1] == 1 and bool(torch.isnan(res.whiteness_p).all())
    assert s["health"]["residuals_white"] == [None] * 64 and not any(s["health"]["residuals_matter"])
    assert all(w == 1.0 for w in s["health"]["residual_widening"])
    assert all(v is None for key in ("z_autocorr_max", "z_whiteness_p", "z_w_xcorr_max") for v in s["metrics"][key])
    assert "not white" not in result_table(s) and "not tested" in residual_verdict(short, res)
    fig = residual_figures(run_figure_data(short))["residuals"]
    assert all("not tested" in " ".join(t.get_text() for t in ax.texts) for ax in fig.axes)
    png(fig)
    short.close()
    from rcotorch.verdict import intervals as ci
    g, _ = _room(2, window_opens=False)
    g.advance(400)
    state = ci.snapshot(g)
    rep = ci.replay(g, state, 80, settle=20)
    assert rep.residuals.steps == 60 and rep.residuals.autocorr.shape[1] == 13
    assert float(rep.residuals.autocorr.abs().max()) <= 1.0 and bool(torch.isfinite(rep.residuals.whiteness_p).all())


def test_a_biased_refinement_is_not_called_converged(tmp_path):
    """Coulomb friction with many Markov parameters settles away from the truth (Fc = 2, c = 0.5, which the
    basis sign(v), v represents exactly): the residuals are not white, and the output error's Gauss-Newton step
    on the window points back towards the truth by more than the intervals' random error, so the intervals are
    widened by it (they hold the step's end and the truth, and so the bias it found: not flagged) and the member
    is undetermined, not converged."""
    run = Run("mass-friction", steps=20000, overrides={"nu": 1000}, out=tmp_path / "run", validation=False)
    run.advance(progress=False)
    s = run.finish(figures=False)
    est, found = s["estimates"], run.intervals()
    assert abs(est["c"] - 0.5) > 0.1 and abs(est["Fc"] - 2.0) > 0.1          # settled well away from the truth
    assert s["status"] == "undetermined" and s["health"]["biased"] is False
    assert s["health"]["residuals_white"] is False
    for key, truth in (("Fc", 2.0), ("c", 0.5)):
        move = float(found.offset[key][0])
        assert (truth - est[key]) * move > 0, key                            # the step points at the truth
        assert float(found.half_width[key][0]) >= abs(move)                  # the interval reaches its end
        assert s["intervals"][key]["lower"] <= truth <= s["intervals"][key]["upper"], key
    assert "undetermined: settled, but the data did not determine Fc, c" in health_line(s)


def test_the_replays_lagged_sums_in_chunks_equal_the_sums_written_out():
    """The replay sums its scores and residuals in chunks of steps: the lagged products G_lag = sum_t s(t)
    s(t - lag)^T and z(t) w(t - lag) equal the sums written out in NumPy, whatever the chunks, by FFT (PyTorch's
    path; the native residual_sums is checked against it in test_the_native_residual_sums_are_pytorchs)."""
    _lagged_sums_equal_the_sums_written_out()


def _lagged_sums_equal_the_sums_written_out():
    from rcotorch.verdict import intervals as ci
    rng = np.random.default_rng(7)
    T, B, n, L = 53, 3, 2, 5
    s = rng.standard_normal((T, B, n))
    want = np.zeros((L + 1, B, n, n))
    for lag in range(L + 1):
        for t in range(lag, T):
            want[lag] += np.einsum("bi,bj->bij", s[t], s[t - lag])
    # the Newey-West long-run covariance with Bartlett weights, written out
    bartlett = want[0] + sum((1 - lag / (L + 1)) * (want[lag] + want[lag].transpose(0, 2, 1))
                             for lag in range(1, L + 1))
    members = torch.tensor([True, False, True])
    for cuts in ([T], [1, 7, 20, T], [L - 1, L, T]):
        sums = ci._ScoreSums(B, n, L, "cpu")
        start = 0
        for end in cuts:
            sums.add(torch.as_tensor(s[start:end]))
            start = end
        got = sums.long_run(members).numpy()
        np.testing.assert_allclose(got[[0, 2]], bartlett[[0, 2]], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(got[1], want[0][1], rtol=1e-12, atol=1e-12)
    for cuts in ([T], [3, 4, 30, T]):                 # the residual checks' lagged sums, stretch by stretch
        acc = ci._LagSums(L, outer=True)
        start = 0
        for end in cuts:
            acc.add(torch.as_tensor(s[start:end]), torch.as_tensor(s[start:end]))
            start = end
        np.testing.assert_allclose(acc.sum.numpy(), want, rtol=1e-12, atol=1e-12)
    w = rng.standard_normal((T, B, 1))
    z = rng.standard_normal((T, B, 2))
    zw = ci._lag_sums(torch.as_tensor(z), torch.as_tensor(w), L, outer=True).numpy()
    zz = ci._lag_sums(torch.as_tensor(z), torch.as_tensor(z), L, outer=False).numpy()
    for lag in range(L + 1):
        np.testing.assert_allclose(zw[lag], np.einsum("tbi,tbj->bij", z[lag:], w[:T - lag]), rtol=1e-12)
        np.testing.assert_allclose(zz[lag], (z[lag:] * z[:T - lag]).sum(0), rtol=1e-12)


def _room(batch, window_opens=True):
    """A heated room (air 2e5 J/K, walls 5e6 J/K; 500 W/K between them, 150 W/K walls to outside, 40 W/K room to
    outside) whose loss to the outside grows by 20 W/K at 10 h (a window left open), the air temperature measured
    to 0.05 K every minute, a random heating of 1000 +- 800 W; identified by the gain on the air temperature,
    with the change detector and the restart. Its walls take two hours to warm: the loop's slowest mode."""
    import control
    Cr, Cw, Grw, Gwo, Gro = 2e5, 5e6, 500.0, 150.0, 40.0
    A = [[-(Grw + Gro) / Cr, Grw / Cr], [Grw / Cw, -(Grw + Gwo) / Cw]]
    G = control.ss(A, [[1 / Cr, 1 / Cr], [0, 0]], [[1, 0], [1, 0]], [[0, 0], [0, 0]])
    known = rt.LTI.from_control(G, inputs={"w": 1, "u": 1}, outputs={"y": 1, "y0": 1}, dt=60.0, name="room")
    det = rt.ChangeDetector(1, warmup=300, window=300, holdoff=300)
    g = rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 1}, p0=1e4), truth=rt.Gain([[0.0]], name="window"),
                      excitation=rt.WhiteNoise(1, std=800.0, mean=1000.0, seed=list(range(1, batch + 1))),
                      noise=rt.WhiteNoise(1, std=0.05, seed=list(range(100, 100 + batch))), nu=400,
                      batch_size=batch, blocks=[det], connections=[("error.out", "detector.z")])
    if window_opens:
        g.add_hook(rt.at_step(600, lambda gr: gr.blocks["window"].K.fill_(-20.0)))
    g.add_hook(rt.ResetOnChange(g, every=10, lam=0.995, hold=600, markov="closed-loop", markov_after=30))
    return g, G


def test_the_replay_settles_for_the_frozen_loops_slowest_mode_and_the_intervals_then_hold_the_truth(tmp_path,
                                                                                                   monkeypatch):
    """The room's intervals replay a 6 h window whose first quarter (1.5 h) is shorter than the walls' time: from
    the window's start, where the known model still carries the change's transient, the output error's step
    pointed away from the truth and every member was 'converged' with an interval missing it (0 of 32). The
    replay now settles for five time constants of the frozen loop's slowest mode (from numpy's eigenvalues of
    the loop closed at each member's estimate, ZOH-discretized by scipy) and runs on past the run's end."""
    import scipy.signal

    from rcotorch.run.end_checks import loop_settle
    g, G = _room(8)
    res = rt.refine(g, 1800, {"dG": lambda gr: -gr.role("estimator").theta[:, 0, 0]},
                    truth_history={"dG": [(0.0, 0.0), (36000.0, 20.0)]}, out=tmp_path / "room", progress=False,
                    figures=False, validation=False)
    theta = res.run.graph.role("estimator").theta[:, 0, 0].numpy()
    Ad, Bd, *_ = scipy.signal.cont2discrete((G.A, G.B, G.C, G.D), 60.0, method="zoh")
    need = [int(np.ceil(5 / -np.log(np.abs(np.linalg.eigvals(Ad + Bd[:, 1:] * t @ G.C[1:])).max()))) for t in theta]
    np.testing.assert_array_equal(loop_settle(res.run.graph).numpy(), need)
    assert min(need) > 0.25 * 360                         # longer than the window's first quarter
    lo, hi = res.lower["dG"].numpy(), res.upper["dG"].numpy()
    covered = (lo <= 20.0) & (20.0 <= hi)
    assert covered.mean() >= 0.75, (lo, hi, res.status)
    # settling for the window's first quarter alone, as before: the intervals miss the truth
    monkeypatch.setattr("rcotorch.run.runner.loop_settle", lambda graph: None)
    g, _ = _room(8)
    short = rt.refine(g, 1800, {"dG": lambda gr: -gr.role("estimator").theta[:, 0, 0]},
                      truth_history={"dG": [(0.0, 0.0), (36000.0, 20.0)]}, out=tmp_path / "short", progress=False,
                      figures=False, validation=False)
    assert ((short.lower["dG"] <= 20.0) & (20.0 <= short.upper["dG"])).double().mean() <= 0.25


def test_members_settling_for_different_times_replay_as_they_would_alone():
    """The replay's settling time one per member: each member's covariance, output-error step and residual
    checks are those of its replay alone with its own settling time (what a member finds does not depend on
    the batch)."""
    from rcotorch.verdict import intervals as ci
    g, _ = _room(2, window_opens=False)
    g.advance(400)
    state = ci.snapshot(g)
    g.advance(300)
    both = ci.replay(g, state, 500, torch.tensor([150, 320]))
    for b, settle in ((0, 150), (1, 320)):
        one, _ = _room(1, window_opens=False)
        one.blocks["excitation"].seed = torch.tensor([b + 1])
        one.blocks["noise"].seed = torch.tensor([100 + b])
        one.reset()
        one.advance(400)
        state1 = ci.snapshot(one)
        one.advance(300)
        alone = ci.replay(one, state1, 500 - 320 + settle, settle)
        for key in ("cov", "offset", "gain"):
            np.testing.assert_allclose(getattr(both.covariance, key)[b].numpy(),
                                       getattr(alone.covariance, key)[0].numpy(), rtol=1e-9, err_msg=key)
        np.testing.assert_allclose(both.residuals.whiteness_p[b].item(), alone.residuals.whiteness_p[0].item(),
                                   rtol=1e-9)
        np.testing.assert_allclose(both.residuals.fit[b].item(), alone.residuals.fit[0].item(), rtol=1e-9)


def test_recorded_data_that_end_before_the_loop_settles_are_replayed_as_far_as_they_reach_and_warn(tmp_path):
    """The room's measurements recorded for 30 h (window 6 h): the replay cannot run past them, settles for the
    window's first quarter alone, and the summary says how long the loop needed."""
    g, G = _room(1, window_opens=False)
    g.blocks["window"].K.fill_(-20.0)
    w = torch.zeros(1800, 1, 1, dtype=torch.float64)
    y = torch.zeros(1800, 1, 1, dtype=torch.float64)
    g.advance(1800, record={g.role_signal("exogenous"): w, g.role_signal("measured"): y})
    data = rt.Recorded(torch.cat([w[:, 0], y[:, 0]], 1).numpy(), {"w": 0, "y": 1}, dt=60.0, name="data")
    known = rt.LTI.from_control(G, inputs={"w": 1, "u": 1}, outputs={"y": 1, "y0": 1}, dt=60.0, name="room")
    graph = rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 1}, p0=1e4), data=data, nu=400)
    assert graph.max_steps == 1800
    res = rt.refine(graph, 1800, {"dG": lambda gr: -gr.role("estimator").theta[:, 0, 0]}, out=tmp_path / "rec",
                    progress=False, figures=False, validation=False)
    said = [x for x in res.summary["warnings"] if "replay settled for" in x]
    assert len(said) == 1 and "5400 s" in said[0] and "the recorded data end sooner" in said[0], said


@pytest.mark.parametrize("normalize", [None, 0.5])
def test_the_native_replay_sums_equal_pytorchs(normalize):
    """The replay's sums over each stretch taken by the native kernel (``kernels.window_sums``) equal PyTorch's
    (two measured outputs, a weight R, normalized regressors, members measuring from different steps, stretches
    of a few steps)."""
    from rcotorch.engine import kernels
    from rcotorch.verdict import intervals as ci
    Ts = 0.05
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.4, 4.0, measured=["position", "velocity"],
                                                       sees=["position", "velocity"]),
                              inputs=["w", "u"], outputs={"y": 2, "y0": 2}, dt=Ts, name="known")
    est = rt.RCOEstimator.static_gain({"y0": 2}, n_z=2, p0=1e3, normalize=normalize, R=[[1.0, 0.2], [0.2, 2.0]])
    g = rt.refinement(known, est, truth=rt.Gain(torch.tensor([[0.5, -0.2]])), excitation=rt.WhiteNoise(1, seed=3),
                      noise=rt.WhiteNoise(2, std=0.01, seed=4), nu=12)
    g.reset(3)
    g.advance(300)
    state = ci.snapshot(g)
    g.advance(300)
    settle = torch.tensor([40, 55, 61])
    import unittest.mock
    took = []
    summed = kernels.window_sums
    with unittest.mock.patch.object(ci, "STRETCH_BYTES", 8 * 3 * 2 * 2 * 7), \
            unittest.mock.patch.object(kernels, "window_sums", lambda *a: took.append(summed(*a)) or took[-1]):
        native = ci.replay(g, state, 300, settle)           # 7 steps a stretch
    assert len(took) == -(-(300 - 40) // 7) and all(took)              # the kernel took each stretch
    with unittest.mock.patch.object(ci, "STRETCH_BYTES", 8 * 3 * 2 * 2 * 7):
        with kernels.disabled():
            plain = ci.replay(g, state, 300, settle)
    for key in ("cov", "gain", "noise", "offset", "offset_cov", "unexplained", "widening"):
        a, b = getattr(native.covariance, key), getattr(plain.covariance, key)
        assert torch.isfinite(a).all(), key
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-8, atol=1e-12 * float(b.abs().max()), err_msg=key)
    np.testing.assert_allclose(native.residuals.whiteness_p.numpy(), plain.residuals.whiteness_p.numpy(), rtol=1e-8)


def _sdof_with_truth(gain):
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.4, 4.0, measured=["position"], sees=["position"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.05, name="known")
    est = rt.RCOEstimator.static_gain({"y0": 1}, p0=1e3)
    return rt.refinement(known, est, truth=rt.Gain(torch.tensor([[gain]])), excitation=rt.WhiteNoise(1, seed=3),
                         noise=rt.WhiteNoise(1, std=0.01, seed=4), nu=12)


@pytest.mark.parametrize("hooked", [False, True])
def test_the_replays_copies_stepped_in_one_graph_give_the_numbers_of_separate_copies(hooked):
    """The replay's copies (moved parameters, the initial theta, the physics at the estimates) stepped inside the
    base copy's graph, sharing its excitation, noise and measured system, give bit for bit the covariance,
    output-error step, bias and residual checks of copies stepped as separate graphs; that graph holds only the
    copies' model side (the estimator, the known model, the error), and a graph with a step hook keeps separate
    copies."""
    from unittest import mock

    from rcotorch.verdict import intervals as ci
    g = _sdof_with_truth(0.5)
    g.reset(3)
    if hooked:
        g.add_hook(lambda graph: None)
    g.advance(300)
    state = ci.snapshot(g)
    g.advance(300)
    physics = _sdof_with_truth(0.45)
    physics.reset(3)
    added = []
    extend = rt.Graph.extend
    with mock.patch.object(rt.Graph, "extend", lambda self, blocks, src: added.extend(b.name for b in blocks) or
                           extend(self, blocks, src)):
        joined = ci.replay(g, state, 300, physics=physics)
    with mock.patch.object(ci, "JOIN_COPIES", False):
        apart = ci.replay(g, state, 300, physics=physics)
    if hooked:
        assert added == []
    else:
        est, known, err = g.roles["estimator"], g.roles["known"], g.roles["error"].split(".")[0]
        assert sorted(added) == sorted([f"{b}__{c}" for c in ("moved0", "initial") for b in (est, known, err)]
                                       + [f"{b}__physical" for b in ci.physical_blocks(g)])
        assert len(ci.physical_blocks(g)) == 2               # the measured system and the truth in its feedback
    assert joined.covariance.sampling is not None
    for key in ("cov", "gain", "noise", "offset", "optimum_cov", "unexplained", "sampling"):
        assert torch.equal(getattr(joined.covariance, key), getattr(apart.covariance, key)), key
    for key in ("whiteness_p", "fit", "fit_initial", "autocorr"):
        assert torch.equal(getattr(joined.residuals, key), getattr(apart.residuals, key)), key


class _DoubleP:
    """A hook that changes the estimator's P (never theta) at every step and says so."""
    keeps_theta = True

    def __init__(self, name):
        self.acts_on = frozenset({name})

    def __call__(self, graph):
        graph.blocks[next(iter(self.acts_on))].P.mul_(2.0)


@pytest.mark.parametrize("case", ["truth", "truth-and-physics", "model", "theta"])
def test_the_replays_copies_join_a_graph_whose_hooks_say_what_they_change(case):
    """Step hooks that declare the blocks they change (``acts_on``; ``keeps_theta`` where they change an
    estimator's P but not its theta) let the copies step inside one graph where no copy needs its own copy of
    such a block: a change of the truth during the replay, and a hook on the estimator's P, give bit for bit the
    numbers of separate copies. Where a copy needs its own copy of a block a hook changes (the physics copy's
    truth, the known model) or a hook may change theta, the copies stay separate graphs."""
    from unittest import mock

    from rcotorch.verdict import intervals as ci
    g = _sdof_with_truth(0.5)
    g.reset(3)
    est = g.roles["estimator"]
    if case == "model":
        g.add_hook(rt.at_step(450, lambda gr: gr.blocks["known"].x.mul_(0.5), acts_on=["known"]))
    else:
        g.add_hook(rt.at_step(450, lambda gr: gr.blocks["unknown"].K.fill_(0.7), acts_on=["unknown"]))
    hook = g.add_hook(_DoubleP(est))
    if case == "theta":
        hook.keeps_theta = False
    g.advance(300)
    state = ci.snapshot(g)
    g.advance(300)
    physics = None
    if case == "truth-and-physics":
        physics = _sdof_with_truth(0.45)
        physics.reset(3)
    made = []
    init = ci._Copies.__init__
    with mock.patch.object(ci._Copies, "__init__", lambda self, *a: init(self, *a) or made.append(self)):
        joined = ci.replay(g, state, 300, physics=physics)
    assert made[0].joined == (case == "truth")
    with mock.patch.object(ci, "JOIN_COPIES", False):
        apart = ci.replay(g, state, 300, physics=physics)
    assert torch.isfinite(joined.covariance.cov).all()
    assert (joined.covariance.sampling is None) == (physics is None)
    for key in ("cov", "gain", "noise", "offset", "optimum_cov", "unexplained", "sampling"):
        a, b = getattr(joined.covariance, key), getattr(apart.covariance, key)
        assert (a is None and b is None) or torch.equal(a, b), key
    for key in ("whiteness_p", "fit", "fit_initial", "autocorr"):
        assert torch.equal(getattr(joined.residuals, key), getattr(apart.residuals, key)), key
    with pytest.raises(rt.ConfigError, match="acts_on must be a list of block names"):
        rt.at_step(5, print, acts_on="unknown")
    with pytest.raises(rt.ConfigError, match=r"at_step's acts_on names \['unknwn'\], which the graph does not have"):
        g.add_hook(rt.at_step(5, print, acts_on=["unknwn"]))             # a misspelt block would join wrongly


def test_a_graph_extended_with_blocks_keeps_its_state_and_refuses_a_taken_name_or_batch():
    """``Graph.extend`` adds blocks in their state (nothing reset) and names what it refuses: a name the graph
    holds, a block reset for another batch size, an input left unconnected."""
    g = _sdof_with_truth(0.5)
    g.reset(2)
    g.advance(50)
    x = g.blocks["known"].x.clone()
    extra = rt.Gain(torch.tensor([[2.0]]), name="twice")
    extra.reset(2)
    g.extend([extra], {("twice", "in"): g.role_signal("measured")})
    assert torch.equal(g.blocks["known"].x, x) and int(g.k) == 50
    g.advance(1)
    names, sources = list(g.blocks), dict(g.sources)
    assert torch.allclose(g.last[("twice", "out")], 2 * g.last[g.role_signal("measured")])
    taken = rt.Gain(torch.tensor([[1.0]]), name="known")
    taken.reset(2)
    with pytest.raises(rt.ConfigError, match="'known'.*taken"):
        g.extend([taken], {("known", "in"): g.role_signal("measured")})
    other = rt.Gain(torch.tensor([[1.0]]), name="other")
    other.reset(3)
    with pytest.raises(rt.ConfigError, match="'other' is reset for 3 members, the graph for 2"):
        g.extend([other], {("other", "in"): g.role_signal("measured")})
    loose = rt.Gain(torch.tensor([[1.0]]), name="loose")
    loose.reset(2)
    with pytest.raises(rt.PortError, match="'loose.in' is not connected"):
        g.extend([loose], {})
    assert list(g.blocks) == names and g.sources == sources           # a refused extension leaves the graph as it was


@pytest.mark.parametrize("lags", [0, 1, 6])
def test_the_native_replay_sums_take_the_scores_long_run_sums_as_pytorch_does(lags):
    """The native kernel's long-run sums of the scores (``_ScoreSums``: sum s s^T, the moving sums of L + 1 scores
    and the ring of the last L carried from stretch to stretch) equal PyTorch's over stretches of several lengths,
    members measuring from different steps, normalized regressors and two outputs."""
    from rcotorch.engine import kernels
    from rcotorch.verdict import intervals as ci
    gen = torch.Generator().manual_seed(7)
    B, nz, n, T, measured = 11, 2, 3, 40, 25
    own = torch.tensor([0, 3, 5, 9, 15, 0, 1, 2, 12, 7, 4])
    W = torch.tensor([[1.0, 0.3], [0.3, 2.0]], dtype=torch.float64)
    eps = torch.rand(B, n, generator=gen, dtype=torch.float64) + 0.5

    class Est:
        norm_inv_s2 = torch.tensor(0.7, dtype=torch.float64)

        def row_scale(self, psi):
            return torch.sqrt(1 + self.norm_inv_s2 * torch.einsum("kzi,zy,kyi->k", psi, W, psi))
    sums = {}
    for native in (True, False):
        ws = ci._WindowSums(B, n, nz, lags, W, eps, own, measured, "cpu")
        with contextlib.nullcontext() if native else kernels.disabled():
            g2 = torch.Generator().manual_seed(3)
            for t0, C in ((0, 7), (7, 1), (8, 13), (21, 19)):
                rec = {"z": torch.randn(C, B, nz, generator=g2, dtype=torch.float64),
                       "moved": torch.randn(C, B, nz, n, generator=g2, dtype=torch.float64),
                       "d": torch.randn(C, B, nz, generator=g2, dtype=torch.float64)}
                at = torch.arange(t0, t0 + C).reshape(-1, 1) - own.reshape(1, B)
                inside = ((at >= 0) & (at < measured)).to(torch.float64)      # each member's measured steps
                ws.add(torch.randn(C, B, nz, n, generator=g2, dtype=torch.float64), rec, t0, inside, Est())
        assert ws.upper == native and t0 + C == T
        sums[native] = ws.scores
    for key in ("gram", "moving", "ring"):
        np.testing.assert_allclose(getattr(sums[True], key).numpy(), getattr(sums[False], key).numpy(), rtol=1e-12,
                                   atol=1e-12, err_msg=key)
    everyone = torch.ones(B, dtype=torch.bool)
    np.testing.assert_allclose(sums[True].long_run(everyone).numpy(), sums[False].long_run(everyone).numpy(),
                               rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("lags, w_on", [(0, True), (1, False), (6, True)])
def test_the_native_residual_sums_are_pytorchs(lags, w_on):
    """The native kernel's residual sums (``kernels.residual_sums``: z's and z-w's lagged sums with their rings
    carried from stretch to stretch, the plain sums of the fit) give the residual checks PyTorch's give, over
    stretches shorter and longer than the lags, members measuring from different steps, two channels of z and y
    and a batch that is not a multiple of the kernel's block of members."""
    from rcotorch.engine import kernels
    from rcotorch.verdict import intervals as ci
    B, nz, nw, T, measured = 67, 2, 2, 40, 25
    own = torch.randint(0, T - measured + 1, (B,), generator=torch.Generator().manual_seed(5))
    out, took = {}, []
    for native in (True, False):
        rs = ci._ResidualSums(B, lags, 3, measured, own, w_on, "cpu")
        with contextlib.nullcontext() if native else kernels.disabled():
            g = torch.Generator().manual_seed(3)
            for t0, C in ((0, 3), (3, 1), (4, 13), (17, 23)):
                rec = {k: torch.randn(C, B, nz, generator=g, dtype=torch.float64) for k in ("z", "y", "initial")}
                rec["w"] = torch.randn(C, B, nw, generator=g, dtype=torch.float64) if w_on else None
                at = torch.arange(t0, t0 + C).reshape(-1, 1) - own.reshape(1, B)
                rs.add(t0, rec, ((at >= 0) & (at < measured)).to(torch.float64))
            took.append(rs.native is not None)
            out[native] = rs.result()
    assert took == [True, False]
    a, b = out[True], out[False]
    for key in ("autocorr", "whiteness_p", "fit", "fit_initial") + (("xcorr",) if w_on else ()):
        x, y = getattr(a, key), getattr(b, key)
        assert torch.isfinite(y).all() or (lags == 0 and key in ("whiteness_p", "xcorr")), key    # 0: untested
        np.testing.assert_allclose(x.numpy(), y.numpy(), rtol=1e-10, atol=1e-12, err_msg=key)
    for name in b.series:
        assert torch.equal(a.series[name], b.series[name]), name


def test_the_replays_copies_join_a_graph_that_already_has_their_names():
    """A graph whose blocks already carry the names the replay gives its copies' blocks ('<name>__moved0') still
    has its copies joined, under names of their own, with the numbers of separate copies."""
    from unittest import mock

    from rcotorch.verdict import intervals as ci
    g = _sdof_with_truth(0.5)
    extra = rt.Gain(torch.tensor([[1.0]]), name=f"{g.roles['estimator']}__moved0")
    g = rt.Graph(list(g.blocks.values()) + [extra],
                 [(f"{s[0]}.{s[1]}", f"{d[0]}.{d[1]}") for d, s in g.sources.items()]
                 + [(".".join(g.role_signal("measured")), f"{extra.name}.in")], roles=g.roles)
    g.reset(2)
    g.advance(200)
    state = ci.snapshot(g)
    g.advance(200)
    added = []
    extend = rt.Graph.extend
    with mock.patch.object(rt.Graph, "extend", lambda self, blocks, src: added.extend(b.name for b in blocks) or
                           extend(self, blocks, src)):
        joined = ci.replay(g, state, 200)
    assert f"{g.roles['estimator']}___moved0" in added and f"{g.roles['estimator']}__moved1" not in added
    with mock.patch.object(ci, "JOIN_COPIES", False):
        apart = ci.replay(g, state, 200)
    for key in ("cov", "gain", "offset"):
        assert torch.equal(getattr(joined.covariance, key), getattr(apart.covariance, key)), key


def test_the_joint_test_of_the_estimate_against_the_output_errors_optimum_is_hausmans():
    """optimum_test: d^T S^+ d against the chi-squared distribution with n degrees of freedom (scipy), per member;
    NaN where the step is not known; a run without the step has no test."""
    from rcotorch.verdict.intervals import ParameterCovariance, optimum_test
    rng = np.random.default_rng(3)
    B, n = 5, 3
    d = torch.tensor(rng.normal(size=(B, n)))
    L = torch.tensor(rng.normal(size=(B, n, n)))
    S = L @ L.mT + 0.1 * torch.eye(n, dtype=torch.float64)
    d[4] = math.nan
    eye = torch.eye(n, dtype=torch.float64).expand(B, n, n)
    pc = ParameterCovariance(cov=eye, gain=eye, noise=eye[:, :1, :1], settles=torch.ones(B, dtype=torch.bool),
                             replayed=100, measured=75, offset=d, offset_cov=S)
    p = optimum_test(pc)
    for b in range(4):
        stat = float(d[b].numpy() @ np.linalg.solve(S[b].numpy(), d[b].numpy()))
        assert float(p[b]) == pytest.approx(scipy.stats.chi2.sf(stat, n), rel=1e-10)
    assert math.isnan(float(p[4]))
    assert optimum_test(ParameterCovariance(cov=eye, gain=eye, noise=eye[:, :1, :1],
                                            settles=torch.ones(B, dtype=torch.bool), replayed=100,
                                            measured=75)) is None
