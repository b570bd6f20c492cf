"""A user's own function in the native engine: StaticMap compiled by numba against the PyTorch engine, the
reason when it cannot be compiled, the array form for several inputs, and the compilation kept per process."""

import numpy as np
import pytest
import torch

import rcotorch as rt
from rcotorch import compiled
from rcotorch.refinement import refinement

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
    # the refinement is on its way to the friction law (Coulomb 2, viscous 0.5): within 10% after 3000 steps
    est = -native.role("estimator").theta[:, 0]
    assert ((est - torch.tensor([2.0, 0.5], dtype=torch.float64)).abs() / torch.tensor([2.0, 0.5]) < 0.1).all()


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
