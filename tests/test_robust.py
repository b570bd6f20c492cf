"""Robustness options of the estimator against closed-form minimizers of their stated costs, and the faults
they address reproduced (covariance windup; gaps in inputs)."""

import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch.wiring import holdoff_samples

BETA = 0.7


def _drive(steps=40, lam=0.98, p0=10.0, seed=0, **options):
    """A static gain on two regressors, beta_1 = BETA, driven by random y0 and z; returns the estimator and per
    step Psi_j (2,), zeta_j and theta(j) (before the update)."""
    rng = np.random.default_rng(seed)
    est = rt.RCOEstimator.static_gain({"y0": 2}, p0=p0, lam=lam, markov=[[[BETA]]], first_delay=1, **options)
    est.reset(1)
    phi_prev, u_prev, rows = np.zeros(2), 0.0, []
    for _ in range(steps):
        y0 = torch.tensor(rng.normal(size=(1, 2)) * 3.0)
        z = torch.tensor(rng.normal(size=(1, 1)))
        theta = est.theta[0, 0].numpy().copy()
        u = float(est.output("u", {"y0": y0})[0, 0])
        rows.append((BETA * phi_prev, float(z[0, 0]) - BETA * u_prev, theta))
        est.update({"y0": y0, "z": z})
        phi_prev, u_prev = y0[0].numpy(), u
    return est, rows


def _minimize(rows, lam, p0, weight=lambda psi: 1.0, r_delta=0.0):
    """argmin lam^K |t|^2 / p0 + sum_j lam^(K-1-j) (weight_j (psi_j t + zeta_j)^2 + r_delta |t - theta_j|^2)."""
    K = len(rows)
    H, g = lam ** K / p0 * np.eye(2), np.zeros(2)
    for j, (psi, zeta, theta) in enumerate(rows):
        f = lam ** (K - 1 - j)
        H += f * (weight(psi) * np.outer(psi, psi) + r_delta * np.eye(2))
        g += f * (-weight(psi) * psi * zeta + r_delta * theta)
    return np.linalg.solve(H, g)


@pytest.mark.parametrize("r_delta", [0.0, 0.3, 5.0])
def test_penalty_on_theta_change_minimizes_its_cost(r_delta):
    est, rows = _drive(r_delta=r_delta)
    expected = _minimize(rows, 0.98, 10.0, r_delta=r_delta)
    np.testing.assert_allclose(est.theta[0, 0].numpy(), expected, rtol=1e-9, atol=1e-12)


def test_penalty_slows_the_estimate():
    free, _ = _drive()
    held, _ = _drive(r_delta=50.0)
    assert float(held.theta.abs().max()) < 0.5 * float(free.theta.abs().max())


@pytest.mark.parametrize("s", [0.5, 3.0, 100.0])
def test_normalized_regressors_minimize_the_weighted_cost(s):
    est, rows = _drive(normalize=s)
    expected = _minimize(rows, 0.98, 10.0, weight=lambda psi: 1.0 / (1.0 + psi @ psi / s**2))
    np.testing.assert_allclose(est.theta[0, 0].numpy(), expected, rtol=1e-9, atol=1e-12)


def test_normalized_regressors_measure_psi_in_the_cost_weight():
    """Two z channels in units 1000x apart, weighed back by R: the normalization measures Psi as the cost does,
    |Psi|_R^2 = sum_p Psi_p^T R Psi_p, so the large channel's units do not shrink every step (with the plain
    Frobenius norm, its rows would set m alone)."""
    beta, R, s, lam, p0 = np.array([0.7, 700.0]), np.diag([1.0, 1e-6]), 2.0, 0.98, 10.0
    rng = np.random.default_rng(4)
    est = rt.RCOEstimator.static_gain({"y0": 2}, n_z=2, R=R.tolist(), p0=p0, lam=lam,
                                      markov=[[[beta[0]], [beta[1]]]], first_delay=1, normalize=s)
    est.reset(1)
    phi_prev, u_prev, rows = np.zeros(2), 0.0, []
    for _ in range(40):
        y0 = torch.tensor(rng.normal(size=(1, 2)) * 3.0)
        z = torch.tensor(rng.normal(size=(1, 2)) * [1.0, 1000.0])
        u = float(est.output("u", {"y0": y0})[0, 0])
        rows.append((np.outer(phi_prev, beta), z[0].numpy() - beta * u_prev))      # Psi (2 params, 2 z), zeta
        est.update({"y0": y0, "z": z})
        phi_prev, u_prev = y0[0].numpy(), u
    K = len(rows)
    H, g = lam ** K / p0 * np.eye(2), np.zeros(2)
    for j, (psi, zeta) in enumerate(rows):
        w = lam ** (K - 1 - j) / (1.0 + np.trace(psi @ R @ psi.T) / s**2)
        H += w * psi @ R @ psi.T
        g -= w * psi @ R @ zeta
    np.testing.assert_allclose(est.theta[0, 0].numpy(), np.linalg.solve(H, g), rtol=1e-9, atol=1e-12)


def _windup(steps, **options):
    est = rt.RCOEstimator.static_gain({"y0": 2}, p0=1.0, lam=0.9, markov=[[[BETA]]], first_delay=1, **options)
    est.reset(2)
    zero = {"y0": torch.zeros(2, 2), "z": torch.zeros(2, 1)}
    traces = []
    for _ in range(steps):
        est.output("u", zero)
        est.update(zero)
        traces.append(est.P.diagonal(dim1=1, dim2=2).sum(-1).clone())
    return est, torch.stack(traces)


def test_trace_bound_stops_covariance_windup():
    # The fault: lam < 1 and no excitation, P grows as P / lam^k until it overflows and the member dies.
    est, traces = _windup(7000)
    assert float(traces[6000].max()) > 1e250
    assert not bool(est.alive.any())
    # With the bound (one per member): trace(P) stays at or below it, members alive, theta and P finite.
    est, traces = _windup(7000, p_max=[10.0, 1e4])
    assert bool((traces <= torch.tensor([10.0, 1e4]) * (1 + 1e-12)).all())
    assert float(traces[-1, 0]) == pytest.approx(10.0) and float(traces[-1, 1]) == pytest.approx(1e4)
    assert bool(est.alive.all()) and bool(torch.isfinite(est.P).all() & torch.isfinite(est.theta).all())


def test_trace_bound_keeps_the_direction_of_P():
    est, _ = _windup(200, p_max=6.0)
    np.testing.assert_allclose(est.P[0].numpy(), 3.0 * np.eye(2), rtol=1e-12)


@pytest.mark.parametrize("key, value", [("r_delta", -1.0), ("normalize", 0.0), ("p_max", float("nan")),
                                        ("p_max", -2.0), ("normalize", float("inf"))])
def test_bad_option_values_are_refused(key, value):
    with pytest.raises(rt.errors.ConfigError, match=key):
        rt.RCOEstimator.static_gain({"y0": 1}, **{key: value})


def _sdof_data(gap: slice, steps=20000):
    """sdof-stiffness (K=0.6, C=0.8, dK=0.5) as a recording of w and the measured velocity, w missing at ``gap``."""
    m, C, K, dK, Ts = 1.0, 0.8, 0.6, 0.5, 0.01
    known = rt.LTI.continuous(*rt.models.sdof_matrices(m, C, K, sees=["position", "velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=Ts, name="known")
    plant = rt.LTI.continuous(*rt.models.sdof_matrices(m, C, K + dK, sees=[], actuation=False),
                              inputs=["w"], outputs=["y"], dt=Ts, name="plant")
    A, B, Cm, D = (t[0].numpy() for t in (plant.A, plant.B, plant.C, plant.D))
    w = np.random.default_rng(1).normal(size=steps)
    x, y = np.zeros(A.shape[0]), np.empty(steps)
    for k in range(steps):
        y[k] = Cm[0] @ x + D[0, 0] * w[k]
        x = A @ x + B[:, 0] * w[k]
    values = np.stack([w, y], 1)
    valid = np.ones_like(values, dtype=bool)
    values[gap, 0], valid[gap, 0] = np.nan, False
    rec = rt.Recording(values, ["w", "y"], Ts, valid=valid)
    return known, rec


def test_missing_inputs_do_not_bias_sdof_stiffness():
    known, rec = _sdof_data(slice(8000, 8010))

    def dk(**kw):
        g = rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3), nu=15,
                          data=rt.Recorded(rec, {"w": "w", "y": "y"}), **kw)
        g.advance(rec.values.shape[0])
        return -float(g.role("estimator").dc_gain()[0, 0, 0]), g

    biased, _ = dk(input_holdoff=0)          # the fault: theta held at the gap only, the model runs on
    held, g = dk()                           # the hold-off derived from the known model
    assert abs(biased - 0.5) > 5 * abs(held - 0.5) and abs(biased - 0.5) > 3e-3
    assert abs(held - 0.5) < 0.01
    # the hold-off: the known model's w -> y response (envelope exp(-0.4 t)) below 1e-3 of its peak, plus the window
    n = g.blocks["data"].holdoff["w"]
    assert n == holdoff_samples(known, g.role("estimator"))
    assert 0.75 * np.log(1e3) / 0.4 / 0.01 < n < 1.2 * np.log(1e3) / 0.4 / 0.01 + 16
    valid = g.blocks["data"].valid_mask[0, :, 0].numpy()
    assert valid[8000:8010 + n].sum() == 0 and valid[8010 + n] == 1 and valid[:8000].all()


def test_holdoff_marks_samples_after_an_input_gap():
    _, rec = _sdof_data(slice(10, 12), steps=40)
    data = rt.Recorded(rec, {"w": "w", "y": "y"}, holdoff={"w": 5})
    np.testing.assert_array_equal(data.valid_mask[0, :, 0].numpy(),
                                  [1.0] * 10 + [0.0] * 7 + [1.0] * 23)
    with pytest.raises(rt.errors.ConfigError, match="holdoff"):
        rt.Recorded(rec, {"w": "w", "y": "y"}, holdoff={"w": -1})


# --- the options as scenario settings ------------------------------------------------------------------------

def _estimator(name, batch=1, members=None, **overrides):
    from rcotorch.run import scenario
    sc = scenario.get(name)
    s = sc.resolve_members(overrides, members) if members else sc.resolve(overrides)
    return sc.build(s, batch, torch.float64, "cpu")


@pytest.mark.parametrize("name", ["sdof-stiffness", "sdof-stiffness-damping", "rlc-circuit", "twodof-stiffness"])
def test_every_scenario_offers_the_options_off_by_default(name):
    from rcotorch.run import scenario
    sc = scenario.get(name)
    assert {k: sc.settings[k] for k in ("r_delta", "normalize", "p_max")} == dict(r_delta=0.0, normalize=0.0, p_max=0.0)
    assert "r_delta" in sc.per_member and "normalize" not in sc.per_member
    est = _estimator(name).role("estimator")
    assert est.rd_sqrt is None and est.norm_inv_s2 is None and est.p_max is None


def test_options_set_as_settings_reach_the_estimator_and_run_as_if_built_with_them():
    g = _estimator("sdof-stiffness", batch=2, r_delta="0.5", normalize=2, p_max="30")
    est = g.role("estimator")
    assert float(est.rd_sqrt) == pytest.approx(0.5 ** 0.5) and float(est.norm_inv_s2) == 0.25
    assert float(est.p_max) == 30.0
    # the same graph built with the options on the estimator itself gives the same run, bit for bit
    from rcotorch.run import scenario
    sc = scenario.get("sdof-stiffness")
    s = sc.resolve()
    known = rt.LTI.continuous(*rt.models.sdof_matrices(s["m"], s["C"], s["K"], sees=["position", "velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=s["Ts"], name="known")
    plant = rt.LTI.continuous(*rt.models.sdof_matrices(s["m"], s["C"] + s["dC"], s["K"] + s["dK"], sees=[],
                                                       actuation=False), inputs=["w"], outputs=["y"], dt=s["Ts"])
    ident = rt.RCOEstimator.static_gain({"y0": 2}, p0=s["p0"], lam=s["lam"], r_delta=0.5, normalize=2.0, p_max=30.0)
    direct = rt.refinement(known, ident, physical=plant, excitation=rt.WhiteNoise(1, std=s["w_std"], seed=s["seed"]),
                           nu=s["nu"], batch_size=2)
    g.advance(3000)
    direct.advance(3000)
    assert torch.equal(g.role("estimator").theta, direct.role("estimator").theta)
    assert float(g.role("estimator").P[0].trace()) <= 30.0 * (1 + 1e-12)


def test_penalty_may_differ_between_members_and_zero_is_no_penalty():
    g = _estimator("sdof-stiffness", batch=2, members=[{"r_delta": 0.0}, {"r_delta": 1e-3}])
    assert g.role("estimator").rd_sqrt.tolist() == [0.0, pytest.approx(1e-3 ** 0.5)]
    off = _estimator("sdof-stiffness", batch=2, members=[{"r_delta": 0.0}, {"r_delta": 0.0}]).role("estimator")
    assert off.rd_sqrt is None


def test_options_run_from_the_command_line_and_are_refused_when_out_of_range(tmp_path):
    from rcotorch.run.runner import Run
    with Run("sdof-stiffness", steps=500, out=tmp_path / "a", overrides={"p_max": "100", "normalize": "0.01"}) as run:
        run.advance(progress=False)
        assert run.summary()["settings"]["p_max"] == 100.0
    with pytest.raises(rt.errors.ConfigError, match="p_max"):
        Run("sdof-stiffness", steps=10, out=tmp_path / "b", overrides={"p_max": "-1"})
