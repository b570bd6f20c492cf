"""python-control interop: named signals on the identified subsystem and on the models, plants relabelled as known
models, and a refined model built by ``control.interconnect`` by name, checked against the truth."""

import control
import numpy as np
import pytest
import torch

import rcotorch as rt


def _static(signals, theta, n_u=1, **kw):
    est = rt.RCOEstimator.static_gain(signals, n_u=n_u, dt=0.1, **kw)
    est.reset(1)
    est.theta.copy_(torch.as_tensor(theta, dtype=torch.float64).reshape(1, n_u, -1))
    return est


def test_identified_subsystem_maps_its_regressor_signals_to_u():
    """u = theta y0 with theta = [a, b]: the gain from the input named y0[1] to u is b (not the reverse)."""
    tf = _static({"y0": 2}, [[2.0, -3.0]]).to_control()
    assert tf.input_labels == ["y0[0]", "y0[1]"] and tf.output_labels == ["u"] and tf.name == "identified"
    assert control.dcgain(tf[tf.output_index["u"], tf.input_index["y0[1]"]]) == pytest.approx(-3.0)
    assert control.dcgain(tf[0, tf.input_index["y0[0]"]]) == pytest.approx(2.0)
    mimo = _static({"q": 1, "v": 1}, [[1.0, 2.0], [3.0, 4.0]], n_u=2, name="gain")
    sys = mimo.to_control()
    assert sys.input_labels == ["q", "v"] and sys.output_labels == ["u[0]", "u[1]"] and sys.name == "gain"
    np.testing.assert_allclose(control.dcgain(sys), [[1.0, 2.0], [3.0, 4.0]])
    cubic = _static({"y0": 1}, [[5.0]], features={"y0^3": lambda s: s["y0"] ** 3}).to_control()
    assert cubic.input_labels == ["y0^3"] and cubic.output_labels == ["u"]


def test_dynamic_mimo_identified_subsystem_is_labelled_through_state_space():
    est = rt.RCOEstimator({"y0": 2}, n_u=2, nc=2, dt=0.05, name="delta")
    est.reset(1)
    est.theta.copy_(0.1 * torch.arange(est.n_u * est.n_phi, dtype=torch.float64).reshape(est.theta.shape))
    tf = est.to_control()
    assert tf.input_labels == ["y0[0]", "y0[1]"] and tf.output_labels == ["u[0]", "u[1]"] and tf.name == "delta"
    z = np.exp(1j * 0.7 * 0.05)
    np.testing.assert_allclose(tf(z), est.frequency_response(np.array([0.7]))[0, 0].numpy(), rtol=1e-9)


def test_models_return_labelled_systems():
    G = rt.models.sdof(1.0, 0.5, 2.0)
    assert G.input_labels == ["w", "u"] and G.output_labels == ["y", "y0[0]", "y0[1]"]
    assert G.state_labels == ["q", "qdot"]
    S = rt.models.structure(np.eye(2), np.eye(2), [[2, -1], [-1, 2]], [1.0, 1.0], ["velocity[1]"],
                            ["position[0]", "position[1]"])
    assert S.input_labels == ["w", "u[0]", "u[1]"] and S.output_labels == ["y", "y0[0]", "y0[1]"]
    assert S.state_labels == ["q[0]", "q[1]", "qdot[0]", "qdot[1]"]
    R = rt.models.series_rlc(250.0, 55e-3, 23.5e-6, measured=["v_R", "current"], sees=["v_C"])
    assert R.input_labels == ["w", "u"] and R.output_labels == ["y[0]", "y[1]", "y0"]
    free = rt.models.sdof(1.0, 0.5, 2.0, measured=["position"], sees=[], actuation=False)
    assert free.input_labels == ["w"] and free.output_labels == ["y"]


def _mass_plant():
    """m x'' + c x' + k x = F + d, with the plant's own names: inputs F, d; outputs pos, vel, x[0], x[1]."""
    A = [[0.0, 1.0], [-30.0, -5.0]]
    return control.ss(A, [[0.0, 0.0], [1.0, 1.0]], [[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [0.0, 1.0]], 0,
                      inputs=["F", "d"], outputs=["pos", "vel", "x[0]", "x[1]"], name="rig")


def test_label_ports_picks_and_renames_signals():
    K = rt.models.label_ports(_mass_plant(), w="F", u="F", y="vel", y0="x")     # u acts where F does
    assert K.input_labels == ["w", "u"] and K.output_labels == ["y", "y0[0]", "y0[1]"] and K.name == "known"
    ref = rt.models.sdof(1.0, 5.0, 30.0)
    for a, b in ((K.A, ref.A), (K.B, ref.B), (K.C, ref.C), (K.D, ref.D)):
        np.testing.assert_array_equal(a, b)
    K2 = rt.models.label_ports(_mass_plant(), w=0, u=["d"], y=["pos", "vel"], y0=[1], name="m")
    assert K2.output_labels == ["y[0]", "y[1]", "y0"] and K2.name == "m"
    np.testing.assert_array_equal(K2.C, [[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])
    with pytest.raises(rt.ConfigError, match=r"input u: the plant has no signal 'force'; its signals are \['F', 'd'\]"):
        rt.models.label_ports(_mass_plant(), w="F", u="force", y="vel", y0="pos")
    with pytest.raises(rt.ConfigError, match="output y0: index 7 is out of range"):
        rt.models.label_ports(_mass_plant(), w="F", u="d", y="vel", y0=7)
    with pytest.raises(rt.ConfigError, match="output y names no signal"):
        rt.models.label_ports(_mass_plant(), w="F", u="d", y=[], y0="pos")
    with pytest.raises(rt.ConfigError, match="expected a control.StateSpace"):
        rt.models.label_ports(np.eye(2), w=0, u=1, y=0, y0=1)


def test_known_model_block_equals_the_hand_built_one():
    blk = rt.models.known_model(_mass_plant(), w="F", u="d", y="vel", y0="pos", dt=0.1)
    ref = rt.LTI.from_control(rt.models.sdof(1.0, 5.0, 30.0, sees=["position"]), inputs=["w", "u"],
                              outputs=["y", "y0"], dt=0.1, name="known")
    assert blk.name == "known" and blk.inputs == {"w": 1, "u": 1} and blk.outputs == {"y": 1, "y0": 1}
    for key in ("A", "B", "C", "D"):
        torch.testing.assert_close(getattr(blk, key), getattr(ref, key), rtol=0, atol=1e-15)
    tf = rt.models.known_model(control.tf([1.0], [1.0, 1.0]), w=0, u=0, y=0, y0=0, dt=0.5)
    assert tf.inputs == {"w": 1, "u": 1} and tf.outputs == {"y": 1, "y0": 1}


def test_refined_model_by_interconnect_matches_the_truth():
    """Refine the SDOF of Section IV, then wire known model and identified subsystem by signal name: the refined
    w -> y map equals the true closed loop (known model with ZOH(10/(s+2)) in positive feedback)."""
    Ts = 0.1
    G = rt.models.sdof(m=1.0, c=5.0, k=30.0, measured=["velocity"], sees=["velocity"])
    Delta = control.tf([10.0], [1.0, 2.0], inputs="y0", outputs="u", name="unknown")
    ident = rt.RCOEstimator({"y0": 1}, nc=5, p0=1e8)
    graph = rt.refinement(rt.models.known_model(G, w="w", u="u", y="y", y0="y0", dt=Ts), ident,
                          truth=rt.LTI.from_control(Delta, inputs=["in"], outputs=["out"], dt=Ts),
                          excitation=rt.WhiteNoise(1, seed=3), nu=10)
    graph.run(20000)
    Gd = control.sample_system(G, Ts, name="known")
    refined = control.interconnect([Gd, ident.to_control()], inputs="w", outputs="y")
    assert refined.input_labels == ["w"] and refined.nstates == Gd.nstates + 5
    # the true closed loop built from the matrices, without names: x+ = A x + B_w w + B_u u, y0 = C_0 x,
    # u = the ZOH-discretized 10/(s+2) of y0 (positive feedback)
    A, Bw, Bu, Cy, C0 = Gd.A, Gd.B[:, :1], Gd.B[:, 1:], Gd.C[:1], Gd.C[1:]
    D = control.tf2ss(control.sample_system(control.tf([10.0], [1.0, 2.0]), Ts))
    Acl = np.block([[A + Bu @ D.D @ C0, Bu @ D.C], [D.B @ C0, D.A]])
    true = control.ss(Acl, np.vstack([Bw, np.zeros((D.nstates, 1))]), np.hstack([Cy, np.zeros((1, D.nstates))]),
                      0, Ts)
    omega = np.logspace(-2, np.log10(np.pi / Ts), 300)
    z = np.exp(1j * omega * Ts)
    err = np.abs(refined(z) - true(z)) / np.abs(true(z))
    assert err.max() < 1e-3, err.max()
