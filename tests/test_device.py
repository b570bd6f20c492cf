"""Every tensor a step touches moves with the graph (``graph.to(device)``), checked without a GPU: while the
PyTorch engine steps each shipped scenario's graph (masked, tied and featured estimators included), every
tensor handed to a torch function must be a buffer of the graph or computed during the run, and no tensor may be
created without naming its device (that one would stay on the CPU when the graph is on a GPU). And whole runs
(build, steps, summary, intervals, validation, figures) on a virtual GPU (``virtual_cuda.py``), where a CPU
tensor that meets the graph's fails as it would on CUDA."""

import traceback

import numpy as np
import pytest
import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten
from virtual_cuda import virtual_cuda

import rcotorch as rt
from rcotorch.engine import memo, rls
from rcotorch.run import scenario as scenarios
from rcotorch.run.runner import Run

FACTORIES = {torch.tensor, torch.as_tensor, torch.zeros, torch.ones, torch.empty, torch.full, torch.eye,
             torch.arange, torch.linspace, torch.randn, torch.rand}


class StrayTensors(TorchFunctionMode):
    """Notes tensors that are neither the graph's buffers nor made during the run, and factory calls without a
    device."""

    def __init__(self, graph):
        super().__init__()
        self.known = {id(t) for t in graph.buffers()} | {id(t) for t in graph.parameters()}
        self.strays: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", str(func))
        if func in FACTORIES and "device" not in kwargs and not (args and isinstance(args[0], torch.Tensor)):
            where = next((f"{f.filename.rsplit('/', 1)[-1]}:{f.lineno}" for f in reversed(traceback.extract_stack())
                          if "rcotorch" in f.filename and "test_" not in f.filename), "?")
            self.strays.append(f"{name}(...) at {where} without a device")
        for t in tree_flatten((args, kwargs))[0]:
            if isinstance(t, torch.Tensor) and id(t) not in self.known and t.dim() > 0:
                where = next((f"{f.filename.rsplit('/', 1)[-1]}:{f.lineno}" for f in reversed(traceback.extract_stack())
                              if "rcotorch" in f.filename and "test_" not in f.filename), "?")
                self.strays.append(f"{name} at {where}: a tensor of shape {tuple(t.shape)} from outside the graph")
        out = func(*args, **kwargs)
        self.known |= {id(t) for t in tree_flatten(out)[0] if isinstance(t, torch.Tensor)}
        return out


CASES = [(name, {}) for name in ("sdof-dynamic-impedance", "sdof-stiffness", "sdof-stiffness-damping",
                                 "twodof-stiffness", "rlc-circuit", "shear-building-damage")] + [
    ("sdof-stiffness", {"truth": "discrete", "noise": 0.05, "normalize": 1.0, "p_max": 1e4, "r_delta": 0.1})]


def _tied_graph():
    """A tied, bounded estimator with features (what the thermosphere's structures use), on a Python graph."""
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.5, 2.0, sees=["position", "velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=0.01, name="known")
    ident = rt.RCOEstimator({"y0": 2}, nc=1, tie=[[0, 0, 1]], p0=10.0, lam=0.999, theta_bounds=(-5, 5),
                            u_bounds=(-10, 10), features=[rt.features.port("y0[0]"), rt.features.power("y0[1]", 3)])
    return rt.refinement(known, ident, truth=rt.Gain([[-0.3, 0.0]]), excitation=rt.WhiteNoise(1, seed=[1, 2]),
                         nu=10, batch_size=2)


@pytest.mark.parametrize("name,overrides", CASES + [("tied", None)], ids=lambda x: x if isinstance(x, str) else "")
def test_every_tensor_a_step_touches_is_the_graphs(name, overrides):
    if overrides is None:
        graph = _tied_graph()
    else:
        sc = scenarios.get(name)
        graph = sc.build(sc.resolve(overrides), 2, torch.float64, "cpu")
    graph.engine = "torch"
    for module in graph.modules():         # derived tensors are made again under the check
        memo.forget(module)
    rls._ones.cache_clear()
    mode = StrayTensors(graph)
    with mode:
        for _ in range(5):
            graph.step()
    assert not mode.strays, sorted(set(mode.strays))


# --- whole runs as on a GPU (tests/virtual_cuda.py) -------------------------------------------------------------

def test_virtual_cuda_refuses_what_cuda_refuses():
    with virtual_cuda():
        g = torch.zeros(3, device="cuda")
        assert g.device.type == "cuda" and g.is_cuda and (g + 1).device.type == "cuda"
        with pytest.raises(RuntimeError, match="same device"):
            torch.stack([g, torch.arange(3.0)])
        with pytest.raises(RuntimeError, match="same device"):
            g * torch.ones(3)
        with pytest.raises(TypeError, match="numpy"):
            g.numpy()
        assert (g * torch.tensor(2.0)).is_cuda                       # a CPU scalar is allowed, as by PyTorch
        c = g.cpu()
        assert not c.is_cuda and c.numpy().shape == (3,) and g.is_cuda
        assert torch.as_tensor(g, device="cpu").device.type == "cpu" and g.is_cuda


@pytest.mark.parametrize("name,steps,batch,overrides,full", [
    ("sdof-stiffness-damping", 200, 2, {}, True),                             # excitation streams, intervals
    ("twodof-stiffness", 200, 1, {}, False),                                  # masked static gain
    ("thermosphere-no-cooling", 30, 1, {"structure": "temperature", "shared": True}, True),  # tied, replay
    ("mass-friction", 200, 2, {}, False),                                     # a NumPy function in the truth
    ("shear-building-damage", 150, 2, {"t_change": 0.5, "warmup": 20, "window": 20, "holdoff": 50, "nu": 30,
                                       "threshold": 5}, False),               # change detector and its figures
], ids=["sdof-stiffness-damping", "twodof-masked", "thermosphere-tied", "numpy-function", "change-detector"])
def test_a_whole_run_on_the_gpu(tmp_path, name, steps, batch, overrides, full):
    """Build, step, summary (intervals, validation, health, metrics, a scenario's replay) and figures of a run on
    the (virtual) GPU: a CPU tensor meeting the graph's anywhere fails here as it would on CUDA. (``full``: with
    the intervals and the held-out validation, which the first case checks for every graph alike.)"""
    with virtual_cuda():
        run = Run(name, steps=steps, batch=batch, device="cuda", overrides=overrides, out=tmp_path, intervals=full,
                  validation=full)
        run.advance(progress=False)
        summary = run.finish(figures=True)
        assert run.graph.role("estimator").theta.is_cuda
    values = [v for v in summary["estimates"].values()]
    assert values and all(np.all(np.isfinite(np.asarray(v, dtype=float))) for v in values)


def test_an_estimator_built_from_gpu_tensors():
    # A frozen estimate handed to a new graph (as a replay does): theta0 and beta on the GPU, the mask on the CPU.
    with virtual_cuda():
        theta0 = torch.full((1, 1, 2), 0.5, device="cuda")
        est = rt.RCOEstimator.static_gain({"y": 2}, mask=[[True, False]], theta0=theta0,
                                          markov=torch.ones(3, 1, 1, device="cuda"), name="identified")
        assert not est.theta0.is_cuda and est.theta0.tolist() == [[[0.5, 0.0]]]


def test_numpy_functions_on_the_gpu_match_the_cpu():
    """A user's function written with NumPy cannot take a GPU tensor: a StaticMap and a Nonlinear block built on
    one run it on host copies and give the CPU's numbers; a function's own TypeError still reaches the user."""
    def friction(v):
        return -(2.0 * np.sign(v) + 0.5 * v)

    def f(x, u):
        return np.concatenate([x[:, 1:2], -4.0 * x[:, :1] - 0.1 * x[:, 1:2] + u["u"]], axis=1)

    def h(x):
        return x[:, :1]

    x = torch.linspace(-1, 1, 6, dtype=torch.float64).reshape(3, 2)
    want_map = friction(x.numpy())
    dyn = rt.Nonlinear(f, h, 2, {"u": 1}, {"y": 1}, dt=0.01, name="osc")
    dyn.reset(3)
    dyn.x = x.clone()
    want_y = dyn.step(u=torch.ones(3, 1, dtype=torch.float64))["y"].numpy()
    with virtual_cuda():
        m = rt.StaticMap(friction, 2, name="friction")
        got = m.output("out", {"in": x.to("cuda")})
        assert got.is_cuda
        np.testing.assert_allclose(got.cpu().numpy(), want_map, rtol=0, atol=0)
        dyn = rt.Nonlinear(f, h, 2, {"u": 1}, {"y": 1}, dt=0.01, name="osc").to("cuda")
        dyn.reset(3)
        dyn.x = x.to("cuda")
        got_y = dyn.step(u=torch.ones(3, 1, dtype=torch.float64, device="cuda"))["y"]
        assert got_y.is_cuda
        np.testing.assert_allclose(got_y.cpu().numpy(), want_y, rtol=0, atol=0)

        def energy(s):                    # np.sum of a tensor takes no keepdims: called with arrays
            return np.sum(s["y0"] ** 2, axis=1, keepdims=True)

        est = rt.RCOEstimator.static_gain({"y0": 2}, features={"e": energy, "y": rt.features.port("y0")})
        phi = est._regressors({"y0": x.to("cuda")})
        assert phi.is_cuda
        np.testing.assert_allclose(phi.cpu().numpy(), np.concatenate([(x.numpy() ** 2).sum(1, keepdims=True),
                                                                      x.numpy()], 1), rtol=0, atol=0)

        def wrong(v):
            return np.sign(v) + "a"                                  # the user's own TypeError

        with pytest.raises(Exception, match="ufunc|str|add"):
            rt.StaticMap(wrong, 1).output("out", {"in": torch.ones(2, 1, device="cuda")})
