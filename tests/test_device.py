"""Every tensor a step touches moves with the graph (``graph.to(device)``), checked without a GPU: while the
PyTorch engine steps each shipped scenario's graph (masked, tied and featured estimators included), every
tensor handed to a torch function must be a buffer of the graph or computed during the run, and no tensor may be
created without naming its device (that one would stay on the CPU when the graph is on a GPU)."""

import traceback

import pytest
import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

import rcotorch as rt
from rcotorch import memo, rls
from rcotorch import scenario as scenarios

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
                                 "twodof-stiffness", "rlc-circuit")] + [
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
