"""Mistakes a new user makes get a library error that names the block, port or setting and what is accepted."""

import pytest

import rcotorch as rt
from rcotorch import scenario as scenarios


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
