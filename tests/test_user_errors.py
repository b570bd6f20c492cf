"""Mistakes a new user makes get a library error that names the block, port or setting and what is accepted."""

import pytest

import rcotorch as rt
from rcotorch.run import scenario as scenarios


def _known():
    return rt.LTI.from_control(rt.models.sdof(1.0, 0.4, 4.0, measured=["velocity"], sees=["position"]), dt=0.01,
                               inputs=["w", "u"], outputs=["y", "y0"], name="known")


def test_a_truth_with_two_ports_is_refused_naming_its_ports():
    two = rt.LTI.from_control(rt.models.sdof(1.0, 0.4, 4.0, measured=["velocity"], sees=["position"]), dt=0.01,
                              inputs=["w", "u"], outputs=["y", "y0"], name="two_port")
    with pytest.raises(rt.PortError, match=r"truth= must be a block with one input and one output.*'two_port' "
                                           r"has inputs \['w', 'u'\]"):
        rt.refinement(_known(), rt.RCOEstimator.static_gain({"y0": 1}), truth=two,
                      excitation=rt.WhiteNoise(1), nu=10)


def test_the_identified_subsystem_before_the_graph_is_built_is_a_clear_error():
    ident = rt.RCOEstimator.static_gain({"y0": 1})
    with pytest.raises(rt.ConfigError, match="no members yet"):
        ident.to_control(0)
    rt.refinement(_known(), ident, truth=rt.Gain(-0.3), excitation=rt.WhiteNoise(1), nu=10, batch_size=2)
    with pytest.raises(rt.ConfigError, match="member 5 out of range; the batch has 2 members"):
        ident.to_control(5)
    assert ident.to_control(1).ninputs == 1


def test_a_structure_signal_name_that_is_not_accepted_names_the_accepted_ones():
    with pytest.raises(rt.ConfigError, match=r"unknown signal 'pos'.*'position', 'velocity'"):
        rt.models.sdof(1.0, 0.4, 4.0, measured=["pos"])
    with pytest.raises(rt.ConfigError, match=r"'velocity\[2\]'.*0 <= i < 2"):
        rt.models.structure([[1, 0], [0, 1]], [[1, 0], [0, 1]], [[2, -1], [-1, 2]], [1, 0],
                            measured=["velocity[2]"], sees=["position[0]"])


def test_a_scenario_folder_that_does_not_exist_is_an_error(monkeypatch, tmp_path):
    monkeypatch.setenv("RCOTORCH_SCENARIOS", str(tmp_path / "missing"))
    with pytest.raises(rt.ConfigError, match=r"RCOTORCH_SCENARIOS names .*missing, which is not a folder"):
        scenarios.available()


def test_a_uniform_shear_building_has_the_closed_form_frequencies_and_rayleigh_damping():
    """n equal storeys: omega_r = 2 sqrt(k/m) sin((2r - 1) pi / (2 (2n + 1))); Rayleigh damping gives the
    damping ratio asked for in the first two modes; a force pair -dk d_j on storey j is that storey's stiffness
    changed by dk."""
    import numpy as np
    m, k, n, zeta = 2.0e4, 2.0e7, 3, 0.03
    G = rt.models.shear_building([m] * n, [k] * n, damping_ratio=zeta, identified=[2],
                                 measured=["displacement[1]", "velocity[-1]"])
    poles = np.linalg.eigvals(G.A)
    wn = np.sort(np.abs(poles))[::2]
    want = 2 * np.sqrt(k / m) * np.sin((2 * np.arange(1, n + 1) - 1) * np.pi / (2 * (2 * n + 1)))
    assert np.allclose(wn, want, rtol=1e-10)
    by_mode = poles[np.argsort(np.abs(poles))][::2]          # one pole of each conjugate pair, slowest first
    assert np.allclose(-by_mode.real[:2] / np.abs(by_mode[:2]), zeta, rtol=1e-8)
    dk = -0.2 * k
    closed = G.A + G.B[:, 1:2] @ (-dk * G.C[2:3])            # u = -dk (x2 - x1), acting as a force pair
    damaged = rt.models.shear_building([m] * n, [k, k + dk, k], damping_ratio=zeta)
    Minv_K = slice(n, 2 * n), slice(0, n)
    assert np.allclose(closed[Minv_K], damaged.A[Minv_K], rtol=1e-12)
    with pytest.raises(rt.ConfigError, match="floors are 1..3"):
        rt.models.shear_building([m] * n, [k] * n, measured=["velocity[4]"])


def test_a_floor_accelerometer_reads_the_derivative_of_its_velocity_plus_the_ground_acceleration():
    """'acceleration[j]' against the time derivative of python-control's velocity response (a fine grid, central
    differences) plus the ground acceleration, under base excitation and with a force pair acting; with a force
    on a floor it is the floor's acceleration alone."""
    import control
    import numpy as np
    m, k = 2.0e4, 2.0e7
    t = np.linspace(0.0, 2.0, 40001)
    w = np.sin(7 * t) + 0.3 * np.sin(23 * t)
    u = 1e4 * np.cos(11 * t)
    for force, ground in (("base", 1.0), (2, 0.0)):
        G = rt.models.shear_building([m] * 3, [k] * 3, damping_ratio=0.02, force=force, identified=[2],
                                     measured=["velocity[2]", "acceleration[2]", "acceleration[-1]", "velocity[-1]"])
        assert np.any(G.D[1:3] != 0)                      # the inputs reach an acceleration at once
        y = control.forced_response(G, t, np.vstack([w, u])).outputs
        h = t[1] - t[0]
        for acc, vel in ((1, 0), (2, 3)):
            derivative = (y[vel, 2:] - y[vel, :-2]) / (2 * h)
            np.testing.assert_allclose(y[acc, 1:-1], derivative + ground * w[1:-1], rtol=0,
                                       atol=2e-5 * np.abs(y[acc]).max())
    with pytest.raises(rt.ConfigError, match="'acceleration\\[j\\]'"):
        rt.models.shear_building([m] * 3, [k] * 3, measured=["accel[1]"])


@pytest.mark.parametrize("name", ["double", "update", "keys", "to"])
def test_a_block_named_like_a_method_of_the_module_container_is_refused_naming_it(name):
    with pytest.raises(rt.ConfigError, match=f"block '{name}' \\(Gain\\) cannot be named so"):
        rt.Graph([rt.Gain(1.0, name=name), rt.WhiteNoise(1, name="w")], [f"w.out -> {name}.in"])


def test_a_function_that_returns_one_value_per_member_as_a_1d_array_is_told_to_return_a_column():
    with pytest.raises(rt.DimensionError, match=r"block 'map': fn must map.*returned \(1,\); return one value per "
                                                r"member as a column"):
        rt.StaticMap(lambda v: v[:, 0] ** 2, 2)
