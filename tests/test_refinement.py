"""``rt.refinement`` leaves the caller's blocks as given: the blocks their user named enter under those names,
one left with its class's default name enters as a copy named for its part, and the estimator's sample time comes
with its Markov parameters."""

import control
import numpy as np
import torch

import rcotorch as rt

TS = 0.1


def _known():
    G = rt.models.sdof(m=1.0, c=5.0, k=30.0, measured=["velocity"], sees=["velocity"])
    return rt.LTI.from_control(G, inputs=["w", "u"], outputs=["y", "y0"], dt=TS, name="known")


def _truth(name):
    return rt.LTI.from_control(control.tf([10.0], [1.0, 2.0]), inputs=["in"], outputs=["out"], dt=TS, name=name)


def _build(truth_name, excitation_name):
    known, ident, truth = _known(), rt.RCOEstimator({"y0": 1}, nc=2, p0=1e4), _truth(truth_name)
    excitation = rt.WhiteNoise(1, seed=[1, 2], name=excitation_name)
    noise = rt.WhiteNoise(1, std=0.01, seed=[3, 4])       # named 'excitation' by default, as the excitation
    g = rt.refinement(known, ident, truth=truth, excitation=excitation, noise=noise, nu=10, batch_size=2)
    return g, known, ident, truth, excitation, noise


def test_the_callers_blocks_keep_their_names_and_sample_times():
    g, known, ident, truth, excitation, noise = _build("delta", "drive")
    assert (known.name, ident.name, truth.name, excitation.name, noise.name) == \
        ("known", "identified", "delta", "drive", "excitation")
    assert ident.dt is None and truth.dt == TS and known.dt == TS
    assert set(g.blocks) == {"known", "identified", "drive", "plant", "delta", "noise", "measurement", "error"}
    assert g.role("estimator") is ident and g.role("known") is known
    assert g.blocks["delta"] is truth and g.role("excitation") is excitation        # named by their user
    assert g.blocks["noise"] is not noise and g.blocks["noise"].name == "noise"     # a default name: a copy
    g.run(50)
    assert noise.batch_size == 0 and g.blocks["noise"].batch_size == 2    # the caller's noise block never reset
    assert int(g.blocks["drive"].k) == 50
    # the estimator's sample time is the known model's, given with the Markov parameters
    assert ident.sample_time == TS and ident.markov_dt == TS and ident.to_control(0).dt == TS


def test_the_run_does_not_depend_on_the_names():
    g_copy, *_ = _build("delta", "drive")
    g_own, _, ident, truth, excitation, _ = _build("unknown", "excitation")
    assert g_own.blocks["unknown"] is truth and g_own.role("excitation") is excitation
    a = g_copy.run(400, record={"z": "error.out"})["z"]
    b = g_own.run(400, record={"z": "error.out"})["z"]
    assert torch.equal(a, b) and float(a.abs().max()) > 0
    assert torch.equal(g_copy.role("estimator").theta, ident.theta)


def test_a_physical_block_keeps_its_name_and_one_with_the_default_name_enters_as_plant():
    A, B, C, D = np.array([[0.9]]), np.array([[1.0]]), np.array([[0.5]]), np.array([[0.0]])
    known = rt.LTI(A, np.array([[1.0, 1.0]]), np.vstack([C, C]), np.zeros((2, 2)), ["w", "u"],
                   {"y": 1, "y0": 1}, dt=TS, name="known")
    rig = rt.LTI(A, B, C, D, ["w"], ["y"], dt=TS, name="rig")
    g = rt.refinement(known, rt.RCOEstimator.static_gain({"y0": 1}, p0=10.0), physical=rig,
                      excitation=rt.WhiteNoise(1, seed=5), nu=5)
    assert g.role("physical") is rig and g.roles["measured"] == "rig.y"
    physical = rt.LTI(A, B, C, D, ["w"], ["y"], dt=TS)                     # the class's default name
    default_name = physical.name
    ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=10.0, dt=0.2)
    g = rt.refinement(known, ident, physical=physical, excitation=rt.WhiteNoise(1, seed=5), nu=5)
    assert physical.name == default_name and ident.dt == 0.2 and ident.sample_time == 0.2
    assert g.role("physical").name == "plant" and g.role("physical") is not physical
    # the same system: the copy's y equals the caller's block's on the same input
    physical.reset(1)
    w = g.run(20, record={"w": "excitation.out", "y": "plant.y"})
    ys = []
    for k in range(20):                                 # recordings are (steps, B, width)
        ys.append(physical.output("y", {"w": w["w"][k]}))
        physical.update({"w": w["w"][k]})
    assert torch.equal(torch.stack(ys), w["y"]) and float(w["y"].abs().max()) > 0
