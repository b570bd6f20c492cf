"""Signals derived from a recording (difference, filtered derivative, function of columns), against closed forms,
and played back by ``Recorded`` as plain columns."""

import numpy as np
import pytest

import rcotorch as rt
from rcotorch.data.recording import derivative, difference, function


def _rec(dt=0.01, n=2000, **columns):
    names = list(columns)
    return rt.Recording(np.stack([np.asarray(columns[k], dtype=float) for k in names], 1), names, dt,
                        units={"x": "m"} if "x" in columns else {})


def test_difference_of_a_square():
    k = np.arange(50.0)
    rec = _rec(dt=0.5, x=k ** 2).derive(d=difference("x"), v=difference("x", per_second=True))
    assert rec.columns == ["x", "d", "v"]
    np.testing.assert_array_equal(rec.column("d"), np.r_[0.0, 2 * k[1:] - 1])      # k^2 - (k-1)^2
    np.testing.assert_array_equal(rec.column("v"), rec.column("d") / 0.5)
    assert rec.unit("d") == "m" and rec.unit("v") == "m/s"


@pytest.mark.parametrize("tau", [0.0, 0.02, 0.3])
def test_filtered_derivative_of_a_ramp_closed_form(tau):
    """x(k) = a k dt: the recursion (tau + dt) y(k) - tau y(k-1) = a dt gives y(k) = a (1 - r^k), r = tau/(tau+dt)."""
    a, dt = 2.5, 0.01
    k = np.arange(400)
    rec = _rec(dt=dt, x=a * k * dt).derive(v=derivative("x", tau=tau))
    r = tau / (tau + dt)
    np.testing.assert_allclose(rec.column("v"), a * (1 - r ** k), rtol=1e-12, atol=1e-12)
    assert rec.unit("v") == "m/s"


def test_derivative_without_filter_is_the_backward_difference_of_a_sine():
    w, dt = 3.0, 0.01
    t = np.arange(1000) * dt
    v = _rec(dt=dt, x=np.sin(w * t)).derive(v=derivative("x")).column("v")
    # (sin(w t_k) - sin(w t_(k-1))) / dt = (2 / dt) cos(w (t_k - dt/2)) sin(w dt / 2)
    np.testing.assert_allclose(v[1:], 2 / dt * np.cos(w * (t[1:] - dt / 2)) * np.sin(w * dt / 2), atol=1e-10)


def test_filtered_derivative_of_a_sine_tends_to_the_continuous_filter():
    """Steady state of s / (tau s + 1) on sin(w t): amplitude w / sqrt(1 + (w tau)^2), phase 90 deg - atan(w tau);
    backward Euler is first order, so the error shrinks in proportion to dt."""
    w, tau = 2.0, 0.25
    amp, phase = w / np.hypot(1.0, w * tau), np.pi / 2 - np.arctan(w * tau)
    errors = []
    for dt in (1e-3, 5e-4):
        t = np.arange(int(20 / dt)) * dt
        v = _rec(dt=dt, x=np.sin(w * t)).derive(v=derivative("x", tau=tau)).column("v")
        late = t > 10 * tau
        errors.append(np.abs(v[late] - amp * np.sin(w * t[late] + phase)).max())
    assert errors[0] < 2e-3 and errors[1] < 0.6 * errors[0], errors


def test_function_of_columns_and_errors():
    rec = _rec(dt=0.1, x=np.arange(5.0), f=np.full(5, 2.0))
    out = rec.derive(p=function(lambda x, f: x * f, "x", "f", unit="W"))
    np.testing.assert_array_equal(out.column("p"), 2 * np.arange(5.0))
    assert out.unit("p") == "W"
    with pytest.raises(rt.DataError, match=r"returned shape \(2,\), expected \(5,\)"):
        rec.derive(p=function(lambda x: x[:2], "x"))
    with pytest.raises(rt.DataError, match="'x' already exists"):
        rec.derive(x=difference("f"))
    with pytest.raises(rt.DataError, match="no column 'y'"):
        rec.derive(v=derivative("y"))
    with pytest.raises(rt.DataError, match="needs a derivation"):
        rec.derive(v=lambda r: r)
    with pytest.raises(rt.DataError, match="needs the sample time"):
        rt.Recording(rec.values, rec.columns).derive(v=derivative("x"))
    with pytest.raises(rt.DataError, match="tau must be >= 0"):
        derivative("x", tau=-1)
    gappy = rt.Recording(rec.values, rec.columns, 0.1, valid=np.array([[True, True]] * 4 + [[False, True]]))
    with pytest.raises(rt.DataError, match="column 'x' has missing samples"):
        gappy.derive(v=difference("x"))


def test_derived_before_rows_keeps_the_filter_history():
    dt = 0.01
    x = np.sin(np.arange(600) * dt * 4)
    whole = _rec(dt=dt, x=x).derive(v=derivative("x", tau=0.05))
    part = whole.rows(200, 300)
    np.testing.assert_array_equal(part.column("v"), whole.column("v")[200:300])
    assert part.columns == ["x", "v"] and part.unit("v") == "m/s"


def test_recorded_plays_derived_signals_back_as_columns():
    dt, a = 0.01, 3.0
    k = np.arange(100)
    rec = _rec(dt=dt, x=a * k * dt, w=np.cos(k))
    block = rt.Recorded(rec, {"w": "w", "y": "v"}, derive={"v": derivative("x", tau=0.1)})
    g = rt.Graph([block], [], batch_size=1)
    out = g.run(100, record={"y": "data.y", "w": "data.w"})
    r = 0.1 / (0.1 + dt)
    np.testing.assert_allclose(out["y"][:, 0, 0].numpy(), a * (1 - r ** k), rtol=1e-12, atol=1e-13)
    np.testing.assert_array_equal(out["w"][:, 0, 0].numpy(), np.cos(k))
    # per-member data (B, T, columns) and a plain array with dt given to the block
    arr = np.stack([np.c_[k * dt, k ** 2 * dt], np.c_[2 * k * dt, k * dt]])         # (2, T, 2)
    block = rt.Recorded(arr, {"y": "d"}, dt=dt, derive={"d": difference(1, per_second=True)}, name="rec")
    out = rt.Graph([block], [], batch_size=2).run(100, record={"y": "rec.y"})["y"][:, :, 0].T.numpy()
    np.testing.assert_allclose(out[0, 1:], (2 * k[1:] - 1.0), rtol=1e-12)
    np.testing.assert_allclose(out[1, 1:], np.ones(99), rtol=1e-12)
    with pytest.raises(rt.DataError, match=r"block 'rec'.*no column 'zz'"):
        rt.Recorded(arr, {"y": "d"}, dt=dt, derive={"d": difference("zz")}, name="rec")
