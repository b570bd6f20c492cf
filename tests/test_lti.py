"""LTI blocks against python-control: stepping, ZOH discretization, per-member parameters, Markov parameters."""

import control
import numpy as np
import pytest
import torch

import rcotorch as rt

DT = 0.1


def _random_stable(seed, n=3, m=2, p=2, dt=DT):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A = Q @ np.diag(rng.uniform(-0.8, 0.8, n)) @ Q.T + 0.1 * rng.standard_normal((n, n))
    A *= 0.9 / max(1.0, np.abs(np.linalg.eigvals(A)).max())
    B, C, D = rng.standard_normal((n, m)), rng.standard_normal((p, n)), rng.standard_normal((p, m))
    return control.ss(A, B, C, D, dt)


def _step_block(block, U, batch=1):
    """Drive a block with inputs U[port] (T, B, width); return the outputs stacked (T, B, width) by port."""
    block.reset(batch)
    T = next(iter(U.values())).shape[0]
    outs = {p: [] for p in block.outputs}
    for k in range(T):
        y = block.step(**{p: u[k] for p, u in U.items()})
        for p in outs:
            outs[p].append(y[p])
    return {p: torch.stack(v) for p, v in outs.items()}


def test_stepping_matches_forced_response():
    sys = _random_stable(1)
    x0 = np.array([0.5, -1.0, 2.0])
    T = 60
    U = np.random.default_rng(2).standard_normal((2, T))
    ref = control.forced_response(sys, T=np.arange(T) * DT, U=U, X0=x0).outputs   # (2, T)
    blk = rt.LTI.from_control(sys, inputs=["a", "b"], outputs=["y1", "y2"], x0=x0)
    out = _step_block(blk, {"a": torch.tensor(U[0]).reshape(T, 1, 1), "b": torch.tensor(U[1]).reshape(T, 1, 1)})
    np.testing.assert_allclose(out["y1"][:, 0, 0].numpy(), ref[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out["y2"][:, 0, 0].numpy(), ref[1], rtol=1e-12, atol=1e-12)
    # One vector port of width 2 is the same system.
    blk2 = rt.LTI(sys.A, sys.B, sys.C, sys.D, inputs={"u": 2}, outputs={"y": 2}, dt=DT, x0=x0)
    out2 = _step_block(blk2, {"u": torch.tensor(U.T).reshape(T, 1, 2)})
    np.testing.assert_allclose(out2["y"][:, 0].numpy().T, ref, rtol=1e-12, atol=1e-12)


def test_zoh_matches_sample_system():
    rng = np.random.default_rng(3)
    A = rng.standard_normal((3, 3)) - 2 * np.eye(3)
    B, C, D = rng.standard_normal((3, 2)), rng.standard_normal((2, 3)), rng.standard_normal((2, 2))
    dt = 0.05
    ref = control.sample_system(control.ss(A, B, C, D), dt, "zoh")
    blk = rt.LTI.continuous(A, B, C, D, inputs=["a", "b"], outputs=["c", "d"], dt=dt)
    for name in "ABCD":
        np.testing.assert_allclose(getattr(blk, name)[0].numpy(), getattr(ref, name), rtol=1e-12, atol=1e-13)
    Ad, Bd = rt.zoh(A, B, dt)
    np.testing.assert_allclose(Ad.numpy(), ref.A, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(Bd.numpy(), ref.B, rtol=1e-12, atol=1e-13)
    # from_control of the continuous system discretizes the same way.
    blk_c = rt.LTI.from_control(control.ss(A, B, C, D), inputs=["a", "b"], outputs=["c", "d"], dt=dt)
    np.testing.assert_allclose(blk_c.A[0].numpy(), ref.A, rtol=1e-12, atol=1e-13)
    # Batched: one (A, B) per member.
    A2 = np.stack([A, A - np.eye(3)])
    Ad2, Bd2 = rt.zoh(A2, B, dt)
    ref2 = control.sample_system(control.ss(A - np.eye(3), B, C, D), dt, "zoh")
    np.testing.assert_allclose(Ad2[1].numpy(), ref2.A, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(Bd2[1].numpy(), ref2.B, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(Ad2[0].numpy(), ref.A, rtol=1e-12, atol=1e-13)


def test_per_batch_parameters_equal_separate_runs():
    systems = [_random_stable(s) for s in (4, 5, 6)]
    x0 = np.array([[1.0, 0.0, -1.0], [0.0, 2.0, 0.5], [0.3, 0.3, 0.3]])
    stack = {k: np.stack([getattr(s, k) for s in systems]) for k in "ABCD"}
    T = 40
    U = torch.tensor(np.random.default_rng(7).standard_normal((T, 3, 2)))
    blk = rt.LTI(stack["A"], stack["B"], stack["C"], stack["D"], {"u": 2}, {"y": 2}, DT, x0=x0)
    out = _step_block(blk, {"u": U}, batch=3)["y"]
    for b, s in enumerate(systems):
        ref = control.forced_response(s, T=np.arange(T) * DT, U=U[:, b].numpy().T, X0=x0[b]).outputs
        np.testing.assert_allclose(out[:, b].numpy().T, ref, rtol=1e-12, atol=1e-12)
        single = rt.LTI(s.A, s.B, s.C, s.D, {"u": 2}, {"y": 2}, DT, x0=x0[b])
        np.testing.assert_allclose(_step_block(single, {"u": U[:, b:b + 1]})["y"][:, 0].numpy(),
                                   out[:, b].numpy(), rtol=1e-13, atol=1e-14)


def test_per_batch_parameters_must_match_batch():
    sys = _random_stable(8)
    blk = rt.LTI(np.stack([sys.A, sys.A]), sys.B, sys.C, sys.D, {"u": 2}, {"y": 2}, DT)
    with pytest.raises(rt.DimensionError, match="2 members"):
        blk.reset(3)


@pytest.mark.parametrize("inp,out", [(0, 0), (1, 0), (0, 1), (1, 1)])
def test_markov_matches_impulse_response(inp, out):
    sys = _random_stable(9)
    n = 12
    blk = rt.LTI.from_control(sys, inputs=["a", "b"], outputs=["c", "d"])
    H = blk.markov(["a", "b"][inp], ["c", "d"][out], n)
    assert H.shape == (1, n, 1, 1)
    # python-control's discrete impulse response applies an impulse of area 1, i.e. a sample of 1/dt.
    ref = control.impulse_response(sys, T=np.arange(n) * DT, input=inp, output=out).outputs * DT
    np.testing.assert_allclose(H[0, :, 0, 0].numpy(), ref, rtol=1e-12, atol=1e-13)
    assert H[0, 0, 0, 0].item() == sys.D[out, inp]


def test_markov_vector_ports_and_per_member():
    sys1, sys2 = _random_stable(10), _random_stable(11)
    blk = rt.LTI(np.stack([sys1.A, sys2.A]), np.stack([sys1.B, sys2.B]), sys1.C, sys1.D, {"u": 2}, {"y": 2}, DT)
    H = blk.markov("u", "y", 6)
    assert H.shape == (2, 6, 2, 2)
    for b, s in enumerate((sys1, sys2)):
        s = control.ss(s.A, s.B, sys1.C, sys1.D, DT)
        ref = control.impulse_response(s, T=np.arange(6) * DT).outputs * DT      # (out, in, T)
        np.testing.assert_allclose(H[b].permute(1, 2, 0).numpy(), ref, rtol=1e-12, atol=1e-13)


def test_feedthrough_structure_from_d():
    A = 0.5 * np.eye(2)
    B = np.ones((2, 3))
    C = np.ones((3, 2))
    # rows: p, q[0], q[1]; cols: a, b, c. Only b -> p and c -> q[1] feed through.
    D = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    blk = rt.LTI(A, B, C, D, inputs=["a", "b", "c"], outputs={"p": 1, "q": 2}, dt=DT)
    assert blk.feedthrough() == {"p": ("b",), "q": ("c",)}
    blk0 = rt.LTI(A, B, C, np.zeros((3, 3)), inputs=["a", "b", "c"], outputs={"p": 1, "q": 2}, dt=DT)
    assert blk0.feedthrough() == {"p": (), "q": ()}
    # Per-member D: an entry nonzero for any member makes the path structural.
    Dm = np.zeros((2, 3, 3))
    Dm[1, 0, 0] = 1e-3
    blkm = rt.LTI(A, B, C, Dm, inputs=["a", "b", "c"], outputs={"p": 1, "q": 2}, dt=DT)
    assert blkm.feedthrough() == {"p": ("a",), "q": ()}


def test_to_control_roundtrip():
    sys = _random_stable(12)
    blk = rt.LTI.from_control(sys, inputs={"u": 2}, outputs=["c", "d"])
    back = blk.to_control()
    assert back.dt == DT
    for name in "ABCD":
        np.testing.assert_array_equal(getattr(back, name), getattr(sys, name))
    assert list(back.input_labels) == ["u[0]", "u[1]"]


def test_bad_shapes_and_ports():
    sys = _random_stable(13)
    with pytest.raises(rt.DimensionError, match="total width"):
        rt.LTI.from_control(sys, inputs=["a"], outputs=["c", "d"])
    with pytest.raises(rt.DimensionError, match="B has shape"):
        rt.LTI(sys.A, np.ones((2, 2)), sys.C, sys.D, ["a", "b"], ["c", "d"], DT)
    with pytest.raises(rt.ConfigError, match="dt"):
        rt.LTI.from_control(control.ss(-1.0, 1.0, 1.0, 0.0), inputs=["a"], outputs=["c"])
    blk = rt.LTI.from_control(sys, inputs=["a", "b"], outputs=["c", "d"])
    with pytest.raises(rt.ConfigError, match="no input port 'x'"):
        blk.markov("x", "c", 3)
    blk.reset(1)
    with pytest.raises(rt.DimensionError, match="expected shape"):
        blk.step(a=torch.zeros(1, 2), b=torch.zeros(1, 1))
