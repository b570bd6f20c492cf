"""numpy_loop.py, a plain per-refinement NumPy loop of sdof-stiffness-damping, against rcotorch.

The loop shares only the excitation samples with the library (rcotorch.engine.rng); its discretization (scipy
expm), Markov parameters, regressor bookkeeping and RLS are written out independently, so agreement to ~1e-9
is a check of the library as well as of the speed baseline."""

import numpy as np
import numpy_loop as nr
import pytest
import torch

from rcotorch.engine import kernels
from rcotorch.run import scenario as scenarios

NAME = "sdof-stiffness-damping"


ENGINES = ["torch", "native"] if kernels.available() else ["torch"]


def _rcotorch(steps, batch=1, engine="auto", **overrides):
    sc = scenarios.get(NAME)
    s = sc.resolve(overrides)
    g = sc.build(s, batch, torch.float64, "cpu")
    g.engine = engine
    g.run(steps)
    return g.blocks["identified"], {k: v.numpy() for k, v in sc.estimates(g, s).items()}


def test_reference_settings_are_the_scenario_defaults():
    s = scenarios.get(NAME).resolve()
    assert {k: s[k] for k in nr.DEFAULTS} == nr.DEFAULTS


@pytest.mark.parametrize("engine", ENGINES)
def test_final_theta_agrees_with_rcotorch_batch_of_one(engine):
    est, e = _rcotorch(2000, engine=engine)
    ref = nr.refine(2000)
    theta = est.theta[0].numpy()
    assert theta.shape == ref["theta"].shape == (1, 3)
    np.testing.assert_allclose(theta, ref["theta"], rtol=1e-9, atol=0)
    P, P_ref = est.P[0].numpy(), ref["P"]
    np.testing.assert_allclose(P, P_ref, rtol=0, atol=1e-8 * np.abs(P_ref).max())
    np.testing.assert_allclose([e["dK"][0], e["dC"][0]], [ref["dK"], ref["dC"]], rtol=1e-9)
    assert abs(ref["dK"] + 0.4) < 0.05 and abs(ref["dC"] - 0.5) < 0.05   # on its way to the truth


@pytest.mark.parametrize("engine", ENGINES)
def test_other_member_and_order_agree(engine):
    """Member 2 of a batch of 3 (noise stream (seed, 2)) with a second-order identified subsystem."""
    est, e = _rcotorch(1500, batch=3, engine=engine, nc=2)
    ref = nr.refine(1500, {"nc": 2}, member=2)
    np.testing.assert_allclose(est.theta[2].numpy(), ref["theta"], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose([e["dK"][2], e["dC"][2]], [ref["dK"], ref["dC"]], rtol=1e-8)


@pytest.mark.slow
def test_full_run_agrees():
    """20,000 steps: the NumPy loop and rcotorch agree to 1e-9, and both land on the paper's result (dK -0.40131,
    dC 0.49911, from its own noise sequence) within three standard deviations of the estimates' spread over
    noise sequences (64 members, each its own stream)."""
    est, e = _rcotorch(20000)
    ref = nr.refine(20000)
    np.testing.assert_allclose(est.theta[0].numpy(), ref["theta"], rtol=1e-9, atol=0)
    _, spread = _rcotorch(20000, batch=64)
    for key, paper in (("dK", -0.40131), ("dC", 0.49911)):
        assert abs(ref[key] - paper) < 3 * spread[key].std(), (key, ref[key], spread[key].std())
