"""Held-out validation (rcotorch.verdict.validation) against independent simulations (python-control)."""

import control
import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch.errors import ConfigError
from rcotorch.verdict.validation import validate

TS, K_MODEL, K_TRUE, DAMP, NOISE = 0.01, 4.0, 5.0, 0.4, 0.01


def _sdof(k, inputs):
    B = [[0, 0], [1, 1]] if len(inputs) == 2 else [[0], [1]]
    C = [[0, 1], [1, 0]] if len(inputs) == 2 else [[0, 1]]
    outputs = {"y": 1, "y0": 1} if len(inputs) == 2 else ["y"]
    return rt.LTI.continuous([[0, 1], [-k, -DAMP]], B, C, np.zeros((len(C), len(inputs))), inputs=inputs,
                             outputs=outputs, dt=TS, name="known" if len(inputs) == 2 else "truth")


def _refined(steps=4000, batch=2):
    ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=100.0)
    g = rt.refinement(_sdof(K_MODEL, ["w", "u"]), ident, physical=_sdof(K_TRUE, ["w"]),
                      excitation=rt.WhiteNoise(1, seed=[1, 2][:batch]),
                      noise=rt.WhiteNoise(1, std=NOISE, seed=[8, 9][:batch]), nu=200, batch_size=batch)
    g.run(steps)
    return g


def _excitation(seed: int, start: int, steps: int) -> np.ndarray:
    src = rt.WhiteNoise(1, seed=[seed])
    src.reset(1)
    src.k.fill_(start)
    return torch.cat([src.step()["out"] for _ in range(steps)]).numpy()[:, 0]


def test_fresh_excitation_validation_equals_a_python_control_simulation_of_the_refined_and_initial_models():
    g = _refined()
    theta = g.role("estimator").theta.detach().clone()
    v = validate(g, 2000)
    assert v.state_fitted and v.refined.shape == (2000, 2, 1)
    for b, seed in enumerate([1, 2]):
        w = _excitation(seed, int(g.k), 2000)
        for model, gain in (("refined", float(theta[b].flatten()[0])), ("initial", 0.0)):
            # the sampled known model with u(k) = gain * position(k) in feedback, on the sources' later samples
            sys = control.c2d(control.ss([[0, 1], [-K_MODEL, -DAMP]], [[0], [1]], [[0, 1]], 0), TS)
            sys = control.ss(sys.A + gain * sys.B @ [[1.0, 0.0]], sys.B, sys.C, 0, TS)
            x0 = getattr(v, "x0" if model == "refined" else "x0_initial")[b].numpy()
            want = control.forced_response(sys, U=w, X0=x0).outputs
            got = getattr(v, model)[:, b, 0].numpy()
            assert np.allclose(got, want, rtol=1e-9, atol=1e-9), np.abs(got - want).max()
        truth = control.c2d(control.ss([[0, 1], [-K_TRUE, -DAMP]], [[0], [1]], [[0, 1]], 0), TS)
        clean = control.forced_response(truth, U=w).outputs
        noise = v.measured[:, b, 0].numpy() - clean
        assert abs(noise.std() / NOISE - 1) < 0.1                  # the measurement noise continues as well
    # the refined model's error is the measurement noise; the initial model's is far larger
    assert torch.all((v.rmse / NOISE - 1).abs() < 0.1), v.rmse
    assert torch.all(v.rmse_initial > 5 * v.rmse) and torch.all(v.fit_percent > v.fit_percent_initial + 40)
    s = v.summary()
    assert s["steps"] == 2000 and len(s["rmse"]) == 2 and "fresh excitation" in s["source"]


def test_the_initial_state_is_fitted_to_the_first_samples():
    """Recorded data start mid-motion: the fitted state makes the refined model's error the noise alone."""
    g = _refined(batch=1)
    sim = _refined(steps=1, batch=1)                 # a recording of the truth: 3000 samples of w and y
    tr = sim.run(3000, record={"w": "excitation.out", "y": "measurement.out"})
    rec = np.concatenate([tr["w"][:, 0], tr["y"][:, 0]], 1)
    ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=100.0)
    data = rt.Recorded(rec, {"w": 0, "y": 1}, dt=TS)
    gd = rt.refinement(_sdof(K_MODEL, ["w", "u"]), ident, data=data, nu=200)
    gd.run(2000)
    v = validate(gd, rows=(2000, 3000))
    assert float(v.rmse[0]) < 1.3 * NOISE, v.rmse            # mid-motion: without the fit the start is off
    assert v.state_fitted and v.steps == 1000
    with pytest.raises(ConfigError, match="overlap"):
        validate(gd, rows=(1500, 3000))
    with pytest.raises(ConfigError, match="rows=.*or data="):
        validate(gd)
    with pytest.raises(ConfigError, match="fresh excitation"):
        validate(g, rows=(0, 100))


def test_a_known_model_that_names_its_fitted_states_keeps_the_others_and_the_fit_stays_finite():
    """A Silverbox-like model whose 4th state carries u(k-1) (``MassSpringDamper(u_ahead=True)``) in a cubic
    spring's loop: fitting that state too threw the free run off (a u(k-1) of 39 on 50 mV data, NaN after six
    samples). With ``fitted_states`` = (0, 1, 2) the state fit leaves it as it was and the refined model scores
    the measurement noise."""
    from rcotorch.models.identification import MassSpringDamper
    dt, n = 1.6384e-3, 3000
    model = MassSpringDamper(42.0, 1.84e5, 1.86e5, -1000.0, dt, spline=True, u_ahead=True)
    w = np.random.default_rng(0).standard_normal(n + 400).cumsum() * 2e-4
    w = np.convolve(w - w.mean(), np.ones(8) / 8, "same")[200:200 + n]
    law = rt.models.identification.Polynomial((-4.0,), (3,))
    channels = model.inputs(w)
    y = model.discrete.simulate(channels, model.state(0.01, 0.0, channels[0]), law)[0]
    y = y + np.random.default_rng(1).normal(0, 1e-5, n)
    known = model.lti(sees=("position",))
    ident = rt.RCOEstimator.static_gain({"y0": 1}, features=[rt.features.power("y0", 3)], p0=1.0)
    g = rt.refinement(known, ident, data=rt.Recorded(np.c_[channels, y], {"w": [0, 1], "y": 2}, dt=dt), nu=60)
    g.run(2000)
    ident.hold(torch.tensor([[-4.0]], dtype=torch.float64))         # the true spring
    v = validate(g, rows=(2000, n))
    assert v.state_fitted and float(v.x0[0, 3]) == 0.0              # u(k-1) as the validation started it
    assert float(v.rmse[0]) == pytest.approx(1e-5, rel=0.15)
    known.fitted_states = None                                      # every state fitted: the fault
    every = validate(g, rows=(2000, n))
    assert float(every.x0[0, 3]) != 0.0 and not float(every.rmse[0]) <= 2e-5


def test_a_member_whose_loop_overflows_is_scored_nan_and_the_others_as_before():
    """theta of member 1 set to 1e200: its frozen loop overflows, so its outputs' sensitivity to the state is not
    finite (the state fit's least squares would fail on it); it keeps its state and scores NaN, member 0 scores
    as it did before, and the fit is reported as not done."""
    import torch

    import rcotorch as rt
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.8, 0.6, sees=["position", "velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=0.01, name="known")
    g = rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3),
                      truth=rt.Gain(torch.tensor([[-0.5, 0.0]])), excitation=rt.WhiteNoise(1, seed=[1, 2]),
                      nu=15, batch_size=2)
    g.run(500)
    before = rt.validate(g, steps=300)
    assert before.state_fitted and bool(torch.isfinite(before.rmse).all())
    theta = g.role("estimator").theta.clone()
    theta[1] = 1e200
    g.role("estimator").set_state(theta=theta)
    v = rt.validate(g, steps=300)
    assert torch.isnan(v.rmse[1]) and not v.state_fitted
    assert float(v.rmse[0]) == pytest.approx(float(before.rmse[0]), rel=1e-12)


def test_a_run_is_validated_on_no_more_held_out_samples_than_it_ran_and_at_least_200():
    """A 10-step run of 4,096 members was validated on 2,000 fresh samples (two simulations and the state's fit of
    each: 2 s against its 0.01 s of steps); the default now takes as many samples as the run ran, between 200 and
    the scenario's validation_steps."""
    import tempfile
    import types

    from rcotorch.run import scenario as scenarios
    from rcotorch.run.runner import Run
    sc = scenarios.get("sdof-stiffness")
    for ran, want in [(10, 200), (300, 300), (1999, 1999), (20000, sc.validation_steps)]:
        graph = types.SimpleNamespace(roles={"excitation": "excitation"}, k=torch.tensor(ran))
        assert sc.validation(graph, sc.resolve({})) == {"steps": want}
    with tempfile.TemporaryDirectory() as out:
        run = Run("sdof-stiffness", steps=300, out=out)
        run.advance(progress=False)
        assert run.validation().steps == 300
        run.close()


def test_scores_summed_stretch_by_stretch_equal_those_of_the_whole_traces(monkeypatch):
    """The scores are summed over stretches of the simulation (a few steps each here); they equal the formulas
    applied to the whole traces, and keeping the traces of the first member only changes no score."""
    import rcotorch.verdict.validation as val
    g = _refined(steps=1500)
    monkeypatch.setattr(val, "STRETCH_BYTES", 8 * 2 * 13)              # 13 steps a stretch
    full = validate(g, 600)
    y, y_hat = full.measured.numpy(), full.refined.numpy()
    assert y.shape == (600, 2, 1)
    z, yy = (y - y_hat)[val.FIT_STEPS:], y[val.FIT_STEPS:]
    rmse = np.sqrt((z ** 2).sum(2).mean(0))
    fit = 100 * (1 - np.sqrt((z ** 2).sum((0, 2))) / np.sqrt(((yy - yy.mean(0)) ** 2).sum((0, 2))))
    np.testing.assert_allclose(full.rmse.numpy(), rmse, rtol=1e-10)
    np.testing.assert_allclose(full.fit_percent.numpy(), fit, rtol=1e-10)
    one = validate(g, 600, keep=1)
    assert one.measured.shape == (600, 1, 1) and one.initial.shape == (600, 1, 1)
    np.testing.assert_array_equal(one.refined.numpy(), full.refined[:, :1].numpy())
    for key in ("rmse", "fit_percent", "rmse_initial", "fit_percent_initial"):
        np.testing.assert_array_equal(getattr(one, key).numpy(), getattr(full, key).numpy())


def test_the_state_fit_of_a_linear_loop_stops_after_its_first_step_and_a_nonlinear_one_takes_every_pass(
        monkeypatch):
    """The refined model's outputs are affine in its initial state where the loop is linear (an LTI known model,
    a static gain): one Gauss-Newton step is the least-squares state, so the second pass stops at its first
    simulation, which lands where the step predicted, and the refined model scores the measurement noise. A cubic
    feature makes the refined model's loop nonlinear: its passes run in full (the initial model, theta = 0, stays
    linear). A theta of the wrong shape is refused, naming the estimator."""
    import rcotorch.verdict.validation as validation

    calls = []
    real = validation._simulate
    monkeypatch.setattr(validation, "_simulate", lambda g, steps, x0: calls.append(1) or real(g, steps, x0))
    g = _refined(batch=1)
    sim = _refined(steps=1, batch=1)
    tr = sim.run(3000, record={"w": "excitation.out", "y": "measurement.out"})
    data = rt.Recorded(np.concatenate([tr["w"][:, 0], tr["y"][:, 0]], 1), {"w": 0, "y": 1}, dt=TS)
    gd = rt.refinement(_sdof(K_MODEL, ["w", "u"]), rt.RCOEstimator.static_gain({"y0": 1}, p0=100.0), data=data,
                       nu=200)
    gd.run(2000)
    v = validate(gd, rows=(2000, 3000), fit_steps=200)
    n = gd.role("known").x.shape[1]
    assert len(calls) == 2 * ((1 + n) + 1)        # per model: one pass and the next one's first simulation
    assert v.state_fitted and float(v.rmse[0]) < 1.3 * NOISE
    del g
    calls.clear()
    ident = rt.RCOEstimator.static_gain({"y0": 1}, features=[rt.features.power("y0", 3)], p0=100.0)
    gn = rt.refinement(_sdof(K_MODEL, ["w", "u"]), ident, data=data, nu=200)
    gn.run(2000)
    ident.hold(torch.tensor([[50.0]], dtype=torch.float64))
    validate(gn, rows=(2000, 3000), fit_steps=200)
    assert len(calls) == 2 * (1 + n) + (1 + n) + 1     # the refined model's passes in full, the initial one's not
    with pytest.raises(rt.errors.DimensionError, match="estimator 'identified'.*must be \\(1, 1\\).*got \\(1, 2\\)"):
        ident.hold(torch.tensor([[0.0, 50.0]], dtype=torch.float64))


@pytest.mark.parametrize("engine", ["native", "torch"])
def test_the_refined_and_initial_models_simulated_in_one_graph_give_the_numbers_of_separate_simulations(
        engine, monkeypatch):
    """Validation runs the initial model as a copy of the estimator and known model joined to the refined
    model's graph, reading the physical system, excitation and noise from it: bit for bit the rmse, fits, fitted
    states and traces of one simulation after the other (what a graph whose step hooks forbid joining gets)."""
    from rcotorch.verdict import joined as joined_module
    g = _refined(steps=1500)
    g.engine = engine
    joined = []
    join = joined_module.join
    monkeypatch.setattr(joined_module, "join", lambda *a, **k: joined.append(a[4]) or join(*a, **k))
    one = validate(g, 600)
    assert joined == ["initial"]
    monkeypatch.setattr(joined_module, "hooks_leave", lambda *a: False)
    apart = validate(g, 600)
    assert joined == ["initial"]                      # no join the second time
    for key in ("rmse", "rmse_initial", "fit_percent", "fit_percent_initial", "x0", "x0_initial", "measured",
                "refined", "initial"):
        assert torch.equal(getattr(one, key), getattr(apart, key)), key
    assert float(one.rmse_initial.min()) > 2 * float(one.rmse.max())    # two models, not one twice
