"""The native engine (rcotorch.lowering, rcotorch._engine): a graph lowered to C and run many steps per call.

It must do what the PyTorch engine does, to rounding: every lowered block and estimator option is run on
both engines from the same state and compared. Independent references for the engine itself: the NumPy loop
(tests/test_numpy_reference.py runs on both engines) and the closed-form RLS (tests/test_rls.py)."""

import os
import subprocess
import sys
import textwrap

import control
import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch import kernels
from rcotorch import scenario as scenarios

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
])
def test_scenarios_agree_with_the_torch_engine(name, overrides):
    sc = scenarios.get(name)
    s = sc.resolve(overrides)
    a, b = _run_both(lambda: sc.build(s, 5, torch.float64, "cpu"), 700, chunks=(3, 1, 2))
    _assert_same_state(a, b)


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
    rec = rt.data.Recording(np.nan_to_num(values), ["w", "y"], DT, valid=np.isfinite(values))

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
        big.advance(300)
    finally:
        torch.set_num_threads(threads)
    for b in (0, 17, 20):
        one = sc.build(sc.resolve(members[b]), 1, torch.float64, "cpu")
        one.engine = "native"
        one.advance(123)
        one.advance(177)
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
    est = rt.RCOEstimator({"y0": 1}, nc=1, features={"v3": lambda s: s["y0"] ** 3})
    g = rt.refinement(known, est, truth=rt.StaticMap(lambda v: -v, 1, name="unknown"),
                      excitation=rt.WhiteNoise(1), nu=4)
    assert "StaticMap" in g.native_status()
    g.engine = "native"
    with pytest.raises(rt.ConfigError, match="StaticMap"):
        g.advance(3)
    g.engine = "auto"
    g.advance(3)                                               # falls back to PyTorch
    assert int(g.k) == 3
    with pytest.raises(rt.ConfigError, match="engine must be one of"):
        g.engine = "fast"
    g2 = rt.refinement(sdof_known(DT), rt.RCOEstimator({"y0": 1}, nc=1, features={"v3": lambda s: s["y0"] ** 3}),
                       truth=rt.Gain([[0.1]], name="unknown"), excitation=rt.WhiteNoise(1), nu=4)
    assert "features" in g2.native_status()
    g2.add_hook(lambda graph: None)
    assert "hooks" in g2.native_status()
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
        from rcotorch import scenario as scenarios
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
        sys.modules["rcotorch._engine"] = None          # as if it had not been built
        import torch
        from rcotorch import scenario as scenarios
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
