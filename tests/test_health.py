"""Member health: converged / not_converged / diverged with step and reason, each fault reproduced in a member
of a batch whose other members must stay bitwise as in a run without the fault."""

import math

import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch import ConfigError
from rcotorch.run import scenario as scenarios
from rcotorch.run.runner import Run
from rcotorch.verdict.health import STATUSES, Criteria, Health, Reason, check_every


def _clean_theta(tmp_path, name, **kw):
    run = Run(name, out=tmp_path / "clean", **kw)
    run.advance(progress=False)
    run.close()
    return run.graph.role("estimator").theta.clone()


@pytest.mark.parametrize("engine", ["native", "torch"])
def test_theta_runaway_is_frozen_with_finite_state_and_the_others_untouched(tmp_path, monkeypatch, engine):
    monkeypatch.setenv("RCOTORCH_ENGINE", engine)
    kw = dict(steps=4000, batch=3, overrides={"truth": "discrete"})     # exact: the others are converged
    run = Run("sdof-stiffness", out=tmp_path / "run", **kw)
    every = check_every(4000)
    run.advance(until=1920 - 1, progress=False)
    est = run.graph.role("estimator")
    theta = est.theta.clone()
    theta[1] = 1e8                                   # member 1's estimate runs away (one step before a check)
    est.set_state(theta=theta)
    run.advance(progress=False)
    summary = run.finish(figures=False)
    # Before the convergence window (from step 3200) the checks are 2 * every apart: 1920 = 12 * 160 is one.
    assert every == 80 and run.health.window_start == 3200 and run.health.is_check(1920)
    assert summary["diverged"] == [{"member": 1, "step": 1920, "reason": "theta_runaway"}]
    status = summary["health"]["status"]               # the others as in a run without the runaway
    assert status[1] == "diverged" and status[0] != "diverged" and status[2] != "diverged"
    assert summary["health"]["diverged_at"] == [None, 1920, None]
    assert est.alive.tolist() == [True, False, True]
    assert torch.isfinite(est.theta).all() and torch.isfinite(est.P).all()
    assert torch.equal(est.theta[[0, 2]], _clean_theta(tmp_path, "sdof-stiffness", **kw)[[0, 2]])


def test_a_model_that_blows_up_is_a_u_runaway(tmp_path):
    """Member 0's simulated model jumps far beyond the data while its theta is held in place (a tiny P): u,
    not theta, leaves the data's scale."""
    run = Run("sdof-stiffness", steps=1000, batch=2, out=tmp_path)
    run.advance(until=400 - 1, progress=False)
    known, est = run.graph.role("known"), run.graph.role("estimator")
    x, P = known.x.clone(), est.P.clone()
    x[0] = 1e9
    P[0] = 1e-12 * torch.eye(2, dtype=P.dtype)
    known.set_state(x=x)
    est.set_state(P=P)
    run.advance(progress=False)
    summary = run.finish(figures=False)
    assert summary["diverged"] == [{"member": 0, "step": 400, "reason": "u_runaway"}]


def test_p_not_positive_definite_is_reported(tmp_path):
    run = Run("sdof-stiffness", steps=600, batch=2, out=tmp_path)
    run.advance(until=288 - 1, progress=False)
    est = run.graph.role("estimator")
    P = est.P.clone()
    P[1] = -torch.eye(2, dtype=P.dtype)               # member 1's covariance loses definiteness (S stays > 0)
    est.set_state(P=P)
    run.advance(progress=False)
    summary = run.finish(figures=False)
    assert summary["diverged"] == [{"member": 1, "step": 288, "reason": "not_positive_definite"}]   # 24 x 12


def test_covariance_windup_without_excitation_matches_the_closed_form(tmp_path):
    """lambda = 0.995 and no excitation: P = p0 lambda^-k I exactly grows, until trace(P) > 1e6 n p0 at
    k > ln(1e6) / -ln(lambda) = 2756.3; the member is frozen at the first check after that (before the
    convergence window, which starts at step 4000, checks are 2 * every = 200 steps apart), P finite."""
    lam, p0, steps = 0.995, 1e3, 5000
    run = Run("sdof-stiffness", steps=steps, out=tmp_path, members=[{"w_std": 0.0}, {"w_std": 1.0}],
              overrides={"lam": lam, "p0": p0, "truth": "discrete"})
    run.advance(progress=False)
    summary = run.finish(figures=False)
    every = check_every(steps)
    k_windup = 2 * every * math.ceil(math.log(1e6) / -math.log(lam) / (2 * every))
    assert k_windup == 2800 < run.health.window_start == 4000
    assert summary["diverged"] == [{"member": 0, "step": k_windup, "reason": "covariance_windup"}]
    P = run.graph.role("estimator").P[0]
    np.testing.assert_allclose(P.numpy(), p0 * lam ** -k_windup * np.eye(2), rtol=1e-9)
    assert summary["health"]["status"][1] in ("converged", "not_converged")


@pytest.mark.parametrize("steps, every, start", [(2000, 40, 1600), (4000, 80, 3200), (202, 4, 164),
                                                 (100_000, 2000, 80_000), (2_000_000, 40_000, 1_600_000)])
def test_checks_are_every_second_step_of_the_cadence_before_the_window_and_every_one_in_it(tmp_path, steps,
                                                                                         every, start):
    """The checks of a run: 2% of the run apart (at most 50,000 steps) from the convergence window's start on
    (the last fifth of the run, from a multiple of that), twice that apart before it; each one stops the engine
    once, and the logs (here every 2 * every steps, and at its halves before the first) fall on check steps."""
    run = Run("sdof-stiffness", steps=steps, out=tmp_path, log_every=2 * every)
    assert (check_every(steps), run.health.window_start) == (every, start)
    expected = list(range(2 * every, start, 2 * every)) + list(range(start, steps + 1, every))
    assert [k for k in range(1, steps + 1) if run.health.is_check(k)] == expected
    if steps > 10_000:
        return
    checked, stops = [], []
    check, advance = run.health.check, run.graph.advance
    run.health.check = lambda *a: (checked.append(int(run.graph.k)), check(*a))[1]
    run.graph.advance = lambda n, **kw: (advance(n, **kw), stops.append(int(run.graph.k)))[0]
    run.advance(progress=False)
    logs = set(range(0, steps + 1, 2 * every)[1:]) | ({(2 * every) >> j for j in range(1, 5)} - {0})
    assert checked == expected and stops == sorted(set(expected) | logs | {steps})
    run.close()


def test_no_excitation_with_lambda_one_is_not_converged(tmp_path):
    """Nothing to learn from (y = 0): not converged, z_ratio undefined (NaN, reported as null)."""
    run = Run("sdof-stiffness", steps=500, out=tmp_path, overrides={"w_std": 0.0})
    run.advance(progress=False)
    summary = run.finish(figures=False)
    assert summary["health"]["status"] == "not_converged" and summary["health"]["z_ratio"] is None


def _recorded_verdict(run: Run, steps: int, start: int) -> tuple[np.ndarray, np.ndarray]:
    """z_ratio and theta_change of the window from ``start`` to ``steps``, from signals recorded at every step of
    a separate stepping of the run's members: rms(z) / rms(y) over the window, and the rms of
    (theta_end - theta_start) phi over the window's regressors over the larger rms of theta_end phi and
    theta_start phi (or 1e-3 of the data's scale of u, rms(y) / |beta|, for a theta near zero)."""
    g = scenarios.get(run.scenario.name).build(run.settings, run.batch, torch.float64, "cpu")
    est = g.role("estimator")
    z_sig, y_sig = g.role_signal("error"), g.role_signal("measured")
    z2, y2, y2_all, phis = 0.0, 0.0, 0.0, []
    for k in range(steps):
        if k == start:
            theta_start = est.theta.clone()
        out = g.step()
        y2_all = y2_all + (out[y_sig] ** 2).sum(1)
        if k >= start:
            z2 = z2 + (out[z_sig] ** 2).sum(1)
            y2 = y2 + (out[y_sig] ** 2).sum(1)
            phis.append(est.phi_now.clone())
    phi = torch.stack(phis)                                                  # (T, B, n_phi)
    theta_end = est.theta

    def rms(theta):
        return torch.sqrt((torch.einsum("bui,tbi->tbu", theta, phi) ** 2).sum(-1).mean(0))
    u_scale = torch.sqrt(y2_all / steps) / est.beta.flatten(1).norm(dim=1)
    change = rms(theta_end - theta_start) / torch.maximum(torch.maximum(rms(theta_end), rms(theta_start)),
                                                          1e-3 * u_scale)
    return torch.sqrt(z2 / y2).numpy(), change.numpy()


def test_statuses_and_their_numbers_against_recorded_signals(tmp_path):
    """A well-tuned member converges, one with a tiny p0 (slow adaptation: z stays large) does not.

    z_ratio and theta_change agree with the values from signals recorded at every step (``_recorded_verdict``);
    with checks 40 steps apart and 16 regressors kept by the estimator, theta's change is measured on
    regressors sampled at the checks, so it agrees to sampling error (member 1's theta stays near zero, so its
    change is measured against the data's scale of u)."""
    steps = 2000
    run = Run("sdof-stiffness", steps=steps, out=tmp_path, members=[{"p0": 1e6}, {"p0": 1e-5}],
              overrides={"truth": "discrete"})
    run.advance(progress=False)
    verdict = run.summary()["health"]
    run.close()
    assert verdict["status"] == ["converged", "not_converged"]
    start = verdict["criteria"]["window_start"]
    assert start == steps - steps // 5
    z_ratio, change = _recorded_verdict(run, steps, start)
    np.testing.assert_allclose(verdict["z_ratio"], z_ratio, rtol=1e-9)
    np.testing.assert_allclose(verdict["theta_change"], change, rtol=0.25)
    c = Criteria()
    assert verdict["theta_change"][0] < c.theta_tol and verdict["z_ratio"][0] < c.z_tol < verdict["z_ratio"][1]


def test_theta_change_counts_each_regressor_of_the_window_once(tmp_path):
    """Checks closer than the estimator's window (a check every 4 steps, 16 regressors kept, as in any run whose
    nu exceeds 2% of its steps): each check adds the regressors of the steps since the last one, so every
    regressor of the convergence window enters theta's change once and none from before it, and the steps
    after the last check enter the verdict too. theta_change then equals the value from recorded signals to
    rounding (adding the estimator's whole window at every check counted most regressors four times and reached
    12 steps before the window)."""
    steps = 202                                   # the last check is at step 200: two steps after it
    run = Run("sdof-stiffness", steps=steps, out=tmp_path, members=[{"p0": 1e6}, {"p0": 1e-5}])
    run.advance(progress=False)
    verdict = run.summary()["health"]
    run.close()
    every = check_every(steps)
    assert every == 4 < run.graph.role("estimator").window == 16 and steps % every == 2
    z_ratio, change = _recorded_verdict(run, steps, verdict["criteria"]["window_start"])
    np.testing.assert_allclose(verdict["z_ratio"], z_ratio, rtol=1e-9)
    np.testing.assert_allclose(verdict["theta_change"], change, rtol=1e-9)


def test_an_estimator_that_reports_its_own_reason_is_read(sdof_known):
    """The estimator's step may record why it froze a member (``diverged_reason``): health reads it."""

    class Reporting(rt.RCOEstimator):
        def reset(self, batch_size):
            super().reset(batch_size)
            self.register_buffer("diverged_reason", torch.zeros(batch_size, dtype=torch.int64))

    ident = Reporting.static_gain({"y0": 1}, p0=1e3)
    g = rt.refinement(sdof_known(), ident, truth=rt.Gain([[-0.5]]), excitation=rt.WhiteNoise(1, seed=2), nu=5,
                      batch_size=2)
    health = Health(g, 100)
    g.run(50)
    ident.alive[1] = False
    ident.diverged_at[1] = 42
    ident.diverged_reason[1] = int(Reason.U_RUNAWAY)
    verdict = health.status(torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), 0)
    assert verdict["reason"].tolist() == [0, int(Reason.U_RUNAWAY)]
    assert STATUSES[int(verdict["status"][1])] == "diverged" and int(verdict["diverged_at"][1]) == 42


@pytest.mark.parametrize("bad", [dict(theta_tol=float("nan")), dict(z_tol=-1.0), dict(window=1.5),
                                 dict(runaway=1.0), dict(windup=float("inf"))])
def test_criteria_are_checked(bad):
    with pytest.raises(ConfigError, match="health criteria"):
        Criteria(**bad)


@pytest.mark.slow
def test_a_million_steps_with_forgetting_and_weak_excitation_end_classified_and_finite(tmp_path):
    """1e6 steps, lambda = 0.995: members with ordinary, weak, very weak and no excitation. P would overflow
    without the windup check; every member ends classified and finite."""
    run = Run("sdof-stiffness", steps=1_000_000, out=tmp_path, overrides={"lam": 0.995, "truth": "discrete"},
              members=[{"w_std": w} for w in (1.0, 1e-3, 1e-6, 0.0)])
    run.advance(progress=False)
    summary = run.finish(figures=False)
    est = run.graph.role("estimator")
    for t in (est.theta, est.P, est.u_now):
        assert torch.isfinite(t).all()
    h = summary["health"]
    assert all(s in STATUSES for s in h["status"])
    assert h["status"][0] == "converged"
    assert h["status"][3] == "diverged" and h["reason"][3] == "covariance_windup"
    assert h["status"][2] == "diverged" and h["reason"][2] == "covariance_windup"
    # frozen at the first check past the bound: checks are 2 * check_every apart before the convergence window
    assert float(est.P[3].diagonal().max()) < 1e6 * 1e3 * 2 * (1 / 0.995) ** (2 * check_every(1_000_000))


def test_the_bounds_kernel_gives_each_reason_as_the_pytorch_checks_do():
    """One member per case, with its reason worked out by hand: the compiled checks and the PyTorch ones (the
    reference, run with the kernels disabled) give the same codes, precedence included."""
    from rcotorch.engine import kernels
    sc = scenarios.get("sdof-stiffness")
    g = sc.build(sc.resolve(), 9, torch.float64, "cpu")
    health = Health(g, 1000)
    est = health.est
    n = est.n_theta
    eye = torch.eye(n, dtype=torch.float64)
    P = torch.stack([eye] * 9)
    P[1] = -eye                                              # not positive definite
    P[2, 0, 1] = P[2, 1, 0] = 2.0                            # symmetric, indefinite (det 1 - 4 < 0)
    P[3, 0, 0] = math.nan                                    # not finite
    P[4] = 1e7 * float(est.p0.reshape(-1)[0]) * eye          # trace beyond windup * n * p0
    P[5, 1, 1] = math.inf                                    # overflowed: windup takes precedence
    theta = torch.zeros_like(est.theta)
    theta[6, 0, 0] = 1e9                                     # theta runaway
    u_now = torch.zeros_like(est.u_now)
    u_now[7] = -1e9                                          # u runaway
    theta[8, 0, 0], P[8] = 1e9, -eye                         # theta runaway over not positive definite
    alive = torch.ones(9, dtype=torch.bool)
    est.set_state(P=P, theta=theta, u_now=u_now, alive=alive)
    s = health.state
    s["y_all"].fill_(1.0)
    s["n_all"], s["samples"] = 1, 1
    s["phi_sq"].fill_(1.0)
    windup_p = health.criteria.windup * n * float(est.p0.reshape(-1)[0])
    assert float(P[4].trace()) > windup_p > float(P[0].trace())
    R = Reason
    expected = [0, R.NOT_POSITIVE_DEFINITE, R.NOT_POSITIVE_DEFINITE, R.NOT_POSITIVE_DEFINITE,
                R.COVARIANCE_WINDUP, R.COVARIANCE_WINDUP, R.THETA_RUNAWAY, R.U_RUNAWAY, R.THETA_RUNAWAY]
    assert kernels.available()
    fast = health._bounds_exceeded()
    with kernels.disabled():
        reference = health._bounds_exceeded()
    assert reference.tolist() == [int(r) for r in expected]
    assert fast.tolist() == reference.tolist()
    est.set_state(alive=torch.zeros(9, dtype=torch.bool))    # frozen members are not checked again
    assert health._bounds_exceeded().tolist() == [0] * 9


def test_the_window_gram_kernel_sums_the_regressors_outer_products():
    """sum_w x x^T over the rows of a (W, B, m) window, x the first n entries, against numpy."""
    from rcotorch.engine import kernels
    rng = np.random.default_rng(3)
    win = torch.from_numpy(rng.standard_normal((7, 300, 5)))
    gram = kernels.window_gram(win, 3)
    x = win.numpy()[:, :, :3]
    expected = np.stack([x[:, b].T @ x[:, b] for b in range(300)])
    np.testing.assert_allclose(gram.numpy(), expected, rtol=1e-13, atol=1e-13)
    with kernels.disabled():
        assert kernels.window_gram(win, 3) is None            # the caller's PyTorch path takes over
