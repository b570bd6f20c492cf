"""The regressors an estimator rebuilds from a recorded stretch (``RCOEstimator.regressors_over``, what the
intervals' replay uses instead of stepping) equal, step by step, those its update used (``last_regressor``
after each step), for every way phi is built: a static gain, a dynamic subsystem with u's past, a strictly
proper one, features, masks and ties, normalized regressors, Markov parameters per member."""

import contextlib
from unittest import mock

import numpy as np
import pytest
import torch

import rcotorch as rt


def _sdof(ident, nu=12, truth=None, B=3):
    Ts = 0.05
    known = rt.LTI.continuous(*rt.models.sdof_matrices(1.0, 0.4, 4.0, measured=["position"],
                                                       sees=["position", "velocity"]),
                              inputs=["w", "u"], outputs={"y": 1, "y0": 2}, dt=Ts, name="known")
    truth = truth if truth is not None else rt.Gain(torch.tensor([[0.5, -0.2]]))
    g = rt.refinement(known, ident, truth=truth, excitation=rt.WhiteNoise(1, seed=3),
                      noise=rt.WhiteNoise(1, std=0.01, seed=4), nu=nu)
    g.reset(B)
    return g


CASES = {
    "static gain": lambda: _sdof(rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3)),
    "dynamic, u's past": lambda: _sdof(rt.RCOEstimator({"y0": 2}, nc=3, p0=1e2, feed_u=True)),
    "dynamic, strictly proper": lambda: _sdof(rt.RCOEstimator({"y0": 2}, nc=2, p0=1e2)),
    "proper with lags": lambda: _sdof(rt.RCOEstimator({"y0": 2}, nc=2, proper=True, p0=1e2)),
    "masked": lambda: _sdof(rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3, mask=[[1.0, 0.0]])),
    "tied": lambda: _sdof(rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3, tie=[[0, 0]])),
    "normalized": lambda: _sdof(rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3, normalize=0.5)),
    "features": lambda: _sdof(rt.RCOEstimator.static_gain(
        {"y0": 2}, p0=1e3, features={"x3": lambda s: s["y0"][:, :1] ** 3, "v": lambda s: s["y0"][:, 1:]})),
    # at least CONVOLVE_NU Markov parameters: filtered as one convolution over time
    "many Markov parameters": lambda: _sdof(rt.RCOEstimator({"y0": 2}, nc=2, p0=1e2), nu=40),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("start", [5, 200])
def test_rebuilt_regressors_equal_those_of_each_update(case, start):
    g = CASES[case]()
    est = g.role("estimator")
    g.engine = "torch"
    g.advance(start)                                     # a window partly or wholly filled before the stretch
    history = est.regressor_history()
    ports = [p for p in est.inputs if p not in ("z", "valid") and (est.name, p) in g.sources]
    signals = {p: g.sources[(est.name, p)] for p in ports}
    inputs = {p: [] for p in ports}
    u, stepped = [], []
    T = 60
    for _ in range(T):
        g.advance(1)
        last = g.last
        for p, sig in signals.items():
            inputs[p].append(last[sig].clone())
        u.append(last[(est.name, "u")].clone())
        stepped.append(est.last_regressor().clone())
    inputs = {p: torch.stack(v) for p, v in inputs.items()}
    u, stepped = torch.stack(u), torch.stack(stepped)
    for lo, hi in [(0, T), (0, 7), (13, 41), (T - 1, T)]:
        got = est.regressors_over(history, inputs, u, lo, hi)
        assert got.shape == stepped[lo:hi].shape
        np.testing.assert_allclose(got.numpy(), stepped[lo:hi].numpy(), rtol=1e-11,
                                   atol=1e-13 * float(stepped.abs().max()))


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("nu", [12, 40])
def test_markov_parameters_per_member_are_filtered_member_by_member(nu, native):
    """On the CPU the native kernel filters the stretch (``kernels.markov_filter``); elsewhere (here: the kernels
    disabled) PyTorch does, by a product per Markov parameter or, for many, one convolution."""
    from rcotorch.engine import kernels
    mf = kernels.markov_filter
    g = _sdof(rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3), nu=nu)
    est = g.role("estimator")
    beta = est.beta.expand(3, -1, -1, -1).clone()
    beta[1] *= 0.5
    beta[2] *= -1.5
    est.set_markov(beta, est.first_delay)
    g.reset(3)
    g.engine = "torch"
    g.advance(30)
    history = est.regressor_history()
    sig = g.sources[(est.name, "y0")]
    rows, u, stepped = [], [], []
    for _ in range(25):
        g.advance(1)
        rows.append(g.last[sig].clone())
        u.append(g.last[(est.name, "u")].clone())
        stepped.append(est.last_regressor().clone())
    called = []
    with contextlib.nullcontext() if native else kernels.disabled(), \
            mock.patch.object(kernels, "markov_filter", lambda *a: called.append(mf(*a)) or called[-1]):
        got = est.regressors_over(history, {"y0": torch.stack(rows)}, torch.stack(u), 0, 25)
    assert len(called) == 1 and (called[0] is not None) == native          # the kernel filtered, or PyTorch
    np.testing.assert_allclose(got.numpy(), torch.stack(stepped).numpy(), rtol=1e-11, atol=1e-15)


@pytest.mark.parametrize("engine", ["torch", "native"])
@pytest.mark.parametrize("case", list(CASES))
def test_a_held_estimator_moves_its_histories_as_a_zero_gain_does(case, engine):
    """A held estimator (``hold``, the intervals' replay and validation) skips the retrospective cost's step: its
    u, theta and the histories ``regressors_over`` reads are those of the same estimator stepped with P = 0
    through the whole update, on both engines, with the program of the graph made before the hold."""
    import copy
    g = CASES[case]()
    g.engine = engine
    g.advance(40)
    held, zero = g, copy.deepcopy(g)
    held.advance(3)
    zero.advance(3)
    held.role("estimator").hold()
    zero.role("estimator").set_state(P=torch.zeros_like(zero.role("estimator").P))
    z_r = held.role("estimator").z_r.clone()
    records = []
    for graph in (held, zero):
        rec = {("identified", "u"): torch.empty(60, 3, 1, dtype=torch.float64),
               ("error", "out"): torch.empty(60, 3, 1, dtype=torch.float64)}
        graph.advance(60, record=rec)
        records.append(rec)
    a, b = held.role("estimator"), zero.role("estimator")
    assert a.held and not b.held
    for sig in records[0]:
        assert torch.equal(records[0][sig], records[1][sig]), sig
    for key, value in a.regressor_history().items():
        assert torch.equal(value, b.regressor_history()[key]), key
    assert torch.equal(a.theta, b.theta) and torch.equal(a.P, b.P)
    assert torch.equal(a.z_r, z_r) and not torch.equal(b.z_r, z_r)       # the held one made no step of the cost
    a.reset(3)
    assert not a.held


@pytest.mark.parametrize("mask, tie", [([[1.0, 0.0]], None), ([[0.0, 1.0]], None), (None, [[0, -1]]),
                                       (None, [[-1, 4]])])
def test_a_pinned_entrys_regressor_is_not_filtered_and_the_others_are_the_whole_filters_bit_for_bit(mask, tie):
    """Where entries of Theta are pinned (a mask, or a negative tie label), the native kernel filters only the
    regressor columns a parameter holds, one call per column; the regressors of eta are those of the whole
    filter, bit for bit."""
    from rcotorch.engine import kernels
    from rcotorch.estimator import rco
    g = _sdof(rt.RCOEstimator.static_gain({"y0": 2}, p0=1e3, mask=mask, tie=tie), nu=20)
    est = g.role("estimator")
    g.engine = "torch"
    g.advance(40)
    history = est.regressor_history()
    sig = g.sources[(est.name, "y0")]
    rows, u = [], []
    for _ in range(30):
        g.advance(1)
        rows.append(g.last[sig].clone())
        u.append(g.last[(est.name, "u")].clone())
    rows, u = torch.stack(rows), torch.stack(u)
    mf, widths = kernels.markov_filter, []
    with mock.patch.object(kernels, "markov_filter", lambda *a: widths.append(a[0].shape[2]) or mf(*a)):
        got = est.regressors_over(history, {"y0": rows}, u, 0, 30)
    assert widths == [1]                                  # one column of phi filtered: the one a parameter holds
    with mock.patch.object(rco.RCOEstimator, "_markov_held_entries", lambda *a: None):
        whole = est.regressors_over(history, {"y0": rows}, u, 0, 30)
    assert torch.equal(got, whole)
