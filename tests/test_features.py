"""The feature vocabulary (rcotorch.blocks.features): names, checks at build time, and values against NumPy."""

import numpy as np
import pytest
import torch

import rcotorch as rt

F = rt.features


def test_names_read_like_the_functions():
    ports = {"y0": 2, "v": 1, "w": 1}
    cases = [(F.power("y0", 3), ["y0[0]^3", "y0[1]^3"]), (F.sign("v") * F.power("v", 2), ["sign(v)*v^2"]),
             (2 * F.saturation("v", -1, 1), ["2*sat(v, -1, 1)"]), (F.dead_zone("w", 0.1), ["dz(w, -0.1, 0.1)"]),
             (F.tanh("v", 0.5), ["tanh(v/0.5)"]), (F.tanh("v"), ["tanh(v)"]), (F.absolute("w"), ["|w|"]),
             (F.affine("y0[1]", 2, -1), ["(2*y0[1]-1)"]), (F.constant(), ["1"]),
             (F.monomial(v=2, w=1), ["v^2*w"]), (F.product("y0[1]", "w"), ["y0[1]*w"])]
    for term, names in cases:
        assert term.names(ports) == names
    est = rt.RCOEstimator({"y0": 2, "v": 1}, nc=1, features=[F.power("y0", 3), F.sign("v")])
    assert est.signal_names == ["y0[0]^3", "y0[1]^3", "sign(v)"]
    assert est.theta_names == ["y0[0]^3(k-1)", "y0[1]^3(k-1)", "sign(v)(k-1)", "u(k-1)"]


def test_values_against_numpy():
    g = np.random.default_rng(0)
    y0, v = g.standard_normal((5, 2)), g.standard_normal((5, 1))
    v[0] = 0.0
    inputs = {"y0": torch.tensor(y0), "v": torch.tensor(v)}
    cases = [(F.power("y0", 3), y0 ** 3), (F.sign("v") * F.power("v", 2), np.sign(v) * v ** 2),
             (F.saturation("y0[1]", -0.3, 0.2), np.clip(y0[:, 1:], -0.3, 0.2)),
             (F.dead_zone("v", -0.1, 0.4), v - np.clip(v, -0.1, 0.4)), (F.tanh("y0", 2.0), np.tanh(y0 / 2.0)),
             (F.absolute("v") * F.port("y0"), np.abs(v) * y0), (F.affine("v", -2, 3), -2 * v + 3),
             (0.5 * F.constant(4.0), np.full((5, 1), 2.0)), (F.monomial({"y0[0]": 2}, v=1), y0[:, :1] ** 2 * v)]
    for term, ref in cases:
        np.testing.assert_allclose(term(inputs).numpy(), ref, rtol=1e-15, atol=0, err_msg=repr(term))


def test_mistakes_are_named_when_the_block_is_built():
    with pytest.raises(rt.ConfigError, match="block 'identified'.*reads port 'Y0'.*did you mean 'y0'"):
        rt.RCOEstimator({"y0": 1}, features=F.power("Y0", 3))
    with pytest.raises(rt.DimensionError, match="channel 2 of port 'y0', which has width 2"):
        rt.RCOEstimator({"y0": 2}, features=F.port("y0[2]"))
    with pytest.raises(rt.DimensionError, match="different widths"):
        rt.RCOEstimator({"y0": 2, "q": 3}, features=F.product("y0", "q"))
    with pytest.raises(rt.ConfigError, match="integer exponent"):
        F.power("y0", 1.5)
    with pytest.raises(rt.ConfigError, match="low <= high"):
        F.saturation("y0", 1, -1)
    with pytest.raises(rt.ConfigError, match="scale > 0"):
        F.tanh("y0", 0)
    with pytest.raises(rt.ConfigError, match="port reference"):
        F.sign("y0[")
    with pytest.raises(rt.ConfigError, match="given twice"):
        rt.RCOEstimator({"y0": 1}, features=[F.power("y0", 3), F.power("y0", 3)])
    with pytest.raises(rt.ConfigError, match="rcotorch.blocks.features terms"):
        rt.RCOEstimator({"y0": 1}, features=[F.port("y0"), lambda s: s["y0"]])


def test_python_functions_stay_allowed_on_pytorch():
    est = rt.RCOEstimator({"y0": 1}, features={"cube": lambda s: s["y0"] ** 3, "sat": F.saturation("y0", -1, 1)})
    assert est.signal_names == ["cube", "sat"] and est.terms is None


def _mass_with_friction(features, batch=3, engine="auto", force=10.0, bump=0.8):
    """A mass on a spring whose known model has no friction; the truth's friction is Coulomb, Stribeck and
    viscous (a NumPy StaticMap of the velocity); the identified subsystem sees y0 = [position, velocity] and
    the excitation w."""
    A, B, C, D = rt.models.sdof_matrices(1.0, 0.0, 4.0, measured=["velocity"], sees=["position", "velocity"])
    known = rt.LTI.continuous(A, B, C, D, inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=0.01, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 2, "w": 1}, features=features, p0=1e3)
    truth = rt.StaticMap(lambda x: -(np.sign(x[:, 1:]) * (1.0 + bump * np.exp(-(x[:, 1:] / 0.5) ** 2))
                                     + 0.3 * x[:, 1:]), 2)
    g = rt.refinement(known, ident, truth=truth, nu=30, batch_size=batch,
                      excitation=rt.WhiteNoise(1, std=force, seed=list(range(1, batch + 1))))
    g.engine = engine
    return g


def _stribeck(s):
    v = s["y0"][:, 1:]
    return np.sign(v) * np.exp(-(v / 0.5) ** 2)


def _wide(s):                       # two signals from both ports, in the components a NumPy user writes
    q, v = s["y0"][:, :1], s["y0"][:, 1:]
    return np.concatenate([np.tanh(q / 0.2) * s["w"], q * np.abs(v)], axis=1)


def test_a_users_feature_functions_run_natively_and_agree_with_pytorch():
    """Feature functions written with NumPy (one of width 2, reading both ports), between terms, are compiled
    into the native engine: the regressors and theta equal the PyTorch engine's, which calls the functions
    themselves, to rounding, and the built-in term tanh(v / 0.5) written as a function gives the term's theta."""
    features = {"sign": F.sign("y0[1]"), "stribeck": _stribeck, "wide": _wide, "v": F.port("y0[1]")}
    fast, ref = _mass_with_friction(features), _mass_with_friction(features, engine="torch")
    assert fast.native_status() is None
    assert fast.role("estimator").theta_names == ["sign(k)", "stribeck(k)", "wide[0](k)", "wide[1](k)", "v(k)"]
    for g in (fast, ref):
        g.advance(400)
    est, est_ref = fast.role("estimator"), ref.role("estimator")
    assert est.theta.abs().max() > 0.1
    torch.testing.assert_close(est.phi_now, est_ref.phi_now, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(est.theta, est_ref.theta, rtol=1e-9, atol=1e-10)
    as_term = _mass_with_friction([F.sign("y0[1]"), F.tanh("y0[1]", 0.5)])
    as_function = _mass_with_friction({"sign": F.sign("y0[1]"), "t": lambda s: np.tanh(s["y0"][:, 1:] / 0.5)})
    assert as_function.native_status() is None
    for g in (as_term, as_function):
        g.advance(400)
    torch.testing.assert_close(as_function.role("estimator").theta, as_term.role("estimator").theta,
                               rtol=1e-12, atol=1e-13)


def test_a_feature_function_in_the_past_regressors_agrees_with_pytorch():
    """With nc = 2 the regressor holds the feature function's past values (computed before the update, not
    before u): natively the same as on PyTorch."""
    def build(engine):
        A, B, C, D = rt.models.sdof_matrices(1.0, 0.0, 4.0, measured=["velocity"], sees=["position", "velocity"])
        known = rt.LTI.continuous(A, B, C, D, inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=0.01, name="known")
        ident = rt.RCOEstimator({"y0": 2}, nc=2, features={"s": _stribeck, "q": F.port("y0[0]")}, p0=10.0)
        g = rt.refinement(known, ident, truth=rt.StaticMap(lambda x: -0.5 * x[:, 1:] - np.sign(x[:, 1:]), 2),
                          nu=20, batch_size=2, excitation=rt.WhiteNoise(1, std=5.0, seed=[1, 2]))
        g.engine = engine
        g.advance(300)
        return g
    fast, ref = build("auto"), build("torch")
    assert fast.ran_engine == "native" and ref.ran_engine == "torch"
    assert fast.role("estimator").theta.abs().max() > 1e-3
    torch.testing.assert_close(fast.role("estimator").theta, ref.role("estimator").theta, rtol=1e-9, atol=1e-10)


def test_friction_identified_with_feature_functions():
    """Coulomb and viscous friction identified natively with the user's own basis functions, written with
    NumPy, against the truth's Fc = 1.0 and c = 0.3 (the force keeps the mass sliding most of the time)."""
    g = _mass_with_friction({"coulomb": lambda s: np.sign(s["y0"][:, 1:]), "viscous": lambda s: s["y0"][:, 1:]},
                            batch=2, force=20.0, bump=0.0)
    assert g.native_status() is None
    g.advance(20000)
    theta = g.role("estimator").theta[:, 0]
    torch.testing.assert_close(-theta, torch.tensor([[1.0, 0.3]] * 2, dtype=theta.dtype), rtol=0, atol=0.005)


def test_a_feature_function_that_does_not_compile_names_itself_and_runs_on_pytorch():
    g = _mass_with_friction({"sign": F.sign("y0[1]"), "sat": lambda s: s["y0"].clamp(-1.0, 1.0)}, batch=2)
    why = g.native_status()
    assert "feature 'sat'" in why and "is not compiled" in why and "test_features.py" in why
    g.advance(5)
    assert int(g.k) == 5


def test_a_feature_function_that_gives_nan_in_one_member_diverges_that_member_alone(recwarn):
    """np.sqrt of the velocity: NaN in the member whose mass moves both ways; it is reported diverged, natively,
    while the other member (at rest) runs on, and building the block warns of nothing (its probe's random
    inputs are negative too)."""
    A, B, C, D = rt.models.sdof_matrices(1.0, 0.1, 4.0, measured=["velocity"], sees=["velocity"])
    known = rt.LTI.continuous(A, B, C, D, inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.01, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 1}, features={"root": lambda s: np.sqrt(s["y0"])}, p0=1.0)
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]
    g = rt.refinement(known, ident, truth=rt.Gain([[-0.5]]), nu=10, batch_size=2,
                      excitation=rt.WhiteNoise(1, std=[0.0, 5.0], seed=1))
    assert g.native_status() is None
    g.advance(50)
    assert g.ran_engine == "native"
    assert ident.alive.tolist() == [True, False] and int(ident.diverged_at[1]) >= 1
    assert bool(torch.isfinite(ident.theta[0]).all())


CENTERS = np.linspace(-2.0, 2.0, 7).reshape(1, -1)


def test_a_radial_basis_over_a_global_array_compiles_and_agrees_with_pytorch():
    """A basis of radial functions, exp(-((v - c_i) / w)^2) for seven centres held in a NumPy array the
    function reads as a global, broadcast to (B, 7): natively as on PyTorch."""
    def rbf(s):
        return np.exp(-((s["y0"][:, 1:] - CENTERS) / 0.6) ** 2)

    fast, ref = _mass_with_friction({"rbf": rbf}, batch=2), _mass_with_friction({"rbf": rbf}, batch=2,
                                                                                 engine="torch")
    assert fast.native_status() is None and fast.role("estimator").n_sig == 7
    for g in (fast, ref):
        g.advance(300)
    assert fast.ran_engine == "native"
    torch.testing.assert_close(fast.role("estimator").theta, ref.role("estimator").theta, rtol=1e-9, atol=1e-10)
