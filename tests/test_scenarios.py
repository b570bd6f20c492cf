"""The seed paper's single-DOF examples reach the accuracy of docs/scenarios.md with their default settings."""

import numpy as np
import pytest

from rcotorch.run.runner import Run

_RUNS: dict = {}


def _finished(name, tmp_path_factory):
    """Each scenario runs once at its defaults; tests share the result."""
    if name not in _RUNS:
        run = Run(name, out=tmp_path_factory.mktemp(name))
        run.advance(progress=False)
        _RUNS[name] = (run, run.finish(figures=False))
    return _RUNS[name]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sdof-dynamic-impedance", "sdof-stiffness", "sdof-stiffness-damping"])
def test_scenario_meets_requirements(name, tmp_path_factory):
    run, summary = _finished(name, tmp_path_factory)
    assert summary["requirements"], "the scenario declares requirements"
    failed = {k: v for k, v in summary["requirements"].items() if not v["pass"]}
    assert not failed, failed
    assert summary["steps"] == run.scenario.steps
    assert summary["diverged"] == []


@pytest.mark.slow
def test_section_iv_frequency_response_matches_zoh_reference(tmp_path_factory):
    """Identified subsystem vs ZOH(10/(s+2)) computed by python-control, on a grid up to Nyquist."""
    import control

    run, _ = _finished("sdof-dynamic-impedance", tmp_path_factory)
    ts = run.settings["Ts"]
    ref = control.sample_system(control.tf([10.0], [1.0, 2.0]), ts, method="zoh")
    tf = run.graph.blocks["identified"].to_control()
    w = np.logspace(-2, np.log10(np.pi / ts), 200)
    z = np.exp(1j * w * ts)
    err = np.abs(tf(z) - ref(z)) / np.abs(ref(z))
    assert err.max() < 0.01
    assert abs(control.dcgain(tf) - 5.0) < 0.01
    assert tf.dt == ts


def test_batched_scenario_members_match_their_single_runs(tmp_path):
    """Member b of a batch-of-3 run (integer seed s) equals a batch-of-one run with stream (s, b)."""
    batched = Run("sdof-stiffness", steps=300, batch=3, out=tmp_path / "b")
    batched.advance(progress=False)
    single = Run("sdof-stiffness", steps=300, batch=1, out=tmp_path / "s")
    single.advance(progress=False)
    th_b = batched.graph.blocks["identified"].theta
    th_s = single.graph.blocks["identified"].theta
    assert np.array_equal(th_b[0].numpy(), th_s[0].numpy())
    assert not np.array_equal(th_b[1].numpy(), th_b[0].numpy())  # other members see other noise
