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
