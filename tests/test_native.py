"""The native engine (rcotorch.engine.lowering, rcotorch.engine._engine): a graph lowered to C and run many
steps per call.

It must do what the PyTorch engine does, to rounding: every lowered block and estimator option is run on
both engines from the same state and compared. Independent references for the engine itself: the NumPy loop
(tests/test_numpy_reference.py runs on both engines) and the closed-form RLS (tests/test_rls.py)."""

import copy
import logging
import os
import subprocess
import sys
import textwrap

import control
import numpy as np
import pytest
import torch

import rcotorch as rt
import rcotorch.graph
from rcotorch.engine import kernels, lowering
from rcotorch.run import scenario as scenarios

pytestmark = pytest.mark.skipif(not kernels.available(), reason=f"no native engine: {kernels.why_unavailable()}")

DT = 0.1


def _pair(build):
    """Two copies of a graph: one on each engine."""
    a, b = build(), build()
    a.engine, b.engine = "torch", "native"
    assert b.native_status() is None, b.native_status()
    return a, b


def _assert_same_state(a, b, rtol=1e-9):
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for key, t in sa.items():
        u = sb[key]
        if t.is_floating_point():
            scale = max(float(t.abs().max()) if t.numel() else 0.0, 1e-300)
            np.testing.assert_allclose(u.numpy(), t.numpy(), rtol=0, atol=rtol * max(scale, 1.0), err_msg=key)
        else:
            assert torch.equal(t, u), key


def _run_both(build, steps, chunks=(1,)):
    a, b = _pair(build)
    acc_a, acc_b = (torch.zeros(a.batch_size, dtype=torch.float64) for _ in range(2))
    a.advance(steps, {("error", "out"): acc_a})
    done = 0
    for c in chunks:                          # the native run in several calls
        n = max(1, int(steps * c / sum(chunks)))
        n = min(n, steps - done)
        b.advance(n, {("error", "out"): acc_b})
        done += n
    b.advance(steps - done, {("error", "out"): acc_b})
    np.testing.assert_allclose(acc_b.numpy(), acc_a.numpy(), rtol=1e-9)
    for sig in a.last:
        np.testing.assert_allclose(b.last[sig].numpy(), a.last[sig].numpy(), rtol=1e-8, atol=1e-12, err_msg=str(sig))
    return a, b


@pytest.mark.parametrize("name,overrides", [
    ("sdof-stiffness-damping", {}),
    ("sdof-stiffness", {"lam": 0.999}),
    ("sdof-dynamic-impedance", {}),
    ("twodof-stiffness", {}),
    ("twodof-stiffness", {"truth": "discrete"}),
    ("rlc-circuit", {}),
    ("silverbox-cubic-stiffness", {}),
])
def test_scenarios_agree_with_the_torch_engine(name, overrides):
    """Every shipped scenario runs natively (the thermosphere: tests/test_thermosphere_native.py)."""
    sc = scenarios.get(name)
    s = sc.resolve(overrides)
    try:
        sc.build(s, 1, torch.float64, "cpu")
    except rt.DataError as e:                       # the Silverbox files live outside the repository
        pytest.skip(str(e))
    a, b = _run_both(lambda: sc.build(s, 3, torch.float64, "cpu"), 700, chunks=(3, 1, 2))
    _assert_same_state(a, b)


def test_the_thermosphere_runs_natively_with_its_markov_refresh():
    sc = scenarios.get("thermosphere-no-cooling")
    g = sc.build(sc.resolve(), 1, torch.float64, "cpu")
    assert g.native_status() is None and any(isinstance(h, rt.MarkovRefresh) for h in g.hooks)


# --- every option of the estimator ---------------------------------------------------------------------
F = rt.features


def _structure_graph(est, B=4, measured=("velocity",), sees=("position", "velocity"), n_u=1):
    """A refinement around an SDOF (n_u = 1) or 2-DOF (n_u = 2, one force per mass) known model with a truth
    of other stiffness and damping, a white-noise force per member and per-member seeds."""
    if n_u == 1:
        M, C, K, Ct, Kt, fw = [[1.0]], [[0.6]], [[1.5]], [[0.9]], [[2.0]], [1.0]
    else:
        M, fw = np.eye(2), [1.0, 1.0]
        C, K = np.array([[1.2, -0.4], [-0.4, 1.0]]), np.array([[1.5, -0.5], [-0.5, 1.3]])
        Ct, Kt = C + np.diag([0.2, 0.0]), K + np.diag([0.4, 0.3])
    G = rt.models.structure(M, C, K, fw, measured=measured, sees=sees)
    T = rt.models.structure(M, Ct, Kt, fw, measured=measured, sees=[], actuation=False)
    known = rt.LTI.from_control(G, inputs={"w": 1, "u": n_u}, outputs={"y": len(measured), "y0": len(sees)},
                                dt=DT, name="known")
    truth = rt.LTI.from_control(T, inputs=["w"], outputs={"y": len(measured)}, dt=DT, name="plant")
    return rt.refinement(known, est, physical=truth, excitation=rt.WhiteNoise(1, seed=list(range(3, 3 + B))),
                         nu=8, batch_size=B)


P0 = [1e2, 1e3, 1e4, 1e5]
OPTIONS = {
    "dynamic nc=2, per-member p0 and lam": lambda: rt.RCOEstimator(
        {"y0": 2}, nc=2, p0=P0, lam=[1.0, 0.999, 0.995, 1.0]),
    "proper with past samples": lambda: rt.RCOEstimator({"y0": 2}, nc=1, proper=True, p0=100.0),
    "FIR (no past u)": lambda: rt.RCOEstimator({"y0": 2}, nc=2, feed_u=False, p0=100.0),
    "regressors y0 and w": lambda: rt.RCOEstimator({"y0": 2, "w": 1}, nc=1, p0=100.0, lam=0.998),
    "masked": lambda: rt.RCOEstimator({"y0": 2}, nc=2, p0=100.0, mask=[[True, False, True, True, True, False]]),
    "tied": lambda: rt.RCOEstimator({"y0": 2}, nc=2, p0=100.0, tie=[[0, 1, 0, 1, 2, 3]]),
    "bounds on u and theta": lambda: rt.RCOEstimator(
        {"y0": 2}, nc=1, p0=P0, u_bounds=(-0.5, 2.0), theta_bounds=([-1, -1, -0.5], 1.5)),
    "two z channels, full R": lambda: rt.RCOEstimator(
        {"y0": 2}, n_z=2, nc=1, p0=P0, R=[[2.0, 0.3], [0.3, 0.5]], lam=0.999),
    "features, static": lambda: rt.RCOEstimator.static_gain(
        {"y0": 2}, p0=100.0, features=[F.port("y0[0]"), F.power("y0[1]", 3), F.sign("y0[1]") * F.power("y0[1]", 2),
                                       F.absolute("y0[0]") * F.port("y0[1]"), F.constant(0.1)]),
    "features, dynamic, every kind": lambda: rt.RCOEstimator(
        {"y0": 2}, nc=2, p0=10.0, features=[
            F.saturation("y0[1]", -0.2, 0.3), F.dead_zone("y0[0]", 0.05), 2.0 * F.tanh("y0[1]", 0.5),
            F.affine("y0[0]", 3.0, 0.1), F.monomial(y0=2), F.product("y0[0]", "y0[1]")]),
    "features over a whole port": lambda: rt.RCOEstimator.static_gain(
        {"y0": 2}, p0=100.0, features=[F.port("y0"), F.power("y0", 3)]),
    "penalty on theta's change, per member": lambda: rt.RCOEstimator(
        {"y0": 2}, nc=1, p0=P0, r_delta=[0.0, 0.1, 1.0, 10.0]),
    "normalized regressors, per member": lambda: rt.RCOEstimator(
        {"y0": 2}, nc=1, p0=P0, normalize=[0.1, 1.0, 10.0, 1e3]),
    "trace bound on P, per member": lambda: rt.RCOEstimator(
        {"y0": 2}, nc=1, p0=P0, lam=0.99, p_max=[1.0, 50.0, 1e3, 1e6]),
    "every robustness option, tied": lambda: rt.RCOEstimator(
        {"y0": 2}, nc=2, p0=100.0, tie=[[0, 1, 0, 1, 2, 3]], lam=0.995, r_delta=0.5, normalize=2.0, p_max=200.0),
}
MIMO_OPTIONS = {   # both velocities measured (n_z = 2)
    "MIMO dynamic": lambda: rt.RCOEstimator({"y0": 2}, n_u=2, n_z=2, nc=1, p0=10.0),
    "MIMO masked static gain": lambda: rt.RCOEstimator.static_gain(
        {"y0": 2}, n_u=2, n_z=2, p0=1e3, lam=0.999, mask=[[True, False], [False, True]]),
    "MIMO tied, two z channels": lambda: rt.RCOEstimator.static_gain(
        {"y0": 2}, n_u=2, n_z=2, p0=1e3, tie=[[0, -1], [-1, 0]]),
    "MIMO features, two z channels": lambda: rt.RCOEstimator(
        {"y0": 2}, n_u=2, n_z=2, nc=1, p0=100.0, R=[[1.0, 0.2], [0.2, 2.0]],
        features=[F.power("y0", 3), F.sign("y0[0]")]),
    "MIMO robustness options, two z channels": lambda: rt.RCOEstimator(
        {"y0": 2}, n_u=2, n_z=2, nc=1, p0=100.0, R=[[1.0, 0.2], [0.2, 2.0]], lam=0.995, r_delta=[0.1, 1.0, 2.0, 5.0],
        normalize=1.0, p_max=500.0),
}


@pytest.mark.parametrize("option", list(OPTIONS) + list(MIMO_OPTIONS))
def test_estimator_options_agree_with_the_torch_engine(option):
    mimo = option in MIMO_OPTIONS
    make = MIMO_OPTIONS[option] if mimo else OPTIONS[option]
    measured = ("velocity[0]", "velocity[1]") if mimo else ("velocity", "position")[:make().n_z]
    sees = ("position[0]", "position[1]") if mimo else ("position", "velocity")
    a, b = _run_both(lambda: _structure_graph(make(), measured=measured, sees=sees, n_u=2 if mimo else 1), 700,
                     chunks=(2, 5))
    _assert_same_state(a, b)
    est = b.role("estimator")
    assert bool(est.alive.all()) and float(est.theta.abs().max()) > 0


def test_per_member_parameters_bounds_and_feedthrough(sdof_known, zoh_first_order):
    """Per-member truth, p0, lambda and seeds; saturated u and projected theta; a Gain; a proper LTI (D != 0)."""
    def build():
        B = 4
        known = sdof_known(DT)
        truth = rt.LTI(np.array([0.8, 0.85, 0.9, 0.7]).reshape(B, 1, 1), [[1.0]], [[1.0]], [[0.3]], ["in"], ["out"],
                       DT, name="unknown")
        est = rt.RCOEstimator({"y0": 1}, nc=2, p0=[1e2, 1e3, 1e4, 1e5], lam=[1.0, 0.999, 0.995, 1.0],
                              u_bounds=(-0.5, 2.0), theta_bounds=([-1, -1, -1, -0.5], 1.5))
        g = rt.refinement(known, est, truth=truth, excitation=rt.WhiteNoise(1, std=[1.0, 2.0, 0.5, 1.0],
                                                                              seed=[3, 4, 5, 6]),
                          nu=8, batch_size=B)
        # route the excitation through a gain, to lower a Gain block too
        blocks = list(g.blocks.values()) + [rt.Gain([[0.5]], name="scale")]
        conns = [(f"{s[0]}.{s[1]}", f"{d[0]}.{d[1]}") for d, s in g.sources.items() if d != ("plant", "w")]
        conns.append(("excitation.out", "scale.in"))
        conns.append(("scale.out", "plant.w"))
        return rt.Graph(blocks, conns, batch_size=B)

    a, b = _run_both(build, 600, chunks=(1, 1))
    _assert_same_state(a, b)
    est = b.blocks["identified"]
    assert float(est.theta.min()) >= -1.0 and float(est.theta.max()) <= 1.5
    assert float(est.u_now.min()) >= -0.5 and float(est.u_now.max()) <= 2.0


def test_recorded_data_with_gaps():
    """Recorded w, y with invalid samples: the held value is played and the update skipped."""
    rng = np.random.default_rng(0)
    T = 400
    w = rng.normal(size=T)
    sysd = control.sample_system(control.ss([[0, 1], [-2, -0.5]], [[0], [1]], [[0, 1]], [[0]]), DT)
    y = control.forced_response(sysd, U=w).outputs
    values = np.stack([w, y], 1)
    values[[50, 51, 200], 1] = np.nan
    rec = rt.Recording(np.nan_to_num(values), ["w", "y"], DT, valid=np.isfinite(values))

    def build():
        G = rt.models.sdof(1.0, 0.6, 1.5, measured=["velocity"], sees=["velocity"])
        known = rt.LTI.from_control(G, inputs=["w", "u"], outputs=["y", "y0"], dt=DT, name="known")
        est = rt.RCOEstimator({"y0": 1}, nc=1, p0=100.0)
        return rt.refinement(known, est, data=rt.Recorded(rec, {"w": "w", "y": "y"}), nu=6)

    a, b = _run_both(build, T, chunks=(1, 3))
    _assert_same_state(a, b)
    with pytest.raises(rt.DataError, match="past the end"):
        b.advance(1)


def test_batch_members_thread_count_and_call_lengths_are_bitwise_invariant():
    """Member b of a batch equals its batch-of-one run bit for bit, with 1 or 2 threads, in any number of
    calls: a member's arithmetic does not depend on the batch, the chunking or the threads."""
    sc = scenarios.get("sdof-stiffness-damping")
    # Seeds and tuning per member (per-member physics would also change how the truth is discretized).
    members = [{"seed": 5 + i, "p0": [1e6, 1e4, 1e5][i % 3], "lam": [1.0, 0.999][i % 2]} for i in range(21)]
    s = sc.resolve_members({}, members)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        big = sc.build(s, len(members), torch.float64, "cpu")
        big.engine = "native"
        assert kernels.threads(len(members), 3200) == 2             # enough work for the second thread
        big.advance(3200)
    finally:
        torch.set_num_threads(threads)
    for b in (0, 17, 20):
        one = sc.build(sc.resolve(members[b]), 1, torch.float64, "cpu")
        one.engine = "native"
        one.advance(1234)
        one.advance(1966)
        e1, eb = one.blocks["identified"], big.blocks["identified"]
        for key in ("theta", "P", "past", "past_u", "z_r"):
            assert torch.equal(getattr(e1, key)[0], getattr(eb, key)[b]), (b, key)
        assert torch.equal(e1.win[:, 0], eb.win[:, b])


def test_engines_take_turns_and_step_sees_native_state():
    sc = scenarios.get("sdof-stiffness-damping")
    s = sc.resolve()
    a, b = _pair(lambda: sc.build(s, 3, torch.float64, "cpu"))
    a.advance(200)
    b.advance(100)
    for _ in range(50):
        b.step()                        # PyTorch steps in between
    b.advance(50)
    _assert_same_state(a, b)
    assert int(b.k) == 200 and int(b.blocks["identified"].k) == 200 and int(b.blocks["excitation"].k) == 200


@pytest.mark.parametrize("states,regressors,feedthrough",
                         [(1, 1, False), (3, 2, False), (2, 3, False), (2, 3, True), (4, 5, False), (6, 6, False),
                          (7, 7, False)])
def test_one_member_runs_the_size_compiled_operations_like_a_batch_member(states, regressors, feedthrough):
    """One member alone runs LTI operations of up to 4 states and 1-2 rows (without feedthrough) or input
    columns, SISO estimators of up to 6 parameters and the error's sum compiled with their sizes as constants
    (the others: the general code), and sums the Markov filter of m = regressors + 1 columns 4, then 2 at a time
    in vectors, then one by one (m = 2, 3, 4, 6, 7, 8). The arithmetic is the same: the member
    equals member 0 of a batch in 16 lanes bit for bit, and the PyTorch engine to rounding."""
    rng = np.random.default_rng(10 * states + regressors)
    A = -np.diag(np.linspace(1.0, 3.0, states)) + 0.3 * np.eye(states, k=1)
    Bk, Cy0 = rng.normal(size=(states, 2)), rng.normal(size=(regressors, states))
    Cy = rng.normal(size=(1, states))
    D = np.zeros((1 + regressors, 2))
    D[0, 0] = 0.5 if feedthrough else 0.0             # w -> y: the general output code at one lane
    known_sys = control.ss(A, Bk, np.vstack([Cy, Cy0]), D)
    truth_sys = control.ss(A - 0.4 * np.outer(Bk[:, 1], Cy0[0]), Bk[:, :1], Cy, D[:1, :1])

    def build(B):
        known = rt.LTI.from_control(known_sys, inputs={"w": 1, "u": 1}, outputs={"y": 1, "y0": regressors},
                                    dt=DT, name="known")
        truth = rt.LTI.from_control(truth_sys, inputs=["w"], outputs=["y"], dt=DT, name="plant")
        est = rt.RCOEstimator.static_gain({"y0": regressors}, p0=100.0, lam=0.999)
        return rt.refinement(known, est, physical=truth, excitation=rt.WhiteNoise(1, seed=list(range(3, 3 + B))),
                             nu=9, batch_size=B)

    one_torch, one = _run_both(lambda: build(1), 300)
    _assert_same_state(one_torch, one)
    batch = build(40)                                 # 16 lanes: the general code
    batch.engine = "native"
    batch.advance(300)
    e1, eb = one.blocks["identified"], batch.blocks["identified"]
    assert e1.theta.numel() == regressors and bool(e1.alive.all()) and float(e1.theta.abs().max()) > 1e-3
    for key in ("theta", "P", "z_r"):
        assert torch.equal(getattr(e1, key)[0], getattr(eb, key)[0]), key
    assert torch.equal(e1.win[:, 0], eb.win[:, 0])
    assert torch.equal(one.blocks["known"].x[0], batch.blocks["known"].x[0])


def test_one_member_sums_the_markov_filter_before_storing_the_current_row_with_the_same_results():
    """One member (the SISO estimator) sums its Markov filter before this step's row is stored, where that row
    is weighed by 0 (first delay 1), and sums again with the row where a sum or the row is not finite. Three
    members with infinite samples, each alone and in a batch of 16 lanes (the general order): phi infinite
    while active (member 0 fails there); phi infinite while inactive, that row the oldest of the ring, where
    the current row goes, when the member is active again (member 1 lives on); u infinite from a finite phi
    (member 2 fails); a finite z so large that the step is not finite while S is (member 3 fails). Each member
    alone equals its batch member bit for bit; the batch equals the PyTorch engine to rounding."""
    T, k1, B = 120, 40, 16
    rng = np.random.default_rng(5)
    data = np.zeros((B, T, 3))
    data[:, :, 0] = rng.normal(size=(B, T))                       # s
    data[:, :, 1] = rng.normal(size=(B, T))                       # z
    data[:, :, 2] = 1.0                                           # valid
    data[0, k1, 0] = 1e308                                        # x 10: inf at k1, in phi(k1 + 1)
    data[1, k1, 0] = 1e308
    data[1, k1 - 2:k1 + 7, 2] = 0.0                               # inactive while that row has a weight
    data[2, k1, 0] = 1e306                                        # finite; u = 1000 x 1e307 overflows
    data[3, :, 0] *= 1e-5                                         # Psi ~ 1e-4, P ~ p0: P Psi ~ 100, S ~ 1
    data[3, k1, 1] = 1e308                                        # z_R finite, the step P Psi z_R / S not
    theta0 = np.full((B, 1, 1), -0.5)
    theta0[2] = 1e3
    p0 = np.ones(B)
    p0[2] = 1e-30                                                 # member 2's theta stays near 1000
    p0[3] = 1e6

    def build(members):
        src = rt.Recorded(data[members], {"s": 0, "z": 1, "v": 2}, name="data")
        est = rt.RCOEstimator({"s": 1}, nc=1, feed_u=False, markov=[[[1.0]], [[0.5]], [[0.25]], [[0.1]], [[0.05]]],
                              theta0=theta0[members], p0=p0[members], name="identified")
        return rt.Graph([src, rt.Gain(10.0, name="g"), est],
                        ["data.s -> g.in", "g.out -> identified.s", "data.z -> identified.z",
                         "data.v -> identified.valid"], batch_size=len(members))

    a, b = _pair(lambda: build(list(range(B))))
    a.advance(T)
    b.advance(T)
    ea, eb = a.blocks["identified"], b.blocks["identified"]
    assert eb.alive[:4].tolist() == [False, True, False, False] and bool(eb.alive[4:].all())
    assert eb.diverged_at[:4].tolist() == [k1 + 1, -1, k1 + 1, k1] and torch.equal(ea.diverged_at, eb.diverged_at)
    for key in ("theta", "P"):
        np.testing.assert_allclose(getattr(eb, key).numpy(), getattr(ea, key).numpy(), rtol=1e-9, atol=1e-12)
    for m in range(5):
        one = build([m])
        one.engine = "native"
        one.advance(T)
        e1 = one.blocks["identified"]
        assert torch.equal(e1.diverged_at[0], eb.diverged_at[m]), m
        for key in ("theta", "P", "z_r"):
            x, y = getattr(e1, key)[0], getattr(eb, key)[m]
            assert torch.equal(torch.isnan(x), torch.isnan(y)) and torch.equal(x.nan_to_num(), y.nan_to_num()), \
                (m, key)
        assert torch.equal(e1.win[:, 0].nan_to_num(), eb.win[:, m].nan_to_num()), m


def test_diverging_member_is_frozen_natively():
    a_ = np.exp(-2.0 * DT)
    poles = [a_, 10.0, 0.9 * a_]

    def build():
        b = 10.0 * (1.0 - np.exp(-2.0 * DT)) / 2.0
        truth = rt.LTI(np.reshape(poles, (3, 1, 1)), [[b]], [[1.0]], [[0.0]], ["in"], ["out"], DT)
        sys = control.ss([[0.0, 1.0], [-30.0, -5.0]], [[0.0, 0.0], [1.0, 1.0]], [[0.0, 1.0], [0.0, 1.0]],
                         np.zeros((2, 2)))
        known = rt.LTI.from_control(sys, inputs=["w", "u"], outputs=["y", "y0"], dt=DT, name="known")
        est = rt.RCOEstimator({"y0": 1}, nc=2, p0=1e4)
        return rt.refinement(known, est, truth=truth, excitation=rt.WhiteNoise(1, seed=[1, 2, 3]), nu=10,
                             batch_size=3)

    a, b = _pair(build)
    a.advance(400)
    b.advance(400)
    ea, eb = a.blocks["identified"], b.blocks["identified"]
    assert eb.alive.tolist() == [True, False, True]
    # Where P loses definiteness while the signals blow up (10x per step) depends on rounding: a step or two.
    assert eb.diverged_at[[0, 2]].tolist() == [-1, -1] and abs(int(eb.diverged_at[1]) - int(ea.diverged_at[1])) <= 3
    assert torch.isfinite(eb.theta).all() and torch.isfinite(eb.P).all()
    for key in ("theta", "P"):
        np.testing.assert_allclose(getattr(eb, key)[[0, 2]].numpy(), getattr(ea, key)[[0, 2]].numpy(), rtol=1e-8,
                                   atol=1e-8)
    assert float(eb.u_now[1].abs().max()) == 0.0             # a frozen member outputs u = 0


def test_engine_choice_and_unsupported_graphs(sdof_known):
    known = sdof_known(DT)
    est = rt.RCOEstimator({"y0": 1}, nc=1)
    g = rt.refinement(known, est, truth=rt.StaticMap(lambda v: torch.neg(v), 1, name="unknown"),
                      excitation=rt.WhiteNoise(1), nu=4)           # a torch function: not compiled
    assert "StaticMap" in g.native_status() and "torch" in g.native_status()
    g.engine = "native"
    with pytest.raises(rt.ConfigError, match="StaticMap"):
        g.advance(3)
    g.engine = "auto"
    g.advance(3)                                               # falls back to PyTorch
    assert int(g.k) == 3
    with pytest.raises(rt.ConfigError, match="engine must be one of"):
        g.engine = "fast"
    g2 = rt.refinement(sdof_known(DT), rt.RCOEstimator({"y0": 1}, nc=1, features={"v3": lambda s: s["y0"].pow(3)}),
                       truth=rt.Gain([[0.1]], name="unknown"), excitation=rt.WhiteNoise(1), nu=4)
    assert "feature 'v3'" in g2.native_status()                # a tensor method: not compiled
    g2.add_hook(lambda graph: None)
    assert "step hook" in g2.native_status()
    g3 = rt.refinement(sdof_known(DT), rt.RCOEstimator({"y0": 1}, nc=1), truth=rt.Gain([[0.1]], name="unknown"),
                       excitation=rt.WhiteNoise(1), nu=4, dtype=torch.float32)
    assert "float32" in g3.native_status()


def _subprocess(code: str, env: dict | None = None) -> str:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                         env=env or dict(os.environ), timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_runs_stay_native_without_a_compiler_on_path(tmp_path):
    """The engine is compiled when the package is installed: nothing is compiled when it runs."""
    env = dict(os.environ, CC=str(tmp_path / "no-such-compiler"), PATH=str(tmp_path))
    out = _subprocess("""
        import torch
        from rcotorch.run import scenario as scenarios
        sc = scenarios.get("sdof-stiffness")
        g = sc.build(sc.resolve(), 2, torch.float64, "cpu")
        g.advance(50)
        print("ENGINE", g.ran_engine, g.engine_reason, int(g.k))
    """, env)
    assert "ENGINE native None 50" in out


def test_without_the_compiled_engine_one_warning_and_the_same_results():
    """The extension absent (a machine without a compiler at install time): one warning, every graph on
    PyTorch, and the results of the native engine to rounding."""
    out = _subprocess("""
        import sys, warnings
        sys.modules["rcotorch.engine._engine"] = None          # as if it had not been built
        import torch
        from rcotorch.run import scenario as scenarios
        sc = scenarios.get("sdof-stiffness-damping")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for _ in range(2):
                g = sc.build(sc.resolve(), 2, torch.float64, "cpu")
                g.advance(300)
        print("WARNINGS", sum("native engine unavailable" in str(w.message) for w in caught))
        print("ENGINE", g.ran_engine, "|", g.engine_reason)
        print("THETA", g.role("estimator").theta.flatten().tolist())
    """)
    lines = dict(line.split(" ", 1) for line in out.splitlines())
    assert lines["WARNINGS"] == "1"
    assert lines["ENGINE"].startswith("torch | the native engine is unavailable")
    sc = scenarios.get("sdof-stiffness-damping")
    g = sc.build(sc.resolve(), 2, torch.float64, "cpu")
    g.engine = "native"
    g.advance(300)
    theta = torch.tensor(eval(lines["THETA"]), dtype=torch.float64)
    np.testing.assert_allclose(theta.numpy(), g.role("estimator").theta.flatten().numpy(), rtol=1e-10)


def test_members_equal_their_batch_of_one_runs_with_features_and_two_z_channels():
    """A member's arithmetic is the same in lanes of 1, 4, 8 or 16 (the lane width follows the batch)."""
    make = MIMO_OPTIONS["MIMO features, two z channels"]
    sees, measured = ("position[0]", "position[1]"), ("velocity[0]", "velocity[1]")

    def build(B, seeds):
        g = _structure_graph(make(), B=B, measured=measured, sees=sees, n_u=2)
        g.blocks["excitation"].seed = torch.tensor(seeds)
        g.reset(B)
        g.engine = "native"
        return g

    big = build(23, list(range(40, 63)))
    big.advance(250)
    for b in (0, 9, 22):
        one = build(1, [40 + b])
        one.advance(100)
        one.advance(150)
        for key in ("theta", "P", "past", "z_r", "u_now"):
            assert torch.equal(getattr(one.role("estimator"), key)[0], getattr(big.role("estimator"), key)[b]), key


def test_checkpoint_and_resume_is_bitwise():
    sc = scenarios.get("twodof-stiffness")
    s = sc.resolve()
    whole = sc.build(s, 3, torch.float64, "cpu")
    whole.advance(500)
    first = sc.build(s, 3, torch.float64, "cpu")
    first.advance(321)
    state = {k: v.clone() for k, v in first.state_dict().items()}
    resumed = sc.build(s, 3, torch.float64, "cpu")
    resumed.load_state_dict(state)
    resumed.advance(179)
    assert resumed.ran_engine == "native"
    for key, t in whole.state_dict().items():
        assert torch.equal(t, resumed.state_dict()[key]), key


@pytest.mark.parametrize("every", [1, 3])
def test_recording_inside_the_engine(every):
    """``run(record=...)`` records natively in one call; the traces are those of the PyTorch engine, and a
    callable (Python after every ``every`` steps) sees the same values."""
    sc = scenarios.get("sdof-stiffness-damping")
    a, b = _pair(lambda: sc.build(sc.resolve(), 4, torch.float64, "cpu"))
    rec = {"z": "error.out", "u": "identified.u", "y0": "known.y0"}
    ta = a.run(301, record=rec, every=every)
    tb = b.run(301, record={**rec, "theta": lambda g: g.role("estimator").theta[:, 0, 0]}, every=every)
    for key in rec:
        assert tb[key].shape == ta[key].shape == (301 // every, 4, 2 if key == "y0" else 1)
        np.testing.assert_allclose(tb[key].numpy(), ta[key].numpy(), rtol=1e-9, atol=1e-12)
    assert tb["theta"].shape == (301 // every, 4) and b.ran_engine == "native"
    if every == 1:
        assert torch.equal(tb["theta"][-1], b.role("estimator").theta[:, 0, 0])


def test_the_program_is_lowered_once_and_again_when_the_graph_changes():
    sc = scenarios.get("sdof-stiffness-damping")
    g = sc.build(sc.resolve(), 2, torch.float64, "cpu")
    prog = lowering.program(g)
    g.advance(10)
    g.run(20, record={"z": "error.out"})
    for _ in range(3):
        g.step()                                       # PyTorch steps replace state tensors: same program
    assert lowering.program(g) is prog
    est = g.role("estimator")
    est.lam.fill_(0.99)                                # a parameter changed in place: lowered again
    assert lowering.program(g) is not prog
    prog = lowering.program(g)
    g.reset(3)                                         # another batch size
    assert lowering.program(g) is not prog


def test_the_program_cache_is_invalidated_patched_after_a_refill_and_not_copied():
    sc = scenarios.get("sdof-stiffness-damping")
    g = sc.build(sc.resolve(), 2, torch.float64, "cpu")
    prog = lowering.program(g)
    lowering.invalidate(g)                             # dropped: lowered again
    assert lowering.program(g) is not prog
    prog = lowering.program(g)
    est = g.role("estimator")
    est.lam.mul_(1.0)                                  # in place: a new version of a parameter
    lowering.refilled(g, est.lam)                      # which the program is told it reads already
    assert lowering.program(g) is prog
    lowering.refilled(g, torch.zeros(1))               # a tensor it was not made with: nothing changes
    assert lowering.program(g) is prog
    twin = copy.deepcopy(g)                            # a copy lowers its own blocks
    assert twin._program_cache.outcome is None and lowering.program(twin) is not prog
    assert lowering.program(g) is prog


def test_engine_choice_is_said_once_and_kept(caplog):
    sc = scenarios.get("thermosphere-no-cooling")
    g = sc.build(sc.resolve(), 1, torch.float64, "cpu")
    g.add_hook(lambda graph: None)                      # a hook after every step keeps it on PyTorch
    rcotorch.graph._TOLD.clear()
    twin = copy.deepcopy(g)                             # a copy (for the intervals, the validation) says no more
    with caplog.at_level(logging.INFO, logger="rcotorch"):
        g.advance(2)
        g.advance(2)
        twin.advance(1)
    said = [r for r in caplog.records if "PyTorch engine" in r.getMessage()]
    assert len(said) == 1 and g.ran_engine == "torch" and g.engine_reason == g.native_status()
    assert twin.ran_engine == "torch"
    g.engine = "native"
    with pytest.raises(rt.ConfigError, match="engine='native', but"):
        g.advance(1)
    sc = scenarios.get("sdof-stiffness")
    g = sc.build(sc.resolve(), 1, torch.float64, "cpu")
    g.advance(5)
    assert (g.ran_engine, g.engine_reason) == ("native", None)
    g.engine = "torch"
    g.advance(5)
    assert (g.ran_engine, g.engine_reason) == ("torch", "engine='torch'")


def test_the_torch_engine_runs_no_compiled_code(monkeypatch):
    class Refuse:
        def __getattr__(self, name):
            raise AssertionError(f"compiled code called: {name}")

    sc = scenarios.get("sdof-stiffness-damping")
    g = sc.build(sc.resolve(), 3, torch.float64, "cpu")
    g.engine = "torch"
    monkeypatch.setattr(kernels, "_engine", Refuse())
    g.advance(30)
    g.run(10, record={"z": "error.out"})
    assert int(g.k) == 40


def test_a_subclass_that_changes_a_block_keeps_the_graph_on_pytorch(sdof_known):
    class Leaky(rt.Gain):
        def output(self, port, inputs):
            return 0.9 * super().output(port, inputs)

    g = rt.refinement(sdof_known(DT), rt.RCOEstimator({"y0": 1}, nc=1), truth=Leaky([[0.1]], name="unknown"),
                      excitation=rt.WhiteNoise(1), nu=4)
    assert "overrides output() of Gain" in g.native_status()


def _anon_huge_kib(lo: int, hi: int) -> int:
    """AnonHugePages (KiB) of this process's mappings that overlap [lo, hi)."""
    total, inside = 0, False
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()[0]
            if "-" in head and not head.endswith(":"):
                a, b = (int(x, 16) for x in head.split("-"))
                inside = a < hi and b > lo
            elif inside and head == "AnonHugePages:":
                total += int(line.split()[1])
    return total


def test_large_recording_buffers_are_backed_by_huge_pages():
    """kernels.empty advises a large buffer as huge-page memory before it is touched: once filled, the
    system backs it with 2 MiB pages (where it offers them on request), and the values are those written."""
    try:
        mode = open("/sys/kernel/mm/transparent_hugepage/enabled").read()
    except OSError:
        pytest.skip("no transparent huge pages on this system")
    if "[never]" in mode:
        pytest.skip("transparent huge pages are off on this system")
    buf = kernels.empty((64, 1024, 128), torch.float64)      # 64 MiB
    buf.fill_(1.5)
    lo = buf.data_ptr()
    assert _anon_huge_kib(lo, lo + buf.numel() * 8) >= 32 * 1024
    assert buf.shape == (64, 1024, 128) and float(buf.sum()) == 1.5 * buf.numel()
    small = kernels.empty((3, 2), torch.float64)               # below one huge page: a plain tensor
    assert small.shape == (3, 2) and small.dtype == torch.float64


class _NoisySystem(rt.Block):
    """A composite block of a user's: a system (input w, output y) plus white noise on y, lowered by inlining
    both inside it."""

    def __init__(self, system, std, seed):
        super().__init__("plant", {"w": system.inputs["w"]}, {"y": system.outputs["y"]})
        self.system, self.noise = system, rt.WhiteNoise(system.outputs["y"], std=std, seed=seed, name="noise")

    def feedthrough(self):
        return {"y": tuple(self.system.feedthrough()["y"])}

    def reset(self, batch_size):
        super().reset(batch_size)
        self.system.reset(batch_size)
        self.noise.reset(batch_size)

    def output(self, port, inputs):
        return self.system.output("y", inputs) + self.noise.output("out", {})

    def update(self, inputs):
        self.system.update({"w": inputs["w"]})
        self.noise.update({})

    def lower(self, b):
        w = self.outputs["y"]
        y, n = b.scratch(w), b.scratch(w)
        b.inline(self.system, {"w": b.input("w")}, {"y": y}, port="y")
        b.inline(self.noise, {}, {"out": n}, port="y")
        b.emit("SUM", [w, 2, b.output("y"), y, 1, n, 1], port="y")


def test_a_composite_block_lowers_the_blocks_it_holds_and_equals_pytorch():
    def build(engine):
        sysd = control.c2d(control.ss([[0, 1], [-4, -0.4]], [[0], [1]], [[0, 1]], 0), 0.01)
        plant = _NoisySystem(rt.LTI.from_control(sysd, inputs=["w"], outputs=["y"]), std=0.05, seed=[3, 4])
        g = rt.Graph([rt.WhiteNoise(1, seed=[1, 2], name="w"), plant], [("w.out", "plant.w")], batch_size=2)
        g.engine = engine
        return g
    native, torch_ = build("native"), build("torch")
    a = native.run(500, record={"y": "plant.y"})["y"]
    b = torch_.run(500, record={"y": "plant.y"})["y"]
    assert native.ran_engine == "native"
    assert torch.allclose(a, b, rtol=1e-12, atol=1e-14)
    assert "blocks.plant.noise.k" in native.state_dict() and int(native.blocks["plant"].noise.k) == 500


@pytest.mark.parametrize("nu", [15, 22])
def test_the_ring_row_past_two_to_the_32_steps_agrees_with_the_torch_engine(nu):
    """The native update takes a step's ring row k mod W by a multiply and a shift below 2^32 steps and by a
    division beyond (kernels.ring_multiplier): started 40 steps before 2^32, both engines agree, across the
    switch, for W = nu + 1 a power of two and not."""
    sc = scenarios.get("sdof-stiffness-damping")
    s = sc.resolve({"nu": nu})
    graphs = []
    for engine in ("native", "torch"):
        g = sc.build(s, 2, torch.float64, "cpu")
        g.engine = engine
        g.run(200)
        for blk in g.blocks.values():                 # every counter moved forward, as after 2^32 steps
            if "k" in dict(blk.named_buffers()):
                blk.k += 2 ** 32 - 240
        g.run(80)
        graphs.append(g)
    a, b = (g.role("estimator") for g in graphs)
    assert int(a.k) == 2 ** 32 + 40
    assert torch.allclose(a.theta, b.theta, rtol=1e-10, atol=0) and torch.allclose(a.P, b.P, rtol=1e-10, atol=0)
    for W in (1, 2, 3, 16, 23, 1000, 2 ** 31 + 11, 2 ** 32 - 1):
        m = kernels.ring_multiplier(W) % 2 ** 64
        for k in (0, 1, W - 1, W, 12345, 2 ** 31, 2 ** 32 - 1):
            assert (m * k % 2 ** 64) * W >> 64 == k % W, (W, k)


def test_shared_parameters_copied_into_the_first_lane_alone_give_the_same_bits(monkeypatch):
    """A shared parameter that the operations read only in the first lane (LTI and gain matrices, the Markov
    weights) is copied into that lane alone; broadcast into every lane instead, the run is the same bit for bit
    (37 members: chunks of 16 lanes and a partial one)."""
    sc = scenarios.get("shear-building-damage")
    s = sc.resolve({})
    states, plain = [], lowering.Builder.param
    for first_lane in (True, False):
        if not first_lane:
            monkeypatch.setattr(lowering.Builder, "param", lambda self, t, first_lane=False: plain(self, t))
        g = sc.build(s, 37, torch.float64, "cpu")
        g.engine = "native"
        g.advance(300)
        assert g.ran_engine == "native"
        modes = [bd.mode for bd in lowering.program(g).binds]
        assert (kernels.BindMode.LOAD_FIRST_LANE in modes) == first_lane and kernels.BindMode.LOAD_AND_STORE in modes
        states.append(g.state_dict())
    for key, t in states[0].items():
        assert torch.equal(t, states[1][key]), key
