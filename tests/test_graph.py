"""Graph building and validation, and the Markov parameters the Figure-1 graph derives from the known model."""

import re

import control
import numpy as np
import pytest
import torch

import rcotorch as rt

DT = 0.1


def _impulse(sys, n, inp, out):
    """H_0..H_(n-1) of a discrete system (python-control's discrete impulse has area 1: a sample of 1/dt)."""
    return control.impulse_response(sys, T=np.arange(n) * sys.dt, input=inp, output=out).outputs * sys.dt


def _double_integrator_known():
    """Two leaky integrators in a chain, u -> x1 -> x2 = y = y0: C B = 0, C A B = 1 (relative degree 2)."""
    A = [[0.9, 0.0], [1.0, 0.8]]
    B = [[0.5, 1.0], [0.0, 0.0]]          # inputs w, u
    C = [[0.0, 1.0], [0.0, 1.0]]          # outputs y, y0
    sys = control.ss(A, B, C, np.zeros((2, 2)), DT)
    return sys, rt.LTI.from_control(sys, inputs=["w", "u"], outputs=["y", "y0"], name="known")


def _truth():
    return rt.LTI([[0.5]], [[1.0]], [[0.2]], [[0.1]], ["in"], ["out"], DT)


@pytest.mark.parametrize("case", ["sdof_velocity", "double_integrator"])
def test_refinement_derives_markov_from_known_model(case, sdof_known):
    nu = 8
    if case == "sdof_velocity":
        known = sdof_known(DT)
        sys = known.to_control()
        d_expected = 1
    else:
        sys, known = _double_integrator_known()
        d_expected = 2
    ref = _impulse(sys, d_expected + nu + 1, inp=1, out=0)          # u -> y
    # Independent check of the relative degree: first nonzero Markov parameter.
    assert np.all(ref[:d_expected] == 0) and ref[d_expected] != 0
    est = rt.RCOEstimator({"y0": 1}, nc=2, p0=10.0)
    g = rt.refinement(known, est, truth=_truth(), excitation=rt.WhiteNoise(1, seed=2), nu=nu, batch_size=2)
    ident = g.blocks["identified"]
    assert ident.first_delay == d_expected
    assert ident.beta.shape == (1, nu, 1, 1)
    np.testing.assert_allclose(ident.beta[0, :, 0, 0].numpy(), -ref[d_expected:d_expected + nu],
                               rtol=1e-12, atol=1e-15)
    # Probing the built graph gives the same map u -> z (from lag 0), for every member.
    n = d_expected + nu
    H = g.markov("identified.u", "error.out", n)
    assert H.shape == (2, n, 1, 1)
    for b in range(2):
        np.testing.assert_allclose(H[b, :, 0, 0].numpy(), -ref[:n], rtol=1e-10, atol=1e-13)
    # Probing leaves the graph itself untouched.
    assert int(g.k) == 0


def test_derive_markov_mimo_and_errors():
    rng = np.random.default_rng(1)
    A = np.diag([0.5, -0.3, 0.7])
    B = rng.standard_normal((3, 3))
    C = rng.standard_normal((4, 3))
    sys = control.ss(A, B, C, np.zeros((4, 3)), DT)
    known = rt.LTI.from_control(sys, inputs={"w": 1, "u": 2}, outputs={"y": 2, "y0": 2}, name="known")
    beta, d = rt.derive_markov(known, "u", "y", 5)
    assert d == 1 and beta.shape == (1, 5, 2, 2)
    for i in range(2):
        for j in range(2):
            ref = _impulse(sys, 6, inp=1 + j, out=i)
            np.testing.assert_allclose(beta[0, :, i, j].numpy(), -ref[1:], rtol=1e-12, atol=1e-15)
    blind = rt.LTI.from_control(control.ss(A, np.c_[B[:, :1], np.zeros((3, 1))], C[:2], np.zeros((2, 2)), DT),
                                inputs=["w", "u"], outputs=["y", "y0"], name="known")
    with pytest.raises(rt.ConfigError, match="zero Markov parameters"):
        rt.derive_markov(blind, "u", "y", 5)
    with pytest.raises(rt.ConfigError, match="nu"):
        rt.derive_markov(known, "u", "y", 0)


def test_refinement_needs_nu_or_markov(sdof_known, zoh_first_order):
    with pytest.raises(rt.ConfigError, match="nu="):
        rt.refinement(sdof_known(), rt.RCOEstimator({"y0": 1}), truth=zoh_first_order(),
                      excitation=rt.WhiteNoise())
    # Given Markov parameters are kept.
    est = rt.RCOEstimator({"y0": 1}, markov=[[[-2.0]], [[-1.0]]], first_delay=3)
    rt.refinement(sdof_known(), est, truth=zoh_first_order(), excitation=rt.WhiteNoise(), nu=5)
    assert est.first_delay == 3 and est.beta.flatten().tolist() == [-2.0, -1.0]


# --- validation ------------------------------------------------------------------------------------------

def _src(width=1, name="src"):
    return rt.WhiteNoise(width, name=name)


def test_unknown_block_suggests_name():
    with pytest.raises(rt.PortError) as e:
        rt.Graph([_src(), rt.Gain(2.0, name="g")], [("srx.out", "g.in")])
    msg = str(e.value)
    assert "no block 'srx'" in msg and "did you mean 'src'" in msg


def test_unknown_port_names_block_port_and_suggestion():
    with pytest.raises(rt.PortError) as e:
        rt.Graph([_src(), rt.Gain(2.0, name="g")], ["src.outt -> g.in"])
    msg = str(e.value)
    assert "'src'" in msg and "'outt'" in msg and "did you mean 'out'" in msg
    with pytest.raises(rt.PortError) as e:
        rt.Graph([_src(), rt.Gain(2.0, name="g")], ["src.out -> g.inn"])
    msg = str(e.value)
    assert "'g'" in msg and "input port 'inn'" in msg and "did you mean 'in'" in msg


def test_unconnected_input():
    with pytest.raises(rt.PortError, match=re.escape("input 'g.in' is not connected")):
        rt.Graph([_src(), rt.Gain(2.0, name="g")], [])


def test_doubly_driven_input():
    with pytest.raises(rt.PortError, match="driven twice") as e:
        rt.Graph([_src(), _src(name="src2"), rt.Gain(2.0, name="g")], ["src.out -> g.in", "src2.out -> g.in"])
    assert "'src.out'" in str(e.value) and "'src2.out'" in str(e.value)


def test_width_mismatch_names_both_ports():
    with pytest.raises(rt.DimensionError) as e:
        rt.Graph([_src(2), rt.Gain(2.0, name="g")], ["src.out -> g.in"])
    msg = str(e.value)
    assert "'src.out' has width 2" in msg and "'g.in' expects width 1" in msg


def test_algebraic_loop_of_two_gains():
    with pytest.raises(rt.AlgebraicLoopError) as e:
        rt.Graph([rt.Gain(0.5, name="a"), rt.Gain(0.5, name="b")], ["a.out -> b.in", "b.out -> a.in"])
    assert "a.out" in str(e.value) and "b.out" in str(e.value)


def test_loop_through_a_state_is_fine():
    lti = rt.LTI([[0.5]], [[1.0]], [[1.0]], [[0.0]], ["in"], ["out"], DT, name="p")
    g = rt.Graph([rt.Gain(0.5, name="a"), lti], ["a.out -> p.in", "p.out -> a.in"])
    assert g.order == [("p", "out"), ("a", "out")]


def test_bad_dtype():
    with pytest.raises(rt.ConfigError, match="dtype"):
        rt.Graph([_src(), rt.Gain(2.0, name="g")], ["src.out -> g.in"], dtype=torch.float16)


def test_duplicate_block_name():
    with pytest.raises(rt.ConfigError, match="two blocks are named 'g'"):
        rt.Graph([_src(), rt.Gain(2.0, name="g"), rt.Gain(1.0, name="g")], ["src.out -> g.in"])


def test_str_shows_connection_table():
    g = rt.Graph([_src(2), rt.Gain(np.ones((1, 2)), name="g"), rt.Sum({"a": 1, "b": -1}, 1, name="s")],
                 ["src.out -> g.in", ("g.out", "s.a"), ("g.out", "s.b")], batch_size=3)
    text = str(g)
    assert "batch 3" in text and "torch.float64" in text
    lines = text.splitlines()
    assert "Connections (source -> destination, width):" in lines
    assert any(re.fullmatch(r"\s*src\.out\s+->\s+g\.in\s+2", line) for line in lines)
    assert any(re.fullmatch(r"\s*g\.out\s+->\s+s\.a\s+1", line) for line in lines)
    assert any(re.fullmatch(r"\s*g\.out\s+->\s+s\.b\s+1", line) for line in lines)
    assert "Unconnected outputs: s.out" in text


def test_graph_steps_gain_and_sum():
    """out = K w - K w = 0 and out = K w computed in feedthrough order."""
    K = np.array([[1.0, -2.0]])
    g = rt.Graph([rt.Sum({"a": 1, "b": -1}, 1, name="s"), rt.Gain(K, name="g"), _src(2)],
                 ["src.out -> g.in", ("g.out", "s.a"), ("g.out", "s.b")], batch_size=2)
    sig = g.step()
    w = sig[("src", "out")]
    torch.testing.assert_close(sig[("g", "out")], w @ torch.tensor(K).T, rtol=0, atol=0)
    assert torch.equal(sig[("s", "out")], torch.zeros(2, 1, dtype=torch.float64))


def test_proper_estimator_with_known_feedthrough_is_an_algebraic_loop(zoh_first_order):
    # D: u -> y0 is nonzero, u -> y is zero (so the Markov parameters start at d = 1).
    sys = control.ss([[0.5]], [[1.0, 1.0]], [[1.0], [1.0]], [[0.0, 0.0], [0.0, 0.3]], DT)
    known = rt.LTI.from_control(sys, inputs=["w", "u"], outputs=["y", "y0"], name="known")
    truth = rt.LTI([[0.5]], [[1.0]], [[0.2]], [[0.0]], ["in"], ["out"], DT)
    with pytest.raises(rt.AlgebraicLoopError, match="identified.u"):
        rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 1}), truth=truth,
                      excitation=rt.WhiteNoise(), nu=4)
    # The strictly proper estimator has no loop.
    truth = rt.LTI([[0.5]], [[1.0]], [[0.2]], [[0.0]], ["in"], ["out"], DT)
    rt.refinement(known, rt.RCOEstimator({"y0": 1}), truth=truth, excitation=rt.WhiteNoise(), nu=4)


def test_float32_graph_is_float32_throughout(sdof_known, zoh_first_order):
    est = rt.RCOEstimator({"y0": 1}, nc=2, p0=100.0)
    g = rt.refinement(sdof_known(DT), est, truth=zoh_first_order(DT), excitation=rt.WhiteNoise(1, seed=4),
                      nu=5, batch_size=2, dtype=torch.float32)
    tr = g.run(50, record={"u": "identified.u", "z": "error.out"})
    assert tr["u"].dtype == torch.float32 and tr["z"].dtype == torch.float32
    assert all(b.dtype == torch.float32 for b in g.buffers() if b.is_floating_point())
    assert bool(est.alive.all()) and torch.isfinite(est.theta).all()
    # Same run in float64 agrees to float32 precision over a short horizon.
    est64 = rt.RCOEstimator({"y0": 1}, nc=2, p0=100.0)
    g64 = rt.refinement(sdof_known(DT), est64, truth=zoh_first_order(DT), excitation=rt.WhiteNoise(1, seed=4),
                        nu=5, batch_size=2)
    tr64 = g64.run(50, record={"z": "error.out"})
    np.testing.assert_allclose(tr["z"].double().numpy(), tr64["z"].numpy(), rtol=1e-3, atol=1e-4)


def test_refinement_feeds_and_regressor_sources(sdof_known, zoh_first_order):
    with pytest.raises(rt.PortError, match="feeds="):
        rt.refinement(sdof_known(), rt.RCOEstimator({"q": 1}), truth=zoh_first_order(),
                      excitation=rt.WhiteNoise(), nu=3)
    g = rt.refinement(sdof_known(), rt.RCOEstimator({"q": 1, "w": 1}), truth=zoh_first_order(),
                      excitation=rt.WhiteNoise(), nu=3, feeds={"q": "known.y"})
    assert g.sources[("identified", "q")] == ("known", "y")
    assert g.sources[("identified", "w")] == ("excitation", "out")
    assert g.sources[("identified", "z")] == ("error", "out")
    assert g.sources[("known", "u")] == ("identified", "u")
    assert g.sources[("unknown", "in")] == ("plant", "y0") and g.sources[("plant", "u")] == ("unknown", "out")
    with pytest.raises(rt.ConfigError, match="exactly one of"):
        rt.refinement(sdof_known(), rt.RCOEstimator({"y0": 1}), excitation=rt.WhiteNoise(), nu=3)


def test_refinement_declares_roles_whatever_the_block_names(sdof_known):
    """The runner, monitor and figures find the parts of a refinement through its roles: a known model and an
    estimator with names of the user's choosing are found, and a wrong role is a clear error."""
    known = sdof_known(DT)
    known.name = "model"
    est = rt.RCOEstimator({"y0": 1}, nc=2, p0=10.0, name="refine")
    g = rt.refinement(known, est, truth=_truth(), excitation=rt.WhiteNoise(1, seed=2), nu=4)
    assert g.role("estimator") is est and g.role("known") is known
    assert g.role_signal("error") == ("error", "out") and g.role_signal("prediction") == ("model", "y")
    assert g.sources[("refine", "z")] == ("error", "out") and g.sources[("model", "u")] == ("refine", "u")
    with pytest.raises(rt.ConfigError, match="no block has the role 'estimator'"):
        rt.Graph([rt.WhiteNoise(1, name="a")], []).role("estimator")
    with pytest.raises(rt.PortError, match="role 'known' names no block 'modle'.*did you mean 'model'"):
        rt.Graph([rt.WhiteNoise(1, name="model")], [], roles={"known": "modle"})
    with pytest.raises(rt.ConfigError, match="unknown role 'estimater'.*did you mean 'estimator'"):
        rt.Graph([rt.WhiteNoise(1, name="model")], [], roles={"estimater": "model"})
