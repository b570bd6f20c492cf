"""Nonlinear blocks: stepping against scipy, Markov parameters against closed forms and finite differences,
and a refinement whose known model is nonlinear."""

import control
import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

import rcotorch as rt
from rcotorch.engine import kernels

A = np.array([[0.9, 0.2, 0.0], [-0.1, 0.8, 0.1], [0.0, 0.05, 0.7]])
B = np.array([[0.0, 1.0], [1.0, 0.5], [0.3, 0.0]])
C = np.array([[1.0, 0.0, 2.0]])


def linear_block():
    At, Bt, Ct = (torch.tensor(M) for M in (A, B, C))
    return rt.Nonlinear(lambda x, s: x @ At.T + torch.cat([s["w"], s["u"]], 1) @ Bt.T, lambda x: x @ Ct.T,
                        3, ["w", "u"], ["y"], dt=0.1, x0=[0.3, -0.2, 0.1], name="known")


@pytest.mark.parametrize("method", ["autograd", "fd"])
@pytest.mark.parametrize("along", ["trajectory", "point"])
def test_markov_of_a_linear_map_is_c_a_b(method, along):
    H = linear_block().markov("u", "y", 8, method=method, along=along)
    ref = [np.zeros((1, 1))] + [C @ np.linalg.matrix_power(A, i - 1) @ B[:, 1:] for i in range(1, 8)]
    np.testing.assert_allclose(H[0].numpy(), np.stack(ref), rtol=1e-7, atol=1e-9)


def test_continuous_rk4_markov_matches_zoh_discretization():
    """x' = Ac x + Bc u with RK4 substeps: Markov parameters approach those of the ZOH-discretized system."""
    Ac = np.array([[0.0, 1.0], [-4.0, -0.4]])
    Bc = np.array([[0.0], [1.0]])
    At, Bt = torch.tensor(Ac), torch.tensor(Bc)
    blk = rt.Nonlinear(lambda x, s: x @ At.T + s["u"] @ Bt.T, lambda x: x[:, 1:], 2, ["u"], ["y"], dt=0.05,
                       continuous=True, substeps=20)
    H = blk.markov("u", "y", 30)[0, :, 0, 0].numpy()
    d = control.sample_system(control.ss(Ac, Bc, [[0.0, 1.0]], 0), 0.05, "zoh")
    ref = [0.0] + [(d.C @ np.linalg.matrix_power(d.A, i - 1) @ d.B).item() for i in range(1, 30)]
    np.testing.assert_allclose(H, ref, rtol=1e-8, atol=1e-12)


def pendulum(name="known", x0=(0.4, 0.0)):
    g_l, c = 9.81, 0.3
    return rt.Nonlinear(lambda x, s: torch.stack([x[:, 1], -g_l * torch.sin(x[:, 0]) - c * x[:, 1] + s["w"][:, 0]
                                                  + s["u"][:, 0]], 1),
                        lambda x: torch.stack([x[:, 1], x[:, 0]], 1), 2, ["w", "u"], {"y": 1, "y0": 1}, dt=0.02,
                        continuous=True, substeps=4, x0=x0, name=name)


def test_rk4_stepping_matches_scipy():
    blk = pendulum()
    blk.reset(1)
    w = 0.5 * np.sin(np.arange(200) * 0.1)
    for k in range(200):
        blk.step(w=torch.tensor([[w[k]]]), u=torch.zeros(1, 1, dtype=torch.float64))

    def rhs(t, x):
        k = min(int(t / 0.02 + 1e-9), 199)
        return [x[1], -9.81 * np.sin(x[0]) - 0.3 * x[1] + w[k]]

    ref = x = np.array([0.4, 0.0])
    for k in range(200):
        ref = solve_ivp(rhs, (k * 0.02, (k + 1) * 0.02), x, rtol=1e-12, atol=1e-12, method="DOP853").y[:, -1]
        x = ref
    np.testing.assert_allclose(blk.x[0].numpy(), ref, rtol=1e-6, atol=1e-8)


def test_nonlinear_autograd_markov_matches_finite_differences_and_batches():
    blk = pendulum(x0=[[0.4, 0.1], [1.2, -0.5]])
    blk.reset(2)
    Ha = blk.markov("u", "y", 12, method="autograd")
    Hf = blk.markov("u", "y", 12, method="fd", eps=1e-6)
    np.testing.assert_allclose(Ha.numpy(), Hf.numpy(), rtol=1e-6, atol=1e-9)
    assert not torch.allclose(Ha[0], Ha[1])          # each member linearized at its own state
    single = pendulum(x0=[1.2, -0.5])
    single.reset(1)
    np.testing.assert_allclose(single.markov("u", "y", 12)[0].numpy(), Ha[1].numpy(), rtol=1e-12)


def test_probing_catches_bad_functions():
    with pytest.raises(rt.DimensionError, match="block 'bad': f must return shape"):
        rt.Nonlinear(lambda x, s: x[:, :1], lambda x: x, 2, ["u"], {"y": 2}, dt=0.1, name="bad")
    with pytest.raises(rt.ConfigError, match="f or h failed"):
        rt.Nonlinear(lambda x, s: x + s["nope"], lambda x: x, 2, ["u"], {"y": 2}, dt=0.1)
    # The usual slips, each named with its mend: components stacked as rows, one output as a 1-d array, and
    # solve_ivp's f(t, x) signature.
    with pytest.raises(rt.DimensionError, match=r"got \(2, 1\): the components along the first axis.*np.stack"):
        rt.Nonlinear(lambda x, s: np.array([x[:, 1], -x[:, 0]]), lambda x: x[:, :1], 2, ["u"], ["y"], dt=0.1)
    with pytest.raises(rt.DimensionError, match=r"h must return shape \(1, 1\).*got \(1,\).*x\[:, 0:1\]"):
        rt.Nonlinear(lambda x, s: x, lambda x: x[:, 0], 2, ["u"], ["y"], dt=0.1)
    with pytest.raises(rt.ConfigError, match=r"called as f\(x, inputs\)"):
        rt.Nonlinear(lambda t, x, u: x, lambda x: x[:, :1], 2, ["u"], ["y"], dt=0.1)


@pytest.mark.slow
def test_refinement_of_a_nonlinear_known_model_recovers_a_stiffness():
    """Known: the pendulum; truth: the same pendulum (discrete interconnection) with an extra spring
    u = -dk theta; the static gain on y0 = theta converges to -dk. Markov parameters by linearization,
    refreshed along the run."""
    dk = 2.0
    known = pendulum()
    truth = rt.Gain([[-dk]])
    ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=10.0)
    g = rt.refinement(known, ident, truth=truth, excitation=rt.WhiteNoise(1, std=2.0, seed=2), nu=60)
    g.add_hook(rt.MarkovRefresh(g, every=200))
    g.run(6000)
    assert abs(float(ident.theta[0, 0, 0]) + dk) < 0.02 * dk
    assert int(g.k) % 200 == 0  # refreshed after the last step, at the known model's present state
    held = {"w": g.last[("excitation", "out")], "u": g.last[("identified", "u")]}
    # The graph runs natively (torch.stack compiles), so the refresh took the engine's central differences:
    # autograd's Markov parameters at the same state to 1e-7 of their size.
    assert g.ran_engine == "native"
    exact = -g.blocks["known"].markov("u", "y", 61, inputs=held)[:, 1:, 0, 0].numpy()
    np.testing.assert_allclose(ident.beta[:, :, 0, 0].numpy(), exact, rtol=0, atol=1e-7 * np.abs(exact).max())


def test_markov_refresh_linearizes_at_the_inputs_received():
    """With an input-dependent linearization (y = x, x' = -x + w u: the u -> y gain scales with w), the refreshed
    beta uses the last w, not zero."""
    blk = rt.Nonlinear(lambda x, s: 0.5 * x + s["w"] * s["u"], lambda x: torch.cat([x, x], 1), 1, ["w", "u"],
                       {"y": 1, "y0": 1}, dt=1.0, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=1.0)
    ident.set_markov([[[-1.0]]], 1)
    src = rt.Recorded(np.full((10, 1), 3.0), {"out": 0}, name="w")
    g = rt.Graph([blk, ident, src, rt.Sum({"y": 1, "y_hat": -1}, 1, name="error")],
                 ["w.out -> known.w", "identified.u -> known.u", "known.y0 -> identified.y0", "known.y -> error.y",
                  "known.y -> error.y_hat", "error.out -> identified.z"],
                 roles={"known": "known", "estimator": "identified"})
    refresh = rt.MarkovRefresh(g, every=1)
    g.step()
    assert refresh()
    # H_i = C A^(i-1) B with A = 0.5, B = w = 3: beta_1 = -3
    assert ident.beta[0, 0, 0, 0].item() == pytest.approx(-3.0)


def numpy_linear_block(form):
    """The linear map of ``linear_block`` written with NumPy (so it compiles), in either form."""
    if form == "components":
        def f(x, s):
            w, u = s["w"][0], s["u"][0]
            return (A[0, 0] * x[0] + A[0, 1] * x[1] + A[0, 2] * x[2] + B[0, 0] * w + B[0, 1] * u,
                    A[1, 0] * x[0] + A[1, 1] * x[1] + A[1, 2] * x[2] + B[1, 0] * w + B[1, 1] * u,
                    A[2, 0] * x[0] + A[2, 1] * x[1] + A[2, 2] * x[2] + B[2, 0] * w + B[2, 1] * u)
        return rt.Nonlinear(f, lambda x: C[0, 0] * x[0] + C[0, 2] * x[2], 3, ["w", "u"], ["y"], dt=0.1,
                            x0=[0.3, -0.2, 0.1], name="known", form="components")
    return rt.Nonlinear(lambda x, s: x @ A.T + np.concatenate((s["w"], s["u"]), 1) @ B.T, lambda x: x @ C.T, 3,
                        ["w", "u"], ["y"], dt=0.1, x0=[0.3, -0.2, 0.1], name="known")


@pytest.mark.skipif(not kernels.available(), reason="no native engine")
@pytest.mark.parametrize("form", ["batch", "components"])
@pytest.mark.parametrize("along", ["trajectory", "point"])
def test_compiled_finite_differences_of_a_linear_map_are_c_a_b(form, along):
    """The central differences in the native engine, of f and h compiled (``compiled=True``), give C A^(i-1) B
    for each input port, as the same differences of the Python functions do."""
    blk = numpy_linear_block(form)
    assert blk.compiled_maps() is not None
    for port, col in (("w", 0), ("u", 1)):
        H = blk.markov(port, "y", 8, method="fd", along=along, compiled=True)
        ref = [np.zeros((1, 1))] + [C @ np.linalg.matrix_power(A, i - 1) @ B[:, col:col + 1] for i in range(1, 8)]
        np.testing.assert_allclose(H[0].numpy(), np.stack(ref), rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(H.numpy(), blk.markov(port, "y", 8, method="fd", along=along).numpy(),
                                   rtol=1e-12, atol=1e-15)


@pytest.mark.skipif(not kernels.available(), reason="no native engine")
def test_compiled_finite_differences_of_a_nonlinear_map_with_wide_ports_equal_pythons():
    """Three states, an input port of width 2 after one of width 1, two output ports (one of width 2), members
    at states of their own: the differences in the native engine equal those of the Python functions to
    rounding, along the free motion and at the point."""
    def f(x, s):
        q, v, r = x
        return (v, -9.81 * np.sin(q) + s["w"][0] + 2.0 * s["u"][0] - 0.3 * s["u"][1] * r,
                -r + s["u"][1] + q * v)

    blk = rt.Nonlinear(f, lambda x: (x[0], x[1] * x[2], np.cos(x[2])), 3, inputs={"w": 1, "u": 2},
                       outputs={"y": 1, "y0": 2}, dt=0.01, continuous=True, substeps=2, form="components",
                       x0=[0.3, -0.2, 0.5])
    blk.reset(5)
    g = torch.Generator().manual_seed(1)
    blk.set_state(x=torch.randn(5, 3, dtype=torch.float64, generator=g))
    held = {"w": torch.randn(5, 1, dtype=torch.float64, generator=g),
            "u": torch.randn(5, 2, dtype=torch.float64, generator=g)}
    for along in ("trajectory", "point"):
        for port, out in (("u", "y0"), ("u", "y"), ("w", "y0")):
            want = blk.markov(port, out, 40, inputs=held, method="fd", along=along)
            got = blk.markov(port, out, 40, inputs=held, method="fd", along=along, compiled=True)
            assert got.shape == want.shape and float(want.abs().max()) > 1e-3
            np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=1e-9, atol=1e-12 * float(want.abs().max()))


@pytest.mark.skipif(not kernels.available(), reason="no native engine")
@pytest.mark.parametrize("arithmetic", [False, True])
def test_markov_refresh_on_the_native_engine_calls_no_python(monkeypatch, arithmetic):
    """A known model refreshed every 50 steps on the native engine: after the compilation, its Python functions
    are not called (the steps and the linearizations run compiled), and the refreshed beta equals the PyTorch
    engine's: to rounding where both take central differences (np.sin: autograd cannot follow it), to 1e-7 where
    the PyTorch engine takes autograd (a model of arithmetic alone, which autograd follows)."""
    from rcotorch.blocks import nonlinear

    calls = [0]

    def counted(fn, *args):
        calls[0] += 1
        return call_user(fn, *args)

    call_user = nonlinear.call_user
    monkeypatch.setattr(nonlinear, "call_user", counted)

    def f(x, s):
        q, v = x
        spring = 4.0 * (q - q ** 3 / 6.0) if arithmetic else 4.0 * np.sin(q)
        return v, -spring - 0.2 * v + s["w"][0] + s["u"][0]

    def build():
        known = rt.Nonlinear(f, lambda x: (x[0], x[1]), 2, inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.02,
                             continuous=True, substeps=2, form="components", name="known")
        ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=10.0)
        g = rt.refinement(known, ident, truth=rt.Gain([[-0.5]]), excitation=rt.WhiteNoise(1, seed=[1, 2]), nu=40,
                          batch_size=2)
        g.add_hook(rt.MarkovRefresh(g, 50))
        return g

    a, b = build(), build()
    a.engine, b.engine = "torch", "native"
    assert a.role("known").differentiable() is arithmetic
    a.advance(300)
    assert calls[0] > 300                           # the PyTorch engine calls f from Python
    b.advance(1)                                    # compiles
    calls[0] = 0
    b.advance(299)
    assert calls[0] == 0
    ea, eb = a.role("estimator"), b.role("estimator")
    assert float(eb.beta.abs().max()) > 1e-4 and not torch.equal(eb.beta[:, 0], eb.beta[:, 5])
    np.testing.assert_allclose(eb.beta.numpy(), ea.beta.numpy(), rtol=1e-7, atol=1e-12)
