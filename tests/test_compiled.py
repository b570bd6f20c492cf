"""A user's own function in the native engine: StaticMap compiled by numba against the PyTorch engine, the
reason when it cannot be compiled, the array form for several inputs, Nonlinear blocks and their Markov
refreshes, and the compilation kept per process and on disk."""

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch.engine import compiled
from rcotorch.engine.lowering import NotLowerable
from rcotorch.wiring import refinement

pytest.importorskip("numba")


def friction(v):
    return -(2.0 * np.sign(v) + 0.5 * v)


def _graph(truth, batch=4, engine="auto"):
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.2, 4.0, measured=["velocity"], sees=["velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.01, name="known")
    ident = rt.RCOEstimator.static_gain({"y0": 1}, features=[rt.features.sign("y0"), rt.features.port("y0")],
                                        p0=1e3)
    g = refinement(known, ident, truth=truth, excitation=rt.WhiteNoise(1, std=20.0, seed=list(range(1, batch + 1))),
                   nu=50, batch_size=batch)
    g.engine = engine
    return g


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_a_numpy_static_map_runs_natively_and_equals_the_pytorch_engine():
    native, torch_ = _graph(rt.StaticMap(friction, 1)), _graph(rt.StaticMap(friction, 1), engine="torch")
    assert native.native_status() is None
    native.advance(3000)
    torch_.advance(3000)
    assert native.ran_engine == "native"
    a, b = native.role("estimator").theta, torch_.role("estimator").theta
    assert torch.allclose(a, b, rtol=1e-12, atol=1e-12), (a - b).abs().max()
    # the refinement converges to the friction law (Coulomb 2, viscous 0.5): within 25% after 3000 steps, within
    # 5% after 10,000
    truth = torch.tensor([2.0, 0.5], dtype=torch.float64)

    def error():
        return (-native.role("estimator").theta[:, 0] - truth).abs() / truth

    assert (error() < 0.25).all()
    native.advance(7000)
    assert (error() < 0.05).all()


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_a_graph_that_ran_compiled_functions_can_be_copied_for_its_intervals(tmp_path):
    """The intervals replay copies of the graph, program and compiled functions included."""
    g = _graph(rt.StaticMap(friction, 1), batch=2)
    res = rt.refine(g, 2000, out=tmp_path / "run", figures=False)
    assert res.summary["engine"] == "native" and res.summary["intervals"]
    assert all(v is not None for v in res.summary["intervals"]["theta[sign(y0)(k)]"]["lower"])


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_several_inputs_compile_in_the_array_form_and_equal_pytorch():
    def coupled(x):
        return np.stack((x[:, 0] * x[:, 1], np.tanh(x[:, 0]) - x[:, 1] ** 3), axis=1)
    c = compiled.compile_map(coupled, 2, 2)
    assert isinstance(c, compiled.Compiled) and c.form == "array"
    blk = rt.StaticMap(coupled, 2)
    g = rt.Graph([rt.WhiteNoise(2, seed=3, name="src"), blk], [("src.out", "map.in")], batch_size=3)
    out_native = g.run(50, record={"y": "map.out"})["y"]
    g2 = rt.Graph([rt.WhiteNoise(2, seed=3, name="src"), rt.StaticMap(coupled, 2)], [("src.out", "map.in")],
                  batch_size=3)
    g2.engine = "torch"
    out_torch = g2.run(50, record={"y": "map.out"})["y"]
    assert g.native_status() is None and torch.allclose(out_native, out_torch, rtol=1e-13, atol=1e-13)


def test_a_function_that_does_not_compile_runs_on_pytorch_and_the_reason_names_it(tmp_path):
    g = _graph(rt.StaticMap(lambda v: -(2.0 * v.sign() + 0.5 * v), 1))
    why = g.native_status()
    assert "block 'unknown' (StaticMap)" in why and "<lambda>" in why and "sign" in why, why
    res = rt.refine(g, 400, out=tmp_path / "run", figures=False, intervals=False)
    assert res.summary["engine"] == "torch" and "sign" in res.summary["engine_reason"]


def test_a_compiled_function_is_kept_for_the_process():
    first = compiled.compile_map(friction, 1, 1)
    assert compiled.compile_map(friction, 1, 1) is first and first.form == "scalar"
    assert compiled.compile_map(friction, 1, 1).address == first.address


GAIN = 2.0


def scaled(v):
    return GAIN * v


def test_a_graph_built_after_a_global_changed_computes_with_the_new_value(monkeypatch):
    """numba reads a function's globals as constants when it compiles; a graph built after one of them changed
    is compiled afresh, as the PyTorch engine would read the new value (a study that sets a global in a loop)."""
    def ratio():
        g = rt.Graph([rt.WhiteNoise(1, seed=1, name="src"), rt.StaticMap(scaled, 1)], [("src.out", "map.in")])
        r = g.run(3, record={"x": "src.out", "y": "map.out"})
        assert g.ran_engine == "native"
        return (r["y"] / r["x"]).reshape(-1)
    assert torch.allclose(ratio(), torch.full((3,), 2.0, dtype=torch.float64), rtol=1e-15, atol=0)
    monkeypatch.setitem(globals(), "GAIN", 5.0)
    assert torch.allclose(ratio(), torch.full((3,), 5.0, dtype=torch.float64), rtol=1e-15, atol=0)


K, C, A = 4.0, 0.3, 2.0


def duffing(x, ins):
    q, v = x[:, 0:1], x[:, 1:2]
    return np.concatenate((v, -K * q - C * v - A * q ** 3 + ins["w"]), axis=1)


def velocity(x):
    return x[:, 1:2]


def _duffing_graph(continuous: bool, engine: str = "auto", f=duffing):
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, C, K, measured=["velocity"], sees=["position"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.01, name="known")
    if continuous:
        plant = rt.Nonlinear(f, velocity, 2, inputs=["w"], outputs=["y"], dt=0.01, continuous=True, substeps=4)
    else:                                   # an explicit Euler map of the same equations, as a discrete block
        plant = rt.Nonlinear(lambda x, ins: x + 0.01 * f(x, ins), velocity, 2, inputs=["w"], outputs=["y"], dt=0.01)
    ident = rt.RCOEstimator.static_gain({"y0": 1}, features=[rt.features.power("y0", 3)], p0=10.0)
    g = refinement(known, ident, physical=plant, excitation=rt.WhiteNoise(1, std=3.0, seed=[1, 2, 3]), nu=30,
                   batch_size=3)
    g.engine = engine
    return g


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.parametrize("continuous", [True, False])
def test_a_numpy_nonlinear_block_runs_natively_and_equals_the_pytorch_engine(continuous):
    native, torch_ = _duffing_graph(continuous), _duffing_graph(continuous, "torch")
    assert native.native_status() is None
    rec_n = native.run(1500, record={"y": "plant.y"})["y"]
    rec_t = torch_.run(1500, record={"y": "plant.y"})["y"]
    assert native.ran_engine == "native" and torch_.ran_engine == "torch"
    assert torch.allclose(rec_n, rec_t, rtol=1e-11, atol=1e-12), (rec_n - rec_t).abs().max()
    assert torch.allclose(native.blocks["plant"].x, torch_.blocks["plant"].x, rtol=1e-11, atol=1e-12)
    a, b = native.role("estimator").theta, torch_.role("estimator").theta
    assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)


def test_a_torch_nonlinear_block_compiles_and_equals_the_pytorch_engine():
    """``torch.cat`` and ``torch.tanh`` in a state function compile through their NumPy stand-ins; the native
    run equals the PyTorch engine's (which calls torch itself)."""
    def f(x, ins):
        q, v = x[:, 0:1], x[:, 1:2]
        return torch.cat((v, -K * q - C * v - A * torch.tanh(q) ** 3 + ins["w"]), dim=1)
    native, torch_ = _duffing_graph(True, f=f), _duffing_graph(True, "torch", f=f)
    assert native.native_status() is None
    rec_n = native.run(1500, record={"y": "plant.y"})["y"]
    rec_t = torch_.run(1500, record={"y": "plant.y"})["y"]
    assert native.ran_engine == "native" and torch_.ran_engine == "torch"
    assert torch.allclose(rec_n, rec_t, rtol=1e-11, atol=1e-12), (rec_n - rec_t).abs().max()


def test_a_nonlinear_block_with_tensor_methods_stays_on_pytorch_and_says_which_function():
    def f(x, ins):
        return torch.cat((x[:, 1:2], -K * x[:, 0:1] - C * x[:, 1:2].clamp(-5, 5) + ins["w"]), dim=1)
    why = _duffing_graph(True, f=f).native_status()
    assert "(Nonlinear)" in why and "state function f" in why and "test_compiled.py" in why, why
    assert "clamp" in why, why


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.parametrize("fn", [
    lambda v: -(2.0 * torch.sign(v) + 0.5 * v),
    lambda v: torch.clamp(3.0 * v, -1.0, 1.0) + torch.clamp(v, min=0.5) + torch.clip(v, max=-2.0),
    lambda v: torch.where(v > 0, torch.sqrt(torch.abs(v)), torch.sigmoid(v)) + torch.relu(v) * torch.pi,
    lambda x: torch.stack((x[:, 0] * torch.tanh(x[:, 1]), torch.exp(-x[:, 0] ** 2)), dim=1),
    lambda x: torch.stack([x[:, 0] * torch.tanh(x[:, 1]), torch.exp(-x[:, 0] ** 2)], dim=-1),
    lambda x: torch.cat([x[:, :1] * x[:, 1:], torch.tanh(x)], dim=1),
    lambda x: np.concatenate([np.abs(x[:, :1]), np.sin(x)], axis=1),
    lambda x: np.concatenate([x[:, 1], np.cos(x[:, 0])]).reshape(2, x.shape[0]).T.copy(),
    lambda x: np.hstack([x[:, 1:], np.sign(x[:, :1]) * x[:, 1:] ** 2]),
    lambda x: np.column_stack([x[:, 0] * x[:, 1], np.exp(-x[:, 1] ** 2)]),
    lambda x: np.vstack([x[:, 0], np.tanh(x[:, 1])]).T.copy(),
    lambda x: np.stack([np.tanh(x[:, 0]), x[:, 1] ** 3], axis=1),
], ids=["sign", "clamp", "where", "stack", "stack list", "cat list", "np concatenate list",
        "np concatenate 1-d list", "np hstack list", "np column_stack list", "np vstack list", "np stack list"])
def test_torch_functions_compile_and_equal_torch_itself(fn):
    """A StaticMap written with torch functions runs natively, its outputs equal to torch's own on the same
    inputs (the PyTorch engine's run), and the reason is None; so do NumPy's joins given a list of arrays, as
    NumPy takes them (numba's own take a tuple)."""
    n = 2 if {"stack", "cat", "concatenate", "hstack", "vstack", "column_stack"} & set(fn.__code__.co_names) else 1
    def graph(engine):
        g = rt.Graph([rt.WhiteNoise(n, std=3.0, seed=5, name="src"), rt.StaticMap(fn, n)], [("src.out", "map.in")],
                     batch_size=3)
        g.engine = engine
        return g
    native, torch_ = graph("auto"), graph("torch")
    assert native.native_status() is None
    a = native.run(300, record={"y": "map.out"})["y"]
    b = torch_.run(300, record={"y": "map.out"})["y"]
    assert native.ran_engine == "native"
    assert torch.allclose(a, b, rtol=1e-13, atol=1e-13), (a - b).abs().max()


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.parametrize("fn", [
    lambda x: np.sum(x ** 2, axis=1, keepdims=True),
    lambda x: x - np.mean(x, axis=-1, keepdims=True),
    lambda x: np.max(np.abs(x), axis=1, keepdims=True) + np.amin(x, axis=1).reshape(-1, 1),
    lambda x: np.prod(x, axis=1).reshape(-1, 1) + np.sum(x, 1, keepdims=True),
    lambda x: torch.sum(x * x, dim=1, keepdim=True) + torch.mean(x, dim=1).reshape(-1, 1),
    lambda x: torch.amax(x, dim=-1, keepdim=True) - torch.amin(x, 1, True),
], ids=["np sum", "np mean", "np max amin", "np prod sum", "torch sum mean", "torch amax amin"])
def test_reductions_over_a_members_components_compile_and_equal_numpy(fn):
    """Reductions along a member's components with an axis and keepdims (numba's own take no keepdims, and its
    max and min no axis) compile, natively equal to the PyTorch engine, which calls a NumPy function that a
    tensor does not serve (np.sum(x, axis=1, keepdims=True) calls x.sum with NumPy's argument names) with
    arrays; and both equal NumPy on the recorded inputs."""
    def graph(engine):
        g = rt.Graph([rt.WhiteNoise(3, std=3.0, seed=5, name="src"), rt.StaticMap(fn, 3)], [("src.out", "map.in")],
                     batch_size=4)
        g.engine = engine
        return g
    native, torch_ = graph("auto"), graph("torch")
    assert native.native_status() is None
    a = native.run(50, record={"x": "src.out", "y": "map.out"})
    b = torch_.run(50, record={"y": "map.out"})["y"]
    assert native.ran_engine == "native"
    assert torch.allclose(a["y"], b, rtol=1e-13, atol=1e-13), (a["y"] - b).abs().max()
    x = a["x"].reshape(-1, 3).numpy()
    want = fn(torch.from_numpy(x)).numpy() if "torch" in fn.__code__.co_names else fn(x)
    np.testing.assert_allclose(a["y"].reshape(len(x), -1).numpy(), want, rtol=1e-13)


def test_torch_functions_imported_by_name_compile_too():
    from torch import tanh
    assert isinstance(compiled.compile_map(lambda v: 2.0 * tanh(v), 1, 1), compiled.Compiled)


G_L, DAMP, K_TRUE = 9.0, 1.0, 3.0


def pendulum_numpy(x, ins):
    q, v = x[:, 0:1], x[:, 1:2]
    return np.concatenate((v, -G_L * np.sin(q) - DAMP * v + ins["w"] + ins["u"]), axis=1)


def pendulum_torch(x, ins):
    q, v = x[:, 0:1], x[:, 1:2]
    return torch.cat((v, -G_L * torch.sin(q) - DAMP * v + ins["w"] + ins["u"]), dim=1)


def pendulum_outputs(x):
    return np.concatenate((x[:, 1:2], x[:, 0:1]), axis=1)    # y: the velocity; y0: the angle the estimator sees


def _pendulum_graph(f, engine="auto", every=50):
    known = rt.Nonlinear(f, pendulum_outputs, 2, inputs=["w", "u"], outputs={"y": 1, "y0": 1}, dt=0.02,
                         continuous=True, substeps=2, name="known")

    def plant_f(x, ins):                     # the same pendulum with a spring nobody modelled
        q, v = x[:, 0:1], x[:, 1:2]
        return np.concatenate((v, -G_L * np.sin(q) - K_TRUE * q - DAMP * v + ins["w"]), axis=1)
    plant = rt.Nonlinear(plant_f, lambda x: x[:, 1:2], 2, inputs=["w"], outputs=["y"], dt=0.02, continuous=True,
                         substeps=2)
    ident = rt.RCOEstimator.static_gain({"y0": 1}, p0=100.0)
    g = refinement(known, ident, physical=plant, excitation=rt.WhiteNoise(1, std=1.0, seed=[4, 5]), nu=20,
                   batch_size=2)
    g.add_hook(rt.MarkovRefresh(g, every))
    g.engine = engine
    return g


def test_finite_difference_markov_parameters_of_a_numpy_model_equal_autograd_of_its_torch_twin():
    numpy_model = rt.Nonlinear(pendulum_numpy, pendulum_outputs, 2, inputs=["w", "u"], outputs={"y": 1, "y0": 1},
                               dt=0.02, continuous=True, substeps=2, x0=[0.7, -0.3])
    torch_model = rt.Nonlinear(pendulum_torch, lambda x: torch.cat((x[:, 1:2], x[:, 0:1]), 1), 2,
                               inputs=["w", "u"], outputs={"y": 1, "y0": 1},
                               dt=0.02, continuous=True, substeps=2, x0=[0.7, -0.3])
    assert not numpy_model.differentiable() and torch_model.differentiable()
    fd = numpy_model.markov("u", "y", 30)                    # 'auto': central differences for NumPy
    ad = torch_model.markov("u", "y", 30)                    # 'auto': autograd for torch
    assert torch.allclose(fd, ad, rtol=1e-6, atol=1e-9), (fd - ad).abs().max()
    assert ad.abs().max() > 1e-3


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_a_markov_refresh_of_a_numpy_known_model_runs_natively_between_refreshes_and_equals_pytorch():
    native, torch_ = _pendulum_graph(pendulum_numpy), _pendulum_graph(pendulum_numpy, "torch")
    assert native.native_status() is None, native.native_status()
    native.add_hook(lambda g: None)
    assert "runs after every step" in native.native_status()     # a hook without a period needs every step
    native.hooks.pop()
    native.run(1200)
    assert native.ran_engine == "native"
    ident, known = native.role("estimator"), native.blocks["known"]
    held = {p: native.last[native.sources[("known", p)]] for p in known.inputs}
    H = known.markov("u", "y", ident.first_delay + ident.nu, inputs=held)   # at the state of step 1200
    assert torch.equal(ident.beta, -H[:, ident.first_delay:])                # refreshed there, natively
    assert not torch.allclose(ident.beta, _pendulum_graph(pendulum_numpy).role("estimator").beta)
    native.run(10)
    torch_.run(1210)
    assert torch_.ran_engine == "torch"
    # The engines' sin differ in the last bit, and the finite-difference refresh amplifies that to about 1e-10
    # in each refresh's Markov parameters.
    a, b = ident.theta, torch_.role("estimator").theta
    assert torch.allclose(a, b, rtol=1e-8, atol=1e-10), (a - b).abs().max()
    assert torch.allclose(ident.beta, torch_.role("estimator").beta, rtol=1e-6, atol=1e-9)


_CACHED_RUN = """
import numpy as np
import rcotorch as rt
from rcotorch.engine import compiled
K = {k}
def spring(x, ins):
    return np.concatenate((x[:, 1:2], -K * x[:, 0:1] + ins["w"]), axis=1)
blk = rt.Nonlinear(spring, lambda x: x[:, 1:2], 2, inputs=["w"], outputs=["y"], dt=0.01, continuous=True,
                   substeps=2)
c = compiled.compile_step(blk.f, 2, blk.inputs, blk.dt, True, 2)
g = rt.Graph([rt.WhiteNoise(1, seed=3, name="w"), blk], [("w.out", "nonlinear.w")])
y = g.run(300, record={{"y": "nonlinear.y"}})["y"]
print(c.owner._cache_hits, g.ran_engine, repr(float(y.abs().sum())))
"""


def test_compiled_functions_are_kept_on_disk_for_later_processes_and_keyed_by_what_they_depend_on(tmp_path):
    env = {**os.environ, "RCOTORCH_CACHE": str(tmp_path)}

    def run(k):
        out = subprocess.run([sys.executable, "-c", _CACHED_RUN.format(k=k)], env=env, capture_output=True,
                             text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        hits, engine, total = out.stdout.split()
        return int(hits), engine, float(total)
    first, second, other = run(4.0), run(4.0), run(9.0)
    assert first[0] == 0 and second[0] > 0            # the second process loads what the first compiled
    assert first[1:] == second[1:] and first[1] == "native"
    assert other[0] == 0 and other[2] != first[2]     # another constant: another key, compiled afresh
    assert (tmp_path / "compiled").stat().st_mode & 0o077 == 0


def test_a_function_whose_globals_have_no_stable_description_is_not_kept_on_disk():
    class Spring:
        k = 4.0
    spring = Spring()

    def f(x):
        return -spring.k * x
    assert compiled._fingerprint(f) is None
    K2 = 3.0

    def g(x):
        return -K2 * x
    assert compiled._fingerprint(g) is not None
    assert compiled._fingerprint(friction) != compiled._fingerprint(g)


def test_compiled_code_that_raises_fails_its_check_quietly(capfd):
    # Code that raises inside a C function cannot pass the exception on (e.g. code from the disk cache that
    # does not fit the sizes asked for): the check reports it, and nothing is printed.
    import numba

    def bad(x, y, vl):
        if vl > 0:
            raise ValueError("cannot assign slice of shape (64, 1) from input of shape (64, 0)")
        y[0] = x[0]

    cf = numba.cfunc(numba.types.void(numba.types.CPointer(numba.types.float64),
                                      numba.types.CPointer(numba.types.float64), numba.types.int64))(bad)
    why = compiled._check(lambda t: t * 1.0, cf, 1, 1)
    assert why == ("the compiled code raised ValueError: cannot assign slice of shape (64, 1) from input of "
                   "shape (64, 0)")
    assert "Exception ignored" not in capfd.readouterr().err


# --- the components form (scipy's solve_ivp convention): one member at a time in compiled code --------------
def duffing_components(x, ins):
    q, v = x
    return v, -K * q - C * v - A * q ** 3 + ins["w"][0]


def velocity_component(x):
    return x[1]


def _duffing_driven(form: str, engine: str, batch: int = 3, steps: int = 400):
    f, h = (duffing_components, velocity_component) if form == "components" else (duffing, velocity)
    blk = rt.Nonlinear(f, h, 2, inputs=["w"], outputs=["y"], dt=0.01, continuous=True, substeps=4,
                       x0=[0.5, 0.0], name="duffing", form=form)
    g = rt.Graph([rt.WhiteNoise(1, std=3.0, seed=list(range(1, batch + 1)), name="w"), blk],
                 [("w.out", "duffing.w")], batch_size=batch)
    g.engine = engine
    rec = g.run(steps, record={"w": "w.out", "y": "duffing.y"})
    return g, rec


def test_a_components_form_block_compiles_to_scalar_code_and_matches_scipy_and_the_other_forms():
    from scipy.integrate import solve_ivp
    g, rec = _duffing_driven("components", "auto")
    assert g.native_status() is None and g.ran_engine == "native"
    assert compiled.compile_map(velocity_component, 2, 1, "components").form == "member"
    # independent reference: scipy's adaptive integrator of the same equations, the input held over each step
    w = rec["w"][:, :, 0].numpy()
    for b in range(3):
        x, ys = np.array([0.5, 0.0]), []
        for k in range(w.shape[0]):
            ys.append(x[1])
            sol = solve_ivp(lambda t, s, u=w[k, b]: [s[1], -K * s[0] - C * s[1] - A * s[0] ** 3 + u], (0.0, 0.01), x,
                            rtol=1e-12, atol=1e-13, method="DOP853")
            x = sol.y[:, -1]
        assert np.allclose(rec["y"][:, b, 0].numpy(), ys, rtol=0, atol=1e-8), b
    # the PyTorch engine (the batch called with (B,) components) and the batch form give the same numbers
    gt, rect = _duffing_driven("components", "torch")
    gb, recb = _duffing_driven("batch", "auto")
    assert gt.ran_engine == "torch"
    assert torch.allclose(rec["y"], rect["y"], rtol=1e-12, atol=1e-13)
    assert torch.allclose(rec["y"], recb["y"], rtol=1e-12, atol=1e-13)


def test_a_discrete_components_block_with_wide_ports_and_several_outputs():
    def f(x, ins):                          # a discrete map of 3 states driven by a port of width 2
        a, b, c = x
        u = ins["u"]
        return 0.9 * a + 0.1 * u[0], 0.8 * b - 0.05 * np.sin(a) + 0.2 * u[1], 0.5 * c + a * b

    def h(x):
        return x[0] + x[2], 2.0 * x[1]

    def run(engine):
        blk = rt.Nonlinear(f, h, 3, inputs={"u": 2}, outputs={"y": 1, "z": 1}, dt=1.0, name="plant",
                           form="components")
        g = rt.Graph([rt.WhiteNoise(2, seed=[4, 5], name="u"), blk], [("u.out", "plant.u")], batch_size=2)
        g.engine = engine
        return g, g.run(200, record={"u": "u.out", "y": "plant.y", "z": "plant.z"})

    g, rec = run("auto")
    assert g.native_status() is None and g.ran_engine == "native"
    u = rec["u"].numpy()
    x = np.zeros((2, 3))
    for k in range(u.shape[0]):              # the same map written out with NumPy over the batch
        assert np.allclose(rec["y"][k, :, 0].numpy(), x[:, 0] + x[:, 2], rtol=1e-13, atol=1e-14)
        assert np.allclose(rec["z"][k, :, 0].numpy(), 2.0 * x[:, 1], rtol=1e-13, atol=1e-14)
        a, b, c = x.T
        x = np.stack((0.9 * a + 0.1 * u[k, :, 0], 0.8 * b - 0.05 * np.sin(a) + 0.2 * u[k, :, 1], 0.5 * c + a * b), 1)
    _, rect = run("torch")
    assert torch.allclose(rec["y"], rect["y"], rtol=1e-13, atol=1e-14)


def test_a_components_function_that_returns_lists_is_compiled_returning_tuples_with_the_same_values(
        monkeypatch):
    def f(x, ins):                          # lists, as scipy.integrate.solve_ivp users write them
        a, b = x
        return [0.9 * a + 0.1 * ins["u"][0], 0.8 * b - 0.05 * np.sin(a)]

    def h(x):
        return [x[0] + x[1]]

    def g_mixed(x, ins):                    # one return is a list display, the other a list made before:
        out = [0.7 * x[0] + ins["u"][0], x[1]]     # as tuples they would not unify, so it compiles as it is
        if len(out) > 2:
            return [x[0], x[1]]
        return out

    import dis
    ops = {i.opname for i in dis.get_instructions(compiled._returning_tuples(f))}
    assert "BUILD_TUPLE" in ops and "BUILD_LIST" not in ops
    assert compiled._returning_tuples(friction) is friction          # no list returned: itself

    def run(fn, engine):
        blk = rt.Nonlinear(fn, h, 2, inputs={"u": 1}, outputs={"y": 1}, dt=1.0, name="plant", form="components")
        g = rt.Graph([rt.WhiteNoise(1, seed=[4, 5, 6], name="u"), blk], [("u.out", "plant.u")], batch_size=3)
        g.engine = engine
        return g, g.run(300, record={"u": "u.out", "y": "plant.y"})

    tried = []
    real = compiled._compile

    def recording(*args):
        tuples = str(args[6]).endswith(" tuples")
        try:
            result = real(*args)
        except NotLowerable:
            tried.append((tuples, True))
            raise
        tried.append((tuples, False))
        return result
    monkeypatch.setattr(compiled, "_compile", recording)
    for fn in (f, g_mixed):
        tried.clear()
        g, rec = run(fn, "auto")
        # f: compiled returning tuples at once; g_mixed: that fails, then compiled as it is
        assert tried[0] == (True, fn is g_mixed) and tried[-1] == (fn is f, False), (fn.__name__, tried)
        assert g.native_status() is None and g.ran_engine == "native", fn.__name__
        _, rect = run(fn, "torch")
        assert torch.allclose(rec["y"], rect["y"], rtol=1e-13, atol=1e-14), fn.__name__
    # the written-out map, with NumPy over the batch
    u = run(f, "auto")[1]["u"][:, :, 0].numpy()
    x, y = np.zeros((3, 2)), []
    for k in range(u.shape[0]):
        y.append(x[:, 0] + x[:, 1])
        x = np.stack((0.9 * x[:, 0] + 0.1 * u[k], 0.8 * x[:, 1] - 0.05 * np.sin(x[:, 0])), 1)
    assert np.allclose(run(f, "auto")[1]["y"][:, :, 0].numpy(), np.array(y), rtol=1e-13, atol=1e-14)


def test_a_components_function_of_the_wrong_size_is_refused_naming_the_block():
    with pytest.raises(rt.DimensionError, match=r"block 'plant': f \(form 'components'\) returned 1 components"):
        rt.Nonlinear(lambda x, ins: (x[1],), lambda x: x[0], 2, inputs=["w"], outputs=["y"], dt=0.1, name="plant",
                     form="components")
    with pytest.raises(rt.ConfigError, match="form must be 'batch' or 'components'"):
        rt.Nonlinear(duffing, velocity, 2, inputs=["w"], outputs=["y"], dt=0.1, form="rows")


def test_the_markov_parameters_of_a_components_model_match_autograd_of_the_torch_model():
    def f_np(x, ins):
        q, v = x
        return v, -G_L * np.sin(q) - DAMP * v + ins["u"][0]

    def f_torch(x, ins):
        q, v = x
        return v, -G_L * torch.sin(q) - DAMP * v + ins["u"][0]

    x0 = [[0.4, -0.2], [1.0, 0.3]]
    H = {}
    for name, f, method in (("np", f_np, "fd"), ("torch", f_torch, "autograd")):
        blk = rt.Nonlinear(f, lambda x: x[1], 2, inputs=["u"], outputs=["y"], dt=0.05, continuous=True, substeps=2,
                           x0=x0, form="components")
        blk.reset(2)
        H[name] = blk.markov("u", "y", 6, method=method)
    assert torch.allclose(H["np"], H["torch"], rtol=1e-6, atol=1e-9)
